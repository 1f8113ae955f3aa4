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
apart, per wavelet size, on the pyramid level where the wavelet spans 4-8 pixels) stored as one
2-channel image and read at all keypoints' rotated sample points by one ``cv2.remap`` per scale
band; the sample positions come from one small matrix product, the 4x4 sub-region sums from one
product with a (400, 16) weight matrix. The dense-band sampling replaces the exact
per-sample integral-image lookups by bilinear interpolation of the same box sums, a sub-sample
approximation of the same wavelet. On a 1920x1200 texture (960x600 working image, ~1800
keypoints) detection + description takes about 55-70 ms of one core
(``scripts/bench_registration.py``).

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


def _box_grid(ii: NDArray, y0: int, x0: int, step: int, ny: int, nx: int, r0: int, r1: int, c0: int, c1: int) -> NDArray:
    """Sums of the boxes rows ``y+r0..y+r1``, cols ``x+c0..x+c1`` (inclusive) at the grid
    ``y = y0 + step*i, x = x0 + step*j`` of a padded integral image ``ii``."""
    ya, yb = y0 + r0, y0 + r1 + 1
    xa, xb = x0 + c0, x0 + c1 + 1
    sl = slice  # local alias keeps the four reads on one line each
    A = ii[sl(ya, ya + step * ny, step), sl(xa, xa + step * nx, step)]
    B = ii[sl(ya, ya + step * ny, step), sl(xb, xb + step * nx, step)]
    C = ii[sl(yb, yb + step * ny, step), sl(xa, xa + step * nx, step)]
    D = ii[sl(yb, yb + step * ny, step), sl(xb, xb + step * nx, step)]
    return D - B - C + A


def _hessian_layer(
    ii: NDArray, pad: int, step: int, ny: int, nx: int, L: int, with_sign: bool = True, value_scale: float = 1.0
) -> tuple[NDArray, NDArray | None]:
    """det(H) (float32) and, if asked, the trace sign of one filter size over the sampling grid
    (``value_scale`` converts the image's values to [0, 1])."""
    lobe = L // 3
    half_long = (3 * lobe - 1) // 2
    half_short = lobe - 1
    half_mid = (lobe - 1) // 2
    # Dyy: a (2l-1) wide, 3l tall box minus 3x its middle third
    dyy = _box_grid(ii, pad, pad, step, ny, nx, -half_long, half_long, -half_short, half_short)
    dyy -= 3.0 * _box_grid(ii, pad, pad, step, ny, nx, -half_mid, half_mid, -half_short, half_short)
    dxx = _box_grid(ii, pad, pad, step, ny, nx, -half_short, half_short, -half_long, half_long)
    dxx -= 3.0 * _box_grid(ii, pad, pad, step, ny, nx, -half_short, half_short, -half_mid, half_mid)
    dxy = _box_grid(ii, pad, pad, step, ny, nx, -lobe, -1, -lobe, -1)
    dxy += _box_grid(ii, pad, pad, step, ny, nx, 1, lobe, 1, lobe)
    dxy -= _box_grid(ii, pad, pad, step, ny, nx, -lobe, -1, 1, lobe)
    dxy -= _box_grid(ii, pad, pad, step, ny, nx, 1, lobe, -lobe, -1)
    norm2 = (value_scale / float(L) ** 2) ** 2  # each filter normalised by L^2
    det = dxx * dyy
    dxy *= dxy
    det -= 0.81 * dxy
    det *= norm2
    return det.astype(np.float32), (np.sign(dxx + dyy).astype(np.int8) if with_sign else None)


