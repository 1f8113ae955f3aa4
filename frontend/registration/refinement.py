"""The stages of :meth:`TexturedSurfaceRegistrar.register` after the joint information. Each is an
object built from the registration config (holding its own caches), whose ``run`` takes a typed
input and returns a frozen result:

7. :class:`DenseStage`: dense point-to-plane refinement on every ``noise.dense_stride_px``-th
   pixel (its :class:`FrameSurfaces` prepare each frame's organised map once);
8. :class:`PhotometricStage`: a plane's in-plane shifts and spin from the texture (its reference
   pixels made once per frame);
9. :class:`WeakGeometryStage`: what the final gates need when the joint information is weak (how
   well the keypoints pin it; for appearance-only loops, the textures' agreement).
"""

from __future__ import annotations

import logging
import math
import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

import frontend.localization as localization
from fpp_graph.errors import FppError
from fpp_graph.geometry import invert
from fpp_graph.types import Frame
from frontend.config import RegistrationConfig
from frontend.dense_alignment import (
    DENSE_INFORMATION_SCALE,
    DenseAlignment,
    DenseEvaluation,
    DenseSchedule,
    align_dense,
    evaluate_dense,
)
from frontend.localization.reference import reference_from_arrays, reference_settings
from frontend.organised_surface import OrganisedSurface
from frontend.registration.keypoints import KEYPOINT_INFORMATION_SCALE
from frontend.registration.stages import (
    IcpOutcome,
    InformationOutcome,
    KeypointPose,
    KeypointTerm,
    PoseEstimate,
    WeakDirectionOutcome,
    WeakRule,
)
from frontend.registration.state import PairFrames
from frontend.registration.texture import TextureAgreement, TextureCamera, texture_agreement
from frontend.registration.weak_directions import (
    DEGENERACY_RATIO,
    HOLD_RATIO,
    Degeneracy,
    check_degeneracy,
    max_motion_m,
    weak_direction_pin,
    weak_direction_sigma_m,
    without_weak_directions,
)

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

PHOTOMETRIC_MAX_PIXELS = 100000
"""Target pixels the photometric step uses (the strongest texture gradients): they carry the
information; more pixels add cost, not precision."""

PHOTOMETRIC_INFORMATION_SCALE = 0.01
"""Multiplies the photometric information: texture errors correlate over the blur kernel and the
shading model's error, so the independent-pixel information is too confident by about this factor
(calibrated by NEES)."""

PHOTOMETRIC_STOP_STEP_SIGMAS = 0.05
"""The photometric step stops once its pose steps are under this many standard deviations of the
pair's constraint (its information times :data:`PHOTOMETRIC_INFORMATION_SCALE`). The steps then
chase the texture's slowly converging gain, offset and ambient ratio, which shrink geometrically
(a ratio of about 0.75 a step), so what is left of the way is at most about 3x the last step,
0.15 standard deviations: 2 % of the constraint's variance."""


# ---------------------------------------------------------------------------------------------
# 7: dense refinement
# ---------------------------------------------------------------------------------------------
class FrameSurfaces:
    """Each frame's organised map prepared for :func:`frontend.dense_alignment.align_dense`, made
    once per frame object (weakly held; read from :attr:`Frame.prepared` where the registrar's
    ``prepare`` stored it)."""

    def __init__(self) -> None:
        self._surfaces: weakref.WeakKeyDictionary[Frame, OrganisedSurface] = weakref.WeakKeyDictionary()

    def surface(self, frame: Frame) -> OrganisedSurface:
        cached = self._surfaces.get(frame)
        if cached is None:
            stored = frame.xyz_map_stored
            xyz_map = frame.xyz_map if stored is None else stored  # the same numbers, without narrowing them again
            cached = OrganisedSurface.from_arrays(xyz_map, frame.prepared) or OrganisedSurface(xyz_map)
            self._surfaces[frame] = cached
        return cached


@dataclass(frozen=True, eq=False)
class DenseInput:
    """What the dense stage refines: the pair, RANSAC's pose (the keypoints' basin), ICP, the
    weak-direction rules and the joint information."""

    pair: PairFrames
    start: KeypointPose
    icp: IcpOutcome
    weak: WeakDirectionOutcome
    information: InformationOutcome


@dataclass(frozen=True, eq=False)
class DenseOutcome:
    """The pose after the dense stage; ``relief_took_over``: an unheld dense fit saw relief and
    replaced the keypoints' weak directions (or refined a pose that had none), so the texture has
    nothing left to set."""

    pose: PoseEstimate
    relief_took_over: bool
    metadata: dict[str, Any] = field(repr=False)


