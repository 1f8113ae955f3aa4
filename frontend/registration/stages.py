"""The stages of :meth:`TexturedSurfaceRegistrar.register` up to the joint information. Each is
an object built from the registration config (holding its own caches), whose ``run`` takes typed
inputs and returns a frozen result:

1. :class:`KeypointMatching`: keypoints on both textures, descriptor matches, sensor-fixed ones
   dropped (its :class:`FeatureCache` describes each frame once);
2. :class:`MatchLifting`: the matches lifted to 3D through both ``xyz_map`` s;
3. :class:`KeypointRansac`: ``T_target_source`` from the 3D matches (:class:`KeypointPose`);
4. :class:`IcpStage`: ICP (a :class:`~frontend.registration.aligner.PointCloudAligner`) from
   RANSAC's pose on coarse then, if needed, fine voxels (its :class:`FrameClouds` voxelise each
   frame once per voxel size);
5. :class:`WeakDirectionStage`: directions ICP cannot be trusted along, from the keypoints;
6. :class:`JointInformationStage`: ICP's and the keypoints' information, and the joint optimum
   when ICP drifted along its flat directions.

A result's ``metadata`` holds the constraint metadata the stage reports, in the order written.
"""

from __future__ import annotations

import enum
import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import FppError
from fpp_graph.geometry import se3_exp
from fpp_graph.types import Frame
from frontend.config import RegistrationConfig, chi2_quantile
from frontend.features.detect import (
    MATCH_RATIO,
    Detector,
    detect_and_describe,
    feature_signature,
    make_detector,
    match_descriptors,
)
from frontend.organised_surface import lift_keypoints
from frontend.registration.aligner import AlignmentRequest, PointCloudAligner
from frontend.registration.icp import (
    ICP_MAX_ITERATIONS,
    ICP_MIN_VOXELS,
    IcpBasin,
    IcpCloud,
    IcpResult,
    information_from_icp,
    measure_alignment,
    organised_subsample,
    prepare_icp_cloud,
)
from frontend.registration.keypoints import (
    KEYPOINT_INFORMATION_SCALE,
    RANSAC_CONFIDENCE,
    RANSAC_MAX_ITERATIONS,
    RansacResult,
    drop_sensor_fixed_matches,
    information_from_keypoints,
    keypoint_inliers,
    ransac_rigid,
)
from frontend.registration.state import PairFrames, StageTimer
from frontend.registration.weak_directions import (
    DEGENERACY_RATIO,
    JOINT_OPTIMUM_PROBABILITY,
    PLANE_DISAGREEMENT_PROBABILITY,
    Degeneracy,
    check_degeneracy,
    disagreement_along,
    joint_keypoint_step,
    plane_directions,
    weak_directions_from,
    without_weak_directions,
)

Array = NDArray[np.float64]

# ---------------------------------------------------------------------------------------------
# 1-3: features, matching, lifting, RANSAC
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class KeypointMatches:
    """Descriptor matches of a pair: ``matches`` (M, 2) rows ``(target keypoint, source keypoint)``
    without the sensor-fixed ones (``sensor_fixed_dropped`` of them), every keypoint of each frame
    (pixels), and ``error``: why detection or matching failed (the arrays are then empty)."""

    matches: NDArray[np.int64]
    keypoints_uv_target: Array
    keypoints_uv_source: Array
    sensor_fixed_dropped: int = 0
    error: str | None = None

    @property
    def count(self) -> int:
        return int(self.matches.shape[0])

    @property
    def metadata(self) -> dict[str, Any]:
        return {"matches": self.count, "sensor_fixed_matches_dropped": self.sensor_fixed_dropped}


class FeatureCache:
    """Each frame's keypoints and descriptors of the configured type, computed once per frame
    object (weakly held: a frame in several pairs is described once)."""

    def __init__(self, config: RegistrationConfig):
        self.config = config
        self.signature = feature_signature(config)
        self._detector: Detector | None = None
        self._described: weakref.WeakKeyDictionary[Frame, Frame] = weakref.WeakKeyDictionary()

    def describe(self, frame: Frame) -> Frame:
        """The frame with keypoints/descriptors (cached)."""
        cached = self._described.get(frame)
        if cached is not None:
            return cached
        if frame.keypoints_uv is not None and frame.metadata.get("feature_signature") == self.signature:
            # already described: nothing to cache (a WeakKeyDictionary holding the frame as its
            # own value would keep every frame alive for the cache's lifetime)
            return frame
        if self._detector is None:
            self._detector = make_detector(self.config)
        described = detect_and_describe(frame, self.config, self._detector)
        self._described[frame] = described
        return described


