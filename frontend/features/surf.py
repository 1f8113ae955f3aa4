"""SURF (Bay et al. 2008) on integral images, in numpy + OpenCV primitives.

OpenCV's pip wheels leave SURF out (it sits behind the non-free build flag), and the paper uses
SURF on the texture images, so the project carries its own. The algorithm is the published one:

1. **Fast-Hessian detector.** The determinant of the Hessian is approximated with box filters
   ``Dxx, Dyy, Dxy`` read from an integral image: filter sizes ``L = 9, 15, 21, 27`` in octave 1,
   doubling the size increment per octave (``15, 27, 39, 51``; ``27, 51, 75, 99``; ...), the
   response ``det = Dxx Dyy - (0.9 Dxy)^2`` (each filter normalised by ``L^2``) sampled every
   ``2^o`` pixels in octave ``o``. Maxima over the 3x3x3 neighbourhood in (scale, y, x) above the
   threshold are interpolated to sub-pixel and sub-scale by a quadratic fit; the scale is
   ``s = 1.2 L / 9``.
2. **Orientation.** Haar wavelet responses of size ``4s`` at the 109 samples of step ``s`` inside a
   circle of radius ``6s``, Gaussian-weighted (sigma ``2s``); a sliding window of pi/3 picks the
   dominant summed direction.
3. **Descriptor.** A ``20s`` square window rotated to the orientation, 4x4 sub-regions of 5x5
   samples; Haar responses of size ``2s`` rotated into the keypoint frame and Gaussian-weighted
   (sigma ``3.3s``) give ``(sum dx, sum dy, sum |dx|, sum |dy|)`` per sub-region: 64 values,
   normalised to unit length.

Speed comes from whole-array work: the working image holds exact integer sums of pixel blocks
(integer box filters run twice as fast as float ones); the detector's first octave is dense
``cv2.boxFilter`` sums, later octaves read all box sums of one filter size at once by strided
slicing of the integral image, and only det(H) is kept per layer (the Laplacian sign is read at
the keypoints). The Haar responses of steps 2 and 3 are dense images (two box sums ``half``
apart, per wavelet size, on the pyramid level where the wavelet spans 4-8 pixels), ``dx`` and
``dy`` as two 1-channel images read at all keypoints' rotated sample points by one
``cv2.remap`` each per scale band; the sample positions come from one small matrix product, the
4x4 sub-region sums from one product with a (400, 16) weight matrix. The dense-band sampling
replaces the exact per-sample integral-image lookups by bilinear interpolation of the same box
sums, a sub-sample approximation of the same wavelet. On a 1920x1200 texture (960x600 working
image, ~1800 keypoints) detection + description takes about 50-60 ms of one core
(``scripts/bench_registration.py``).

Steps 2 and 3 are in :mod:`frontend.features.surf_descriptors`.

Images wider than ``max_working_width`` are first reduced by an integer factor with area
averaging (the original SURF likewise starts at sampling step 2); coordinates and scales are
returned in full-image pixels.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from frontend.features.surf_descriptors import HaarBank, descriptors, orientations

log = logging.getLogger(__name__)

_SCALE_PER_FILTER = 1.2 / 9.0


@dataclass(frozen=True)
class SurfParams:
    """Parameters of the SURF detector/descriptor.

    Attributes
    ----------
    hessian_threshold : float
        Minimum ``det(H)`` of a keypoint, on the image scaled to [0, 1].
    n_octaves, n_intervals : int
        Scale-space size (4 intervals per octave as in the paper).
    max_features : int
        Keep at most this many keypoints, strongest first.
    upright : bool
        Skip orientation assignment (U-SURF); faster, not rotation invariant.
    max_working_width : int
        Reduce wider images by an integer factor before detection (0 disables).
    """

    hessian_threshold: float = 1e-4
    n_octaves: int = 4
    n_intervals: int = 4
    max_features: int = 4000
    upright: bool = False
    max_working_width: int = 1024


@dataclass(frozen=True, eq=False)
class SurfKeypoints:
    """SURF output, in full-image pixel coordinates.

    Attributes
    ----------
    uv : (K, 2) float64
        Keypoint positions ``(u = column, v = row)``, pixel-centre convention.
    scale : (K,) float64
        SURF scale ``s`` in pixels (``1.2`` for the 9x9 filter).
    orientation_rad : (K,) float64
        Dominant orientation (0 for upright SURF).
    response : (K,) float64
        Determinant-of-Hessian response.
    laplacian_sign : (K,) int8
        Sign of the trace of the Hessian (+1 dark blob on bright, -1 bright blob).
    descriptors : (K, 64) float32
        Unit-length descriptors.
    """

    uv: NDArray[np.float64]
    scale: NDArray[np.float64]
    orientation_rad: NDArray[np.float64]
    response: NDArray[np.float64]
    laplacian_sign: NDArray[np.int8]
    descriptors: NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.uv.shape[0])


def hessian_layer(
    ii: NDArray, pad: int, step: int, ny: int, nx: int, L: int, with_sign: bool = True, value_scale: float = 1.0
) -> tuple[NDArray, NDArray | None]:
    """det(H) (float32) and, if asked, the trace sign of one filter size over the sampling grid
    ``y = pad + step i, x = pad + step j`` of the integral image ``ii`` of the image padded by
    ``pad`` (``value_scale`` converts the image's values to [0, 1]). ``ii`` is float64, or int32
    holding exact integer sums (see :func:`integral_image`): half the memory traffic of the strided
    reads, and the products are then formed in float32 like the dense layers'.

    The box sums are separable differences of ``ii``: first across the boxes' columns at the
    grid's columns, for every integral row the boxes reach (boxes sharing their columns share
    this strip), then along the rows at the grid's rows; Dxx likewise transposed: about 30%
    fewer element operations than four corner reads per box."""
    lobe = L // 3
    half_long = (3 * lobe - 1) // 2
    half_short = lobe - 1
    half_mid = (lobe - 1) // 2
    # integral rows (columns) pad - half_long .. pad + step (n - 1) + half_long + 1 hold every
    # corner: offsets -half_long .. half_long + 1 around the grid (half_long >= lobe)
    lo = pad - half_long
    y_hi, x_hi = pad + step * (ny - 1) + half_long + 2, pad + step * (nx - 1) + half_long + 2

    def cols(c: int) -> slice:  # integral columns x + c at the grid
        return slice(pad + c, pad + c + step * nx, step)

    def rows(r: int) -> slice:
        return slice(pad + r, pad + r + step * ny, step)

    def at_rows(strip: NDArray, r: int) -> NDArray:  # a column strip (rows lo..) at grid rows y + r
        return strip[slice(r + half_long, r + half_long + step * ny, step)]

    def at_cols(strip: NDArray, c: int) -> NDArray:
        return strip[:, slice(c + half_long, c + half_long + step * nx, step)]

    band = ii[lo:y_hi]
    # Dyy: a (2l-1) wide, 3l tall box minus 3x its middle third (same columns)
    strip = band[:, cols(half_short + 1)] - band[:, cols(-half_short)]
    dyy = at_rows(strip, half_long + 1) - at_rows(strip, -half_long)
    mid = at_rows(strip, half_mid + 1) - at_rows(strip, -half_mid)
    mid *= 3
    dyy -= mid
    # Dxx: the same transposed
    strip = ii[rows(half_short + 1), lo:x_hi] - ii[rows(-half_short), lo:x_hi]
    dxx = at_cols(strip, half_long + 1) - at_cols(strip, -half_long)
    mid = at_cols(strip, half_mid + 1) - at_cols(strip, -half_mid)
    mid *= 3
    dxx -= mid
    # Dxy: +1 on the quadrants rows/cols -l..-1 and 1..l alike, -1 on the mixed ones. With the
    # row sums left (cols -l..-1) minus right (cols 1..l) g(r) = ii[r, 0] - ii[r, -l] -
    # (ii[r, l+1] - ii[r, 1]), it is g(0) - g(-l) - g(l+1) + g(1).
    strip = band[:, cols(0)] - band[:, cols(-lobe)]
    strip -= band[:, cols(lobe + 1)]
    strip += band[:, cols(1)]
    dxy = at_rows(strip, 0) - at_rows(strip, -lobe)
    dxy -= at_rows(strip, lobe + 1)
    dxy += at_rows(strip, 1)
    sign = np.sign(dxx + dyy).astype(np.int8) if with_sign else None
    if ii.dtype.kind == "i":
        norm = np.float32(value_scale / float(L) ** 2)  # each filter normalised by L^2
        dxx, dyy, dxy = (np.multiply(f, norm, dtype=np.float32) for f in (dxx, dyy, dxy))
        det = dxx * dyy
        dxy *= dxy
        dxy *= np.float32(0.81)
        det -= dxy
        return det, sign
    norm2 = (value_scale / float(L) ** 2) ** 2  # each filter normalised by L^2
    det = dxx * dyy
    dxy *= dxy
    det -= 0.81 * dxy
    det *= norm2
    return det.astype(np.float32), sign


def hessian_layer_dense(
    img: NDArray, L: int, with_sign: bool = True, value_scale: float = 1.0, padded: tuple[NDArray, int] | None = None
) -> tuple[NDArray, NDArray | None]:
    """det(H) and (if asked) the trace sign at every pixel (sampling step 1) with cv2.boxFilter;
    equals :func:`hessian_layer` with ``step = 1`` but runs on SIMD box filters. ``img`` is
    float32, or uint8/uint16 (exact integer box sums, twice as fast) with ``value_scale``
    converting its values to [0, 1]. ``padded`` may pass ``(img padded by P, P)`` with
    ``P >= L // 3`` (replicated border), shared by the layers of an octave."""
    lobe = L // 3
    rep = cv2.BORDER_REPLICATE
    H, W = img.shape
    wide = 2 * lobe - 1
    # All three filters from one lobe-sized box sum each, on the image padded by (at least) a
    # lobe: the 3-lobe box is three stacked 1-lobe boxes, so "whole - 3 x middle" = upper +
    # lower - 2 x middle (three box filters instead of five). Padding first gives the
    # replicated border's sums.
    if padded is None or padded[1] < lobe:
        padded = (cv2.copyMakeBorder(img, lobe, lobe, lobe, lobe, rep), lobe)
    imgp, P = padded
    u, d = P - lobe, P + lobe  # rows (columns) of the upper (left) and lower (right) boxes
    # three full-size float32 buffers and one padded one (dxx's is returned as det): fresh
    # arrays cost page faults, which on this scale are a fair part of the arithmetic's time
    s = cv2.boxFilter(imgp, cv2.CV_32F, (wide, lobe), normalize=False, borderType=rep)
    dyy = cv2.add(s[u : u + H, P : P + W], s[d : d + H, P : P + W])
    cv2.scaleAdd(s[P : P + H, P : P + W], -2.0, dyy, dst=dyy)
    cv2.boxFilter(imgp, cv2.CV_32F, (lobe, wide), dst=s, normalize=False, borderType=rep)
    dxx = cv2.add(s[P : P + H, u : u + W], s[P : P + H, d : d + W])
    cv2.scaleAdd(s[P : P + H, P : P + W], -2.0, dxx, dst=dxx)
    # Dxy: the lobe x lobe box sums at the four quadrant centres (+-c, +-c)
    cv2.boxFilter(imgp, cv2.CV_32F, (lobe, lobe), dst=s, normalize=False, borderType=rep)
    c = (lobe + 1) // 2
    o, e = P - c, P + c
    dxy = cv2.add(s[o : o + H, o : o + W], s[e : e + H, e : e + W])
    dxy -= s[o : o + H, e : e + W]
    dxy -= s[e : e + H, o : o + W]
    sign = np.sign(dxx + dyy).astype(np.int8) if with_sign else None
    norm2 = (value_scale / float(L) ** 2) ** 2  # each filter normalised by L^2
    cv2.multiply(dxy, dxy, dst=dxy, scale=0.81 * norm2)
    det = cv2.multiply(dxx, dyy, dst=dxx, scale=norm2)
    det -= dxy
    return det, sign


