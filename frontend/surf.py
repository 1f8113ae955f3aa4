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

Speed comes from whole-array work: the detector reads all box sums of one filter size at once by
strided slicing of the integral image; the Haar responses of steps 2 and 3 are dense box-filtered
images (``cv2.boxFilter``, per scale band, on a pyramid level matched to the scale) sampled at all
keypoints' rotated sample points by one ``cv2.remap`` per band. The dense-band sampling replaces
the exact per-sample integral-image lookups by bilinear interpolation of the same box sums, which
is a sub-sample approximation of the same wavelet.

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


def _hessian_layer(ii: NDArray, pad: int, step: int, ny: int, nx: int, L: int) -> tuple[NDArray, NDArray]:
    """det(H) and trace sign of one filter size over the sampling grid."""
    lobe = L // 3
    half_long = (3 * lobe - 1) // 2
    half_short = lobe - 1
    half_mid = (lobe - 1) // 2
    # Dyy: a (2l-1) wide, 3l tall box minus 3x its middle third
    dyy = _box_grid(ii, pad, pad, step, ny, nx, -half_long, half_long, -half_short, half_short) - 3.0 * _box_grid(
        ii, pad, pad, step, ny, nx, -half_mid, half_mid, -half_short, half_short
    )
    dxx = _box_grid(ii, pad, pad, step, ny, nx, -half_short, half_short, -half_long, half_long) - 3.0 * _box_grid(
        ii, pad, pad, step, ny, nx, -half_short, half_short, -half_mid, half_mid
    )
    dxy = (
        _box_grid(ii, pad, pad, step, ny, nx, -lobe, -1, -lobe, -1)
        + _box_grid(ii, pad, pad, step, ny, nx, 1, lobe, 1, lobe)
        - _box_grid(ii, pad, pad, step, ny, nx, -lobe, -1, 1, lobe)
        - _box_grid(ii, pad, pad, step, ny, nx, 1, lobe, -lobe, -1)
    )
    norm = 1.0 / float(L * L)
    dxx *= norm
    dyy *= norm
    dxy *= norm
    det = dxx * dyy - (0.81 * dxy * dxy)
    return det.astype(np.float32), np.sign(dxx + dyy).astype(np.int8)


def _hessian_layer_dense(img: NDArray[np.float32], L: int) -> tuple[NDArray, NDArray]:
    """det(H) and trace sign at every pixel (sampling step 1) with cv2.boxFilter; equals
    :func:`_hessian_layer` with ``step = 1`` but runs on SIMD float32 box filters."""
    lobe = L // 3
    bf = cv2.boxFilter
    rep = cv2.BORDER_REPLICATE
    wide, short = 2 * lobe - 1, lobe
    dyy = bf(img, cv2.CV_32F, (wide, 3 * lobe), normalize=False, borderType=rep) - 3.0 * bf(img, cv2.CV_32F, (wide, short), normalize=False, borderType=rep)
    dxx = bf(img, cv2.CV_32F, (3 * lobe, wide), normalize=False, borderType=rep) - 3.0 * bf(img, cv2.CV_32F, (short, wide), normalize=False, borderType=rep)
    q = bf(img, cv2.CV_32F, (lobe, lobe), normalize=False, borderType=rep)
    c = (lobe + 1) // 2
    qp = cv2.copyMakeBorder(q, c, c, c, c, rep)
    H, W = img.shape
    dxy = qp[: H, : W] + qp[2 * c :, 2 * c :] - qp[: H, 2 * c :] - qp[2 * c :, : W]
    norm = np.float32(1.0 / float(L * L))
    dxx *= norm
    dyy *= norm
    dxy *= norm
    det = dxx * dyy - np.float32(0.81) * dxy * dxy
    return det, np.sign(dxx + dyy).astype(np.int8)


def _filter_size(octave: int, interval: int) -> int:
    return 3 * ((2 ** (octave + 1)) * (interval + 1) + 1)


