"""Every reason :meth:`TexturedSurfaceRegistrar.register` can reject a pair for, in one table.

A :class:`Gate` is checked at its :class:`Checkpoint` on the typed result of the stage before
it, in table order; the first that fails rejects the pair with its reason text. The reason
strings are part of the interface: tests assert them and reports count them.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from fpp_graph.types import Frame
from frontend.config import RegistrationConfig
from frontend.registration.state import PairFrames, PairReport, Rejected

if TYPE_CHECKING:
    from frontend.registration.refinement import WeakGeometryCheck

log = logging.getLogger(__name__)

MIN_FITNESS = 0.1
"""Share of source points with a target neighbour after ICP: at least the overlap (``gates.min_overlap``)."""

MIN_TEXTURE_AGREEMENT = 0.9
"""Appearance-only loop on weak geometry: share of the overlap blocks whose textures correlate; a
true revisit's blocks agree except for occlusions and specular spots, a look-alike place only on
its repeated object."""

MIN_TEXTURE_OVERLAP = 0.7
"""... and the share of the source view that overlap covers: most of the view, so it includes the
surroundings, not the repeated object alone."""

MIN_AGREEMENT_BLOCKS = 20
"""Fewer informative overlap blocks cannot tell a look-alike from a revisit: the agreement share of
fewer blocks has a standard error over 7 % (binomial at 0.9)."""

MIN_TEXTURE_PX = 32
"""Smaller textures (either side) cannot hold a descriptor patch (ORB 31 px, SURF's smallest scale)."""


class Checkpoint(enum.Enum):
    """Where in the pipeline a gate is checked, and the stage result its gates read."""

    INPUT = "input"  # before any work: PairFrames
    FEATURES = "features"  # after detection and matching: KeypointMatches
    MATCHES = "matches"  # after dropping sensor-fixed matches: KeypointMatches
    LIFTED = "lifted"  # after lifting the matches to 3D: LiftedMatches
    RANSAC = "ransac"  # KeypointPose
    ICP = "icp"  # IcpOutcome
    POSE = "pose"  # after the weak-direction rules (ICP's pose, or with directions from the keypoints): WeakDirectionOutcome
    REVISIT = "revisit"  # an appearance-only revisit on weak geometry before the dense or the photometric step: WeakGeometryCheck
    FINAL = "final"  # after the dense and photometric refinements: WeakGeometryCheck


Predicate = Callable[[Any, RegistrationConfig], bool]
Report = Callable[[Any, RegistrationConfig], str]


@dataclass(frozen=True)
class Gate:
    """One reason to reject a pair.

    Attributes
    ----------
    name : str
    checkpoint : Checkpoint
    fails : callable (result, config) -> bool
        True rejects the pair; ``result`` is the typed result of the checkpoint's stage.
    reason : callable (result, config) -> str
        The rejection reason (only called when ``fails``).
    threshold : str or None
        The config key (dotted, in ``registration``) or the constant that sets the threshold
        (None: no threshold).
    metadata : callable (result, reported metadata) -> dict, optional
        The rejected constraint's metadata; default: everything the stages reported so far.
    """

    name: str
    checkpoint: Checkpoint
    fails: Predicate
    reason: Report
    threshold: str | None
    metadata: Callable[[Any, dict[str, Any]], dict[str, Any]] | None = None


def _frame_gates(role: str) -> list[Gate]:
    """The input checks of the ``role`` ("target" or "source") frame of a :class:`PairFrames`."""

    def frame(p: PairFrames) -> Frame:
        return p.target if role == "target" else p.source

    def no_points(p: PairFrames, c: RegistrationConfig) -> bool:
        f = frame(p)
        # the frame's point list is the map's valid pixels: checking it is O(1), a scan of the
        # full map costs ~5 ms per 1920x1200 frame (the map is scanned only without points)
        return f.points.shape[0] == 0 and not np.any(np.isfinite(f.xyz_map[..., 2]))

    return [
        Gate(f"{role}_xyz_map", Checkpoint.INPUT, lambda p, c: frame(p).xyz_map is None,
             lambda p, c: f"{role} frame {frame(p).id} has no xyz_map: keypoints cannot be lifted to 3D", None),
        Gate(f"{role}_texture", Checkpoint.INPUT, lambda p, c: frame(p).texture is None,
             lambda p, c: f"{role} frame {frame(p).id} has no texture image: no keypoints", None),
        Gate(f"{role}_points", Checkpoint.INPUT, no_points,
             lambda p, c: f"{role} frame {frame(p).id} has no valid 3D points", None),
        Gate(f"{role}_texture_size", Checkpoint.INPUT, lambda p, c: min(frame(p).texture.shape) < MIN_TEXTURE_PX,
             lambda p, c: f"{role} frame {frame(p).id}: texture {frame(p).texture.shape} too small for keypoints", "MIN_TEXTURE_PX"),
    ]


def _weak_unconstrained(check: WeakGeometryCheck) -> str:
    return "; ".join(check.degeneracy.unconstrained)


def _with_weak_directions(check: WeakGeometryCheck, meta: dict[str, Any]) -> dict[str, Any]:
    return {**meta, "unconstrained_directions": check.degeneracy.directions}


def _agreement_fails(check: WeakGeometryCheck, c: RegistrationConfig) -> bool:
    a = check.agreement
    return a is not None and not (a.fraction >= MIN_TEXTURE_AGREEMENT and a.blocks >= MIN_AGREEMENT_BLOCKS)


def _look_alike_gates(checkpoint: Checkpoint) -> list[Gate]:
    """The look-alike tests of an appearance-only revisit on weak geometry (``agreement`` set):
    before the dense or photometric step (:attr:`Checkpoint.REVISIT`) and again on the final pose."""
    return [
        Gate("texture_agreement", checkpoint, _agreement_fails,
             lambda k, c: "look-alike place: degenerate geometry (unconstrained " + _weak_unconstrained(k)
             + f") and the textures agree on only {100 * k.agreement.fraction:.1f} % of {k.agreement.blocks} overlap blocks"
             + f" (< {100 * MIN_TEXTURE_AGREEMENT:.0f} % of >= {MIN_AGREEMENT_BLOCKS}) for an appearance-only candidate",
             "MIN_TEXTURE_AGREEMENT", metadata=_with_weak_directions),
        # the agreeing overlap may be the repeated object alone: twins on opposite walls agree
        # on all of an overlap that is only the object
        Gate("texture_overlap", checkpoint, lambda k, c: k.agreement is not None and not k.agreement.overlap >= MIN_TEXTURE_OVERLAP,
             lambda k, c: "possible look-alike place: degenerate geometry (unconstrained " + _weak_unconstrained(k)
             + f") and the agreeing overlap covers only {100 * k.agreement.overlap:.0f} % of the view"
             + f" (< {100 * MIN_TEXTURE_OVERLAP:.0f} %) for an appearance-only candidate",
             "MIN_TEXTURE_OVERLAP", metadata=_with_weak_directions),
    ]


GATES: tuple[Gate, ...] = (
    *_frame_gates("target"),
    *_frame_gates("source"),
    Gate("features", Checkpoint.FEATURES, lambda m, c: m.error is not None, lambda m, c: f"features failed: {m.error}", None),
    Gate("matches", Checkpoint.MATCHES, lambda m, c: m.count < c.gates.min_inliers,
         lambda m, c: f"too few matches ({m.count} < {c.gates.min_inliers})", "gates.min_inliers"),
    Gate("matches_3d", Checkpoint.LIFTED, lambda lifted, c: lifted.count < c.gates.min_inliers,
         lambda lifted, c: f"too few matches with valid 3D ({lifted.count} < {c.gates.min_inliers})", "gates.min_inliers",
         metadata=lambda lifted, meta: {"matches": meta["matches"]}),
    Gate("ransac_inliers", Checkpoint.RANSAC, lambda k, c: k.ransac.num_inliers < c.gates.min_inliers,
         lambda k, c: f"too few inliers ({k.ransac.num_inliers} < {c.gates.min_inliers} RANSAC inliers of {k.lifted.count})", "gates.min_inliers"),
    Gate("icp_points", Checkpoint.ICP, lambda i, c: i.too_few_voxels is not None,
         lambda i, c: "too few points for ICP ({} target, {} source voxels of {:g} mm)".format(*i.too_few_voxels[:2], 1e3 * i.too_few_voxels[2]), "ICP_MIN_VOXELS"),
    Gate("icp_finite", Checkpoint.ICP, lambda i, c: not np.all(np.isfinite(i.icp.T_target_source)),
         lambda i, c: "ICP diverged (non-finite pose)", None),
    Gate("icp_basin", Checkpoint.POSE, lambda w, c: w.shift_m > c.lengths.max_icp_shift_m,
         lambda w, c: f"ICP left the RANSAC basin (moved keypoint inliers by {1e3 * w.shift_m:.2f} mm > {1e3 * c.lengths.max_icp_shift_m:.2f} mm)", "MAX_ICP_SHIFT_SIGMAS"),
    Gate("keypoints_after_icp", Checkpoint.POSE, lambda w, c: w.keypoint_inliers < c.gates.min_inliers,
         lambda w, c: f"too few inliers after ICP ({w.keypoint_inliers} < {c.gates.min_inliers} keypoints agree)", "gates.min_inliers"),
    Gate("fitness", Checkpoint.POSE, lambda w, c: w.icp.fitness < MIN_FITNESS,
         lambda w, c: f"low fitness ({w.icp.fitness:.3f} < {MIN_FITNESS})", "MIN_FITNESS"),
    Gate("overlap", Checkpoint.POSE, lambda w, c: w.icp.overlap < c.gates.min_overlap,
         lambda w, c: f"low overlap ({w.icp.overlap:.3f} < {c.gates.min_overlap})", "gates.min_overlap"),
    Gate("inlier_rmse", Checkpoint.POSE, lambda w, c: not w.icp.inlier_rmse_m <= c.lengths.max_inlier_rmse_m,
         lambda w, c: f"high inlier RMSE ({1e3 * w.icp.inlier_rmse_m:.3f} mm > {1e3 * c.lengths.max_inlier_rmse_m:.3f} mm)", "MAX_INLIER_RMSE_SIGMAS"),
    *_look_alike_gates(Checkpoint.REVISIT),
    *_look_alike_gates(Checkpoint.FINAL),
    Gate("weak_directions_pinned", Checkpoint.FINAL, lambda k, c: k.degeneracy.degenerate and not k.weak_sigma_m <= c.lengths.max_weak_sigma_m,
         lambda k, c: "degenerate geometry: unconstrained " + _weak_unconstrained(k)
         + f" (sigma {1e3 * k.weak_sigma_m:.3f} mm > {1e3 * c.lengths.max_weak_sigma_m:.3f} mm even with keypoints)",
         "MAX_WEAK_SIGMA_SIGMAS", metadata=_with_weak_directions),
)


def check(checkpoint: Checkpoint, result: Any, report: PairReport, config: RegistrationConfig) -> None:
    """Raise :class:`~.state.Rejected` with the rejected constraint of the first gate at
    ``checkpoint`` that ``result`` (that stage's typed result) fails."""
    for gate in GATES:
        if gate.checkpoint is checkpoint and gate.fails(result, config):
            raise Rejected(report.rejected(gate.reason(result, config), gate.metadata(result, report.meta) if gate.metadata else None))


__all__ = ["GATES", "Checkpoint", "Gate", "check"]