class KeypointMatching:
    """Stage 1: keypoints of both frames and their matches (ratio test :data:`MATCH_RATIO`, mutual
    check), without the projector's sensor-fixed features."""

    def __init__(self, config: RegistrationConfig):
        self.features = FeatureCache(config)

    def run(self, pair: PairFrames, timer: StageTimer) -> KeypointMatches:
        empty = np.zeros((0, 2))
        try:
            with timer.timed("features"):
                described_target, described_source = self.features.describe(pair.target), self.features.describe(pair.source)
            with timer.timed("match"):
                matches = match_descriptors(described_target.descriptors, described_source.descriptors, MATCH_RATIO, True)
        except FppError as exc:
            return KeypointMatches(np.zeros((0, 2), np.int64), empty, empty, error=str(exc))
        uv_target, uv_source = described_target.keypoints_uv, described_source.keypoints_uv
        matches, dropped = drop_sensor_fixed_matches(matches, uv_target, uv_source, pair.target.texture.shape[1])
        return KeypointMatches(matches, uv_target, uv_source, dropped)


@dataclass(frozen=True, eq=False)
class LiftedMatches:
    """The matches whose keypoints both have a 3D point (sensor frames, metres), with the keypoint
    indices behind each row (``matches``)."""

    points_target_m: Array
    points_source_m: Array
    matches: NDArray[np.int64]

    @property
    def count(self) -> int:
        return int(self.points_target_m.shape[0])


class MatchLifting:
    """Stage 2: :func:`~frontend.organised_surface.lift_keypoints` on both sides (depth edges from
    the noise model: ``lengths.keypoint_edge_step_m``); rows valid in both kept."""

    def __init__(self, config: RegistrationConfig):
        self.edge_m = config.lengths.keypoint_edge_step_m

    def run(self, pair: PairFrames, matched: KeypointMatches) -> LiftedMatches:
        m = matched.matches
        P_target, valid_target = lift_keypoints(pair.target.xyz_map, matched.keypoints_uv_target[m[:, 0]], self.edge_m)
        P_source, valid_source = lift_keypoints(pair.source.xyz_map, matched.keypoints_uv_source[m[:, 1]], self.edge_m)
        ok = valid_target & valid_source
        return LiftedMatches(P_target[ok], P_source[ok], m[ok])


@dataclass(frozen=True, eq=False)
class KeypointPose:
    """RANSAC's pose from the lifted matches: the start of ICP and the keypoints' basin."""

    lifted: LiftedMatches
    ransac: RansacResult

    @property
    def T_target_source(self) -> Array:
        return self.ransac.T_target_source

    @property
    def inliers_source_m(self) -> Array:
        """RANSAC's inliers (source frame, metres)."""
        return self.lifted.points_source_m[self.ransac.inliers]

    def metadata(self, feature: str) -> dict[str, Any]:
        ransac = self.ransac
        return {"matches_3d": self.lifted.count, "ransac_inliers": ransac.num_inliers, "ransac_iterations": ransac.iterations,
                "ransac_rmse_m": ransac.inlier_rmse_m, "T_ransac": ransac.T_target_source, "feature": feature}


class KeypointRansac:
    """Stage 3: closed-form (Kabsch) RANSAC on the lifted matches, seeded per pair so results do not
    depend on pair order; a pose guess is scored as one more hypothesis."""

    def __init__(self, config: RegistrationConfig, seed: int):
        self.inlier_m, self.seed = config.lengths.ransac_inlier_m, seed

    def run(self, pair: PairFrames, lifted: LiftedMatches) -> KeypointPose:
        rng = np.random.default_rng([self.seed, pair.source.id & 0xFFFFFFFF, pair.target.id & 0xFFFFFFFF])
        extra = [np.asarray(pair.T_guess, dtype=np.float64)] if pair.T_guess is not None else None
        ransac = ransac_rigid(lifted.points_target_m, lifted.points_source_m, self.inlier_m, RANSAC_MAX_ITERATIONS, RANSAC_CONFIDENCE, rng, extra)
        return KeypointPose(lifted, ransac)


def _quality(icp: IcpResult | None, inlier_count: int) -> dict[str, Any]:
    """The constraint's quality figures: RANSAC's inlier count and ICP's correspondences (if any)."""
    if icp is None:
        return {"inlier_count": inlier_count}
    return {"fitness": icp.fitness, "inlier_rmse_m": icp.inlier_rmse_m, "inlier_count": inlier_count, "overlap": icp.overlap}


