"""Frame-to-keyframe tracking from a motion prediction: the dense fit alone.

A 30 Hz camera moves a few millimetres and a fraction of a degree between frames, so a
constant-velocity prediction already lies inside the basin of the dense point-to-plane fit
(:func:`frontend.dense_alignment.align_dense`, projective association on the organised maps).
Keypoints, RANSAC and ICP are there to find a pose without a guess; with a good guess they are
the expensive part of a pair (about 80 % of it on 640x480 RGB-D frames). :class:`DenseTracker`
refines the prediction densely and accepts the result only where the dense fit alone can be
trusted; any other outcome is a rejected constraint with its reason, and the keyframe manager
then registers the frame the full way (the prediction joins RANSAC as one more hypothesis).

Gates (each a measured property of the fit, thresholds from the sensor's noise model):

* the dense fit raised or returned a non-finite pose;
* directions the geometry leaves nearly free (a wall's in-plane shifts and spin, a long hall's
  axis: :func:`~frontend.registration.weak_directions.check_degeneracy` with
  ``DEGENERACY_RATIO``) are taken from the keypoints as a full registration
  takes them (the dense fit alone keeps the prediction's error there: nothing in the geometry
  corrects it). The keyframe's keypoints are followed into the frame by
  Lucas-Kanade from the dense pose's prediction, so the frame itself is never described
  (SURF on a 640x480 frame costs about what tracking it does); rejected when too few followed
  keypoints agree with the dense pose or they leave a direction above
  ``lengths.max_weak_sigma_m`` (the full registration's gate);
* the correction moved the source points (RMS) further than the correspondence gate
  (``lengths.icp_max_correspondence_m``): the prediction was outside the basin the initial
  association assumes (RMS, not the largest motion: a 1 degree turn misjudged moves a point 3 m
  away by 5 cm while the view as a whole stays inside the gate);
* the residuals' robust sigma above ``lengths.max_inlier_rmse_m`` (the surfaces do not fit);
* fewer correspondences than ``gates.min_overlap`` of the pixels sampled from both views.
"""

from __future__ import annotations

import dataclasses
import logging
import weakref
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import FppError
from fpp_graph.geometry import invert, se3_exp, transform_points
from fpp_graph.types import Constraint, ConstraintKind, Frame
from frontend.config import RegistrationConfig
from frontend.dense_alignment import (
    DENSE_INFORMATION_SCALE,
    DenseAlignment,
    DenseSchedule,
    align_dense,
)
from frontend.organised_surface import OrganisedSurface, lift_keypoints
from frontend.registration.icp import with_shared_error_floor
from frontend.registration.keypoints import (
    KEYPOINT_INFORMATION_SCALE,
    information_from_keypoints,
    keypoint_inliers,
)
from frontend.registration.weak_directions import (
    DEGENERACY_RATIO,
    Degeneracy,
    check_degeneracy,
    joint_keypoint_step,
    weak_direction_sigma_m,
    without_weak_directions,
)

if TYPE_CHECKING:
    from frontend.registration.refinement import FrameSurfaces
    from frontend.registration.stages import FeatureCache

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


