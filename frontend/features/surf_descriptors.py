"""SURF orientation and descriptor (steps 2 and 3 of :mod:`frontend.features.surf`).

Haar wavelet responses are dense images per scale band (:class:`HaarBank`), read at all
keypoints' rotated sample points by ``cv2.remap``; the sample positions come from one small
matrix product, the 4x4 sub-region sums from one product with a (400, 16) weight matrix.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray


class HaarBank:
    """Dense Haar-wavelet response images per scale band, sampled bilinearly with cv2.remap.

    A wavelet of side ``size_px`` is evaluated on the pyramid level ``k`` where it spans 4-8
    level pixels, as ``2 half`` level pixels (half = 2, 3 or 4: the side is rounded by at most
    one level pixel, as SURF rounds it to whole image pixels). Its x response is the difference of two
    ``half x 2 half`` box sums ``half`` apart, one separable filter (``cv2.sepFilter2D``: a
    -1/+1 step across, a box along), the y response likewise; ``cv2.remap`` reads ``dx`` and
    ``dy`` at any set of positions (bilinear interpolation is linear, so the difference of
    interpolated box sums is the interpolated difference). They are two 1-channel images, not
    one 2-channel one: OpenCV remaps 1-channel float32 with exact float weights on SIMD, 2-channel
    float32 with 1/32-pixel fixed-point weights per element, 3x slower for both channels.
    """

    def __init__(self, image: NDArray):
        # float32 levels (an integer level would round its averages; float32 filters run faster
        # than integer ones here); each keypoint reads one level and its descriptor is
        # normalised, so units do not matter
        self._pyramid = [image if image.dtype == np.float32 else image.astype(np.float32)]
        self._cache: dict[tuple[int, int], tuple[NDArray[np.float32], NDArray[np.float32]]] = {}

    def _level(self, k: int) -> NDArray:
        while len(self._pyramid) <= k:
            self._pyramid.append(cv2.resize(self._pyramid[-1], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
        return self._pyramid[k]

    @staticmethod
    def level_of(size_px: float) -> tuple[int, int]:
        """Pyramid level ``k`` and the wavelet half side ``half`` (level pixels) for ``size_px``."""
        k = max(0, int(math.floor(math.log2(max(size_px, 1.0) / 4.0))))
        return k, max(1, int(round(size_px / 2.0**k / 2.0)))

    def responses(self, k: int, half: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """``dx, dy`` (H_k, W_k) of side ``2 half`` on level ``k``, to be read at
        ``(X - 0.5, Y - 0.5)`` for a wavelet centred at level coordinates ``(X, Y)``."""
        key = (k, half)
        if key not in self._cache:
            img = self._level(k)
            step = np.concatenate([-np.ones(half), np.ones(half)]).astype(np.float32)
            box = np.ones(2 * half, np.float32)
            # the filters are correlations anchored at tap half - 1: output pixel X holds the
            # window over X - half + 1 .. X + half, centred at X + 0.5
            a = (half - 1, half - 1)
            rep = cv2.BORDER_REPLICATE
            dx = cv2.sepFilter2D(img, cv2.CV_32F, step, box, anchor=a, borderType=rep)
            dy = cv2.sepFilter2D(img, cv2.CV_32F, box, step, anchor=a, borderType=rep)
            self._cache[key] = (dx, dy)
        return self._cache[key]

    def sample(self, size_px: float, x: NDArray, y: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Haar responses (dx, dy) of side ``size_px`` at image positions ``x, y`` (any shape)."""
        k, half = self.level_of(size_px)
        shape = x.shape
        f = 2.0**k
        # level coordinates X = (x + 0.5) / f - 0.5, read at X - 0.5 (see responses)
        mx = (np.asarray(x, np.float32).reshape(shape[0], -1) * np.float32(1.0 / f)) + np.float32(0.5 / f - 1.0)
        my = (np.asarray(y, np.float32).reshape(shape[0], -1) * np.float32(1.0 / f)) + np.float32(0.5 / f - 1.0)
        dx, dy = self.read(k, half, mx, my)
        return dx.reshape(shape), dy.reshape(shape)

    def read(self, k: int, half: int, mx: NDArray[np.float32], my: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """``dx, dy`` (``(rows, cols)`` float32 each) at level read positions ``mx, my`` (``(rows, cols)`` float32)."""
        rows = 16384  # cv2.remap needs fewer than 32767 rows/columns per call
        out = []
        for resp in self.responses(k, half):
            parts = [
                cv2.remap(resp, mx[i : i + rows], my[i : i + rows], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                for i in range(0, mx.shape[0], rows)
            ]
            out.append(parts[0] if len(parts) == 1 else np.concatenate(parts))
        return out[0], out[1]


def _scale_bands(scale: NDArray) -> NDArray[np.int64]:
    """Group keypoints into bands of scale (ratio 2^(1/4)) that share dense Haar images."""
    return np.round(4.0 * np.log2(scale / 1.2)).astype(np.int64)


def _read_positions(uv: NDArray, scale: NDArray, theta: NDArray | None, basis: NDArray[np.float32], k: int) -> tuple[NDArray, NDArray]:
    """Level-``k`` read positions (see :meth:`HaarBank.responses`) of a sample grid in units of
    the keypoint scale, rotated by ``theta``, for keypoints ``uv``: ``(n, m)`` each, by one small
    float32 matrix product per coordinate. ``basis`` is ``(3, m)``: rows 1, u, v of the grid."""
    f = 2.0**k
    c = uv / f + (0.5 / f - 1.0)  # (n, 2) level read position of the centre
    a = scale / f
    co = a * (np.cos(theta) if theta is not None else 1.0)
    si = a * (np.sin(theta) if theta is not None else 0.0)
    ax = np.stack([c[:, 0], co, -si], axis=1).astype(np.float32)  # x = cx + co u - si v
    ay = np.stack([c[:, 1], si, co], axis=1).astype(np.float32)  # y = cy + si u + co v
    return ax @ basis, ay @ basis


def _grid_basis(grid: NDArray) -> NDArray[np.float32]:
    """``(3, m)`` float32 rows 1, u, v of a ``(2, m)`` sample grid (see :func:`_read_positions`)."""
    return np.vstack([np.ones((1, grid.shape[1])), grid]).astype(np.float32)


_ORI_I, _ORI_J = np.meshgrid(np.arange(-6, 7), np.arange(-6, 7))
_ORI_MASK = _ORI_I**2 + _ORI_J**2 < 36
_ORI_I, _ORI_J = _ORI_I[_ORI_MASK].astype(np.float64), _ORI_J[_ORI_MASK].astype(np.float64)  # 109 samples
_ORI_BASIS = _grid_basis(np.stack([_ORI_I, _ORI_J]))
_ORI_W = np.exp(-(_ORI_I**2 + _ORI_J**2) / (2 * 2.0**2)).astype(np.float32)
_ORI_BINS = 72
# (72, 72) 0/1: column j sums the pi/3 window of bins j+1 .. j+12 (mod 72) of atan2 + pi; the
# rows are rolled by half a turn because the bins come from cv2.phase, in [0, 2 pi)
_ORI_WINDOW = np.roll(
    ((np.arange(_ORI_BINS)[:, None] - np.arange(_ORI_BINS)[None, :] - 1) % _ORI_BINS < _ORI_BINS // 6).astype(np.float64),
    -(_ORI_BINS // 2),
    axis=0,
)
_DESC_C = np.arange(-10, 10) + 0.5
_DESC_U, _DESC_V = np.meshgrid(_DESC_C, _DESC_C)  # (20, 20): u along x (columns), v along y (rows)
_DESC_BASIS = _grid_basis(np.stack([_DESC_U.ravel(), _DESC_V.ravel()]))  # (3, 400), row-major
_DESC_W = np.exp(-(_DESC_U**2 + _DESC_V**2) / (2 * 3.3**2)).ravel()
# (400, 16): Gaussian weight of each sample in its 5x5 sub-region (row-major 4x4 sub-regions)
_DESC_SUM = np.zeros((400, 16), np.float32)
_DESC_SUM[np.arange(400), (np.arange(400) // 20 // 5) * 4 + (np.arange(400) % 20) // 5] = _DESC_W


def orientations(bank: HaarBank, uv: NDArray, scale: NDArray) -> NDArray:
    out = np.zeros(uv.shape[0])
    bands = _scale_bands(scale)
    n_bins = _ORI_BINS
    for b in np.unique(bands):
        sel = np.flatnonzero(bands == b)
        k, half = bank.level_of(4.0 * 1.2 * 2.0 ** (b / 4.0))
        mx, my = _read_positions(uv[sel], scale[sel], None, _ORI_BASIS, k)
        dx, dy = bank.read(k, half, mx, my)
        dx *= _ORI_W
        dy *= _ORI_W
        # direction bins from cv2.phase (SIMD, within 2e-4 rad of atan2 against 0.087 rad bins);
        # numpy's float32 arctan2 is ~30x slower
        bins = (cv2.phase(dx, dy) * np.float32(n_bins / (2 * np.pi))).astype(np.int32)
        np.minimum(bins, n_bins - 1, out=bins)  # a phase rounded up to 2 pi
        bins += (n_bins * np.arange(sel.size, dtype=np.int32))[:, None]
        hx = np.bincount(bins.ravel(), weights=dx.ravel(), minlength=sel.size * n_bins).reshape(sel.size, n_bins)
        hy = np.bincount(bins.ravel(), weights=dy.ravel(), minlength=sel.size * n_bins).reshape(sel.size, n_bins)
        # pi/3 sliding-window sums of all 72 windows: one small product each
        sx = hx @ _ORI_WINDOW
        sy = hy @ _ORI_WINDOW
        best = np.argmax(sx**2 + sy**2, axis=1)
        r = np.arange(sel.size)
        out[sel] = np.arctan2(sy[r, best], sx[r, best])
    return out


def descriptors(bank: HaarBank, uv: NDArray, scale: NDArray, theta: NDArray) -> NDArray[np.float32]:
    desc = np.zeros((uv.shape[0], 64), np.float32)
    bands = _scale_bands(scale)
    for b in np.unique(bands):
        sel = np.flatnonzero(bands == b)
        n = sel.size
        k, half = bank.level_of(2.0 * 1.2 * 2.0 ** (b / 4.0))
        mx, my = _read_positions(uv[sel], scale[sel], theta[sel], _DESC_BASIS, k)
        dx, dy = bank.read(k, half, mx, my)  # (n, 400) each: image-axis responses
        co = np.cos(theta[sel]).astype(np.float32)[:, None]
        si = np.sin(theta[sel]).astype(np.float32)[:, None]
        # responses in the keypoint frame, as rows (rx of keypoint 0, ry of keypoint 0, rx of 1, ...):
        # rx = dx co + dy si, ry = dy co - dx si, in place (dx, dy are this band's own arrays)
        rt = np.empty((n, 2, 400), np.float32)
        rx, ry = rt[:, 0], rt[:, 1]
        np.multiply(dy, si, out=ry)
        np.multiply(dx, co, out=rx)
        rx += ry
        np.multiply(dy, co, out=ry)
        dx *= si
        ry -= dx
        rt = rt.reshape(2 * n, 400)
        # Gaussian-weighted sums per 4x4 sub-region of sum r and sum |r|: one matrix product each
        sums = (rt @ _DESC_SUM).reshape(n, 2, 16)
        abs_sums = (np.abs(rt, out=rt) @ _DESC_SUM).reshape(n, 2, 16)
        # per sub-region (sum dx, sum dy, sum |dx|, sum |dy|), sub-regions row-major
        d = np.concatenate([sums, abs_sums], axis=1).transpose(0, 2, 1).reshape(n, 64)
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        desc[sel] = d / np.maximum(norm, np.float32(1e-12))
    return desc