def _trace_sign_at(ii: NDArray, pad: int, y: NDArray, x: NDArray, L: int) -> NDArray[np.int8]:
    """Sign of ``Dxx + Dyy`` of filter size ``L`` at integer image pixels ``(y, x)``, from the
    integral image of the image padded by ``pad`` (the sign of the Laplacian, per keypoint)."""
    lobe = L // 3
    half_long = (3 * lobe - 1) // 2
    half_short = lobe - 1
    half_mid = (lobe - 1) // 2
    width = ii.shape[1]
    flat = ii.ravel()  # flat reads: 2-D fancy indexing costs twice as much
    base = (y.astype(np.int64) + pad) * width + (x.astype(np.int64) + pad)

    def at(r: int, c: int) -> NDArray:
        return flat[base + (r * width + c)].astype(np.float64)

    def box(r0: int, r1: int, c0: int, c1: int) -> NDArray:
        return at(r1 + 1, c1 + 1) - at(r0, c1 + 1) - at(r1 + 1, c0) + at(r0, c0)

    dyy = box(-half_long, half_long, -half_short, half_short) - 3.0 * box(-half_mid, half_mid, -half_short, half_short)
    dxx = box(-half_short, half_short, -half_long, half_long) - 3.0 * box(-half_short, half_short, -half_mid, half_mid)
    return np.sign(dxx + dyy).astype(np.int8)