class DenseTracker:
    """``T_target_source`` refined densely from a motion prediction, or a rejected constraint
    saying why (the registrar's ``track``).

    Parameters
    ----------
    config : RegistrationConfig
        The noise model's ``lengths`` and stride, ``gates``.
    surfaces : FrameSurfaces
        The dense stage's organised maps (shared: a frame is prepared once).
    features : FeatureCache
        The matching stage's keypoints (shared: a keyframe is described once).
    """

    def __init__(self, config: RegistrationConfig, surfaces: FrameSurfaces, features: FeatureCache):
        self.config, self.surfaces, self.features = config, surfaces, features

    def track(self, target: Frame, source: Frame, T_predicted: NDArray[np.float64]) -> Constraint:
        """``target``, ``source`` need ``xyz_map`` (and texture keypoints where the geometry is
        weak); ``T_predicted`` is the predicted ``T_target_source`` (e.g. constant velocity).

        Returns an ODOMETRY constraint, ``metadata["tracked"] = True``; information: the dense
        fit's (scaled by ``DENSE_INFORMATION_SCALE``) plus the keypoints' where they set weak
        directions, with the views' shared depth error added, as a full registration's."""
        config = self.config
        T0 = _nearest_rigid(T_predicted)

        def rejected(reason: str) -> Constraint:
            log.debug("frame %d: tracking against %d rejected: %s", source.id, target.id, reason)
            return Constraint.rejected(source.id, target.id, f"tracking: {reason}", kind=ConstraintKind.ODOMETRY, metadata={"tracked": True})

        if target.xyz_map is None or source.xyz_map is None:
            return rejected("a frame has no xyz_map")
        fits = _DenseFits.of(self.surfaces.surface(target), self.surfaces.surface(source), config)
        try:
            dense = fits.from_prediction(T0)
        except FppError as exc:
            return rejected(f"dense fit failed ({exc})")
        if problem := _fit_problem(dense, T0, config):
            return rejected(problem)
        information, meta = DENSE_INFORMATION_SCALE * dense.information, {}
        degeneracy = check_degeneracy(dense.information, dense.source_points, DEGENERACY_RATIO)
        if degeneracy.degenerate:
            held = self._hold_weak_directions(target, source, dense, degeneracy, T0, fits)
            if isinstance(held, str):
                return rejected(held)
            dense, information, meta = held
        information = with_shared_error_floor(information, dense.source_points, config.sensor_noise().shared_depth_sigma_per_m2)
        T = dense.T_target_source
        return Constraint(
            source_id=source.id, target_id=target.id, T_target_source=T, information=information, kind=ConstraintKind.ODOMETRY,
            fitness=dense.overlap, inlier_rmse_m=dense.sigma_m, inlier_count=dense.num_residuals, overlap=dense.overlap,
            metadata={"tracked": True, "dense_iterations": dense.iterations, "dense_sigma_m": dense.sigma_m,
                      "tracking_correction_m": rms_motion_m(T, T0, dense.source_points),
                      "unconstrained_directions": list(degeneracy.unconstrained), **meta},
        )

    def _hold_weak_directions(
        self, target: Frame, source: Frame, dense: DenseAlignment, degeneracy: Degeneracy, T0: Array, fits: _DenseFits,
    ) -> tuple[DenseAlignment, Array, dict] | str:
        """The dense fit again from the keypoints' pose for the weak directions (:meth:`_keypoint_step`)
        with the keypoints as the prior, as a full registration's dense stage: the relief outweighs
        them where it has any (a table's objects), they hold the directions it leaves free (a
        long hall's axis). Returns that fit, its information (with the prior) and metadata, or why not."""
        config = self.config
        weak = "; ".join(degeneracy.unconstrained)
        step = self._keypoint_step(target, source, dense, degeneracy)
        if isinstance(step, str):
            return f"degenerate geometry (unconstrained {weak}) and {step}"
        T_keypoints, information_keypoints, meta = step
        prior = KEYPOINT_INFORMATION_SCALE * information_keypoints
        try:
            held = fits.whole(T_keypoints, prior)
        except FppError as exc:
            return f"dense fit from the keypoints' pose failed ({exc})"
        if problem := _fit_problem(held, T0, config):
            return problem
        information = DENSE_INFORMATION_SCALE * held.information + prior
        weak_sigma_m = weak_direction_sigma_m(information, degeneracy, held.source_points)
        max_sigma_m = config.lengths.max_weak_sigma_m
        if not weak_sigma_m <= max_sigma_m:
            return f"degenerate geometry (unconstrained {weak}; sigma {1e3 * weak_sigma_m:.1f} mm > {1e3 * max_sigma_m:.1f} mm even with keypoints)"
        return held, information, meta

    def _keypoint_step(self, target: Frame, source: Frame, dense: DenseAlignment, degeneracy: Degeneracy) -> tuple[Array, Array, dict] | str:
        """The weak directions from the keyframe's keypoints, as a full registration sets them (the
        weak-direction stage of :mod:`frontend.registration`): correspondences the dense pose
        explains within the correspondence gate (it may be off along a weak direction by the
        prediction's error), then the keypoints' optimum given the dense fit's other directions
        (:func:`joint_keypoint_step` on the dense information without the weak directions: with
        them, the fit's slight curvature there would hold the axis at the prediction's error).

        The correspondences are the keyframe's keypoints followed into the frame
        (:meth:`_followed_keypoints`), not keypoints detected in the frame and matched by
        descriptor: the frame needs no detector, and a tracked frame costs no description.
        Returns the pose, the keypoints' information (unscaled) and metadata, or why the keypoints
        cannot do it."""
        config, T = self.config, dense.T_target_source
        min_inliers = config.gates.min_inliers
        followed = self._followed_keypoints(self.features.describe(target), source, T)
        if isinstance(followed, str):
            return followed
        P, Q = followed
        near = np.linalg.norm(transform_points(T, P) - Q, axis=1) < config.lengths.icp_max_correspondence_m
        if int(near.sum()) < min_inliers:
            return f"too few keypoints agree with the dense pose ({int(near.sum())} < {min_inliers})"
        information_rest = without_weak_directions(DENSE_INFORMATION_SCALE * dense.information, degeneracy, dense.source_points)
        T = T @ se3_exp(joint_keypoint_step(T, information_rest, P[near], Q[near], iterations=5))
        residuals_m = np.linalg.norm(transform_points(T, P[near]) - Q[near], axis=1)
        keep = keypoint_inliers(residuals_m, config.lengths.ransac_inlier_m)
        if int(keep.sum()) < min_inliers:
            return f"too few keypoint inliers ({int(keep.sum())} < {min_inliers})"
        information_keypoints = information_from_keypoints(T, P[near][keep], residuals_m[keep])
        return T, information_keypoints, {"tracking_keypoint_inliers": int(keep.sum()), "tracking_keypoints_followed": len(P)}

    def _followed_keypoints(self, target: Frame, source: Frame, T_target_source: Array) -> tuple[Array, Array] | str:
        """``(P_source, Q_target)``: the keyframe's keypoints (3D, target frame) and where they are in
        the frame, found by pyramidal Lucas-Kanade on the two textures from the dense pose's
        prediction of their pixels, and lifted through the frame's map.

        Lucas-Kanade refines a position to a fraction of a pixel from a start inside its window; the
        dense pose is off only along the weak directions, by the motion prediction's error (a few
        pixels). A keypoint the flow loses, or that lands off the frame's surface (no depth, a depth
        edge), is left out; mismatches that remain are the geometric gates' to cut, as after
        descriptor matching (window and pyramid: :data:`FOLLOW_WINDOW_PX`, :data:`FOLLOW_LEVELS`)."""
        if target.keypoints_uv is None or len(target.keypoints_uv) == 0:
            return "the keyframe has no keypoints"
        if target.texture is None or source.texture is None:
            return "a frame has no texture to follow keypoints on"
        config = self.config
        edge_m = config.lengths.keypoint_edge_step_m
        lifted = _lifted_keyframe_keypoints(target, edge_m)
        Q, uv_target = lifted.points_m, lifted.uv
        u, v = self.surfaces.surface(source).project(transform_points(invert(T_target_source), Q))
        predicted = np.stack([u, v], axis=1).astype(np.float32)
        H, W = source.texture.shape
        seen = np.all(np.isfinite(predicted), axis=1) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
        if int(seen.sum()) < config.gates.min_inliers:
            return f"too few keyframe keypoints in view ({int(seen.sum())} < {config.gates.min_inliers})"
        uv_source, status, _ = cv2.calcOpticalFlowPyrLK(
            target.texture, source.texture, uv_target[seen].reshape(-1, 1, 2), predicted[seen].reshape(-1, 1, 2).copy(),
            winSize=(FOLLOW_WINDOW_PX, FOLLOW_WINDOW_PX), maxLevel=FOLLOW_LEVELS, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        uv_source = uv_source.reshape(-1, 2)
        # Lucas-Kanade reports success wherever it converges, on sensor noise too (a bare wall's
        # keypoints are noise blobs that the next frame does not repeat); a window whose texture
        # is the scene's correlates with itself in the other view, noise does not: at zero-mean
        # normalised correlation 0.5 the shared texture's variance equals the noise's
        followed = status.ravel().astype(bool)
        keyframe_windows = tuple(w[seen][followed] for w in lifted.windows)
        followed[followed] = window_correlation(keyframe_windows, patch_windows(source.texture, uv_source[followed])) >= MIN_PATCH_CORRELATION
        P, on_surface = lift_keypoints(source.xyz_map, uv_source[followed], edge_m)
        return P[on_surface], Q[seen][followed][on_surface]


@dataclasses.dataclass(frozen=True, eq=False)
class _DenseFits:
    """The dense fits of one tracked pair, at the strides ``DENSE_MAX_POINTS`` leaves them."""

    target: OrganisedSurface
    source: OrganisedSurface
    schedule: DenseSchedule

    @classmethod
    def of(cls, target: OrganisedSurface, source: OrganisedSurface, config: RegistrationConfig) -> _DenseFits:
        schedule = DenseSchedule.of(config)
        coarse_px, fine_px = schedule.strides(target, source)
        return cls(target, source, dataclasses.replace(schedule, coarse_stride_px=coarse_px, fine_stride_px=fine_px, max_points=None))

    def _iterate(self, T_start: Array, stride_px: int, iterations: int, gate_m: float) -> DenseAlignment:
        """``iterations`` at one stride from the residual gate ``gate_m``."""
        return align_dense(self.target, self.source, T_start, DenseSchedule(stride_px, stride_px, 0, iterations, gate_m))

    def whole(self, T_start: Array, prior: Array | None = None) -> DenseAlignment:
        """The whole dense fit from ``T_start``: its coarse iterations, then its fine ones."""
        return align_dense(self.target, self.source, T_start, self.schedule, prior_information=prior)

    def from_prediction(self, T0: Array) -> DenseAlignment:
        """The whole fit from ``T0``, stopped after its coarse iterations where they already show
        weak directions: the fit is then redone from the keypoints' pose with them as its prior
        (:meth:`DenseTracker._hold_weak_directions`), and the fine iterations from the prediction,
        twice the cost of both coarse ones, would be thrown away. Otherwise the fine iterations go
        on with the gate the coarse ones left: the whole fit, bit for bit."""
        schedule = self.schedule
        if schedule.coarse_stride_px == schedule.fine_stride_px:
            return self.whole(T0)
        coarse = self._iterate(T0, schedule.coarse_stride_px, schedule.coarse_iterations, schedule.max_distance_m)
        if check_degeneracy(coarse.information, coarse.source_points, DEGENERACY_RATIO).degenerate:
            return coarse
        fine = self._iterate(coarse.T_target_source, schedule.fine_stride_px, schedule.fine_iterations, coarse.gate_m)
        return dataclasses.replace(fine, iterations=coarse.iterations + fine.iterations)


def _fit_problem(dense: DenseAlignment, T0: Array, config: RegistrationConfig) -> str | None:
    """Why the dense fit from the prediction ``T0`` cannot be used (None: it can)."""
    lengths = config.lengths
    if not np.all(np.isfinite(dense.T_target_source)):
        return "non-finite pose"
    correction_m = rms_motion_m(dense.T_target_source, T0, dense.source_points)
    if correction_m > lengths.icp_max_correspondence_m:
        return (f"far from the prediction (moved the points by {1e3 * correction_m:.1f} mm RMS > "
                f"{1e3 * lengths.icp_max_correspondence_m:.1f} mm correspondence gate)")
    if not dense.sigma_m <= lengths.max_inlier_rmse_m:
        return f"surfaces do not fit (residual sigma {1e3 * dense.sigma_m:.2f} mm > {1e3 * lengths.max_inlier_rmse_m:.2f} mm)"
    if dense.overlap < config.gates.min_overlap:
        return f"low overlap ({dense.overlap:.3f} < {config.gates.min_overlap})"
    return None


def _nearest_rigid(T: NDArray) -> Array:
    """``T`` with its rotation block replaced by the nearest rotation: a prediction composed from
    text-file poses (7-Scenes' 4x4s) can be off orthonormal by more than a Constraint admits,
    and the fit keeps what it is given."""
    out = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def _lifted_keyframe_keypoints(keyframe: Frame, edge_m: float) -> _LiftedKeypoints:
    """The keyframe's keypoints on its surface: their 3D points, pixels and texture windows, made
    once per keyframe and edge step (every frame tracked against it follows the same ones)."""
    cached = _LIFTED.get(keyframe)
    if cached is None or cached.edge_m != edge_m:
        Q, lifted = lift_keypoints(keyframe.xyz_map, keyframe.keypoints_uv, edge_m)
        uv = np.asarray(keyframe.keypoints_uv, dtype=np.float32)[lifted]
        cached = _LiftedKeypoints(edge_m, Q[lifted], uv, patch_windows(keyframe.texture, uv))
        _LIFTED[keyframe] = cached
    return cached


@dataclasses.dataclass(frozen=True)
class _LiftedKeypoints:
    edge_m: float
    points_m: Array  # (n, 3), keyframe frame
    uv: NDArray[np.float32]  # (n, 2) pixels
    windows: tuple[NDArray[np.float32], NDArray[np.float32]]  # patch_windows of the keyframe's texture at uv


_LIFTED: weakref.WeakKeyDictionary[Frame, _LiftedKeypoints] = weakref.WeakKeyDictionary()
"""Each described keyframe's lifted keypoints while it lives (frames are immutable)."""


# zero-mean normalised correlation of a followed keypoint's window between the two views below
# which the texture they share is weaker than their independent noise (SNR 1: rho = s / (s + n))
MIN_PATCH_CORRELATION = 0.5
# The window covers the support of SURF's smallest filter (9 x 9 px), the texture that made a
# keypoint; a wider one (OpenCV's default 21 px) adds pixels the keypoint does not depend on, at
# twice the cost (7-Scenes chess: 5.2 mm ATE either way).
FOLLOW_WINDOW_PX = 11
# Pyramid levels above the image: the search reaches 2^levels half-windows (+-20 px); the dense
# pose is off only along weak directions, by the motion prediction's error over one frame.
FOLLOW_LEVELS = 2


def patch_windows(image: NDArray, uv: NDArray, window_px: int = FOLLOW_WINDOW_PX) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The zero-mean ``window_px`` square windows of ``image`` centred at ``uv`` (bilinear), one
    row each, and their squared norms: each row depends on its own point alone, so a keyframe's
    windows are made once and indexed for every frame that follows its keypoints."""
    half = (window_px - 1) / 2.0
    offsets = np.arange(window_px, dtype=np.float32) - np.float32(half)
    du, dv = np.meshgrid(offsets, offsets)
    uv = np.asarray(uv, dtype=np.float32)
    map_u = uv[:, 0, None] + du.ravel()[None, :]
    map_v = uv[:, 1, None] + dv.ravel()[None, :]
    patch = cv2.remap(image.astype(np.float32), map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    windows = patch - patch.mean(axis=1, keepdims=True)
    return windows, np.einsum("ij,ij->i", windows, windows)


def window_correlation(a: tuple[NDArray[np.float32], NDArray[np.float32]], b: tuple[NDArray[np.float32], NDArray[np.float32]]) -> NDArray[np.float32]:
    """Zero-mean normalised correlation of two sets of :func:`patch_windows`, row by row (0 for a flat window)."""
    (wa, aa), (wb, bb) = a, b
    norm = np.sqrt(aa * bb)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, np.einsum("ij,ij->i", wa, wb) / norm, 0.0).astype(np.float32)


def rms_motion_m(T_a: NDArray, T_b: NDArray, points: NDArray) -> float:
    """RMS distance between ``points`` moved by ``T_a`` and by ``T_b`` (0 without points)."""
    if not len(points):
        return 0.0
    d = transform_points(T_a, points) - transform_points(T_b, points)
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d))))


__all__ = ["DenseTracker", "rms_motion_m"]
