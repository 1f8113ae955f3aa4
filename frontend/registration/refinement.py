"""The stages of :meth:`FppPairRegistrar.register` after the joint information, each a function
from typed inputs to a frozen result:

7. :func:`dense_stage`: dense point-to-plane refinement on every ``dense.stride_px``-th pixel;
8. :func:`photometric_stage`: a plane's in-plane shifts and spin from the texture;
9. :func:`check_weak_geometry`: what the final gates need when the joint information is weak
   (how well the keypoints pin it; for appearance-only loops, the textures' agreement).

The refinements themselves are the registrar's :meth:`~FppPairRegistrar.refine_dense` and
:meth:`~FppPairRegistrar.refine_plane_photometric` (they use its per-frame caches and camera),
passed in as callables.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.types import Frame
from frontend.config import RegistrationConfig
from frontend.dense_alignment import DenseAlignment
from frontend.registration.stages import (
    IcpOutcome,
    KeypointTerm,
    PoseEstimate,
    WeakDirectionOutcome,
    WeakRule,
)
from frontend.registration.texture import TextureAgreement, texture_agreement
from frontend.registration.weak_directions import (
    Degeneracy,
    check_degeneracy,
    max_motion_m,
    weak_direction_sigma_m,
    without_weak_directions,
)

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

DenseRefiner = Callable[[Frame, Frame, NDArray, NDArray, "Degeneracy | None", NDArray], "tuple[DenseAlignment | None, str]"]
"""``(target, source, T_target_source, information_keypoints, pinned, support_points) -> (fit or None, why not)``."""
ReliefCheck = Callable[[Frame, Frame, NDArray], bool]
"""``(target, source, T_target_source) -> whether every pixel's geometry there shows more than a plane``."""
PhotometricRefiner = Callable[[Frame, Frame, NDArray, Degeneracy, NDArray, NDArray, NDArray], "tuple[NDArray | None, NDArray | None, str]"]
"""``(target, source, T_target_source, weak, information_geometry, support_points, information_start) -> (pose,
information, why not)``; ``information_start``: the start's (geometry and keypoints)."""


# ---------------------------------------------------------------------------------------------
# 7: dense refinement
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class DenseOutcome:
    """The pose after the dense stage.

    Attributes
    ----------
    pose : PoseEstimate
    relief_took_over : bool
        An unheld dense fit saw relief and replaced the keypoints' weak directions (or refined a
        pose that had none): the texture then has nothing left to set.
    metadata : dict
    """

    pose: PoseEstimate
    relief_took_over: bool
    metadata: dict[str, Any] = field(repr=False)


def _held_plane_fit(
    target: Frame, source: Frame, refine: DenseRefiner, pose: PoseEstimate, weak: WeakDirectionOutcome,
    ransac_inliers_source_m: Array, T_ransac: Array, config: RegistrationConfig,
) -> DenseAlignment | None:
    """A wall whose plane directions the texture sets (stage 8): the dense fit gives its tilts and
    distance, with the plane's directions held at the keypoints' values (unheld they slide 0.06 ->
    0.3 mm and take the tilts along). 12 simulated corridor pairs: 0.029 mm median with ICP's
    tilts, 0.017 mm with these. If every pixel sees relief after all (a doll on a table) the
    unheld re-check decides instead (None)."""
    held, _ = refine(target, source, pose.T_target_source, pose.information_keypoints, weak.directions, weak.icp.source_points)
    if held is None or not check_degeneracy(held.information, held.source_points, config.weak_directions.degeneracy_ratio).plane_like:
        return None
    if not max_motion_m(held.T_target_source, T_ransac, ransac_inliers_source_m) <= config.lengths.max_icp_shift_m:
        return None
    return held