def _hessian_layer_dense(img: NDArray, L: int, with_sign: bool = True, value_scale: float = 1.0) -> tuple[NDArray, NDArray | None]:
    """det(H) and (if asked) the trace sign at every pixel (sampling step 1) with cv2.boxFilter;
    equals :func:`_hessian_layer` with ``step = 1`` but runs on SIMD box filters. ``img`` is
    float32, or uint8/uint16 (exact integer box sums, twice as fast) with ``value_scale``
    converting its values to [0, 1]."""
    lobe = L // 3
    rep = cv2.BORDER_REPLICATE

    def bf(size: tuple[int, int]) -> NDArray[np.float32]:
        return cv2.boxFilter(img, cv2.CV_32F, size, normalize=False, borderType=rep)

    wide, short = 2 * lobe - 1, lobe
    dyy = cv2.scaleAdd(bf((wide, short)), -3.0, bf((wide, 3 * lobe)))  # -3 * middle + whole
    dxx = cv2.scaleAdd(bf((short, wide)), -3.0, bf((3 * lobe, wide)))
    q = bf((lobe, lobe))
    c = (lobe + 1) // 2
    qp = cv2.copyMakeBorder(q, c, c, c, c, rep)
    H, W = img.shape
    dxy = cv2.add(qp[:H, :W], qp[2 * c :, 2 * c :])
    dxy -= qp[:H, 2 * c :]
    dxy -= qp[2 * c :, :W]
    norm2 = (value_scale / float(L) ** 2) ** 2  # each filter normalised by L^2
    det = cv2.multiply(dxx, dyy, scale=norm2)
    det -= cv2.multiply(dxy, dxy, scale=0.81 * norm2)
    return det, (np.sign(dxx + dyy).astype(np.int8) if with_sign else None)


def _trace_sign_at(ii: NDArray, pad: int, y: NDArray, x: NDArray, L: int) -> NDArray[np.int8]:
    """Sign of ``Dxx + Dyy`` of filter size ``L`` at integer image pixels ``(y, x)``, from the
    integral image of the image padded by ``pad`` (the sign of the Laplacian, per keypoint)."""
    lobe = L // 3
    half_long = (3 * lobe - 1) // 2
    half_short = lobe - 1
    half_mid = (lobe - 1) // 2
    yy = y.astype(np.int64) + pad
    xx = x.astype(np.int64) + pad

    def box(r0: int, r1: int, c0: int, c1: int) -> NDArray:
        return ii[yy + r1 + 1, xx + c1 + 1] - ii[yy + r0, xx + c1 + 1] - ii[yy + r1 + 1, xx + c0] + ii[yy + r0, xx + c0]

    dyy = box(-half_long, half_long, -half_short, half_short) - 3.0 * box(-half_mid, half_mid, -half_short, half_short)
    dxx = box(-half_short, half_short, -half_long, half_long) - 3.0 * box(-half_short, half_short, -half_mid, half_mid)
    return np.sign(dxx + dyy).astype(np.int8)


def _filter_size(octave: int, interval: int) -> int:
    return 3 * ((2 ** (octave + 1)) * (interval + 1) + 1)


_NMS_KERNEL = np.ones((3, 3), np.uint8)


