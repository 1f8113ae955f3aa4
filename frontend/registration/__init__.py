"""Pairwise registration of frames with a texture and an organised point map: the project's
:class:`~fpp_graph.types.PairRegistrar`, :class:`TexturedSurfaceRegistrar`.

``TexturedSurfaceRegistrar.register(target, source)`` runs a list of stages, each an object built
from the registration config with a typed input and a frozen result, every result checked by its
rows of the gate table (:data:`.gates.GATES`): keypoint matching, the lift to 3D, closed-form
RANSAC (:func:`kabsch`, the paper's eq. 10), ICP through a :class:`PointCloudAligner`
(small_gicp's by default, :func:`~.icp.make_aligner`), the weak directions from the keypoints,
the joint information (:mod:`.stages`); the dense fit over every ``noise.dense_stride_px``-th
pixel, the photometric step on planes with the rig's :class:`TextureCamera`, and the weak-geometry
check (:mod:`.refinement`). docs/registration.md describes each.

A pair that fails a gate, or cannot be attempted at all (no texture, no 3D points), returns
``Constraint.rejected(...)`` with the reason, so a caller looping over candidates never sees an
exception for bad overlap or bad frames.

Error convention of the information matrix: ``e = Log(T_true^-1 T_est)`` (right perturbation,
``T_est = T_true Exp(e)``), ``e = [omega (rad), v (m)]``, as :mod:`fpp_graph.geometry` and GTSAM.

Layout: algorithms in :mod:`.keypoints`, :mod:`.icp` (the protocol in :mod:`.aligner`),
:mod:`.weak_directions` and :mod:`.texture`; the stages in :mod:`.stages` (1-6) and
:mod:`.refinement` (7-9); the pair's shared input and report in :mod:`.state`; the rejections in
:mod:`.gates`; the list of stages in :mod:`.registrar`; tracking from a prediction in :mod:`.tracking`.
"""

import warnings

from fpp_graph.geometry import kabsch
from frontend.organised_surface import fit_pinhole, lift_keypoints
from frontend.registration.aligner import AlignmentRequest, PointCloudAligner
from frontend.registration.icp import make_aligner
from frontend.registration.registrar import TexturedSurfaceRegistrar
from frontend.registration.texture import TextureCamera


def __getattr__(name: str):
    """``FppPairRegistrar``: the former name of :class:`TexturedSurfaceRegistrar` (deprecated)."""
    if name == "FppPairRegistrar":
        warnings.warn("frontend.registration.FppPairRegistrar is deprecated: use TexturedSurfaceRegistrar", DeprecationWarning, stacklevel=2)
        return TexturedSurfaceRegistrar
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "AlignmentRequest",
    "PointCloudAligner",
    "TexturedSurfaceRegistrar",
    "make_aligner",
    "TextureCamera",
    "fit_pinhole",
    "kabsch",
    "lift_keypoints",
]