def dense_stage(
    target: Frame, source: Frame, refine: DenseRefiner, pose: PoseEstimate, keypoints: KeypointTerm, icp: IcpOutcome,
    weak: WeakDirectionOutcome, ransac_inliers_source_m: Array, T_ransac: Array, config: RegistrationConfig, texture_sets_planes: bool,
    sees_relief: ReliefCheck | None = None,
) -> DenseOutcome:
    """Every pixel instead of 2 mm voxels: on simulated turntable pairs the median error fell
    from 0.0051 deg / 0.043 mm to ~0.001 deg / 0.01 mm (module doc of dense_alignment).

    Pinned: the directions already taken from the keypoints. One weak direction of curved relief
    (the doll's spin about the turntable axis, where GICP's error was) is left to the dense fit;
    a plane is not refined (it keeps the earlier pose), except held for the texture (stage 8).
    The dense information replaces ICP's (the same surfaces, measured densely).
    ``sees_relief``: when every pixel already shows relief, the held fit is not tried (it would
    find the relief and be redone unheld). It is asked at ICP's pose, where the unheld fit then
    starts: the registrar's fit takes that evaluation as its first step's normal equations.
    """
    cfg, support = config, weak.icp.source_points
    meta: dict[str, Any] = {}
    held_plane = texture_sets_planes and weak.rule is WeakRule.PLANE
    if held_plane and sees_relief is not None and sees_relief(target, source, icp.icp.T_target_source):
        held_plane, meta["dense_relief_at_start"] = False, True
    if held_plane:
        held = _held_plane_fit(target, source, refine, pose, weak, ransac_inliers_source_m, T_ransac, cfg)
        if held is not None:
            meta.update({"T_before_dense": pose.T_target_source, "dense_pinned": list(weak.directions.unconstrained), "dense_iterations": held.iterations,
                         "dense_residuals": held.num_residuals, "dense_sigma_m": held.sigma_m})
            info_geometry = without_weak_directions(cfg.dense.information_scale * held.information, weak.directions, support)
            return DenseOutcome(keypoints.at(held.T_target_source, info_geometry), False, meta)
    pinned, T_start = weak.directions, pose.T_target_source
    if weak.rule is WeakRule.PLANE:
        # The plane rule read the pair as a plane from ICP's voxels and took the in-plane
        # directions from the keypoints. A doll on a turntable looks like that to ICP (the table
        # dominates), and ORB keypoints 1.4 mm off then replaced ICP's 0.04 mm pose. Every pixel
        # decides: from ICP's own pose, unpinned; if the dense information is not plane-like the
        # relief constrains the plane's directions.
        pinned, T_start = None, icp.icp.T_target_source
        meta["dense_rechecks_plane_rule"] = True
    if icp.degeneracy.plane_like:
        dense, why_not = None, "plane-like geometry (ICP: " + "; ".join(icp.degeneracy.unconstrained) + ")"
    else:
        dense, why_not = refine(target, source, T_start, pose.information_keypoints, pinned, support)
    if pinned is not None:
        meta["dense_pinned"] = list(pinned.unconstrained)
    relief_took_over = False
    if dense is not None:
        dense_deg = check_degeneracy(dense.information, dense.source_points, cfg.weak_directions.degeneracy_ratio)
        meta["dense_eigenvalue_ratios"] = dense_deg.eigenvalue_ratios
        # (against RANSAC's pose, as ICP's shift is: the keypoints' basin)
        shift_dense = max_motion_m(dense.T_target_source, T_ransac, ransac_inliers_source_m)
        meta.update({"dense_shift_m": shift_dense, "dense_iterations": dense.iterations, "dense_residuals": dense.num_residuals, "dense_sigma_m": dense.sigma_m})
        if dense_deg.plane_like:
            # a plane even to every pixel (a wall: ratios <= 0.016 where the doll's are >= 0.2):
            # its tilts and normal shift came out no better than ICP's (9 simulated corridor
            # pairs: 0.064 -> 0.098 mm median) and the in-plane directions are the keypoints'
            why_not = "plane-like geometry (" + "; ".join(dense_deg.unconstrained) + ")"
        elif shift_dense > cfg.lengths.max_icp_shift_m:
            why_not = f"moved the keypoint inliers by {1e3 * shift_dense:.2f} mm"
        else:
            meta["T_before_dense"] = pose.T_target_source
            info_dense = cfg.dense.information_scale * dense.information
            if pinned is not None:
                info_dense = without_weak_directions(info_dense, pinned, support)
            pose, relief_took_over = keypoints.at(dense.T_target_source, info_dense), True
    if why_not and why_not != "off":
        meta["dense_not_used"] = why_not
        log.debug("pair %d->%d: dense refinement not used: %s", source.id, target.id, why_not)
    return DenseOutcome(pose, relief_took_over, meta)


