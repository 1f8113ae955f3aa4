"""The project's :class:`~fpp_graph.types.PairRegistrar` for FPP frames: :class:`FppPairRegistrar`."""

from __future__ import annotations

import dataclasses
import logging
import math
import weakref
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import FppError, InputDataError
from fpp_graph.geometry import invert
from fpp_graph.slam.frame_store import stored_xyz_map_float32
from fpp_graph.types import Constraint, ConstraintKind, Frame
from frontend.config import RegistrationConfig
from frontend.dense_alignment import (
    DenseAlignment,
    DenseEvaluation,
    align_dense,
    dense_strides,
    evaluate_dense,
)
from frontend.features.detect import Detector, detect_and_describe, feature_signature, make_detector
from frontend.organised_surface import OrganisedSurface
from frontend.registration.gates import Checkpoint, rejection
from frontend.registration.icp import (
    IcpCloud,
    organised_subsample,
    prepare_icp_cloud,
    with_shared_error_floor,
)
from frontend.registration.keypoints import RansacResult, ransac_rigid
from frontend.registration.refinement import (
    check_weak_geometry,
    dense_stage,
    photometric_applies,
    photometric_stage,
)
from frontend.registration.stages import (
    handle_weak_directions,
    joint_information,
    lift_matches,
    match_keypoints,
    ransac_metadata,
    run_icp,
)
from frontend.registration.state import PairState
from frontend.registration.texture import TextureCamera
from frontend.registration.tracking import track_dense
from frontend.registration.weak_directions import (
    Degeneracy,
    check_degeneracy,
    surface_is_plane_like,
    weak_direction_pin,
    weak_direction_sigma_m,
)

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from frontend.localization import ReferencePixels

PHOTOMETRIC_STOP_STEP_SIGMAS = 0.05
"""The photometric step stops refining a pair once its pose steps are under this many standard
deviations of the pair's constraint (its information times ``photometric.information_scale``).
Past that point the steps chase the texture's slowly converging gain, offset and ambient ratio
(a ratio of about 0.75 per step on simulated corridor walls), so what is left of the way is at
most about 3x the last step, 0.15 standard deviations: 2 % of the constraint's variance. On 13
simulated corridor pairs (with the coarse levels' rule, :data:`~frontend.localization.photometric.COARSE_STOP_STEP_PX`):
335 -> 126 Gauss-Newton steps, every pose within 0.09 standard deviations (0.75 um) of the one
converged to 1e-7."""


PREPARED_REFERENCE = "photometric_reference."
"""Name prefix of the photometric reference pixels :meth:`FppPairRegistrar.prepare` stores in
:attr:`~fpp_graph.types.Frame.prepared`."""