def integral_image(padded: NDArray, max_filter: int) -> NDArray:
    """Integral image of ``padded``: int32 for an integer image whose total and whose largest
    filter's combined box sums fit (exact), else float64."""
    ii = cv2.integral(padded, sdepth=cv2.CV_64F)
    if padded.dtype.kind == "u":
        peak = float(padded.max())
        if peak * padded.size < 2**31 and 4.0 * peak * max_filter**2 < 2**31:
            return ii.astype(np.int32)
    return ii


def _filter_size(octave: int, interval: int) -> int:
    return 3 * ((2 ** (octave + 1)) * (interval + 1) + 1)


_NMS_KERNEL = np.ones((3, 3), np.uint8)


def _quadratic_offsets(below: NDArray, layer_i: NDArray, above: NDArray, ys: NDArray, xs: NDArray, nx: int) -> tuple[NDArray, ...]:
    """Sub-pixel, sub-scale offsets ``(dx, dy, ds)`` of the maxima at ``(ys, xs)`` of ``layer_i``.

    Returns ``c, gx, gy, gs, off, ok``: the value, the gradient, the offsets (K, 3) and where the
    fit is well posed with every offset below half a sample.
    """
    # quadratic interpolation in (x, y, s): offset = -H^-1 g, from the 19 distinct
    # values of the 3x3x3 cube (flat reads), H inverted in closed form (symmetric 3x3)
    flat = ys * nx + xs
    lo, mid, hi = (layer.ravel() for layer in (below, layer_i, above))

    def at(layer: NDArray, dy: int, dx: int) -> NDArray:
        return layer[flat + (dy * nx + dx)].astype(np.float64)

    c = at(mid, 0, 0)
    x_p, x_m, y_p, y_m, s_p, s_m = at(mid, 0, 1), at(mid, 0, -1), at(mid, 1, 0), at(mid, -1, 0), at(hi, 0, 0), at(lo, 0, 0)
    gx, gy, gs = (x_p - x_m) / 2, (y_p - y_m) / 2, (s_p - s_m) / 2
    hxx = x_p + x_m - 2 * c
    hyy = y_p + y_m - 2 * c
    hss = s_p + s_m - 2 * c
    hxy = (at(mid, 1, 1) - at(mid, 1, -1) - at(mid, -1, 1) + at(mid, -1, -1)) / 4
    hxs = (at(hi, 0, 1) - at(hi, 0, -1) - at(lo, 0, 1) + at(lo, 0, -1)) / 4
    hys = (at(hi, 1, 0) - at(hi, -1, 0) - at(lo, 1, 0) + at(lo, -1, 0)) / 4
    # cofactors (the adjugate of a symmetric matrix is symmetric)
    a00 = hyy * hss - hys * hys
    a01 = hys * hxs - hxy * hss
    a02 = hxy * hys - hyy * hxs
    a11 = hxx * hss - hxs * hxs
    a12 = hxy * hxs - hxx * hys
    a22 = hxx * hyy - hxy * hxy
    det_h = hxx * a00 + hxy * a01 + hxs * a02
    ok = np.abs(det_h) > 1e-20
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = -1.0 / det_h
        off = np.stack(
            [(a00 * gx + a01 * gy + a02 * gs) * inv_det, (a01 * gx + a11 * gy + a12 * gs) * inv_det, (a02 * gx + a12 * gy + a22 * gs) * inv_det],
            axis=1,
        )
        ok &= np.all(np.abs(off) < 0.5, axis=1)
    return c, gx, gy, gs, off, ok


