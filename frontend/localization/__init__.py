"""Locating a camera in the map from its texture image: the paper's localisation (eqs. 11-21).

Two steps, each a public function:

- :func:`localize_dlt` (``dlt.py``): DLT on 3D map points and their 2D keypoints, in RANSAC, then
  Levenberg-Marquardt on the reprojection error.
- :func:`localize_photometric` (``photometric.py``): direct photometric refinement of that pose
  against map frames (:class:`DenseReference`) with the FPP texture's shading model.

``reference.py`` prepares a reference frame's pixels for the photometric step (once per frame).
``surface.py`` holds what the photometric step needs of an organised FPP map: range smoothing
along the rays, the depth-edge mask, normals and the projector's irradiance.
"""

from frontend.localization.dlt import (
    DltSettings,
    LocalizationResult,
    localize_dlt,
)
from frontend.localization.photometric import (
    PhotometricQuery,
    PhotometricSettings,
    localize_photometric,
    pyramid_for_start,
)
from frontend.localization.reference import DenseReference, ReferencePixels, reference_pixels

__all__ = [
    "DenseReference",
    "DltSettings",
    "LocalizationResult",
    "PhotometricQuery",
    "PhotometricSettings",
    "ReferencePixels",
    "localize_dlt",
    "localize_photometric",
    "pyramid_for_start",
    "reference_pixels",
]