# ---------------------------------------------------------------------------------------------
# 4: ICP
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class IcpOutcome:
    """ICP from RANSAC's pose: its result (None when a cloud had fewer than ``ICP_MIN_VOXELS``:
    ``too_few_voxels`` = (target voxels, source voxels, voxel_m)), the clouds and voxel size of the
    last run, whether the coarse voxels read as a plane and ICP was redone on the fine ones
    (``coarse_plane_like``) or was not, its coarse run sliding unconverged (``fine_skipped``), and its
    information at its pose (``information_raw``, None when it diverged) with its ``degeneracy``."""

    icp: IcpResult | None
    target_cloud: IcpCloud | None
    source_cloud: IcpCloud | None
    voxel_m: float | None
    coarse_plane_like: bool = False
    too_few_voxels: tuple[int, int, float] | None = None
    information_raw: Array | None = None
    degeneracy: Degeneracy | None = None
    fine_skipped: bool = False

    @property
    def metadata(self) -> dict[str, Any]:
        meta: dict[str, Any] = {}
        if self.voxel_m is not None:
            meta["icp_voxel_m"] = self.voxel_m
        if self.coarse_plane_like:
            meta["coarse_icp_plane_like"] = True
        if self.fine_skipped:
            meta["fine_icp_skipped"] = "coarse ICP on a plane did not converge"
        if self.icp is not None:
            icp = self.icp
            meta.update({"T_icp": icp.T_target_source, "icp_iterations": icp.iterations, "icp_converged": icp.converged, "icp_correspondences": icp.num_correspondences})
        return meta

    def quality(self, inlier_count: int) -> dict[str, Any]:
        return _quality(self.icp, inlier_count)


class FrameClouds:
    """Each frame's voxel-downsampled ICP cloud per voxel size (weakly held per frame: a frame in
    several pairs is voxelised, and its KD-trees and covariances made, once)."""

    def __init__(self) -> None:
        self._clouds: weakref.WeakKeyDictionary[Frame, dict[float, IcpCloud]] = weakref.WeakKeyDictionary()

    def cloud(self, frame: Frame, voxel_m: float) -> IcpCloud:
        per_frame = self._clouds.setdefault(frame, {})
        cached = per_frame.get(voxel_m)
        if cached is None:
            pts = organised_subsample(frame.xyz_map, voxel_m) if frame.xyz_map is not None else frame.points
            cached = prepare_icp_cloud(pts, voxel_m)
            per_frame[voxel_m] = cached
        return cached


