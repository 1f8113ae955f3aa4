"""Organised FPP maps as surfaces for photometric localisation: range smoothing along the rays,
depth-edge masks, normals and the projector's irradiance.

An FPP point's range noise (about 0.25 mm per pixel at 1920x1200) moves its projection in another
view by a good fraction of a pixel; these helpers smooth it without moving planes or (to first
order) curved relief, and keep pixels whose smoothing would reach across a depth edge out.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import row_bands
from frontend.dense_alignment import cross_rows

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


def projector_irradiance(normals: Array, to_projector: Array) -> tuple[Array, Array]:
    """The FPP texture's shading model: irradiance ``E = cos(theta) / d^2`` of surface points with
    unit ``normals`` from a projector at ``to_projector`` (point to projector, metres), and
    ``cos(theta)``; over the last axis, any leading shape."""
    return projector_irradiance_rows(np.moveaxis(normals, -1, 0), np.moveaxis(to_projector, -1, 0))


def projector_irradiance_rows(normals: Array, to_projector: Array) -> tuple[Array, Array]:
    """:func:`projector_irradiance` over the first axis (3, ...): for callers that hold coordinates
    as rows, which are picked and summed faster than (N, 3) records (the sums are those of
    ``np.linalg.norm`` and ``np.sum`` over the last axis, in their order)."""
    a0, a1, a2 = to_projector[0], to_projector[1], to_projector[2]
    d = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    cos = np.abs(normals[0] * a0 + normals[1] * a1 + normals[2] * a2) / d
    return cos / d**2, cos


def _twice_smoothed_inverse_depth(inv_z: NDArray, ok: NDArray[np.bool_], sigma_px: float) -> Array:
    """``2 G(f) - G(G(f))`` of inverse depth by normalised Gaussian convolution over the ``ok`` pixels
    (:class:`_BandedTwicing`), float64."""
    outside = ~ok
    f32 = np.empty(inv_z.shape, dtype=np.float32)
    _masked_float32(inv_z, outside, f32)
    bands = row_bands(inv_z.shape[0], SMOOTHING_BAND_ROWS)
    twicing = _BandedTwicing.of(f32, outside, sigma_px, ok.astype(np.float32), bands)
    out = np.empty(inv_z.shape, dtype=np.float64)
    for rows in bands:
        out[rows] = twicing.rows(rows)
    return out


def smoothing_scale(depth_m: Array, sigma_px: float) -> Array:
    """Per pixel, the factor ``smoothed depth / depth`` that moves organised points along their
    rays to a smoothed depth without the smoothing's bias (NaN where invalid).

    Inverse depth is smoothed (normalised Gaussian convolution over the valid pixels): on a plane
    it is affine in the pixel coordinates, so a plane stays exactly where it is. On a curved
    surface a Gaussian of variance s^2 shifts it by s^2/2 times its Laplacian; "twicing"
    (``2 G(f) - G(G(f))``) cancels that term, leaving a fourth-order bias ~s^4 of the surface's
    fourth derivatives. ``sigma_px`` is the Gaussian's standard deviation in pixels; the smoothed
    points are ``xyz_map * scale[..., None]`` (callers that need a few pixels scale just those:
    the full (H, W, 3) product costs ~0.1 s)."""
    z = depth_m
    ok = np.isfinite(z)
    inv_z = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
    twice = _twice_smoothed_inverse_depth(inv_z, ok, sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 / (twice * np.where(ok, z, np.nan))


@functools.lru_cache(maxsize=16)
def _smoother_noise_gains(small_px: float, large_px: float) -> tuple[float, float, float]:
    """White-noise gains (L2 norms) of the twicing kernels k_s, k_l: ``||delta - k_s||``,
    ``||k_s - k_l||`` and ``||G_l * (k_s - k_l)||`` (numerically, from an impulse)."""
    n = 2 * int(math.ceil(10.0 * large_px)) + 1
    impulse = np.zeros((n, n))
    impulse[n // 2, n // 2] = 1.0
    ok = np.ones((n, n), bool)
    k_small = _twice_smoothed_inverse_depth(impulse, ok, small_px)
    k_large = _twice_smoothed_inverse_depth(impulse, ok, large_px)
    diff = k_small - k_large
    diff_averaged = cv2.GaussianBlur(diff.astype(np.float32), (0, 0), large_px).astype(np.float64)
    return float(np.linalg.norm(impulse - k_small)), float(np.linalg.norm(diff)), float(np.linalg.norm(diff_averaged))


def adaptive_smoothing_scale(depth_m: Array, small_px: float, large_px: float, kappa: float = 3.0, at: NDArray[np.intp] | None = None) -> Array:
    """The factor of :func:`smoothing_scale` with ``large_px`` wherever the data cannot tell it from
    ``small_px``, else ``small_px``; with ``at`` (flat pixel indices) only at those pixels, (len(at),).

    A plane is exact under either width, and the range noise left falls as 1/width, so walls want
    the wide one; on curved relief (an object's limb) the wide one keeps a bias that the twicing does
    not cancel, small per pixel but the same over thousands of pixels, which is what moves a pose.
    The test (a Lepski-type choice of bandwidth) therefore looks at the two estimates'
    difference averaged over the wide window, where noise cancels and a bias does not: the wide one
    is used where that average, and the pixel's own difference, stay within ``kappa`` standard
    deviations of what noise alone gives. The noise level is local (the variance of the raw
    inverse depth about the narrow estimate over the wide window): it changes with range and albedo.

    Its eight Gaussian blurs run over the whole frame; the arithmetic between them runs in bands of
    :data:`SMOOTHING_BAND_ROWS` rows, each pixel's by itself, so the numbers are those of the
    whole-frame passes (tested) while a band's float64 planes stay in the core's cache. The last
    step (each pixel's choice between the widths) reads only its own pixel of the blurred planes,
    so a caller that needs a few pixels (the photometric reference: 100 000 of a 1920x1200 frame
    and their normals' neighbours) asks for those: the same numbers, without a third of the work."""
    z = depth_m
    ok = np.isfinite(z)
    outside = ~ok
    inv_z = np.zeros(z.shape, dtype=np.result_type(z, 1.0))
    np.divide(1.0, z, out=inv_z, where=ok)
    bands = row_bands(z.shape[0], SMOOTHING_BAND_ROWS)
    inv_z32 = inv_z.astype(np.float32)  # 0 outside already: the normalised blur's masking is a no-op here
    ok32 = ok.astype(np.float32)
    narrow = _BandedTwicing.of(inv_z32, outside, small_px, ok32, bands)
    wide = _BandedTwicing.of(inv_z32, outside, large_px, ok32, bands)  # its normalisation serves the local means too
    residual2 = np.empty_like(inv_z32)
    difference = np.empty_like(inv_z32)
    for rows in bands:
        narrow_rows, wide_rows = narrow.rows(rows), wide.rows(rows)
        r = inv_z[rows] - narrow_rows
        r *= r
        _masked_float32(r, outside[rows], residual2[rows])
        wide_rows -= narrow_rows
        _masked_float32(wide_rows, outside[rows], difference[rows])
    local_variance = cv2.GaussianBlur(residual2, (0, 0), large_px)
    local_difference = cv2.GaussianBlur(difference, (0, 0), large_px)
    gains = _smoother_noise_gains(float(small_px), float(large_px))

    def chosen(pick, narrow: _BandedTwicing, wide: _BandedTwicing, local_variance, local_difference, ok, z) -> tuple[Array, int]:
        """The factor at the pixels ``pick`` selects (a band's rows, or flat indices into raveled planes)
        and how many took the wide width."""
        narrow_at, wide_at = narrow.rows(pick), wide.rows(pick)
        use_wide = _wide_is_unbiased(narrow_at, wide_at, local_variance[pick], local_difference[pick], wide.den[pick], ok[pick], gains, kappa)
        return 1.0 / (np.where(use_wide, wide_at, narrow_at) * np.where(ok[pick], z[pick], np.nan)), int(np.count_nonzero(use_wide))

    planes = (narrow, wide, local_variance, local_difference, ok, z)
    with np.errstate(invalid="ignore", divide="ignore"):
        if at is not None:
            # flat indices into raveled planes: picking by (row, column) pairs costs several times more
            flat = np.asarray(at, dtype=np.intp)
            scale, wide_pixels = chosen(flat, *(p.raveled() if isinstance(p, _BandedTwicing) else p.reshape(-1) for p in planes))
            counted = int(np.count_nonzero(ok.reshape(-1)[flat]))
        else:
            scale, wide_pixels, counted = np.empty(z.shape, dtype=np.float64), 0, int(ok.sum())
            for rows in bands:
                scale[rows], band_wide_pixels = chosen(rows, *planes)
                wide_pixels += band_wide_pixels
    log.debug("adaptive range smoothing: %.0f%% of %d pixels at %.1f px, the rest at %.1f px", 100.0 * wide_pixels / max(counted, 1), counted, large_px, small_px)
    return scale


SMOOTHING_BAND_ROWS = 32
"""Rows per band of :func:`adaptive_smoothing_scale`'s per-pixel arithmetic: 32 rows of a
1920-pixel frame are 0.5 MB per float64 plane, and a band's few planes fit a 4 MB L2 cache."""


def _masked_float32(values: Array, outside: NDArray[np.bool_], out: NDArray[np.float32]) -> None:
    """``out[:] = values`` as float32, 0 where ``outside``: a normalised blur's input."""
    out[...] = values
    np.putmask(out, outside, np.float32(0.0))


@dataclass(frozen=True, eq=False)
class _BandedTwicing:
    """``2 G(f) - G(G(f))`` of one width by normalised convolution (``G(f where valid, else 0) /
    max(G(valid), 1e-6)``, the Gaussians in float32, the quotients in float64), kept as its two
    float32 blurs and their normalisation ``den`` and evaluated a band of rows at a time (:meth:`rows`)."""

    den: NDArray[np.float32]
    once: NDArray[np.float32]
    again: NDArray[np.float32]

    @classmethod
    def of(cls, f32: NDArray[np.float32], outside: NDArray[np.bool_], sigma_px: float, ok32: NDArray[np.float32], bands: list[slice]) -> _BandedTwicing:
        """Of ``f32`` (0 ``outside`` the valid pixels, whose indicator is ``ok32``)."""
        den = np.maximum(cv2.GaussianBlur(ok32, (0, 0), sigma_px), np.float32(1e-6))
        once = cv2.GaussianBlur(f32, (0, 0), sigma_px)
        normalised = np.empty_like(f32)
        for rows in bands:
            _masked_float32(np.divide(once[rows], den[rows], dtype=np.float64), outside[rows], normalised[rows])
        return cls(den, once, cv2.GaussianBlur(normalised, (0, 0), sigma_px))

    def raveled(self) -> _BandedTwicing:
        """The same planes raveled, for :meth:`rows` of flat pixel indices."""
        return _BandedTwicing(self.den.reshape(-1), self.once.reshape(-1), self.again.reshape(-1))

    def rows(self, pick: slice | NDArray[np.intp]) -> Array:
        """The twice-smoothed values of the pixels ``pick`` selects (a band's rows, or flat indices
        into :meth:`raveled` planes), float64."""
        out = np.divide(self.once[pick], self.den[pick], dtype=np.float64)
        out *= 2.0
        out -= np.divide(self.again[pick], self.den[pick], dtype=np.float64)
        return out


def _wide_is_unbiased(
    narrow: Array, wide: Array, local_variance: NDArray[np.float32], local_difference: NDArray[np.float32], den: NDArray[np.float32],
    ok: NDArray[np.bool_], gains: tuple[float, float, float], kappa: float,
) -> NDArray[np.bool_]:
    """Pixels where the wide estimate stays within ``kappa`` noise deviations of the narrow one,
    pixel by pixel and averaged over the wide window (see :func:`adaptive_smoothing_scale`);
    ``local_variance`` / ``local_difference``: the blurred squared residual about the narrow
    estimate and the blurred difference, ``den`` their normalisation."""
    gain_residual, gain_difference, gain_averaged = gains
    sigma_pixel = np.sqrt(np.divide(local_variance, den, dtype=np.float64))
    sigma_pixel /= gain_residual  # raw inverse-depth noise
    use_wide = np.abs(np.divide(local_difference, den, dtype=np.float64)) < kappa * gain_averaged * sigma_pixel
    use_wide &= ok
    use_wide &= np.abs(wide - narrow) < kappa * gain_difference * sigma_pixel
    return use_wide


def depth_edge_free_mask(depth_m: NDArray, reach_px: int, kappa: float = 8.0, relative_floor: float = 1e-4) -> NDArray[np.bool_]:
    """Valid pixels farther than ``reach_px`` from a depth edge or an invalid pixel.

    A depth edge is a second difference of inverse depth along a row or a column above ``kappa``
    robust standard deviations of the frame's second differences (or ``relative_floor`` of the
    median inverse depth, for noise-free maps). A plane at any slant has none (its inverse depth is
    affine in the pixels), so tilted walls and tables stay in, while a test of the depth spanned by
    a window would drop every surface tilted beyond about 70 degrees and keep pixels whose
    smoothing reaches across an edge.

    ``depth_m`` is (H, W), metres, NaN where invalid; returns (H, W) bool.
    """
    z = np.asarray(depth_m, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.float32(1.0) / z
    finite = np.isfinite(inv_z) & (z > 0)
    if not finite.any():
        return finite
    d2u = np.full(z.shape, np.nan, np.float32)
    d2v = np.full(z.shape, np.nan, np.float32)
    for d2, ahead, here, behind in ((d2u[:, 1:-1], inv_z[:, 2:], inv_z[:, 1:-1], inv_z[:, :-2]), (d2v[1:-1], inv_z[2:], inv_z[1:-1], inv_z[:-2])):
        np.add(ahead, behind, out=d2)  # in place: full-size temporaries cost more than the arithmetic
        d2 -= here
        d2 -= here
    sample = np.abs(np.concatenate([d2u[::3].ravel(), d2v[:, ::3].ravel()]))
    sample = sample[np.isfinite(sample)]
    floor = relative_floor * float(np.median(inv_z[::3, ::3][finite[::3, ::3]])) if finite[::3, ::3].any() else 0.0
    threshold = max(kappa * 1.4826 * float(np.median(sample)) if sample.size else 0.0, floor)
    with np.errstate(invalid="ignore"):
        smooth = finite & (np.abs(d2u) < threshold) & (np.abs(d2v) < threshold)  # NaN (border, holes) fails
    r = max(1, int(reach_px))
    return cv2.erode(smooth.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))) > 0


def organised_normals_at(xyz_map: NDArray, flat_index: NDArray, step_px: int, scale: NDArray | None = None) -> Array:
    """Unit normals (N, 3) of an organised map at some pixels (``flat_index`` into the H x W grid), of
    ``xyz_map * scale[..., None]`` when a per-pixel ``scale`` is given: central differences ``step_px``
    pixels apart along u and v, NaN within ``step_px`` of the border or next to an invalid point.
    Their sign is arbitrary (callers use ``|n . d|``); ``scale`` is read at :func:`with_normal_stencil`'s pixels only."""
    xyz = np.asarray(xyz_map, dtype=np.float64)
    inside, (right, left, below, above) = _normal_stencil(flat_index, xyz.shape[:2], step_px)
    # flat indices: picking 100 000 pixels of a 1920x1200 map by (row, column) pairs cost 4x more
    xyz_flat = xyz.reshape(-1, 3)
    scale_flat = None if scale is None else np.asarray(scale).reshape(-1)

    def at(i: NDArray[np.intp]) -> Array:
        return xyz_flat[i] if scale_flat is None else xyz_flat[i] * scale_flat[i][:, None]

    du = at(right) - at(left)
    dv = at(below) - at(above)
    n = cross_rows(du, dv).T
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[~inside] = np.nan
    return n


def with_normal_stencil(flat_index: NDArray, shape: tuple[int, int], step_px: int) -> NDArray[np.intp]:
    """The pixels ``flat_index`` and those :func:`organised_normals_at` reads for their normals, as
    sorted unique flat indices: a caller that scales only some pixels (:func:`adaptive_smoothing_scale`'s
    ``at``) scales these."""
    read = np.zeros(int(shape[0]) * int(shape[1]), dtype=bool)
    read[np.asarray(flat_index, dtype=np.intp)] = True
    for pixels in _normal_stencil(flat_index, shape, step_px)[1]:
        read[pixels] = True
    return np.flatnonzero(read)


def _normal_stencil(flat_index: NDArray, shape: tuple[int, int], step_px: int) -> tuple[NDArray[np.bool_], tuple[NDArray[np.intp], ...]]:
    """Whether each pixel is ``step_px`` inside the border, and the flat indices of its right, left,
    lower and upper neighbours ``step_px`` away (clamped inside the grid)."""
    H, W = int(shape[0]), int(shape[1])
    k = int(step_px)
    r, c = np.divmod(np.asarray(flat_index, dtype=np.int64), W)
    inside = (c >= k) & (c < W - k) & (r >= k) & (r < H - k)
    r, c = np.clip(r, k, max(k, H - k - 1)), np.clip(c, k, max(k, W - k - 1))
    return inside, (r * W + np.minimum(c + k, W - 1), r * W + (c - k), np.minimum(r + k, H - 1) * W + c, (r - k) * W + c)
