"""Pairwise registration of FPP frames: the project's :class:`~fpp_graph.types.PairRegistrar`.

``FppPairRegistrar.register(target, source)`` runs these stages, each a function from typed inputs
to a frozen result (:mod:`.stages`, :mod:`.refinement`), on a running :class:`~.state.PairState`:

1. :func:`~.stages.match_keypoints`: keypoints on both texture images
   (:func:`frontend.features.detect.detect_and_describe`, once per frame), descriptor matches with ratio
   test and mutual check, the projector's sensor-fixed features dropped
   (:func:`drop_sensor_fixed_matches`);
2. :func:`~.stages.lift_matches`: matched keypoints to 3D through each frame's ``xyz_map``
   (:func:`lift_keypoints`: bilinear where the four neighbouring pixels are valid and on one
   surface, else skipped);
3. :func:`ransac_rigid`: ``T_target_source`` from 3-point samples by the closed-form SVD solution
   (:func:`kabsch`, the paper's eq. 10) inside RANSAC, refitted on all inliers;
4. :func:`~.stages.run_icp`: GICP or point-to-plane ICP (:func:`refine_icp`, small_gicp) on evenly
   strided subsets of the voxel-downsampled clouds (:class:`IcpCloud`), and its information
   (:func:`information_from_icp`, ``[rot, trans]``, scaled by the NEES-calibrated
   ``icp.information_scale`` and the sensor's ``noise.information_correlation``);
5. :func:`~.stages.handle_weak_directions`: on plane-like pairs (a wall) whose ICP pose disagrees
   with the keypoints in the plane, the in-plane shifts and the spin (:func:`plane_directions`)
   go to the keypoints' optimum given ICP's normal shift and tilts (:func:`joint_keypoint_step`);
   when ICP lost the keypoints on weak geometry, its flat directions come from RANSAC's pose;
6. :func:`~.stages.joint_information`: ICP's and the keypoints' information; on other weak pairs
   ICP's pose is checked against the joint optimum;
7. :func:`~.refinement.dense_stage`: dense point-to-plane alignment of every
   ``dense.stride_px``-th pixel of both organised maps (:meth:`FppPairRegistrar.refine_dense`,
   :mod:`frontend.dense_alignment`) with the keypoints as prior; its information (scaled by
   ``dense.information_scale``) replaces ICP's. Plane-like pairs (three weak directions) keep
   step 5's pose, unless:
8. :func:`~.refinement.photometric_stage`: with the rig's :class:`TextureCamera`
   (``FppPairRegistrar(texture_camera=...)``), plane-like pairs take every plane-like ICP pose
   through the keypoints' in-plane optimum (step 5), a dense fit with the in-plane directions
   held gives the tilts and the distance, and :meth:`FppPairRegistrar.refine_plane_photometric`
   sets the in-plane shifts and spin from the texture
   (:func:`frontend.localization.localize_photometric` with the FPP shading model, the
   geometry's directions held). Its information joins the constraint, not the gates. An
   appearance-only loop candidate takes step 9's look-alike test first (``Checkpoint.REVISIT``):
   the step costs 2-3 s a pair at 1920x1200 and a look-alike place is refused anyway;
9. :func:`~.refinement.check_weak_geometry`: whether the keypoints pin weak joint geometry
   (:func:`check_degeneracy`) and, for appearance-only loop candidates, whether the textures
   agree over the overlap (:func:`texture_agreement`).

Every rejection reason is one row of the gate table :data:`.gates.GATES` (too few
matches/inliers, ICP leaving the RANSAC basin, low fitness/overlap, high inlier RMSE, look-alike
places, degenerate geometry), checked after the stage whose result it reads.

A pair that fails any check returns ``Constraint.rejected(...)`` with the reason; a pair that
cannot be attempted at all (no texture, no 3D points) is rejected the same way, so a caller
looping over candidates never sees an exception for bad overlap or bad frames.

Error convention of the information matrix: ``e = Log(T_true^-1 T_est)`` (right perturbation,
``T_est = T_true Exp(e)``), ``e = [omega (rad), v (m)]``, as :mod:`fpp_graph.geometry` and GTSAM.

Layout: algorithms in :mod:`.keypoints` (lift, RANSAC, keypoint information), :mod:`.icp`,
:mod:`.weak_directions` and :mod:`.texture`; the stages in :mod:`.stages` (1-6) and
:mod:`.refinement` (7-9); the running state in :mod:`.state`; the rejections in :mod:`.gates`;
the orchestrator and per-frame caches in :mod:`.registrar`.
"""

from fpp_graph.geometry import kabsch
from frontend.organised_surface import fit_pinhole
from frontend.registration.icp import (
    ICP_SOURCE_MAX_POINTS,
    ICP_TARGET_MAX_POINTS,
    IcpCloud,
    IcpResult,
    IcpRole,
    information_from_icp,
    organised_subsample,
    prepare_icp_cloud,
    refine_icp,
)
from frontend.registration.keypoints import (
    RansacResult,
    drop_sensor_fixed_matches,
    information_from_keypoints,
    keypoint_inliers,
    lift_keypoints,
    ransac_rigid,
)
from frontend.registration.registrar import FppPairRegistrar, with_features
from frontend.registration.texture import TextureAgreement, TextureCamera, texture_agreement
from frontend.registration.weak_directions import (
    Degeneracy,
    centred_coordinates,  # noqa: F401  (private; the tests import it from here)
    check_degeneracy,
    disagreement_along,  # noqa: F401  (private; the tests import it from here)
    joint_keypoint_step,
    plane_directions,
    weak_direction_pin,
    weak_directions_from,  # noqa: F401  (private; the tests import it from here)
    without_weak_directions,
)

__all__ = [
    "ICP_SOURCE_MAX_POINTS",
    "ICP_TARGET_MAX_POINTS",
    "Degeneracy",
    "FppPairRegistrar",
    "IcpCloud",
    "IcpResult",
    "IcpRole",
    "RansacResult",
    "TextureAgreement",
    "TextureCamera",
    "check_degeneracy",
    "drop_sensor_fixed_matches",
    "fit_pinhole",
    "information_from_icp",
    "information_from_keypoints",
    "joint_keypoint_step",
    "kabsch",
    "keypoint_inliers",
    "lift_keypoints",
    "organised_subsample",
    "plane_directions",
    "prepare_icp_cloud",
    "ransac_rigid",
    "refine_icp",
    "texture_agreement",
    "weak_direction_pin",
    "with_features",
    "without_weak_directions",
]
