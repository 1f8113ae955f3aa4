"""Pairwise registration of frames with a texture and an organised point map: the project's
:class:`~fpp_graph.types.PairRegistrar`, :class:`TexturedSurfaceRegistrar`.

``TexturedSurfaceRegistrar.register(target, source)`` runs a list of stages, each an object built
from the registration config with a typed input and a frozen result (:mod:`.stages`,
:mod:`.refinement`), every result checked by its rows of the gate table (:data:`.gates.GATES`):

1. :class:`~.stages.KeypointMatching`: keypoints on both texture images
   (:func:`frontend.features.detect.detect_and_describe`, once per frame), descriptor matches with
   ratio test and mutual check, the projector's sensor-fixed features dropped
   (:func:`drop_sensor_fixed_matches`);
2. :class:`~.stages.MatchLifting`: matched keypoints to 3D through each frame's ``xyz_map``
   (:func:`lift_keypoints`: bilinear where the four neighbouring pixels are valid and on one
   surface, else skipped);
3. :class:`~.stages.KeypointRansac`: ``T_target_source`` from 3-point samples by the closed-form
   SVD solution (:func:`kabsch`, the paper's eq. 10) inside RANSAC, refitted on all inliers;
4. :class:`~.stages.IcpStage`: ICP through a :class:`PointCloudAligner` (small_gicp's GICP or
   point-to-plane ICP, :func:`~.icp.make_aligner`) on evenly strided subsets of the
   voxel-downsampled clouds (:class:`IcpCloud`), and its information (:func:`information_from_icp`,
   ``[rot, trans]``, scaled by the sensor's ``noise.information_correlation``);
5. :class:`~.stages.WeakDirectionStage`: on plane-like pairs (a wall) whose ICP pose disagrees
   with the keypoints in the plane, the in-plane shifts and the spin (:func:`plane_directions`)
   go to the keypoints' optimum given ICP's normal shift and tilts (:func:`joint_keypoint_step`);
   when ICP lost the keypoints on weak geometry, its flat directions come from RANSAC's pose;
6. :class:`~.stages.JointInformationStage`: ICP's and the keypoints' information; on other weak
   pairs ICP's pose is checked against the joint optimum;
7. :class:`~.refinement.DenseStage`: dense point-to-plane alignment of every
   ``noise.dense_stride_px``-th pixel of both organised maps (:mod:`frontend.dense_alignment`)
   with the keypoints as prior; its information replaces ICP's. Plane-like pairs keep stage 5's
   pose, unless:
8. :class:`~.refinement.PhotometricStage`: with the rig's :class:`TextureCamera`
   (``TexturedSurfaceRegistrar(texture_camera=...)``), a plane's tilts and distance come from a
   dense fit with its in-plane directions held, and the in-plane shifts and spin from the texture
   (:func:`frontend.localization.localize_photometric` with the FPP shading model, the
   geometry's directions held). Its information joins the constraint, not the gates. An
   appearance-only loop candidate takes stage 9's look-alike test first (``Checkpoint.REVISIT``);
9. :class:`~.refinement.WeakGeometryStage`: whether the keypoints pin weak joint geometry
   (:func:`check_degeneracy`) and, for appearance-only loop candidates, whether the textures
   agree over the overlap (:func:`texture_agreement`).

A pair that fails a gate returns ``Constraint.rejected(...)`` with the reason; a pair that cannot
be attempted at all (no texture, no 3D points) is rejected the same way, so a caller looping over
candidates never sees an exception for bad overlap or bad frames.

Error convention of the information matrix: ``e = Log(T_true^-1 T_est)`` (right perturbation,
``T_est = T_true Exp(e)``), ``e = [omega (rad), v (m)]``, as :mod:`fpp_graph.geometry` and GTSAM.

Layout: algorithms in :mod:`.keypoints` (RANSAC, keypoint information), :mod:`.icp` (with the
aligner protocol in :mod:`.aligner`), :mod:`.weak_directions` and :mod:`.texture`; the stages in
:mod:`.stages` (1-6) and :mod:`.refinement` (7-9); the pair's shared input and report in
:mod:`.state`; the rejections in :mod:`.gates`; the list of stages in :mod:`.registrar`; tracking
from a motion prediction in :mod:`.tracking`.
"""

import warnings

from fpp_graph.geometry import kabsch
from frontend.organised_surface import fit_pinhole, lift_keypoints
from frontend.registration.aligner import AlignmentRequest, PointCloudAligner
from frontend.registration.icp import (
    ICP_SOURCE_MAX_POINTS,
    ICP_TARGET_MAX_POINTS,
    IcpCloud,
    IcpResult,
    IcpRole,
    SmallGicpAligner,
    information_from_icp,
    make_aligner,
    organised_subsample,
    prepare_icp_cloud,
    refine_icp,
)
from frontend.registration.keypoints import (
    RansacResult,
    drop_sensor_fixed_matches,
    information_from_keypoints,
    keypoint_inliers,
    ransac_rigid,
)
from frontend.registration.registrar import TexturedSurfaceRegistrar, with_features
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



def __getattr__(name: str):
    """``FppPairRegistrar``: the former name of :class:`TexturedSurfaceRegistrar` (deprecated)."""
    if name == "FppPairRegistrar":
        warnings.warn("frontend.registration.FppPairRegistrar is deprecated: use TexturedSurfaceRegistrar", DeprecationWarning, stacklevel=2)
        return TexturedSurfaceRegistrar
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "AlignmentRequest",
    "PointCloudAligner",
    "SmallGicpAligner",
    "TexturedSurfaceRegistrar",
    "make_aligner",
    "ICP_SOURCE_MAX_POINTS",
    "ICP_TARGET_MAX_POINTS",
    "Degeneracy",
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