def fast_hessian(image01: NDArray[np.float32], params: SurfParams) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Detect blobs: returns ``uv (K,2)``, ``scale (K,)``, ``response (K,)``, ``laplacian_sign (K,)``
    in the coordinates of ``image01`` (float32 in [0, 1])."""
    H, W = image01.shape
    max_L = _filter_size(params.n_octaves - 1, params.n_intervals - 1)
    pad = max_L // 2 + 2
    padded = cv2.copyMakeBorder(image01, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    integral = cv2.integral(padded, sdepth=cv2.CV_64F)
    out_uv, out_s, out_r, out_sign = [], [], [], []
    computed: dict[int, tuple[int, NDArray, NDArray]] = {}
    for o in range(params.n_octaves):
        step = 2**o
        ny, nx = H // step, W // step
        if ny < 3 or nx < 3:
            break
        sizes = [_filter_size(o, i) for i in range(params.n_intervals)]
        if sizes[-1] > min(H, W):
            break
        layers, signs = [], []
        for L in sizes:
            if L in computed:
                # octaves share filter sizes (15, 27 of octave 2 exist in octave 1): subsample
                prev_step, det_prev, sign_prev = computed[L]
                k = step // prev_step
                layers.append(np.ascontiguousarray(det_prev[::k, ::k][:ny, :nx]))
                signs.append(sign_prev[::k, ::k][:ny, :nx])
                continue
            if step == 1:
                det, sign = _hessian_layer_dense(image01, L)
            else:
                det, sign = _hessian_layer(integral, pad, step, ny, nx, L)
            computed[L] = (step, det, sign)
            layers.append(det)
            signs.append(sign)
        stack = np.stack(layers)  # (n_int, ny, nx); read by v() below
        kernel = np.ones((3, 3), np.uint8)
        dil = np.stack([cv2.dilate(layer, kernel) for layer in layers])
        for i in range(1, params.n_intervals - 1):
            L = sizes[i]
            # a keypoint's filter must lie inside the (unpadded) image
            border = int(math.ceil((L // 2 + 1) / step)) + 1
            centre = stack[i]
            nb = np.maximum(np.maximum(dil[i - 1], dil[i + 1]), dil[i])
            cand = (centre >= nb) & (centre > params.hessian_threshold)
            cand[:border] = False
            cand[-border:] = False
            cand[:, :border] = False
            cand[:, -border:] = False
            ys, xs = np.nonzero(cand)
            if ys.size == 0:
                continue
            # quadratic interpolation in (x, y, s): offset = -H^-1 g
            def v(ds: int, dy: int, dx: int, i: int = i, ys: NDArray = ys, xs: NDArray = xs, stack: NDArray = stack) -> NDArray:
                return stack[i + ds, ys + dy, xs + dx].astype(np.float64)

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
            out_sign.append(signs[i][ys[ok], xs[ok]])
    if not out_uv:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, np.int8)
    return np.concatenate(out_uv), np.concatenate(out_s), np.concatenate(out_r), np.concatenate(out_sign)


class _HaarBank:
    """Dense Haar-wavelet response images per scale band, sampled bilinearly with cv2.remap."""

    def __init__(self, image01: NDArray[np.float32]):
        self._pyramid = [image01]
        self._cache: dict[tuple[int, int], tuple[NDArray, NDArray, float]] = {}

    def _level(self, k: int) -> NDArray:
        while len(self._pyramid) <= k:
            self._pyramid.append(cv2.resize(self._pyramid[-1], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
        return self._pyramid[k]

    def sample(self, size_px: float, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        """Haar responses (dx, dy) of side ``size_px`` (image pixels) at positions ``x, y`` (any shape)."""
        k = max(0, int(math.floor(math.log2(max(size_px, 1.0) / 6.0))))
        img = self._level(k)
        f = float(2**k)
        half = max(1, int(round(size_px / f / 2.0)))
        key = (k, half)
        if key not in self._cache:
            # dx = right half - left half of a (2h x 2h) window: a (h wide, 2h tall) box sampled
            # h/2 either side of the centre (cv2.boxFilter's even-size anchor sits at k//2)
            bx = cv2.boxFilter(img, cv2.CV_32F, (half, 2 * half), normalize=False, borderType=cv2.BORDER_REPLICATE)
            by = cv2.boxFilter(img, cv2.CV_32F, (2 * half, half), normalize=False, borderType=cv2.BORDER_REPLICATE)
            self._cache[key] = (bx, by, f)
        bx, by, f = self._cache[key]
        h = float(half)
        anchor = (h - 1) / 2.0 - (half // 2)  # box centre minus anchor pixel, for the odd/even size
        anchor2 = (2 * h - 1) / 2.0 - half  # the same along the 2h side
        xs = ((x + 0.5) / f - 0.5).astype(np.float32)
        ys = ((y + 0.5) / f - 0.5).astype(np.float32)
        shape = xs.shape
        xs2, ys2 = xs.reshape(shape[0], -1), ys.reshape(shape[0], -1)

        def rm(src: NDArray, mx: NDArray, my: NDArray) -> NDArray:
            return cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

        dx = rm(bx, xs2 + np.float32(h / 2 - anchor), ys2 - np.float32(anchor2)) - rm(bx, xs2 - np.float32(h / 2 + anchor), ys2 - np.float32(anchor2))
        dy = rm(by, xs2 - np.float32(anchor2), ys2 + np.float32(h / 2 - anchor)) - rm(by, xs2 - np.float32(anchor2), ys2 - np.float32(h / 2 + anchor))
        return dx.reshape(shape), dy.reshape(shape)


def _scale_bands(scale: NDArray) -> NDArray[np.int64]:
    """Group keypoints into bands of scale (ratio 2^(1/4)) that share dense Haar images."""
    return np.round(4.0 * np.log2(scale / 1.2)).astype(np.int64)


_ORI_I, _ORI_J = np.meshgrid(np.arange(-6, 7), np.arange(-6, 7))
_ORI_MASK = _ORI_I**2 + _ORI_J**2 < 36
_ORI_I, _ORI_J = _ORI_I[_ORI_MASK].astype(np.float64), _ORI_J[_ORI_MASK].astype(np.float64)  # 109 samples
_ORI_W = np.exp(-(_ORI_I**2 + _ORI_J**2) / (2 * 2.0**2))
_DESC_C = np.arange(-10, 10) + 0.5
_DESC_U, _DESC_V = np.meshgrid(_DESC_C, _DESC_C)  # (20, 20): u along x, v along y
_DESC_W = np.exp(-(_DESC_U**2 + _DESC_V**2) / (2 * 3.3**2))


def _orientations(bank: _HaarBank, uv: NDArray, scale: NDArray) -> NDArray:
    out = np.zeros(uv.shape[0])
    bands = _scale_bands(scale)
    n_bins = 72
    for b in np.unique(bands):
        sel = np.flatnonzero(bands == b)
        s_band = 1.2 * 2.0 ** (b / 4.0)
        s = scale[sel, None]
        x = uv[sel, 0, None] + _ORI_I[None] * s
        y = uv[sel, 1, None] + _ORI_J[None] * s
        dx, dy = bank.sample(4.0 * s_band, x, y)
        dx = dx * _ORI_W
        dy = dy * _ORI_W
        ang = np.arctan2(dy, dx)
        bins = ((ang + np.pi) / (2 * np.pi) * n_bins).astype(np.int64) % n_bins
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
        s_band = 1.2 * 2.0 ** (b / 4.0)
        s = scale[sel, None, None]
        co = np.cos(theta[sel])[:, None, None]
        si = np.sin(theta[sel])[:, None, None]
        u = _DESC_U[None] * s
        v = _DESC_V[None] * s
        x = uv[sel, 0, None, None] + co * u - si * v
        y = uv[sel, 1, None, None] + si * u + co * v
        dx, dy = bank.sample(2.0 * s_band, x, y)
        rx = (co * dx + si * dy) * _DESC_W
        ry = (-si * dx + co * dy) * _DESC_W
        n = sel.size
        # (n, 20, 20) -> (n, 4, 5, 4, 5): sub-region row, sample row, sub-region col, sample col
        rx = rx.reshape(n, 4, 5, 4, 5)
        ry = ry.reshape(n, 4, 5, 4, 5)
        d = np.stack(
            [rx.sum(axis=(2, 4)), ry.sum(axis=(2, 4)), np.abs(rx).sum(axis=(2, 4)), np.abs(ry).sum(axis=(2, 4))], axis=-1
        ).reshape(n, 64)
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        desc[sel] = (d / np.maximum(norm, 1e-12)).astype(np.float32)
    return desc


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
    work = img.astype(np.float32) * np.float32(1.0 / 255.0)
    if factor > 1:
        work = cv2.resize(work, (img.shape[1] // factor, img.shape[0] // factor), interpolation=cv2.INTER_AREA)
    uv, scale, resp, sign = fast_hessian(work, p)
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
