"""eq. 2 on one band of rows: wrapped phase and modulation of N phase-shifted images.

Also the band's named work buffers (:class:`Scratch`), shared by the decoding steps
(:mod:`frontend.fpp.phase`, :mod:`frontend.fpp.unwrapping`). Conventions: :mod:`frontend.fpp.phase`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

TWO_PI = 2.0 * math.pi


def phase_weights(n_steps: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """sin and cos of the phase shifts ``delta_n``, with exact 0 and +-1 where they belong."""
    delta = TWO_PI * np.arange(n_steps) / n_steps
    sin, cos = np.sin(delta), np.cos(delta)
    for w in (sin, cos):  # exact values let the sums skip zero weights
        w[np.abs(w) < 1e-12] = 0.0
        w[np.abs(w - 1) < 1e-12] = 1.0
        w[np.abs(w + 1) < 1e-12] = -1.0
    return sin, cos


class Scratch:
    """Named work buffers of one band size, reused across bands and frames (one per thread)."""

    def __init__(self, rows: int, width: int) -> None:
        self.rows, self.width = rows, width
        self._buffers: dict[tuple[str, str], NDArray] = {}

    def get(self, name: str, dtype: type, rows: int) -> NDArray:
        key = (name, np.dtype(dtype).str)
        buf = self._buffers.get(key)
        if buf is None:
            buf = np.empty((self.rows, self.width), dtype=dtype)
            self._buffers[key] = buf
        return buf[:rows]  # a leading row slice of a C-contiguous array stays contiguous

    def const(self, name: str, value: float, dtype: type, rows: int) -> NDArray:
        key = ("const:" + name, np.dtype(dtype).str)
        buf = self._buffers.get(key)
        if buf is None:
            buf = np.full((self.rows, self.width), value, dtype=dtype)
            self._buffers[key] = buf
        return buf[:rows]


def wrapped_phase_band(imgs: list[NDArray], sin: NDArray, cos: NDArray, phi: NDArray, mod: NDArray, work: Scratch) -> None:
    """eq. 2 into ``phi`` ([0, 2 pi)) and ``mod`` (b), from one frequency's N images.

    S and C are summed over symmetric pairs: ``sin delta_(N-n) = -sin delta_n`` and
    ``cos delta_(N-n) = cos delta_n``, so each pair costs one integer difference and one
    integer sum (exact), and N = 4 needs no multiplication at all.
    """
    n = len(imgs)
    r = imgs[0].shape[0]
    idt = np.int32 if imgs[0].dtype == np.uint16 else np.int16
    s = work.get("S", np.float32, r)
    c = work.get("C", np.float32, r)
    ti = work.get("tmp_int", idt, r)
    tf = work.get("tmp_float", np.float32, r)
    if n % 2 == 0:
        np.subtract(imgs[0], imgs[n // 2], out=ti, dtype=idt)  # cos 0 = 1, cos pi = -1
        np.copyto(c, ti, casting="unsafe")
    else:
        np.copyto(c, imgs[0], casting="unsafe")
    for k in range(1, (n - 1) // 2 + 1):
        sk, ck = float(sin[k]), float(cos[k])
        np.subtract(imgs[k], imgs[n - k], out=ti, dtype=idt)
        if k == 1:
            if sk == 1.0:  # N = 4
                np.copyto(s, ti, casting="unsafe")
            else:
                np.multiply(ti, np.float32(sk), out=s, casting="unsafe")
        else:
            np.copyto(tf, ti, casting="unsafe")
            cv2.scaleAdd(tf, sk, s, dst=s)
        if ck != 0.0:
            np.add(imgs[k], imgs[n - k], out=ti, dtype=idt)
            np.copyto(tf, ti, casting="unsafe")
            cv2.scaleAdd(tf, ck, c, dst=c)
    cv2.cartToPolar(c, s, mod, phi)  # |(C, S)| and atan2(S, C) in [0, 2 pi) (cv2.phase's), in one pass
    np.multiply(mod, np.float32(2.0 / n), out=mod)