class IcpStage:
    """Stage 4: ICP from RANSAC's pose, on coarse voxels (``ICP_COARSE_VOXELS`` of the noise
    model's) when the dense refinement follows.

    With the dense refinement on, ICP only has to reach its basin and tell relief from a plane,
    which coarser voxels do at a fraction of the cost. A plane to ICP (three weak directions)
    skips the dense stage and keeps ICP's pose, so it is redone on the fine voxels, unless the
    texture sets the plane's directions (``texture_sets_planes``: the dense fit then gives the
    tilts and the texture the rest), or unless the coarse ICP had not converged (``fine_skipped``:
    it was sliding along the plane, and the fine voxels would too). ICP stops once it has moved
    one of RANSAC's inliers further than ``lengths.max_icp_shift_m`` and is not slowing down
    (:class:`~frontend.registration.icp.IcpBasin`).
    """

    def __init__(self, config: RegistrationConfig, aligner: PointCloudAligner, texture_sets_planes: bool):
        lengths = config.lengths
        self.aligner, self.texture_sets_planes, self.lengths = aligner, texture_sets_planes, lengths
        dense_follows = config.dense.enabled and lengths.icp_coarse_voxel_m > lengths.icp_voxel_m
        self.voxels_m = [lengths.icp_coarse_voxel_m, lengths.icp_voxel_m] if dense_follows else [lengths.icp_voxel_m]
        self.clouds = FrameClouds()

    def run(self, pair: PairFrames, start: KeypointPose, timer: StageTimer) -> IcpOutcome:
        lengths = self.lengths
        timer.zero("icp_prepare", "icp")
        ran_voxel_m: float | None = None
        coarse_plane_like = fine_skipped = False
        basin = IcpBasin(np.asarray(start.inliers_source_m, dtype=np.float64).reshape(-1, 3), lengths.max_icp_shift_m)
        request = AlignmentRequest(start.T_target_source, lengths.icp_max_correspondence_m, ICP_MAX_ITERATIONS, lengths.icp_convergence_m, basin)
        for voxel in self.voxels_m:
            started = timer.start()
            tcloud, scloud = self.clouds.cloud(pair.target, voxel), self.clouds.cloud(pair.source, voxel)
            # KD-trees, normals, covariances of the ICP subsets (lazy, kept for the frame's next pairs)
            _ = (tcloud.target, scloud.source)
            timer.stop("icp_prepare", started, accumulate=True)
            if min(tcloud.size, scloud.size) < ICP_MIN_VOXELS:
                return IcpOutcome(None, tcloud, scloud, ran_voxel_m, coarse_plane_like, (tcloud.size, scloud.size, voxel))
            started = timer.start()
            icp = self.aligner.align(tcloud, scloud, request)
            timer.stop("icp", started, accumulate=True)
            ran_voxel_m = voxel
            if not np.all(np.isfinite(icp.T_target_source)):
                return IcpOutcome(icp, tcloud, scloud, voxel, coarse_plane_like)  # rejected by the gates
            info_raw = information_from_icp(icp, scale=lengths.icp_information_scale)
            degeneracy = check_degeneracy(info_raw, icp.source_points, DEGENERACY_RATIO)
            if voxel == lengths.icp_voxel_m or not degeneracy.plane_like or self.texture_sets_planes:
                break
            if not icp.converged:
                # A plane whose coarse ICP still moves at its iteration bound is sliding along
                # itself toward more overlap (a view that barely shares the plane); the fine
                # voxels slide the same way at 4-5x the cost. The coarse pose goes to the gates,
                # which judge it as they would the fine one: the plane's in-plane directions are
                # the keypoints' either way.
                fine_skipped = True
                break
            coarse_plane_like = True
        return IcpOutcome(icp, tcloud, scloud, ran_voxel_m, coarse_plane_like, None, info_raw, degeneracy, fine_skipped)


# ---------------------------------------------------------------------------------------------
# 5: weak directions from the keypoints
# ---------------------------------------------------------------------------------------------
class WeakRule(enum.Enum):
    """Which directions of ICP's pose were replaced from the keypoints."""

    NONE = "none"
    """ICP's pose kept in every direction."""
    PLANE = "plane"
    """A plane's in-plane shifts and spin, at the keypoints' optimum given ICP's normal shift and tilts."""
    FLAT_FROM_RANSAC = "flat from RANSAC"
    """ICP lost the keypoints on weak geometry: its flat directions from RANSAC's pose."""


@dataclass(frozen=True, eq=False)
class WeakDirectionOutcome:
    """The pose after the weak-direction rules: ICP's correspondences measured there (``icp``), the
    ``rule`` applied and the ``directions`` taken from the keypoints (None with :attr:`WeakRule.NONE`),
    ``|P_target - T P_source|`` of every lifted match and how many are within RANSAC's distance, and
    ``shift_m``: the largest move of RANSAC's inliers from RANSAC's pose (ICP left its basin when large)."""

    T_target_source: Array
    icp: IcpResult
    rule: WeakRule
    directions: Degeneracy | None
    keypoint_residuals_m: Array
    keypoint_inliers: int
    shift_m: float
    metadata: dict[str, Any] = field(repr=False)

    def quality(self, inlier_count: int) -> dict[str, Any]:
        return _quality(self.icp, inlier_count)


def _keypoint_fit(T: Array, start: KeypointPose, threshold_m: float) -> tuple[float, Array, NDArray[np.bool_]]:
    """(shift of RANSAC's inliers from RANSAC's pose, residual of every match, residual below threshold) at ``T``."""
    lifted, Ps_in, T_r = start.lifted, start.inliers_source_m, start.T_target_source
    shift = np.linalg.norm((Ps_in @ T[:3, :3].T + T[:3, 3]) - (Ps_in @ T_r[:3, :3].T + T_r[:3, 3]), axis=1)
    residuals = np.linalg.norm(lifted.points_target_m - (lifted.points_source_m @ T[:3, :3].T + T[:3, 3]), axis=1)
    return (float(shift.max()) if shift.size else 0.0), residuals, residuals < threshold_m