class DenseStage:
    """Stage 7: every pixel instead of voxels (the decoded map's noise averages over ~100x more
    points). The dense information replaces ICP's (the same surfaces, measured densely).

    Pinned: the directions already taken from the keypoints. One weak direction of curved relief
    (a spin about an object's axis) is left to the dense fit; a plane is not refined (it keeps the
    earlier pose), except held for the texture (stage 8): the dense fit then gives its tilts and
    distance with the plane's directions held at the keypoints' values (unheld, the plane's
    directions slide and take the tilts along). Whether every pixel already shows relief is asked
    first, at ICP's pose, by one evaluation at the coarse stride (a held fit would find the relief
    and be redone unheld); that evaluation is the first step of the fit that starts there.
    """

    def __init__(self, config: RegistrationConfig, texture_sets_planes: bool):
        self.enabled, self.texture_sets_planes = config.dense.enabled, texture_sets_planes
        self.schedule, self.lengths = DenseSchedule.of(config), config.lengths
        self.surfaces = FrameSurfaces()

    def _available(self, pair: PairFrames) -> bool:
        return self.enabled and pair.target.xyz_map is not None and pair.source.xyz_map is not None

    def relief_at(self, pair: PairFrames, T_target_source: NDArray) -> tuple[bool, DenseEvaluation | None]:
        """Whether every pixel's geometry at ``T_target_source`` constrains more than a plane does
        (fewer than three directions below :data:`DEGENERACY_RATIO`), and the evaluation that says
        so (a fit starting at this pose takes it as its first iteration's normal equations)."""
        if not self._available(pair):
            return False, None
        target_surface, source_surface = self.surfaces.surface(pair.target), self.surfaces.surface(pair.source)
        coarse_px, _ = self.schedule.strides(target_surface, source_surface)
        try:
            evaluation = evaluate_dense(target_surface, source_surface, T_target_source, coarse_px, self.lengths.icp_max_correspondence_m)
            info, used = evaluation.information()
        except FppError:
            return False, None  # the held fit decides (and says why it cannot)
        return not check_degeneracy(info, used, DEGENERACY_RATIO).plane_like, evaluation

    def fit(
        self, pair: PairFrames, T_target_source: NDArray, information_keypoints: NDArray, pinned: Degeneracy | None, support_points: NDArray,
        start: DenseEvaluation | None = None,
    ) -> tuple[DenseAlignment | None, str]:
        """The dense fit from ``T_target_source``: the ``pinned`` directions held where they are,
        the keypoints' information the prior elsewhere (the dense term outweighs it by orders of
        magnitude on relief). Returns the fit or None, and why it was not used."""
        if not self._available(pair):
            return None, "off"
        prior = KEYPOINT_INFORMATION_SCALE * np.asarray(information_keypoints, dtype=np.float64)
        if pinned is not None and len(pinned.directions):
            prior = prior + weak_direction_pin(pinned, support_points, strength=HOLD_RATIO * max(float(np.trace(prior)), 1.0))
        try:
            dense = align_dense(self.surfaces.surface(pair.target), self.surfaces.surface(pair.source), T_target_source, self.schedule,
                                prior_information=prior, start=start)
        except FppError as exc:
            return None, str(exc)
        if not np.all(np.isfinite(dense.T_target_source)):
            return None, "non-finite pose"
        return dense, ""

    def _held_plane_fit(self, given: DenseInput, start: DenseEvaluation | None) -> DenseAlignment | None:
        """The plane's fit with its directions held at the keypoints' values; None when every pixel
        sees relief after all (the unheld fit then decides) or it left RANSAC's basin."""
        pose, weak = given.information.pose, given.weak
        held, _ = self.fit(given.pair, pose.T_target_source, pose.information_keypoints, weak.directions, weak.icp.source_points, start)
        if held is None or not check_degeneracy(held.information, held.source_points, DEGENERACY_RATIO).plane_like:
            return None
        if not max_motion_m(held.T_target_source, given.start.T_target_source, given.start.inliers_source_m) <= self.lengths.max_icp_shift_m:
            return None
        return held

    def run(self, given: DenseInput) -> DenseOutcome:
        weak, icp, keypoints, pose = given.weak, given.icp, given.information.keypoints, given.information.pose
        support, meta = weak.icp.source_points, {}
        held_plane, start = self.texture_sets_planes and weak.rule is WeakRule.PLANE, None
        if held_plane:
            relief, start = self.relief_at(given.pair, icp.icp.T_target_source)
            if relief:
                held_plane, meta["dense_relief_at_start"] = False, True
        if held_plane:
            held, start = self._held_plane_fit(given, start), None
            if held is not None:
                meta.update({"T_before_dense": pose.T_target_source, "dense_pinned": list(weak.directions.unconstrained), "dense_iterations": held.iterations,
                             "dense_residuals": held.num_residuals, "dense_sigma_m": held.sigma_m})
                info_geometry = without_weak_directions(DENSE_INFORMATION_SCALE * held.information, weak.directions, support)
                return DenseOutcome(keypoints.at(held.T_target_source, info_geometry), False, meta)
        pinned, T_start = weak.directions, pose.T_target_source
        if weak.rule is WeakRule.PLANE:
            # The plane rule read the pair as a plane from ICP's voxels and took the in-plane
            # directions from the keypoints; an object on a large plane looks like that to ICP
            # (the plane dominates its voxels). Every pixel decides: from ICP's own pose,
            # unpinned; if the dense information is not plane-like the relief constrains them.
            pinned, T_start = None, icp.icp.T_target_source
            meta["dense_rechecks_plane_rule"] = True
        if icp.degeneracy.plane_like:
            dense, why_not = None, "plane-like geometry (ICP: " + "; ".join(icp.degeneracy.unconstrained) + ")"
        else:
            dense, why_not = self.fit(given.pair, T_start, pose.information_keypoints, pinned, support, start)
        if pinned is not None:
            meta["dense_pinned"] = list(pinned.unconstrained)
        pose, relief_took_over, why_not = self._judged(given, dense, why_not, pinned, meta)
        if why_not and why_not != "off":
            meta["dense_not_used"] = why_not
            log.debug("pair %d->%d: dense refinement not used: %s", given.pair.source.id, given.pair.target.id, why_not)
        return DenseOutcome(pose, relief_took_over, meta)

    def _judged(
        self, given: DenseInput, dense: DenseAlignment | None, why_not: str, pinned: Degeneracy | None, meta: dict[str, Any],
    ) -> tuple[PoseEstimate, bool, str]:
        """The unheld fit's pose if it sees relief and stays in RANSAC's basin, else the earlier pose
        and why not."""
        pose = given.information.pose
        if dense is None:
            return pose, False, why_not
        dense_deg = check_degeneracy(dense.information, dense.source_points, DEGENERACY_RATIO)
        meta["dense_eigenvalue_ratios"] = dense_deg.eigenvalue_ratios
        # (against RANSAC's pose, as ICP's shift is: the keypoints' basin)
        shift_dense = max_motion_m(dense.T_target_source, given.start.T_target_source, given.start.inliers_source_m)
        meta.update({"dense_shift_m": shift_dense, "dense_iterations": dense.iterations, "dense_residuals": dense.num_residuals, "dense_sigma_m": dense.sigma_m})
        if dense_deg.plane_like:
            # a plane even to every pixel: its tilts and normal shift come out no better than
            # ICP's, and the in-plane directions are the keypoints'
            return pose, False, "plane-like geometry (" + "; ".join(dense_deg.unconstrained) + ")"
        if shift_dense > self.lengths.max_icp_shift_m:
            return pose, False, f"moved the keypoint inliers by {1e3 * shift_dense:.2f} mm"
        meta["T_before_dense"] = pose.T_target_source
        info_dense = DENSE_INFORMATION_SCALE * dense.information
        if pinned is not None:
            info_dense = without_weak_directions(info_dense, pinned, given.weak.icp.source_points)
        return given.information.keypoints.at(dense.T_target_source, info_dense), True, why_not