class FppPairRegistrar:
    """Keypoints + RANSAC + ICP registration of two FPP frames (implements ``PairRegistrar``).

    Keypoints and ICP clouds are cached per :class:`Frame` object (weakly), so a frame taking
    part in several pairs is described and voxelised once.

    Parameters
    ----------
    config : RegistrationConfig
    seed : int
        RANSAC sampling seed (results are reproducible).
    texture_camera : TextureCamera, optional
        The rig's camera and projector centre; enables the photometric refinement of plane-like
        pairs (``photometric.enabled``).
    """

    def __init__(self, config: RegistrationConfig | None = None, seed: int = 0, texture_camera: TextureCamera | None = None):
        self.config = config or RegistrationConfig()
        self.seed = seed
        self.texture_camera = texture_camera
        self._detector: Detector | None = None
        self._feature_signature = feature_signature(self.config)
        self._features: weakref.WeakKeyDictionary[Frame, Frame] = weakref.WeakKeyDictionary()
        self._clouds: weakref.WeakKeyDictionary[Frame, dict[float, IcpCloud]] = weakref.WeakKeyDictionary()
        self._surfaces: weakref.WeakKeyDictionary[Frame, OrganisedSurface] = weakref.WeakKeyDictionary()
        self._references: weakref.WeakKeyDictionary[Frame, ReferencePixels] = weakref.WeakKeyDictionary()
        # the last relief check's normal equations, for the fit that may start where it looked
        self._relief_evaluation: tuple[weakref.ref[Frame], weakref.ref[Frame], DenseEvaluation] | None = None
        self.last_timings_s: dict[str, float] = {}
        self.last_cpu_timings_s: dict[str, float] = {}  # process CPU time per stage (wall in last_timings_s)

    # -- per-frame work ----------------------------------------------------------------------
    def describe(self, frame: Frame) -> Frame:
        """The frame with keypoints/descriptors of the configured type (cached)."""
        cached = self._features.get(frame)
        if cached is not None:
            return cached
        if frame.keypoints_uv is not None and frame.metadata.get("feature_signature") == self._feature_signature:
            # already described: nothing to cache (a WeakKeyDictionary holding the frame as its
            # own value would keep every frame alive for the registrar's lifetime)
            return frame
        else:
            if self._detector is None:
                self._detector = make_detector(self.config)
            described = detect_and_describe(frame, self.config, self._detector)
        self._features[frame] = described
        return described

    def icp_cloud(self, frame: Frame, voxel_m: float | None = None) -> IcpCloud:
        """The frame's voxel-downsampled ICP cloud (cached per voxel size; default ``noise.voxel_m``)."""
        voxel = float(self.config.lengths.icp_voxel_m if voxel_m is None else voxel_m)
        per_frame = self._clouds.setdefault(frame, {})
        cached = per_frame.get(voxel)
        if cached is None:
            pts = organised_subsample(frame.xyz_map, voxel) if frame.xyz_map is not None else frame.points
            cached = prepare_icp_cloud(pts, voxel)
            per_frame[voxel] = cached
        return cached

    def dense_surface(self, frame: Frame) -> OrganisedSurface:
        """The frame's organised map prepared for :func:`frontend.dense_alignment.align_dense`
        (cached; read from :attr:`Frame.prepared` where :meth:`prepare` stored it)."""
        cached = self._surfaces.get(frame)
        if cached is None:
            stored = stored_xyz_map_float32(frame)
            xyz_map = frame.xyz_map if stored is None else stored  # the same numbers, without narrowing them again
            cached = OrganisedSurface.from_arrays(xyz_map, frame.prepared) or OrganisedSurface(xyz_map)
            self._surfaces[frame] = cached
        return cached

    def photometric_reference(self, frame: Frame) -> ReferencePixels:
        """The frame's pixels as the photometric step's reference: those :meth:`prepare` stored
        with it, else computed (cached per frame: a worker verifying several loop candidates
        against one keyframe prepares them once)."""
        cached = self._references.get(frame)
        if cached is None:
            from frontend.localization.reference import reference_from_arrays

            cached = reference_from_arrays(frame.prepared, PREPARED_REFERENCE, self._reference_settings(frame.texture))
            if cached is None:
                cached = self._reference_pixels(frame.xyz_map, frame.texture)
            self._references[frame] = cached
        return cached

    def prepare(self, frame: Frame) -> Frame:
        """``frame`` with what every pair it takes part in will need, made once where the frame is
        made (a decode worker) and stored with it (:attr:`Frame.prepared`), so that the tracking
        process and each worker verifying one of its loops read it instead of making it again:

        * its dense surface (:meth:`OrganisedSurface.to_arrays`: normals and rays, ~50 ms of a
          1920x1200 map, ~8 ms of a 640x480 one, ~5 bytes a pixel on disk). A doll turntable
          run made 39 frames' surfaces about 220 times: as the target and source of odometry
          and of loop candidates on two workers, each holding a few frames;
        * the photometric step's reference pixels (0.3-0.9 s of a 1920x1200 frame) for a frame
          whose own surface is plane-like (:func:`surface_is_plane_like`): each of its pairs
          takes the step (a simulated corridor run computed them 173 times for 92 frames).

        Both are made from the map as the frame store keeps it (float32), so every process
        reading the frame back gets the numbers it would have made itself. A frame without a
        map is returned as it is.
        """
        if frame.xyz_map is None:
            return frame
        stored_map = np.asarray(frame.xyz_map, dtype=np.float32)
        prepared: dict[str, NDArray] = {}
        if self.config.dense.enabled:
            try:
                prepared.update(OrganisedSurface(stored_map).to_arrays())
            except InputDataError as exc:
                # too few valid pixels for a surface: each pair that needs one says so again
                log.debug("frame %d: no dense surface stored with it (%s)", frame.id, exc)
        cfg = self.config
        if (
            self.texture_sets_planes and frame.texture is not None
            and surface_is_plane_like(frame.xyz_map, cfg.lengths.icp_voxel_m, cfg.weak_directions.degeneracy_ratio)
        ):
            from frontend.localization.reference import reference_to_arrays

            pixels = self._reference_pixels(stored_map.astype(np.float64), frame.texture)
            prepared.update(reference_to_arrays(pixels, PREPARED_REFERENCE))
        return dataclasses.replace(frame, prepared={**frame.prepared, **prepared}) if prepared else frame

    def _reference_settings(self, texture: NDArray) -> tuple:
        from frontend.localization.reference import reference_settings

        assert self.texture_camera is not None
        return reference_settings(np.shape(texture)[1], self.texture_camera.projector_centre_m, self.config.photometric.max_pixels)

    def _reference_pixels(self, xyz_map: NDArray, texture: NDArray) -> ReferencePixels:
        from frontend.localization import DenseReference, reference_pixels

        assert self.texture_camera is not None
        return reference_pixels(
            DenseReference(xyz_map, texture, np.eye(4)), self.texture_camera.projector_centre_m, self.config.photometric.max_pixels,
            width_px=np.shape(texture)[1],
        )

    def refine_dense(
        self, target: Frame, source: Frame, T_target_source: NDArray, information_keypoints: NDArray, weak: Degeneracy | None, source_points: NDArray
    ) -> tuple[DenseAlignment | None, str]:
        """Dense point-to-plane refinement of an accepted pose (:mod:`frontend.dense_alignment`).

        Directions the geometry leaves free (``weak``: a wall's in-plane shifts and spin) are
        pinned where ICP and the keypoints put them; the keypoints' information is the prior
        elsewhere (the dense term outweighs it by orders of magnitude on relief).

        Returns
        -------
        (DenseAlignment or None, why it was not used)
        """
        cfg, dense_cfg = self.config, self.config.dense
        start = self._evaluation_of(target, source)
        if not dense_cfg.enabled or target.xyz_map is None or source.xyz_map is None:
            return None, "off"
        prior = cfg.keypoints.information_scale * np.asarray(information_keypoints, dtype=np.float64)
        if weak is not None and len(weak.directions):
            strength = cfg.weak_directions.hold_ratio * max(float(np.trace(prior)), 1.0)
            prior = prior + weak_direction_pin(weak, source_points, strength=strength)
        try:
            dense = align_dense(
                self.dense_surface(target), self.dense_surface(source), T_target_source, prior_information=prior,
                coarse_stride_px=dense_cfg.coarse_stride_px, fine_stride_px=dense_cfg.stride_px,
                max_iterations=dense_cfg.coarse_iterations, fine_iterations=dense_cfg.fine_iterations, max_points=dense_cfg.max_points,
                max_distance_m=cfg.lengths.icp_max_correspondence_m, start=start,
            )
        except FppError as exc:
            return None, str(exc)
        if not np.all(np.isfinite(dense.T_target_source)):
            return None, "non-finite pose"
        return dense, ""

    def dense_sees_relief(self, target: Frame, source: Frame, T_target_source: NDArray) -> bool:
        """Whether every pixel's geometry at ``T_target_source`` constrains more than a plane does
        (fewer than three directions below ``weak_directions.degeneracy_ratio``): the question a
        fit held for the texture answers (:func:`frontend.registration.refinement.dense_stage`),
        asked of one evaluation at the coarse stride. On the doll turntable's loop candidates the
        held fit found relief on 118 of 150 and was redone unheld each time, 21.6 of the 36.9 s
        their dense stage took. The evaluation is kept for :meth:`refine_dense` of the same
        pair: a fit starting at this pose takes it as its first iteration's normal equations."""
        self._relief_evaluation = None
        cfg, dense_cfg = self.config, self.config.dense
        if not dense_cfg.enabled or target.xyz_map is None or source.xyz_map is None:
            return False
        target_surface, source_surface = self.dense_surface(target), self.dense_surface(source)
        coarse_px, _ = dense_strides(target_surface, source_surface, dense_cfg.coarse_stride_px, dense_cfg.stride_px, dense_cfg.max_points)
        try:
            evaluation = evaluate_dense(target_surface, source_surface, T_target_source, coarse_px, cfg.lengths.icp_max_correspondence_m)
            info, used = evaluation.information()
        except FppError:
            return False  # the held fit decides (and says why it cannot)
        self._relief_evaluation = (weakref.ref(target), weakref.ref(source), evaluation)
        return not check_degeneracy(info, used, cfg.weak_directions.degeneracy_ratio).plane_like

    def _evaluation_of(self, target: Frame, source: Frame) -> DenseEvaluation | None:
        """The last relief check's evaluation if it was of this pair (once: it is then dropped)."""
        kept, self._relief_evaluation = self._relief_evaluation, None
        if kept is None or kept[0]() is not target or kept[1]() is not source:
            return None
        return kept[2]

    def refine_plane_photometric(
        self, target: Frame, source: Frame, T_target_source: NDArray, weak: Degeneracy, information_geometry: NDArray, source_points: NDArray,
        information_start: NDArray | None = None,
    ) -> tuple[NDArray | None, NDArray | None, str]:
        """The ``weak`` directions (a wall's in-plane shifts and spin) by photometric alignment.

        The source's texture is predicted from the target's FPP map and texture with the
        projector's shading (:func:`frontend.localization.localize_photometric`) while the
        directions the geometry fixes are held where ICP / the dense fit put them. On a wall the
        keypoints set the in-plane shifts to ~0.05 mm (blob centres on blurred texture); every
        textured pixel does it to a few micrometres once the tilts are not free: 12 simulated corridor pairs
        with the tilts held at the truth, 0.058 -> 0.004 mm median (unheld, the tilts and the in-plane shifts trade off).
        ``information_start`` (the start's, keypoints included) sets the coarsest pyramid level the
        step needs (:func:`~frontend.localization.pyramid_for_start`; without it, all three).

        Returns
        -------
        (T_target_source or None, its photometric information (6 x 6, ``[rot, trans]``, scaled) or None, why not)
        """
        cfg = self.config
        cam = self.texture_camera
        if not cfg.photometric.enabled or cam is None:
            return None, None, "off" if not cfg.photometric.enabled else "no texture camera"
        if target.texture is None or source.texture is None or target.xyz_map is None or source.xyz_map is None:
            return None, None, "no texture or xyz map"
        from frontend.localization import DenseReference, localize_photometric, pyramid_for_start

        # holds: the complement of the weak directions, far above the texture's information
        strength = cfg.weak_directions.hold_ratio * max(float(np.trace(information_geometry)), 1.0)
        prior = weak_direction_pin(weak, source_points, strength, complement=True)
        iterations = pyramid_for_start(self._start_sigma_px(information_start, weak, source_points))
        try:
            result = localize_photometric(
                [DenseReference(target.xyz_map, target.texture, np.eye(4))], source.texture, invert(np.asarray(T_target_source, dtype=np.float64)),
                cam.K, cam.dist, projector_centre_m=cam.projector_centre_m, valid_query=np.isfinite(source.xyz_map[..., 2]),
                max_pixels=cfg.photometric.max_pixels, prior_information=prior, reference_pixels=[self.photometric_reference(target)],
                levels=len(iterations), iterations=iterations,
                # in the raw information's units: the constraint's covariance is 1 / information_scale of it
                stop_step_sigmas=PHOTOMETRIC_STOP_STEP_SIGMAS / math.sqrt(cfg.photometric.information_scale),
            )
        except FppError as exc:
            return None, None, str(exc)
        if not result.success:
            return None, None, f"did not converge ({result.pixels_used} pixels)"
        # Exp(xi) T_source_target = (T_target_source Exp(-xi))^-1: the same quadratic form
        # All six directions: the texture's in-plane estimate is tied to the tilts it was held at
        # (a wall's shift trades against its tilt), and only the joint matrix with the geometry's
        # tilt information carries that into the in-plane covariance (the weak directions' part
        # alone put the corridor NEES mean at 55 for 9.6 with the whole matrix, scale 0.01).
        return invert(result.T_camera_world), cfg.photometric.information_scale * result.information, ""

    def _start_sigma_px(self, information_start: NDArray | None, weak: Degeneracy, source_points: NDArray) -> float:
        """One standard deviation of the start's least certain weak direction as the texture
        camera's pixels at the points' median depth (NaN when unknown)."""
        if information_start is None or self.texture_camera is None or not len(source_points):
            return float("nan")
        sigma_m = weak_direction_sigma_m(information_start, weak, source_points)
        depth_m = float(np.median(source_points[:, 2]))
        return sigma_m * float(self.texture_camera.K[0, 0]) / depth_m if depth_m > 0 else float("nan")

    # -- the pair ------------------------------------------------------------------------------
    @property
    def texture_sets_planes(self) -> bool:
        """Whether the texture sets a plane's in-plane directions (the rig's camera is known and the
        photometric and dense refinements are on): ICP then keeps its coarse pose on planes, the
        plane rule always applies, and the dense fit holds the plane's directions."""
        cfg = self.config
        return self.texture_camera is not None and cfg.photometric.enabled and cfg.dense.enabled

    def register(
        self,
        target: Frame,
        source: Frame,
        T_guess: NDArray[np.float64] | None = None,
        kind: ConstraintKind | str = ConstraintKind.ODOMETRY,
    ) -> Constraint:
        """Estimate ``T_target_source``; a failed pair returns a rejected Constraint with the reason.

        Stages: :mod:`.stages` and :mod:`.refinement`; every rejection is a row of
        :data:`.gates.GATES`, checked after the stage whose result it reads.

        Parameters
        ----------
        target, source : Frame
            Need ``xyz_map`` and ``texture`` (same size per frame, checked by Frame).
        T_guess : (4, 4), optional
            Prior ``T_target_source``; scored as one more RANSAC hypothesis (never trusted alone).
        kind : ConstraintKind
            Recorded on the constraint.

        Returns
        -------
        Constraint
            Accepted with information ``[rot, trans]``, or rejected with ``rejection_reason``.
        """
        cfg, s = self.config, PairState(target, source, kind, T_guess)
        self.last_timings_s, self.last_cpu_timings_s = s.timer.wall_s, s.timer.cpu_s
        if rejected := rejection(Checkpoint.INPUT, s, cfg):
            return rejected
        s.matches = match_keypoints(target, source, self.describe, cfg, s.timer)
        if rejected := rejection(Checkpoint.FEATURES, s, cfg):
            return rejected
        s.meta.update(s.matches.metadata)
        if rejected := rejection(Checkpoint.MATCHES, s, cfg):
            return rejected
        started = s.timer.start()  # the "ransac" time includes the lift
        s.lifted = lift_matches(target, source, s.matches, cfg)
        if rejected := rejection(Checkpoint.LIFTED, s, cfg):
            return rejected
        s.ransac = self._ransac(s)
        s.timer.stop("ransac", started)
        s.meta.update(ransac_metadata(s.matches, s.lifted, s.ransac, cfg.features.type))
        if rejected := rejection(Checkpoint.RANSAC, s, cfg):
            return rejected
        s.icp = run_icp(target, source, s.ransac.T_target_source, cfg, self.icp_cloud, self.texture_sets_planes, s.timer,
                        s.lifted.points_source_m[s.ransac.inliers])
        s.meta.update(s.icp.metadata)
        if rejected := rejection(Checkpoint.ICP, s, cfg):
            return rejected
        s.weak = handle_weak_directions(s.lifted, s.ransac, s.icp, cfg, self.texture_sets_planes)
        s.meta.update(s.weak.metadata)
        if rejected := rejection(Checkpoint.POSE, s, cfg):
            return rejected
        started = s.timer.start()
        information = joint_information(s.lifted, s.icp, s.weak, cfg)
        s.keypoints, s.pose = information.keypoints, information.pose
        s.meta.update(information.metadata)
        s.timer.stop("information", started)
        is_loop = ConstraintKind(kind) is ConstraintKind.LOOP
        appearance_only = is_loop and T_guess is None
        if appearance_only and s.pose.degeneracy.degenerate and (rejected := self._look_alike(s)):
            return rejected
        self._refine_dense(s)
        checked_pose = None
        if photometric_applies(self.texture_sets_planes, s.weak, s.dense):
            if appearance_only:
                if rejected := self._look_alike(s):
                    return rejected
                checked_pose = s.pose
            self._refine_photometric(s)
        if s.pose is not checked_pose:  # the photometric step moved it (or nothing checked yet)
            self._check_weak_geometry(s, is_loop)
        return rejection(Checkpoint.FINAL, s, cfg) or self._accept(s)

    def track(self, target: Frame, source: Frame, T_predicted: NDArray[np.float64]) -> Constraint:
        """``T_target_source`` from a motion prediction by the dense fit alone (implements
        :class:`~fpp_graph.types.FrameTracker`; gates in :mod:`.tracking`); rejected when only a
        full :meth:`register` can be trusted."""
        return track_dense(target, source, T_predicted, self.config, self.dense_surface, self.describe)

    def _ransac(self, s: PairState) -> RansacResult:
        """RANSAC on the lifted matches, seeded per pair so results do not depend on pair order."""
        cfg, lifted = self.config, s.lifted
        rng = np.random.default_rng([self.seed, s.source.id & 0xFFFFFFFF, s.target.id & 0xFFFFFFFF])
        extra = [np.asarray(s.T_guess, dtype=np.float64)] if s.T_guess is not None else None
        return ransac_rigid(lifted.points_target_m, lifted.points_source_m, cfg.lengths.ransac_inlier_m, cfg.ransac.max_iterations, cfg.ransac.confidence, rng, extra)

    def _refine_dense(self, s: PairState) -> None:
        """The dense stage (every pixel; a wall held for the texture)."""
        inliers_source_m = s.lifted.points_source_m[s.ransac.inliers]
        started = s.timer.start()
        s.dense = dense_stage(
            s.target, s.source, self.refine_dense, s.pose, s.keypoints, s.icp, s.weak, inliers_source_m, s.ransac.T_target_source, self.config,
            self.texture_sets_planes, self.dense_sees_relief,
        )
        s.pose = s.dense.pose
        s.meta.update(s.dense.metadata)
        s.timer.stop("dense", started)

    def _refine_photometric(self, s: PairState) -> None:
        """The photometric step: the plane's directions from the projector-lit texture."""
        inliers_source_m = s.lifted.points_source_m[s.ransac.inliers]
        started = s.timer.start()
        s.photometric = photometric_stage(s.target, s.source, self.refine_plane_photometric, s.pose, s.keypoints, s.weak, inliers_source_m, self.config)
        s.pose = s.photometric.pose
        s.meta.update(s.photometric.metadata)
        s.timer.stop("photometric", started)

    def _look_alike(self, s: PairState) -> Constraint | None:
        """The look-alike test of an appearance-only revisit on weak geometry at the current pose
        (:attr:`Checkpoint.REVISIT`): the rejection, or None.

        It runs before each expensive step a look-alike would take: first at the keypoint / ICP
        pose, before the dense stage (0.3-0.6 s a pair at 1920x1200), since a look-alike's
        textures disagree by whole blocks, not by the dense stage's sub-millimetre correction
        (turntable: 32 look-alikes 0.54-0.83 -> 0.10-0.17 s each, every verdict of its 155
        candidates the same); then at the dense pose, before the photometric step (2-3 s a
        pair), which rarely converges on a look-alike's mismatched textures and never lifted a
        rejected pair's agreement over the gate (61 simulated pairs: it moved 11 by at most
        0.18, none across). A pair that passes is tested again on its final pose.
        """
        self._check_weak_geometry(s, is_loop=True)
        return rejection(Checkpoint.REVISIT, s, self.config)

    def _check_weak_geometry(self, s: PairState, is_loop: bool) -> None:
        """Step 9 at the current pose: whether the keypoints pin weak geometry and, for an
        appearance-only revisit, whether the textures agree."""
        s.check = check_weak_geometry(s.target, s.source, s.pose, s.weak.icp.source_points, is_loop, s.T_guess, self.config)
        s.meta.update(s.check.metadata)

    def _accept(self, s: PairState) -> Constraint:
        s.meta["timings_s"] = dict(s.timer.wall_s)
        photometric = s.photometric.information if s.photometric is not None else np.zeros((6, 6))
        return Constraint(
            source_id=s.source.id,
            target_id=s.target.id,
            T_target_source=s.pose.T_target_source,
            # The gates use the keypoints' raw information; the constraint carries it scaled:
            # keypoint errors are correlated (one detector, the same texture), so n keypoints
            # are worth fewer than n independent points. Calibrated by NEES on simulated pairs:
            # the corridor median fell from 64 to 10 at 0.1 with the turntable unchanged (4.6:
            # there ICP's information dominates every direction).
            information=with_shared_error_floor(
                s.pose.information_geometry + self.config.keypoints.information_scale * s.pose.information_keypoints + photometric,
                s.weak.icp.source_points, self.config.sensor_noise().shared_depth_sigma_per_m2,
            ),
            kind=s.kind,
            metadata=s.meta,
            **s.quality,
        )


def with_features(frame: Frame, config: RegistrationConfig) -> Frame:
    """Alias of :func:`frontend.features.detect.detect_and_describe` for pipeline code that only imports this module."""
    return detect_and_describe(frame, config)