def fast_hessian(image01: NDArray, params: SurfParams, value_scale: float = 1.0) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Detect blobs: returns ``uv (K,2)``, ``scale (K,)``, ``response (K,)``, ``laplacian_sign (K,)``
    in the coordinates of ``image01``: float32 in [0, 1], or uint8/uint16 whose values times
    ``value_scale`` are in [0, 1] (responses are those of the [0, 1] image either way)."""
    H, W = image01.shape
    max_L = _filter_size(params.n_octaves - 1, params.n_intervals - 1)
    pad = max_L // 2 + 2
    padded = cv2.copyMakeBorder(image01, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    integral = integral_image(padded, max_L)
    out_uv, out_s, out_r, out_sign = [], [], [], []
    computed: dict[int, tuple[int, NDArray]] = {}
    dense_padded: tuple[NDArray, int] | None = None
    thr = np.float32(params.hessian_threshold)
    for o in range(params.n_octaves):
        step = 2**o
        ny, nx = H // step, W // step
        if ny < 3 or nx < 3:
            break
        sizes = [_filter_size(o, i) for i in range(params.n_intervals)]
        if sizes[-1] > min(H, W):
            break
        layers = []
        for L in sizes:
            if L in computed:
                # octaves share filter sizes (15, 27 of octave 2 exist in octave 1): subsample
                prev_step, det_prev = computed[L]
                k = step // prev_step
                layers.append(np.ascontiguousarray(det_prev[::k, ::k][:ny, :nx]))
                continue
            if step == 1:
                if dense_padded is None:  # one replicated border for the octave's layers
                    P = max(sizes) // 3
                    dense_padded = (cv2.copyMakeBorder(image01, P, P, P, P, cv2.BORDER_REPLICATE), P)
                det, _ = hessian_layer_dense(image01, L, with_sign=False, value_scale=value_scale, padded=dense_padded)
            else:
                det, _ = hessian_layer(integral, pad, step, ny, nx, L, with_sign=False, value_scale=value_scale)
            computed[L] = (step, det)
            layers.append(det)
        for i in range(1, params.n_intervals - 1):
            L = sizes[i]
            # a keypoint's filter must lie inside the (unpadded) image
            b = int(math.ceil((L // 2 + 1) / step)) + 1
            if ny <= 2 * b or nx <= 2 * b:
                continue
            inner = (slice(b, ny - b), slice(b, nx - b))
            centre = layers[i][inner]
            # 3x3x3 maximum: the 3x3 dilation of the three layers' pointwise maximum (one
            # dilation per interval instead of one per layer and two maxima of dilations)
            nb = np.maximum(layers[i - 1], layers[i])
            np.maximum(nb, layers[i + 1], out=nb)
            nb = cv2.dilate(nb, _NMS_KERNEL)[inner]
            cand = centre >= nb
            cand &= centre > thr
            # flatnonzero + divmod: np.nonzero on a 2-D mask is ~15x slower
            ys, xs = np.divmod(np.flatnonzero(cand), cand.shape[1])
            if ys.size == 0:
                continue
            ys += b
            xs += b

            c, gx, gy, gs, off, ok = _quadratic_offsets(layers[i - 1], layers[i], layers[i + 1], ys, xs, nx)
            if not np.any(ok):
                continue
            x_img = (xs[ok] + off[ok, 0]) * step
            y_img = (ys[ok] + off[ok, 1]) * step
            filter_step = sizes[1] - sizes[0]
            L_interp = L + off[ok, 2] * filter_step
            out_uv.append(np.stack([x_img, y_img], axis=1))
            out_s.append(_SCALE_PER_FILTER * L_interp)
            out_r.append(c[ok] + 0.5 * (gx[ok] * off[ok, 0] + gy[ok] * off[ok, 1] + gs[ok] * off[ok, 2]))
            out_sign.append(_trace_sign_at(integral, pad, ys[ok] * step, xs[ok] * step, L))
    if not out_uv:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, np.int8)
    return np.concatenate(out_uv), np.concatenate(out_s), np.concatenate(out_r), np.concatenate(out_sign)


def block_sums(img: NDArray[np.uint8], factor: int) -> NDArray:
    """Sums of ``factor x factor`` pixel blocks (uint16 up to factor 16, else float32); the
    image itself for factor 1. A partial last block row/column is dropped."""
    if factor == 1:
        return img
    H, W = img.shape[0] // factor * factor, img.shape[1] // factor * factor
    # rows first (whole contiguous rows), then the strided columns of the 1/factor-high result
    rows = np.add(img[0:H:factor, :W], img[1:H:factor, :W], dtype=np.uint16 if factor <= 16 else np.float32)
    for dy in range(2, factor):
        rows += img[dy:H:factor, :W]
    out = np.add(rows[:, 0::factor], rows[:, 1::factor])
    for dx in range(2, factor):
        out += rows[:, dx::factor]
    return out


def surf_detect_and_compute(texture: NDArray, params: SurfParams | None = None) -> SurfKeypoints:
    """Detect SURF keypoints on an 8-bit grey image and compute their 64-D descriptors.

    Parameters
    ----------
    texture : (H, W) uint8
        Grey image (the FPP texture).
    params : SurfParams, optional

    Returns
    -------
    SurfKeypoints
        In full-image pixel coordinates, strongest first, at most ``params.max_features``.

    Raises
    ------
    InputDataError
        The image is not a 2-D uint8 array of at least 32x32 pixels.
    """
    p = params or SurfParams()
    img = np.asarray(texture)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise InputDataError(f"SURF needs an H x W uint8 grey image, got {img.dtype} {img.shape}")
    if min(img.shape) < 32:
        raise InputDataError(f"SURF needs an image of at least 32x32 pixels, got {img.shape}")
    factor = 1
    if p.max_working_width > 0 and img.shape[1] > p.max_working_width:
        factor = int(math.ceil(img.shape[1] / p.max_working_width))
    # the working image holds exact sums of factor x factor pixel blocks (area averaging without
    # rounding; integer box filters run twice as fast as float ones)
    work = block_sums(img, factor)
    uv, scale, resp, sign = fast_hessian(work, p, value_scale=1.0 / (255.0 * factor * factor))
    if uv.shape[0] > p.max_features:
        keep = np.argpartition(-resp, p.max_features - 1)[: p.max_features]
        uv, scale, resp, sign = uv[keep], scale[keep], resp[keep], sign[keep]
    order = np.argsort(-resp, kind="stable")
    uv, scale, resp, sign = uv[order], scale[order], resp[order], sign[order]
    bank = HaarBank(work)
    theta = np.zeros(uv.shape[0]) if p.upright or uv.shape[0] == 0 else orientations(bank, uv, scale)
    desc = descriptors(bank, uv, scale, theta) if uv.shape[0] else np.zeros((0, 64), np.float32)
    # back to full-image pixels (pixel-centre convention)
    uv_full = (uv + 0.5) * factor - 0.5
    return SurfKeypoints(uv=uv_full, scale=scale * factor, orientation_rad=theta, response=resp, laplacian_sign=sign, descriptors=desc)