class WeakDirectionStage:
    """Stage 5: ICP's pose, with the directions ICP cannot be trusted along taken from the keypoints.

    ICP's information there is dropped later (normal scatter makes it claim a fraction of the
    point noise in-plane on a plane, which is not information about the pose):

    - plane-like pairs (two or more weak ICP directions: a wall, an object on a big table) whose
      ICP pose disagrees with the keypoints in the plane (chi-square, 3 dof,
      :data:`~frontend.registration.weak_directions.PLANE_DISAGREEMENT_PROBABILITY`, under the
      keypoints' covariance given ICP's other directions), or whose in-plane directions the
      texture sets: the in-plane shifts and the spin about the normal go to the keypoints'
      optimum given ICP's normal shift and tilts. On a plane GICP slides along faint relief and
      the decoder's texture-correlated ripple, while the keypoints see the texture; where the two
      agree ICP's pose is kept: on relief it is the more precise.
    - otherwise, when ICP lost the keypoints on weak geometry (drifted along its flat directions
      rather than a wrong pair): those flat directions from RANSAC's pose.

    The new pose is kept only if it stays in RANSAC's basin with enough keypoint inliers; its
    correspondences are measured there (the aligner with no iteration).
    """

    def __init__(self, config: RegistrationConfig, texture_sets_planes: bool):
        self.lengths, self.min_inliers, self.texture_sets_planes = config.lengths, config.gates.min_inliers, texture_sets_planes

    def _candidate(self, start: KeypointPose, icp: IcpOutcome, lost_keypoints: bool) -> tuple[Degeneracy | None, WeakRule, dict[str, Any]]:
        """The directions to take from the keypoints, if any."""
        fit, deg_icp, ransac = icp.icp, icp.degeneracy, start.ransac
        meta: dict[str, Any] = {}
        if len(deg_icp.unconstrained) >= 2:
            Ps_in = start.inliers_source_m
            plane = plane_directions(icp.information_raw, fit.source_points)
            meta["plane_spin_ratio"] = float(plane.eigenvalue_ratios[2])
            info_keypoints = KEYPOINT_INFORMATION_SCALE * information_from_keypoints(ransac.T_target_source, Ps_in, np.full(Ps_in.shape[0], ransac.inlier_rmse_m))
            m2 = disagreement_along(fit.T_target_source, ransac.T_target_source, info_keypoints, plane, fit.source_points)
            meta["plane_keypoint_mahalanobis2"] = m2
            # (with the rig's texture camera the texture sets the plane's directions later: always)
            if m2 > chi2_quantile(PLANE_DISAGREEMENT_PROBABILITY, 3) or lost_keypoints or self.texture_sets_planes:
                return plane, WeakRule.PLANE, meta
        if lost_keypoints and deg_icp.degenerate:
            return deg_icp, WeakRule.FLAT_FROM_RANSAC, meta
        return None, WeakRule.NONE, meta

    def run(self, start: KeypointPose, icp: IcpOutcome) -> WeakDirectionOutcome:
        lengths, fit, lifted = self.lengths, icp.icp, start.lifted
        T = fit.T_target_source
        shift_m, residuals, agree = _keypoint_fit(T, start, lengths.ransac_inlier_m)
        kp_inliers = int(np.sum(agree))
        meta: dict[str, Any] = {"icp_shift_m": shift_m, "keypoint_inliers_after_icp": kp_inliers, "matches_used": lifted.matches[agree]}
        meta["icp_eigenvalue_ratios"] = icp.degeneracy.eigenvalue_ratios
        lost_keypoints = shift_m > lengths.max_icp_shift_m or kp_inliers < self.min_inliers
        weak, rule, candidate_meta = self._candidate(start, icp, lost_keypoints)
        meta.update(candidate_meta)
        if weak is not None:
            if rule is WeakRule.FLAT_FROM_RANSAC:
                T_new = weak_directions_from(T, start.T_target_source, weak, fit.source_points)
            else:
                # the keypoints' optimum given ICP's normal shift and tilts (RANSAC's own in-plane
                # estimate carries its tilt error through the lever arm of a narrow overlap strip)
                info_rest = without_weak_directions(icp.information_raw, weak, fit.source_points)
                step = joint_keypoint_step(T, info_rest, start.inliers_source_m, lifted.points_target_m[start.ransac.inliers], iterations=5)
                T_new = T @ se3_exp(step)
            shift_new_m, residuals_new, agree_new = _keypoint_fit(T_new, start, lengths.ransac_inlier_m)
            if shift_new_m <= lengths.max_icp_shift_m and int(np.sum(agree_new)) >= self.min_inliers:
                remeasured = measure_alignment(icp.target_cloud, icp.source_cloud, np.asarray(T_new, dtype=np.float64).copy(), True, 0,
                                               lengths.icp_max_correspondence_m)
                kp_inliers_new = int(np.sum(agree_new))
                meta.update({"icp_shift_m": shift_new_m, "weak_directions_from_keypoints": weak.unconstrained, "icp_drift_m": shift_m})
                meta.update({"keypoint_inliers_after_icp": kp_inliers_new, "matches_used": lifted.matches[agree_new]})
                return WeakDirectionOutcome(T_new, remeasured, rule, weak, residuals_new, kp_inliers_new, shift_new_m, meta)
        return WeakDirectionOutcome(T, fit, WeakRule.NONE, None, residuals, kp_inliers, shift_m, meta)