# ---------------------------------------------------------------------------------------------
# 8: photometric step
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PhotometricOutcome:
    """The pose after the photometric step.

    Attributes
    ----------
    pose : PoseEstimate
    information : (6, 6)
        The texture's information (scaled), zero when the step was not used. Carried by the
        constraint only: the gates (a plane is admitted when the keypoints pin it; look-alike
        places) stay on the geometry and the keypoints.
    metadata : dict
    """

    pose: PoseEstimate
    information: Array
    metadata: dict[str, Any] = field(repr=False)


def photometric_applies(texture_sets_planes: bool, weak: WeakDirectionOutcome, dense: DenseOutcome) -> bool:
    """The weak directions came from the keypoints and no relief took over: the texture sets them."""
    return texture_sets_planes and weak.directions is not None and not dense.relief_took_over


def photometric_stage(
    target: Frame, source: Frame, refine: PhotometricRefiner, pose: PoseEstimate, keypoints: KeypointTerm,
    weak: WeakDirectionOutcome, ransac_inliers_source_m: Array, config: RegistrationConfig,
) -> PhotometricOutcome:
    """The weak directions from the texture (:meth:`FppPairRegistrar.refine_plane_photometric`),
    kept when they move the keypoint inliers by at most RANSAC's inlier distance."""
    meta: dict[str, Any] = {}
    information = np.zeros((6, 6))
    T = pose.T_target_source
    T_photo, info_photo, why_not = refine(target, source, T, weak.directions, pose.information_geometry, weak.icp.source_points, pose.information)
    if T_photo is not None:
        shift_photo = max_motion_m(T_photo, T, ransac_inliers_source_m)
        meta["photometric_shift_m"] = shift_photo
        if shift_photo > config.lengths.ransac_inlier_m:
            why_not = f"moved the keypoint inliers by {1e3 * shift_photo:.2f} mm"
        else:
            meta["T_before_photometric"] = T
            pose, information = keypoints.at(T_photo, pose.information_geometry), info_photo
    if why_not:
        meta["photometric_not_used"] = why_not
        log.debug("pair %d->%d: photometric refinement not used: %s", source.id, target.id, why_not)
    return PhotometricOutcome(pose, information, meta)


# ---------------------------------------------------------------------------------------------
# 9: weak geometry, before the final gates
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class WeakGeometryCheck:
    """What the final gates judge a pose by.

    Attributes
    ----------
    degeneracy : Degeneracy
        Of the joint information.
    weak_sigma_m : float
        Largest standard deviation along the weak directions with the keypoints (NaN when none).
    agreement : TextureAgreement or None
        The textures' agreement, for a weak appearance-only loop candidate only.
    metadata : dict
    """

    degeneracy: Degeneracy
    weak_sigma_m: float
    agreement: TextureAgreement | None
    metadata: dict[str, Any] = field(repr=False)


def check_weak_geometry(
    target: Frame, source: Frame, pose: PoseEstimate, support_points_m: Array, is_loop: bool, T_guess: NDArray | None,
    config: RegistrationConfig,
) -> WeakGeometryCheck:
    """Weak joint geometry (one plane, an object on a table) is acceptable only if the keypoints pin
    those directions (``gates.max_weak_sigma_sigmas``) and, for a revisit proposed by appearance alone, only
    if the textures agree over the whole overlap: look-alike places (repeated posters) fool
    keypoints, whose inliers all sit on the repeated object while the surroundings differ
    (simulated corridor: true revisits 0.989-1.000 of the blocks, look-alike posters 0.37-0.81)."""
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
    if is_loop and T_guess is None:
        agreement = texture_agreement(target, source, pose.T_target_source, max_distance_m=config.lengths.texture_distance_m)
        meta.update({"texture_agreement": agreement.fraction, "texture_agreement_blocks": agreement.blocks, "texture_agreement_overlap": agreement.overlap})
    elif is_loop:
        meta["weak_loop_guess_deviation_m"] = float(np.linalg.norm(pose.T_target_source[:3, 3] - np.asarray(T_guess, dtype=np.float64)[:3, 3]))
    return WeakGeometryCheck(deg, weak_sigma_m, agreement, meta)