# ---------------------------------------------------------------------------------------------
# 8: photometric step
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PhotometricInput:
    """What the photometric step refines: the pair, RANSAC's pose (its inliers bound the step),
    the weak directions, the pose after the dense stage and the keypoints' term."""

    pair: PairFrames
    start: KeypointPose
    weak: WeakDirectionOutcome
    pose: PoseEstimate
    keypoints: KeypointTerm


@dataclass(frozen=True, eq=False)
class PhotometricOutcome:
    """The pose after the photometric step, and the texture's information (scaled; zero when the
    step was not used), which the constraint carries and the gates do not judge."""

    pose: PoseEstimate
    information: Array
    metadata: dict[str, Any] = field(repr=False)


class PhotometricStage:
    """Stage 8: the weak directions (a plane's in-plane shifts and spin) by photometric alignment.

    The source's texture is predicted from the target's FPP map and texture with the projector's
    shading (:func:`frontend.localization.localize_photometric`) while the directions the
    geometry fixes are held where ICP / the dense fit put them: on a plane the keypoints set the
    in-plane shifts to a fraction of a pixel (blob centres on blurred texture), every textured
    pixel does it several times better once the tilts are not free (unheld, the tilts and the
    in-plane shifts trade off). The result is kept when it moves the keypoint inliers by at most
    RANSAC's inlier distance.
    """

    def __init__(self, config: RegistrationConfig, texture_camera: TextureCamera | None):
        self.enabled, self.texture_camera, self.lengths = config.photometric.enabled, texture_camera, config.lengths
        self._references: weakref.WeakKeyDictionary[Frame, localization.ReferencePixels] = weakref.WeakKeyDictionary()

    @staticmethod
    def applies(texture_sets_planes: bool, weak: WeakDirectionOutcome, dense: DenseOutcome) -> bool:
        """The weak directions came from the keypoints and no relief took over: the texture sets them."""
        return texture_sets_planes and weak.directions is not None and not dense.relief_took_over

    def reference_pixels(self, xyz_map: NDArray, texture: NDArray) -> localization.ReferencePixels:
        """A frame's pixels as the step's reference (0.3-0.9 s of a 1920x1200 frame)."""
        assert self.texture_camera is not None
        return localization.reference_pixels(
            localization.DenseReference(xyz_map, texture, np.eye(4)), self.texture_camera.projector_centre_m, PHOTOMETRIC_MAX_PIXELS,
            width_px=np.shape(texture)[1],
        )

    def reference(self, frame: Frame, prepared_prefix: str) -> localization.ReferencePixels:
        """The frame's reference pixels: those stored with it under ``prepared_prefix``, else made
        (cached per frame: a worker verifying several loop candidates against one keyframe makes
        them once)."""
        cached = self._references.get(frame)
        if cached is None:
            assert self.texture_camera is not None
            settings = reference_settings(np.shape(frame.texture)[1], self.texture_camera.projector_centre_m, PHOTOMETRIC_MAX_PIXELS)
            cached = reference_from_arrays(frame.prepared, prepared_prefix, settings)
            if cached is None:
                cached = self.reference_pixels(frame.xyz_map, frame.texture)
            self._references[frame] = cached
        return cached

    def _start_sigma_px(self, information_start: NDArray, weak: Degeneracy, source_points: NDArray) -> float:
        """One standard deviation of the start's least certain weak direction as the texture
        camera's pixels at the points' median depth (NaN when unknown)."""
        if self.texture_camera is None or not len(source_points):
            return float("nan")
        sigma_m = weak_direction_sigma_m(information_start, weak, source_points)
        depth_m = float(np.median(source_points[:, 2]))
        return sigma_m * float(self.texture_camera.K[0, 0]) / depth_m if depth_m > 0 else float("nan")

    def fit(self, given: PhotometricInput, prepared_prefix: str) -> tuple[NDArray | None, NDArray | None, str]:
        """``(T_target_source or None, its photometric information (6 x 6, [rot, trans], scaled) or None, why not)``.

        The start's information (keypoints included) sets the coarsest pyramid level the step
        needs (:func:`~frontend.localization.pyramid_for_start`)."""
        cam, target, source = self.texture_camera, given.pair.target, given.pair.source
        if not self.enabled or cam is None:
            return None, None, "off" if not self.enabled else "no texture camera"
        if target.texture is None or source.texture is None or target.xyz_map is None or source.xyz_map is None:
            return None, None, "no texture or xyz map"
        weak, support, pose = given.weak.directions, given.weak.icp.source_points, given.pose
        # holds: the complement of the weak directions, far above the texture's information
        prior = weak_direction_pin(weak, support, HOLD_RATIO * max(float(np.trace(pose.information_geometry)), 1.0), complement=True)
        iterations = localization.pyramid_for_start(self._start_sigma_px(pose.information, weak, support))
        query = localization.PhotometricQuery(source.texture, invert(np.asarray(pose.T_target_source, dtype=np.float64)), cam.K, cam.dist,
                                              cam.projector_centre_m, np.isfinite(source.xyz_map[..., 2]))
        # the stop in the raw information's units: the constraint's covariance is 1 / information_scale of it
        settings = localization.PhotometricSettings(PHOTOMETRIC_MAX_PIXELS, iterations,
                                                    stop_step_sigmas=PHOTOMETRIC_STOP_STEP_SIGMAS / math.sqrt(PHOTOMETRIC_INFORMATION_SCALE))
        try:
            result = localization.localize_photometric([localization.DenseReference(target.xyz_map, target.texture, np.eye(4))], query, settings,
                                                       prior_information=prior, reference_pixels=[self.reference(target, prepared_prefix)])
        except FppError as exc:
            return None, None, str(exc)
        if not result.success:
            return None, None, f"did not converge ({result.pixels_used} pixels)"
        # Exp(xi) T_source_target = (T_target_source Exp(-xi))^-1: the same quadratic form. All six
        # directions: the texture's in-plane estimate is tied to the tilts it was held at (a
        # plane's shift trades against its tilt), and only the joint matrix with the geometry's
        # tilt information carries that into the in-plane covariance.
        return invert(result.T_camera_world), PHOTOMETRIC_INFORMATION_SCALE * result.information, ""

    def run(self, given: PhotometricInput, prepared_prefix: str) -> PhotometricOutcome:
        meta: dict[str, Any] = {}
        pose, information = given.pose, np.zeros((6, 6))
        T = pose.T_target_source
        T_photo, info_photo, why_not = self.fit(given, prepared_prefix)
        if T_photo is not None:
            shift_photo = max_motion_m(T_photo, T, given.start.inliers_source_m)
            meta["photometric_shift_m"] = shift_photo
            if shift_photo > self.lengths.ransac_inlier_m:
                why_not = f"moved the keypoint inliers by {1e3 * shift_photo:.2f} mm"
            else:
                meta["T_before_photometric"] = T
                pose, information = given.keypoints.at(T_photo, pose.information_geometry), info_photo
        if why_not:
            meta["photometric_not_used"] = why_not
            log.debug("pair %d->%d: photometric refinement not used: %s", given.pair.source.id, given.pair.target.id, why_not)
        return PhotometricOutcome(pose, information, meta)