def fast_hessian(image01: NDArray, params: SurfParams, value_scale: float = 1.0) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Detect blobs: returns ``uv (K,2)``, ``scale (K,)``, ``response (K,)``, ``laplacian_sign (K,)``
    in the coordinates of ``image01``: float32 in [0, 1], or uint8/uint16 whose values times
    ``value_scale`` are in [0, 1] (responses are those of the [0, 1] image either way)."""
    H, W = image01.shape
    max_L = _filter_size(params.n_octaves - 1, params.n_intervals - 1)
    pad = max_L // 2 + 2
    padded = cv2.copyMakeBorder(image01, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    integral = cv2.integral(padded, sdepth=cv2.CV_64F)
    out_uv, out_s, out_r, out_sign = [], [], [], []
    computed: dict[int, tuple[int, NDArray]] = {}
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
                det, _ = _hessian_layer_dense(image01, L, with_sign=False, value_scale=value_scale)
            else:
                det, _ = _hessian_layer(integral, pad, step, ny, nx, L, with_sign=False, value_scale=value_scale)
            computed[L] = (step, det)
            layers.append(det)
        dil = [cv2.dilate(layer, _NMS_KERNEL) for layer in layers]
        for i in range(1, params.n_intervals - 1):
            L = sizes[i]
            # a keypoint's filter must lie inside the (unpadded) image
            b = int(math.ceil((L // 2 + 1) / step)) + 1
            if ny <= 2 * b or nx <= 2 * b:
                continue
            inner = (slice(b, ny - b), slice(b, nx - b))
            centre = layers[i][inner]
            nb = np.maximum(dil[i - 1][inner], dil[i + 1][inner])
            np.maximum(nb, dil[i][inner], out=nb)
            cand = centre >= nb
            cand &= centre > thr
            ys, xs = np.nonzero(cand)
            if ys.size == 0:
                continue
            ys += b
            xs += b

            # quadratic interpolation in (x, y, s): offset = -H^-1 g
            def v(ds: int, dy: int, dx: int, i: int = i, ys: NDArray = ys, xs: NDArray = xs, layers: list = layers) -> NDArray:
                return layers[i + ds][ys + dy, xs + dx].astype(np.float64)

            c = v(0, 0, 0)
            g = np.stack([(v(0, 0, 1) - v(0, 0, -1)) / 2, (v(0, 1, 0) - v(0, -1, 0)) / 2, (v(1, 0, 0) - v(-1, 0, 0)) / 2], axis=1)
            hxx = v(0, 0, 1) + v(0, 0, -1) - 2 * c
            hyy = v(0, 1, 0) + v(0, -1, 0) - 2 * c
            hss = v(1, 0, 0) + v(-1, 0, 0) - 2 * c
            hxy = (v(0, 1, 1) - v(0, 1, -1) - v(0, -1, 1) + v(0, -1, -1)) / 4
            hxs = (v(1, 0, 1) - v(1, 0, -1) - v(-1, 0, 1) + v(-1, 0, -1)) / 4
            hys = (v(1, 1, 0) - v(1, -1, 0) - v(-1, 1, 0) + v(-1, -1, 0)) / 4
            Hm = np.stack(
                [np.stack([hxx, hxy, hxs], 1), np.stack([hxy, hyy, hys], 1), np.stack([hxs, hys, hss], 1)], axis=1
            )
            det_h = np.linalg.det(Hm)
            ok = np.abs(det_h) > 1e-20
            off = np.zeros_like(g)
            off[ok] = -np.linalg.solve(Hm[ok], g[ok][..., None])[..., 0]
            ok &= np.all(np.abs(off) < 0.5, axis=1)
            if not np.any(ok):
                continue
            x_img = (xs[ok] + off[ok, 0]) * step
            y_img = (ys[ok] + off[ok, 1]) * step
            filter_step = sizes[1] - sizes[0]
            L_interp = L + off[ok, 2] * filter_step
            out_uv.append(np.stack([x_img, y_img], axis=1))
            out_s.append(_SCALE_PER_FILTER * L_interp)
            out_r.append(c[ok] + 0.5 * np.einsum("ij,ij->i", g[ok], off[ok]))
            out_sign.append(_trace_sign_at(integral, pad, ys[ok] * step, xs[ok] * step, L))
    if not out_uv:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, np.int8)
    return np.concatenate(out_uv), np.concatenate(out_s), np.concatenate(out_r), np.concatenate(out_sign)


class _HaarBank:
    """Dense Haar-wavelet response images per scale band, sampled bilinearly with cv2.remap.

    A wavelet of side ``size_px`` is evaluated on the pyramid level ``k`` where it spans 4-8
    level pixels, as ``2 half`` level pixels (half = 2, 3 or 4: the side is rounded by at most
    one level pixel, as SURF rounds it to whole image pixels). Its x response is the difference of two
    ``half x 2 half`` box sums (``cv2.boxFilter``) ``half`` apart, the y response likewise; both
    are stored as one 2-channel image shifted by whole pixels, so that one ``cv2.remap`` reads
    ``(dx, dy)`` at any set of positions (bilinear interpolation is linear, so the difference of
    interpolated box sums is the interpolated difference).
    """

    _PAD = 8  # level border for the shifted box sums (half <= 4 -> shifts <= 3)

    def __init__(self, image: NDArray):
        self._pyramid = [image]
        self._padded: dict[int, NDArray[np.float32]] = {}
        self._cache: dict[tuple[int, int], NDArray[np.float32]] = {}

    def _level(self, k: int) -> NDArray:
        while len(self._pyramid) <= k:
            # levels from 1 on in float32 (an integer level would round its averages); each
            # keypoint reads one level and its descriptor is normalised, so units do not matter
            src = self._pyramid[-1] if self._pyramid[-1].dtype == np.float32 else self._pyramid[-1].astype(np.float32)
            self._pyramid.append(cv2.resize(src, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
        return self._pyramid[k]

    @staticmethod
    def level_of(size_px: float) -> tuple[int, int]:
        """Pyramid level ``k`` and the wavelet half side ``half`` (level pixels) for ``size_px``."""
        k = max(0, int(math.floor(math.log2(max(size_px, 1.0) / 4.0))))
        return k, max(1, int(round(size_px / 2.0**k / 2.0)))

    def responses(self, k: int, half: int) -> NDArray[np.float32]:
        """(H_k, W_k, 2) ``(dx, dy)`` of side ``2 half`` on level ``k``, to be read at
        ``(X - 0.5, Y - 0.5)`` for a wavelet centred at level coordinates ``(X, Y)``."""
        key = (k, half)
        if key not in self._cache:
            img = self._level(k)
            H, W = img.shape
            P = self._PAD
            if k not in self._padded:
                self._padded[k] = cv2.copyMakeBorder(img, P, P, P, P, cv2.BORDER_REPLICATE)
            padded = self._padded[k]
            # cv2.boxFilter anchors an even side at its middle pixel: the right (lower) box of a
            # wavelet centred at X sits p pixels after the anchor column, the left (upper) one q
            # before, p + q = half; the remaining half-pixel offsets go into the read position
            p = half // 2 + 1
            q = half - p
            assert max(p, q) < P, "wavelet wider than the level border"
            bx = cv2.boxFilter(padded, cv2.CV_32F, (half, 2 * half), normalize=False, borderType=cv2.BORDER_REPLICATE)
            by = cv2.boxFilter(padded, cv2.CV_32F, (2 * half, half), normalize=False, borderType=cv2.BORDER_REPLICATE)
            out = np.empty((H, W, 2), np.float32)
            np.subtract(bx[P + 1 : P + 1 + H, P + p : P + p + W], bx[P + 1 : P + 1 + H, P - q : P - q + W], out=out[..., 0])
            np.subtract(by[P + p : P + p + H, P + 1 : P + 1 + W], by[P - q : P - q + H, P + 1 : P + 1 + W], out=out[..., 1])
            self._cache[key] = out
        return self._cache[key]

    def sample(self, size_px: float, x: NDArray, y: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Haar responses (dx, dy) of side ``size_px`` at image positions ``x, y`` (any shape)."""
        k, half = self.level_of(size_px)
        shape = x.shape
        f = 2.0**k
        # level coordinates X = (x + 0.5) / f - 0.5, read at X - 0.5 (see responses)
        mx = (np.asarray(x, np.float32).reshape(shape[0], -1) * np.float32(1.0 / f)) + np.float32(0.5 / f - 1.0)
        my = (np.asarray(y, np.float32).reshape(shape[0], -1) * np.float32(1.0 / f)) + np.float32(0.5 / f - 1.0)
        out = self.read(k, half, mx, my)
        return out[..., 0].reshape(shape), out[..., 1].reshape(shape)

    def read(self, k: int, half: int, mx: NDArray[np.float32], my: NDArray[np.float32]) -> NDArray[np.float32]:
        """``(rows, cols, 2)`` responses at level read positions ``mx, my`` (``(rows, cols)`` float32)."""
        resp = self.responses(k, half)
        rows = 16384  # cv2.remap needs fewer than 32767 rows/columns per call
        parts = [
            cv2.remap(resp, mx[i : i + rows], my[i : i + rows], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            for i in range(0, mx.shape[0], rows)
        ]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _scale_bands(scale: NDArray) -> NDArray[np.int64]:
    """Group keypoints into bands of scale (ratio 2^(1/4)) that share dense Haar images."""
    return np.round(4.0 * np.log2(scale / 1.2)).astype(np.int64)


def _read_positions(uv: NDArray, scale: NDArray, theta: NDArray | None, grid: NDArray[np.float32], k: int) -> tuple[NDArray, NDArray]:
    """Level-``k`` read positions (see :meth:`_HaarBank.responses`) of a sample grid ``(2, m)`` in
    units of the keypoint scale, rotated by ``theta``, for keypoints ``uv``: ``(n, m)`` each, by
    one small float32 matrix product per coordinate."""
    f = 2.0**k
    c = uv / f + (0.5 / f - 1.0)  # (n, 2) level read position of the centre
    a = scale / f
    co = a * (np.cos(theta) if theta is not None else 1.0)
    si = a * (np.sin(theta) if theta is not None else 0.0)
    basis = np.vstack([np.ones((1, grid.shape[1]), np.float32), grid]).astype(np.float32)  # (3, m): 1, u, v
    ax = np.stack([c[:, 0], co, -si], axis=1).astype(np.float32)  # x = cx + co u - si v
    ay = np.stack([c[:, 1], si, co], axis=1).astype(np.float32)  # y = cy + si u + co v
    return ax @ basis, ay @ basis


_ORI_I, _ORI_J = np.meshgrid(np.arange(-6, 7), np.arange(-6, 7))
_ORI_MASK = _ORI_I**2 + _ORI_J**2 < 36
_ORI_I, _ORI_J = _ORI_I[_ORI_MASK].astype(np.float64), _ORI_J[_ORI_MASK].astype(np.float64)  # 109 samples
_ORI_GRID = np.stack([_ORI_I, _ORI_J]).astype(np.float32)
_ORI_W = np.exp(-(_ORI_I**2 + _ORI_J**2) / (2 * 2.0**2)).astype(np.float32)
_DESC_C = np.arange(-10, 10) + 0.5
_DESC_U, _DESC_V = np.meshgrid(_DESC_C, _DESC_C)  # (20, 20): u along x (columns), v along y (rows)
_DESC_GRID = np.stack([_DESC_U.ravel(), _DESC_V.ravel()]).astype(np.float32)  # (2, 400), row-major
_DESC_W = np.exp(-(_DESC_U**2 + _DESC_V**2) / (2 * 3.3**2)).ravel()
# (400, 16): Gaussian weight of each sample in its 5x5 sub-region (row-major 4x4 sub-regions)
_DESC_SUM = np.zeros((400, 16), np.float32)
_DESC_SUM[np.arange(400), (np.arange(400) // 20 // 5) * 4 + (np.arange(400) % 20) // 5] = _DESC_W


def _orientations(bank: _HaarBank, uv: NDArray, scale: NDArray) -> NDArray:
    out = np.zeros(uv.shape[0])
    bands = _scale_bands(scale)
    n_bins = 72
    for b in np.unique(bands):
        sel = np.flatnonzero(bands == b)
        k, half = bank.level_of(4.0 * 1.2 * 2.0 ** (b / 4.0))
        mx, my = _read_positions(uv[sel], scale[sel], None, _ORI_GRID, k)
        resp = bank.read(k, half, mx, my)
        dx = resp[..., 0] * _ORI_W
        dy = resp[..., 1] * _ORI_W
        ang = np.arctan2(dy, dx)
        bins = ((ang + np.float32(np.pi)) * np.float32(n_bins / (2 * np.pi))).astype(np.int64) % n_bins
        flat = bins + n_bins * np.arange(sel.size)[:, None]
        hx = np.bincount(flat.ravel(), weights=dx.ravel(), minlength=sel.size * n_bins).reshape(sel.size, n_bins)
        hy = np.bincount(flat.ravel(), weights=dy.ravel(), minlength=sel.size * n_bins).reshape(sel.size, n_bins)
        win = n_bins // 6  # pi/3 sliding window
        cx = np.cumsum(np.concatenate([hx, hx[:, :win]], axis=1), axis=1)
        cy = np.cumsum(np.concatenate([hy, hy[:, :win]], axis=1), axis=1)
        sx = cx[:, win:] - cx[:, :-win]
        sy = cy[:, win:] - cy[:, :-win]
        best = np.argmax(sx**2 + sy**2, axis=1)
        r = np.arange(sel.size)
        out[sel] = np.arctan2(sy[r, best], sx[r, best])
    return out


def _descriptors(bank: _HaarBank, uv: NDArray, scale: NDArray, theta: NDArray) -> NDArray[np.float32]:
    desc = np.zeros((uv.shape[0], 64), np.float32)
    bands = _scale_bands(scale)
    for b in np.unique(bands):
        sel = np.flatnonzero(bands == b)
        n = sel.size
        k, half = bank.level_of(2.0 * 1.2 * 2.0 ** (b / 4.0))
        mx, my = _read_positions(uv[sel], scale[sel], theta[sel], _DESC_GRID, k)
        resp = bank.read(k, half, mx, my)  # (n, 400, 2): image-axis dx, dy
        co = np.cos(theta[sel]).astype(np.float32)[:, None]
        si = np.sin(theta[sel]).astype(np.float32)[:, None]
        dx, dy = resp[..., 0], resp[..., 1]
        # responses in the keypoint frame, as rows (rx of keypoint 0, ry of keypoint 0, rx of 1, ...)
        rt = np.empty((n, 2, 400), np.float32)
        np.multiply(dx, co, out=rt[:, 0])
        rt[:, 0] += dy * si
        np.multiply(dy, co, out=rt[:, 1])
        rt[:, 1] -= dx * si
        rt = rt.reshape(2 * n, 400)
        # Gaussian-weighted sums per 4x4 sub-region of sum r and sum |r|: one matrix product each
        sums = (rt @ _DESC_SUM).reshape(n, 2, 16)
        abs_sums = (np.abs(rt) @ _DESC_SUM).reshape(n, 2, 16)
        # per sub-region (sum dx, sum dy, sum |dx|, sum |dy|), sub-regions row-major
        d = np.concatenate([sums, abs_sums], axis=1).transpose(0, 2, 1).reshape(n, 64)
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        desc[sel] = d / np.maximum(norm, np.float32(1e-12))
    return desc


def _block_sums(img: NDArray[np.uint8], factor: int) -> NDArray:
    """Sums of ``factor x factor`` pixel blocks (uint16 up to factor 16, else float32); the
    image itself for factor 1. A partial last block row/column is dropped."""
    if factor == 1:
        return img
    H, W = img.shape[0] // factor * factor, img.shape[1] // factor * factor
    out = img[0:H:factor, 0:W:factor].astype(np.uint16 if factor <= 16 else np.float32)
    for dy in range(factor):
        for dx in range(factor):
            if dy or dx:
                out += img[dy:H:factor, dx:W:factor]
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
    work = _block_sums(img, factor)
    uv, scale, resp, sign = fast_hessian(work, p, value_scale=1.0 / (255.0 * factor * factor))
    if uv.shape[0] > p.max_features:
        keep = np.argpartition(-resp, p.max_features - 1)[: p.max_features]
        uv, scale, resp, sign = uv[keep], scale[keep], resp[keep], sign[keep]
    order = np.argsort(-resp, kind="stable")
    uv, scale, resp, sign = uv[order], scale[order], resp[order], sign[order]
    bank = _HaarBank(work)
    theta = np.zeros(uv.shape[0]) if p.upright or uv.shape[0] == 0 else _orientations(bank, uv, scale)
    desc = _descriptors(bank, uv, scale, theta) if uv.shape[0] else np.zeros((0, 64), np.float32)
    # back to full-image pixels (pixel-centre convention)
    uv_full = (uv + 0.5) * factor - 0.5
    return SurfKeypoints(uv=uv_full, scale=scale * factor, orientation_rad=theta, response=resp, laplacian_sign=sign, descriptors=desc)
