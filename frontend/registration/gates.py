"""Every reason :meth:`FppPairRegistrar.register` can reject a pair for, in one table.

A :class:`Gate` is checked at its :class:`Checkpoint` (after the stage that produces what it
reads), in table order; the first that fails rejects the pair with its reason text. The reason
strings are part of the interface: tests assert them and reports count them.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fpp_graph.types import Constraint, Frame
from frontend.config import RegistrationConfig
from frontend.registration.state import PairState

log = logging.getLogger(__name__)

class Checkpoint(enum.Enum):
    """Where in the pipeline a gate is checked: after the stage that fills what it reads."""

    INPUT = "input"  # before any work
    FEATURES = "features"  # after detection and matching
    MATCHES = "matches"  # after dropping sensor-fixed matches
    LIFTED = "lifted"  # after lifting the matches to 3D
    RANSAC = "ransac"
    ICP = "icp"
    POSE = "pose"  # after the weak-direction rules: ICP's pose, or with directions from the keypoints
    REVISIT = "revisit"  # an appearance-only revisit on weak geometry about to take the dense or the photometric step: the look-alike test first
    FINAL = "final"  # after the dense and photometric refinements


Predicate = Callable[[PairState, RegistrationConfig], bool]
Report = Callable[[PairState, RegistrationConfig], str]


@dataclass(frozen=True)
class Gate:
    """One reason to reject a pair.

    Attributes
    ----------
    name : str
    checkpoint : Checkpoint
    fails : callable (state, config) -> bool
        True rejects the pair.
    reason : callable (state, config) -> str
        The rejection reason (only called when ``fails``).
    config_key : str or None
        The :class:`~frontend.config.RegistrationConfig` key that sets the threshold (dotted,
        in its section; None: no threshold).
    metadata : callable (state) -> dict, optional
        The rejected constraint's metadata; default: everything the stages reported so far.
    """

    name: str
    checkpoint: Checkpoint
    fails: Predicate
    reason: Report
    config_key: str | None
    metadata: Callable[[PairState], dict[str, Any]] | None = None


def _frame_gates(role: str) -> list[Gate]:
    """The input checks of the ``role`` ("target" or "source") frame."""

    def frame(s: PairState) -> Frame:
        return s.target if role == "target" else s.source

    def no_points(s: PairState, c: RegistrationConfig) -> bool:
        f = frame(s)
        # the frame's point list is the map's valid pixels: checking it is O(1), a scan of the
        # full map costs ~5 ms per 1920x1200 frame (the map is scanned only without points)
        return f.points.shape[0] == 0 and not np.any(np.isfinite(f.xyz_map[..., 2]))

    return [
        Gate(f"{role}_xyz_map", Checkpoint.INPUT, lambda s, c: frame(s).xyz_map is None,
             lambda s, c: f"{role} frame {frame(s).id} has no xyz_map: keypoints cannot be lifted to 3D", None),
        Gate(f"{role}_texture", Checkpoint.INPUT, lambda s, c: frame(s).texture is None,
             lambda s, c: f"{role} frame {frame(s).id} has no texture image: no keypoints", None),
        Gate(f"{role}_points", Checkpoint.INPUT, no_points,
             lambda s, c: f"{role} frame {frame(s).id} has no valid 3D points", None),
        Gate(f"{role}_texture_size", Checkpoint.INPUT, lambda s, c: min(frame(s).texture.shape) < c.gates.min_texture_px,
             lambda s, c: f"{role} frame {frame(s).id}: texture {frame(s).texture.shape} too small for keypoints", "gates.min_texture_px"),
    ]


def _weak_unconstrained(s: PairState) -> str:
    return "; ".join(s.check.degeneracy.unconstrained)


def _with_weak_directions(s: PairState) -> dict[str, Any]:
    return {**s.meta, "unconstrained_directions": s.check.degeneracy.directions}


def _agreement_fails(s: PairState, c: RegistrationConfig) -> bool:
    a = s.check.agreement
    return a is not None and not (a.fraction >= c.gates.min_texture_agreement and a.blocks >= c.gates.min_agreement_blocks)


def _look_alike_gates(checkpoint: Checkpoint) -> list[Gate]:
    """The look-alike tests of an appearance-only revisit on weak geometry (``s.check.agreement``
    set): before the photometric step (:attr:`Checkpoint.REVISIT`) and again on the final pose."""
    return [
        Gate("texture_agreement", checkpoint, _agreement_fails,
             lambda s, c: "look-alike place: degenerate geometry (unconstrained " + _weak_unconstrained(s)
             + f") and the textures agree on only {100 * s.check.agreement.fraction:.1f} % of {s.check.agreement.blocks} overlap blocks"
             + f" (< {100 * c.gates.min_texture_agreement:.0f} % of >= {c.gates.min_agreement_blocks}) for an appearance-only candidate",
             "gates.min_texture_agreement", metadata=_with_weak_directions),
        # the agreeing overlap may be the repeated object alone (poster twins on opposite walls
        # registered 0.2 m apart agreed on 100 % of their 0.37-0.63 overlap)
        Gate("texture_overlap", checkpoint, lambda s, c: s.check.agreement is not None and not s.check.agreement.overlap >= c.gates.min_texture_overlap,
             lambda s, c: "possible look-alike place: degenerate geometry (unconstrained " + _weak_unconstrained(s)
             + f") and the agreeing overlap covers only {100 * s.check.agreement.overlap:.0f} % of the view"
             + f" (< {100 * c.gates.min_texture_overlap:.0f} %) for an appearance-only candidate",
             "gates.min_texture_overlap", metadata=_with_weak_directions),
    ]


GATES: tuple[Gate, ...] = (
    *_frame_gates("target"),
    *_frame_gates("source"),
    Gate("features", Checkpoint.FEATURES, lambda s, c: s.matches.error is not None,
         lambda s, c: f"features failed: {s.matches.error}", None),
    Gate("matches", Checkpoint.MATCHES, lambda s, c: s.matches.count < c.gates.min_inliers,
         lambda s, c: f"too few matches ({s.matches.count} < {c.gates.min_inliers})", "gates.min_inliers"),
    Gate("matches_3d", Checkpoint.LIFTED, lambda s, c: s.lifted.count < c.gates.min_inliers,
         lambda s, c: f"too few matches with valid 3D ({s.lifted.count} < {c.gates.min_inliers})", "gates.min_inliers",
         metadata=lambda s: {"matches": s.matches.count}),
    Gate("ransac_inliers", Checkpoint.RANSAC, lambda s, c: s.ransac.num_inliers < c.gates.min_inliers,
         lambda s, c: f"too few inliers ({s.ransac.num_inliers} < {c.gates.min_inliers} RANSAC inliers of {s.lifted.count})", "gates.min_inliers"),
    Gate("icp_points", Checkpoint.ICP, lambda s, c: s.icp.too_few_voxels is not None,
         lambda s, c: "too few points for ICP ({} target, {} source voxels of {:g} mm)".format(*s.icp.too_few_voxels[:2], 1e3 * s.icp.too_few_voxels[2]), None),
    Gate("icp_finite", Checkpoint.ICP, lambda s, c: not np.all(np.isfinite(s.icp.icp.T_target_source)),
         lambda s, c: "ICP diverged (non-finite pose)", None),
    Gate("icp_basin", Checkpoint.POSE, lambda s, c: s.weak.shift_m > c.lengths.max_icp_shift_m,
         lambda s, c: f"ICP left the RANSAC basin (moved keypoint inliers by {1e3 * s.weak.shift_m:.2f} mm > {1e3 * c.lengths.max_icp_shift_m:.2f} mm)", "gates.max_icp_shift_sigmas"),
    Gate("keypoints_after_icp", Checkpoint.POSE, lambda s, c: s.weak.keypoint_inliers < c.gates.min_inliers,
         lambda s, c: f"too few inliers after ICP ({s.weak.keypoint_inliers} < {c.gates.min_inliers} keypoints agree)", "gates.min_inliers"),
    Gate("fitness", Checkpoint.POSE, lambda s, c: s.weak.icp.fitness < c.gates.min_fitness,
         lambda s, c: f"low fitness ({s.weak.icp.fitness:.3f} < {c.gates.min_fitness})", "gates.min_fitness"),
    Gate("overlap", Checkpoint.POSE, lambda s, c: s.weak.icp.overlap < c.gates.min_overlap,
         lambda s, c: f"low overlap ({s.weak.icp.overlap:.3f} < {c.gates.min_overlap})", "gates.min_overlap"),
    Gate("inlier_rmse", Checkpoint.POSE, lambda s, c: not s.weak.icp.inlier_rmse_m <= c.lengths.max_inlier_rmse_m,
         lambda s, c: f"high inlier RMSE ({1e3 * s.weak.icp.inlier_rmse_m:.3f} mm > {1e3 * c.lengths.max_inlier_rmse_m:.3f} mm)", "gates.max_inlier_rmse_sigmas"),
    *_look_alike_gates(Checkpoint.REVISIT),
    *_look_alike_gates(Checkpoint.FINAL),
    Gate("weak_directions_pinned", Checkpoint.FINAL, lambda s, c: s.check.degeneracy.degenerate and not s.check.weak_sigma_m <= c.lengths.max_weak_sigma_m,
         lambda s, c: "degenerate geometry: unconstrained " + _weak_unconstrained(s)
         + f" (sigma {1e3 * s.check.weak_sigma_m:.3f} mm > {1e3 * c.lengths.max_weak_sigma_m:.3f} mm even with keypoints)",
         "gates.max_weak_sigma_sigmas", metadata=_with_weak_directions),
)


def rejection(checkpoint: Checkpoint, state: PairState, config: RegistrationConfig) -> Constraint | None:
    """The rejected constraint of the first gate at ``checkpoint`` that fails, else None."""
    for gate in GATES:
        if gate.checkpoint is checkpoint and gate.fails(state, config):
            return reject(state, gate.reason(state, config), gate.metadata(state) if gate.metadata else state.meta)
    return None


def reject(state: PairState, reason: str, metadata: dict[str, Any]) -> Constraint:
    log.info("pair %d->%d rejected: %s", state.source.id, state.target.id, reason)
    meta = dict(metadata)
    meta["timings_s"] = dict(state.timer.wall_s)
    return Constraint.rejected(state.source.id, state.target.id, reason, kind=state.kind, metadata=meta, **state.quality)


__all__ = ["GATES", "Checkpoint", "Gate", "rejection"]
