"""A reference frame of the photometric step and its usable pixels, prepared once per frame.

:func:`reference_pixels` picks, smooths and lifts the pixels of one map frame that
:func:`frontend.localization.localize_photometric` aligns; they depend on the frame and the
settings alone, not on the query, so a caller that aligns several views against one frame (a
registrar's loop candidates against one keyframe) can prepare them once and pass them in
(``reference_pixels=``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import transform_points
from frontend.localization.surface import (
    adaptive_smoothing_scale,
    depth_edge_free_mask,
    organised_normals_at,
    projector_irradiance,
    smoothing_scale,
    with_normal_stencil,
)

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class DenseReference:
    """One map frame for :func:`localize_photometric`.

    Attributes
    ----------
    xyz_map : (H, W, 3) float64
        Organised points in the frame's own sensor frame, metres, NaN where invalid.
    texture : (H, W) uint8
        Its texture image.
    T_world_reference : (4, 4) float64
        The frame's pose in the map (identity: the frame is the world).
    """

    xyz_map: NDArray
    texture: NDArray
    T_world_reference: NDArray = field(default_factory=lambda: np.eye(4))


@dataclass(frozen=True, eq=False)
class ReferencePixels:
    """The usable pixels of one :class:`DenseReference` (:func:`reference_pixels`).

    Attributes
    ----------
    index : (N,) int64
        Flat pixel index in the reference's maps.
    X_world, n_world : (N, 3) float64
        Points (smoothed along their rays) and unit normals in the world frame (NaN normals where unknown).
    E_ref : (N,) float64
        The projector's irradiance at each point in the reference view (1 without a projector).
    has_normal : (N,) bool
    settings : tuple
        What they were computed with (projector centre, max pixels, normal step, the two
        smoothing widths); :func:`localize_photometric` refuses them for other settings.
    """

    index: NDArray[np.int64]
    X_world: Array
    n_world: Array
    E_ref: Array
    has_normal: NDArray[np.bool_]
    settings: tuple


def smoothing_widths(width_px: int, range_smoothing_px: float | None, max_range_smoothing_px: float | None) -> tuple[float, float]:
    """The range smoothing's narrow and wide widths (pixels) for a ``width_px`` wide image:
    defaults ``width / 960`` (2 px at 1920) and five times that (see :func:`localize_photometric`)."""
    narrow = width_px / 960.0 if range_smoothing_px is None else float(range_smoothing_px)
    return narrow, 5.0 * narrow if max_range_smoothing_px is None else float(max_range_smoothing_px)


def pixel_settings(projector_centre_m: Array | None, max_pixels: int, normal_step_px: int, smoothing_px: float, max_smoothing_px: float) -> tuple:
    """The :attr:`ReferencePixels.settings` key of these arguments."""
    centre = None if projector_centre_m is None else tuple(float(c) for c in np.asarray(projector_centre_m, dtype=np.float64).reshape(3))
    return (centre, int(max_pixels), int(normal_step_px), float(smoothing_px), float(max_smoothing_px))


_STORED = ("index", "X_world", "n_world", "E_ref", "has_normal")


def settings_array(settings: tuple) -> Array:
    """:attr:`ReferencePixels.settings` as 7 numbers (projector centre NaN when there is none)."""
    centre, max_pixels, normal_step_px, smoothing_px, max_smoothing_px = settings
    return np.array([*((math.nan,) * 3 if centre is None else centre), max_pixels, normal_step_px, smoothing_px, max_smoothing_px], dtype=np.float64)


def reference_to_arrays(pixels: ReferencePixels, prefix: str) -> dict[str, NDArray]:
    """``pixels`` as named arrays (``prefix`` + field name, and ``prefix + "settings"``), e.g. for
    :attr:`fpp_graph.types.Frame.prepared`; :func:`reference_from_arrays` reads them back."""
    arrays: dict[str, NDArray] = {prefix + name: getattr(pixels, name) for name in _STORED}
    arrays[prefix + "settings"] = settings_array(pixels.settings)
    return arrays


def reference_from_arrays(arrays: Mapping[str, NDArray], prefix: str, settings: tuple) -> ReferencePixels | None:
    """The pixels :func:`reference_to_arrays` stored under ``prefix``, if they were prepared with
    ``settings`` (:func:`pixel_settings`); None when absent or made with other settings."""
    stored = arrays.get(prefix + "settings")
    if stored is None or not all(prefix + name in arrays for name in _STORED):
        return None
    wanted = settings_array(settings)
    if stored.shape != wanted.shape or not np.array_equal(stored, wanted, equal_nan=True):
        return None
    return ReferencePixels(*(np.asarray(arrays[prefix + name]) for name in _STORED), settings=settings)


def reference_settings(
    width_px: int, projector_centre_m: Array | None = None, max_pixels: int = 150_000, normal_step_px: int = 4,
    range_smoothing_px: float | None = None, max_range_smoothing_px: float | None = None,
) -> tuple:
    """The :attr:`ReferencePixels.settings` of :func:`reference_pixels` with these arguments."""
    return pixel_settings(projector_centre_m, max_pixels, normal_step_px, *smoothing_widths(width_px, range_smoothing_px, max_range_smoothing_px))


def reference_pixels(
    ref: DenseReference, projector_centre_m: Array | None = None, max_pixels: int = 150_000, normal_step_px: int = 4,
    range_smoothing_px: float | None = None, max_range_smoothing_px: float | None = None, width_px: int | None = None,
) -> ReferencePixels:
    """The pixels of ``ref`` that :func:`localize_photometric` with the same arguments would align
    (``width_px``: the query's image width, which sets the default smoothing; default the reference's)."""
    width = int(np.shape(ref.texture)[1]) if width_px is None else int(width_px)
    settings = reference_settings(width, projector_centre_m, max_pixels, normal_step_px, range_smoothing_px, max_range_smoothing_px)
    smoothing_px, max_smoothing_px = settings[3], settings[4]
    return ReferencePixels(*reference_pixel_arrays(ref, projector_centre_m, max_pixels, normal_step_px, smoothing_px, max_smoothing_px), settings=settings)


def reference_pixel_arrays(
    ref: DenseReference, projector_centre_m: Array | None, max_pixels: int, normal_step_px: int, range_smoothing_px: float,
    max_range_smoothing_px: float = 0.0,
) -> tuple[NDArray[np.int64], Array, Array, Array, NDArray[np.bool_]]:
    """Flat pixel index, world points, world normals and projector irradiance of the usable pixels of one
    reference: valid, away from depth edges by the smoothing's reach (:func:`depth_edge_free_mask`),
    not saturated or black, the ``max_pixels`` with the strongest texture gradient.

    The points are smoothed along their rays (:func:`smoothing_scale`, up to
    ``max_range_smoothing_px`` where the data allow: :func:`adaptive_smoothing_scale`): an
    FPP point's range noise (about 0.25 mm per pixel at 1920x1200) moves its projection in the
    other view by a good fraction of a pixel, and errors in the regressors bias a photometric fit
    (errors-in-variables: the bias grows with the regressors' noise variance, which the smoothing
    divides)."""
    xyz = np.asarray(ref.xyz_map, dtype=np.float64)
    tex = np.asarray(ref.texture)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or tex.shape != xyz.shape[:2]:
        raise InputDataError(f"photometric localisation needs an (H, W, 3) xyz map and an H x W texture of one frame, got {xyz.shape} and {tex.shape}")
    T = np.asarray(ref.T_world_reference, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputDataError("photometric localisation: T_world_reference must be a finite 4x4 pose")
    intensity = tex.astype(np.float32)
    # the smoothing's reach: past ~2.5 sigma a Gaussian's weights are below 5 % of its peak
    smooth = depth_edge_free_mask(xyz[..., 2], max(2, math.ceil(2.5 * range_smoothing_px))) & (intensity > 2) & (intensity < 250)
    grad = np.abs(cv2.Sobel(intensity, cv2.CV_32F, 1, 0, ksize=3)) + np.abs(cv2.Sobel(intensity, cv2.CV_32F, 0, 1, ksize=3))
    idx = np.flatnonzero(smooth.ravel())
    if idx.size > max_pixels:
        g = grad.ravel()[idx]
        idx = idx[np.argpartition(g, idx.size - max_pixels)[idx.size - max_pixels:]]
    scale = None
    if range_smoothing_px > 0 and smooth.any():
        if max_range_smoothing_px > range_smoothing_px:
            # the factor where it is read (the pixels and their normals' stencil), NaN elsewhere
            read = idx if projector_centre_m is None else with_normal_stencil(idx, xyz.shape[:2], normal_step_px)
            scale = np.full(xyz.shape[:2], np.nan)
            scale.flat[read] = adaptive_smoothing_scale(xyz[..., 2], range_smoothing_px, max_range_smoothing_px, at=read)
        else:
            scale = smoothing_scale(xyz[..., 2], range_smoothing_px)
    X = xyz.reshape(-1, 3)[idx]
    if scale is not None:
        X = X * scale.ravel()[idx, None]
    if projector_centre_m is None:
        E = np.ones(idx.size)
        n_world = np.full((idx.size, 3), np.nan)
        has_normal = np.zeros(idx.size, bool)
    else:
        n = organised_normals_at(xyz, idx, normal_step_px, scale)
        E, _ = projector_irradiance(n, projector_centre_m - X)
        has_normal = np.isfinite(E) & (E > 0)
        n_world = n @ np.ascontiguousarray(T[:3, :3].T)
    return idx, transform_points(T, X), n_world, E, has_normal