# ---------------------------------------------------------------------------------------------
# 9: weak geometry, before the final gates
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class WeakGeometryCheck:
    """What the final gates judge a pose by: the joint information's degeneracy, the largest standard
    deviation along its weak directions with the keypoints (NaN when none), and the textures'
    agreement (a weak appearance-only loop candidate only)."""

    degeneracy: Degeneracy
    weak_sigma_m: float
    agreement: TextureAgreement | None
    metadata: dict[str, Any] = field(repr=False)


class WeakGeometryStage:
    """Stage 9: weak joint geometry (one plane, an object on a table) is acceptable only if the
    keypoints pin those directions (``lengths.max_weak_sigma_m``) and, for a revisit proposed by
    appearance alone, only if the textures agree over the whole overlap: look-alike places
    (repeated objects) fool keypoints, whose inliers all sit on the repeated object while the
    surroundings differ."""

    def __init__(self, config: RegistrationConfig):
        self.texture_distance_m = config.lengths.texture_distance_m

    def run(self, pair: PairFrames, pose: PoseEstimate, support_points_m: Array) -> WeakGeometryCheck:
        deg = pose.degeneracy
        meta: dict[str, Any] = {"eigenvalue_ratios": deg.eigenvalue_ratios}
        if not deg.degenerate:
            return WeakGeometryCheck(deg, float("nan"), None, meta)
        weak_sigma_m = weak_direction_sigma_m(pose.information, deg, support_points_m)
        # the same directions from the dense geometry alone (no keypoints), for diagnosis: on a plane,
        # noisy normals make point-to-plane information claim ~0.1 mm in-plane, so it cannot tell
        # relief from a plane and is not used to admit loops
        meta["weak_direction_geometry_sigma_m"] = weak_direction_sigma_m(pose.information_geometry, deg, support_points_m)
        meta["geometrically_weak"] = deg.unconstrained
        meta["weak_direction_sigma_m"] = weak_sigma_m
        agreement = None
        if pair.appearance_only:
            agreement = texture_agreement(pair.target, pair.source, pose.T_target_source, max_distance_m=self.texture_distance_m)
            meta.update({"texture_agreement": agreement.fraction, "texture_agreement_blocks": agreement.blocks, "texture_agreement_overlap": agreement.overlap})
        elif pair.is_loop:
            meta["weak_loop_guess_deviation_m"] = float(np.linalg.norm(pose.T_target_source[:3, 3] - np.asarray(pair.T_guess, dtype=np.float64)[:3, 3]))
        return WeakGeometryCheck(deg, weak_sigma_m, agreement, meta)