# ---------------------------------------------------------------------------------------------
# 6: information
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """A pose and its information, ``[rot, trans]``: the geometry's (ICP's or the dense fit's, without
    the directions taken from the keypoints), the keypoints' raw one (the gates judge it raw, the
    constraint carries it scaled), their sum (what the gates judge) and its degeneracy."""

    T_target_source: Array
    information_geometry: Array
    information_keypoints: Array
    information: Array
    degeneracy: Degeneracy


@dataclass(frozen=True, eq=False)
class KeypointTerm:
    """The keypoints' point-to-point term at any pose: all lifted matches, the inliers chosen at the
    weak-direction stage's pose, and the source points behind the geometry's information (the
    degeneracy test's centroid and radius)."""

    points_target_m: Array
    points_source_m: Array
    inliers: NDArray[np.bool_]
    support_points_m: Array
    degeneracy_ratio: float

    def at(self, T_target_source: Array, information_geometry: Array) -> PoseEstimate:
        """The keypoints' information at ``T_target_source``, the joint information and its degeneracy."""
        T = T_target_source
        residuals = np.linalg.norm(self.points_target_m - (self.points_source_m @ T[:3, :3].T + T[:3, 3]), axis=1)
        info_keypoints = information_from_keypoints(T, self.points_source_m[self.inliers], residuals[self.inliers])
        joint = information_geometry + info_keypoints
        return PoseEstimate(T, information_geometry, info_keypoints, joint, check_degeneracy(joint, self.support_points_m, self.degeneracy_ratio))


@dataclass(frozen=True, eq=False)
class InformationOutcome:
    pose: PoseEstimate
    keypoints: KeypointTerm
    metadata: dict[str, Any] = field(repr=False)


class JointInformationStage:
    """Stage 6: ICP's information at the final pose plus the keypoints'.

    Where the dense geometry is weak (an object on a big table plane, a wall), ICP's cost is
    flat: the keypoints' point-to-point information constrains exactly those directions. ICP can
    drift along them while the information claims the keypoints pin them. When ICP's pose is
    inconsistent with the joint optimum of ICP's and the keypoints' costs (chi-square, 6 dof,
    :data:`~frontend.registration.weak_directions.JOINT_OPTIMUM_PROBABILITY`), move there and take
    the information there; otherwise keep ICP's pose, which on relief is the more precise.
    """

    def __init__(self, config: RegistrationConfig):
        self.lengths = config.lengths

    def run(self, lifted: LiftedMatches, icp: IcpOutcome, weak: WeakDirectionOutcome) -> InformationOutcome:
        lengths = self.lengths
        # ICP's information at the final pose: the one computed by ICP unless the pose moved
        info_icp = icp.information_raw
        if weak.directions is not None:
            info_icp = without_weak_directions(information_from_icp(weak.icp, scale=lengths.icp_information_scale), weak.directions, weak.icp.source_points)
        inliers = keypoint_inliers(weak.keypoint_residuals_m, lengths.ransac_inlier_m)
        term = KeypointTerm(lifted.points_target_m, lifted.points_source_m, inliers, weak.icp.source_points, DEGENERACY_RATIO)
        T = weak.T_target_source
        pose = term.at(T, info_icp)
        meta: dict[str, Any] = {}
        if pose.degeneracy.degenerate and weak.directions is None:
            step = joint_keypoint_step(T, info_icp, lifted.points_source_m[inliers], lifted.points_target_m[inliers])
            m2 = float(step @ pose.information @ step)
            meta["joint_keypoint_step"] = step
            meta["joint_keypoint_step_mahalanobis2"] = m2
            if m2 > chi2_quantile(JOINT_OPTIMUM_PROBABILITY, 6):
                meta["moved_to_joint_optimum"] = True
                pose = term.at(T @ se3_exp(step), info_icp)
        return InformationOutcome(pose, term, meta)
