"""Gray-code structured light for rig calibration: the patterns, their decoding, capture folders.

Gray-code layout (checked against the pattern PNGs that procam-calibration ships and against
``cv2.structured_light.GrayCodePattern.generate``): for a projector of ``W x H`` pixels there are
``n_c = ceil(log2 W)`` column bits and ``n_r = ceil(log2 H)`` row bits; images come as
``[col bit MSB, its inverse, ..., col bit LSB, inverse, row bit MSB, inverse, ..., row LSB,
inverse]`` (2 n_c + 2 n_r images), then, in procam-calibration captures, white and black.
A bit is 1 where the pattern image is brighter than its inverse; the bits form the binary
reflected Gray code of the projector column (row), MSB first.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import CalibrationError


def gray_code_bit_counts(projector_width: int, projector_height: int) -> tuple[int, int]:
    """Number of column and row bits of OpenCV's Gray-code pattern for a projector size."""
    return max(1, math.ceil(math.log2(projector_width))), max(1, math.ceil(math.log2(projector_height)))


def gray_code_patterns(projector_width: int, projector_height: int) -> NDArray[np.uint8]:
    """The Gray-code pattern images (2 n_c + 2 n_r, H, W) uint8 in OpenCV's order (see module doc)."""
    n_c, n_r = gray_code_bit_counts(projector_width, projector_height)
    cols = np.arange(projector_width)
    rows = np.arange(projector_height)
    out = np.empty((2 * (n_c + n_r), projector_height, projector_width), dtype=np.uint8)
    for k in range(n_c):
        bit = ((cols ^ (cols >> 1)) >> (n_c - 1 - k)) & 1
        out[2 * k] = (255 * bit)[None, :]
        out[2 * k + 1] = 255 - out[2 * k]
    for k in range(n_r):
        bit = ((rows ^ (rows >> 1)) >> (n_r - 1 - k)) & 1
        out[2 * (n_c + k)] = (255 * bit)[:, None]
        out[2 * (n_c + k) + 1] = 255 - out[2 * (n_c + k)]
    return out


@dataclass(frozen=True, eq=False)
class GrayCodeDecoding:
    """Decoded projector coordinates per camera pixel.

    Attributes
    ----------
    column, row : (H, W) int32
        Projector column and row (pixels, times the Gray-code step); -1 where invalid.
    valid : (H, W) bool
        Lit by the projector (white - black above the black threshold), every bit reliable
        (pattern and inverse differ by at least the white threshold) and inside the projector.
    """

    column: NDArray[np.int32]
    row: NDArray[np.int32]
    valid: NDArray[np.bool_]


def _gray_bits_to_int(bits: NDArray[np.bool_]) -> NDArray[np.int32]:
    """(n, H, W) Gray-code bits, MSB first -> (H, W) integers."""
    value = np.zeros(bits.shape[1:], dtype=np.int32)
    binary = np.zeros(bits.shape[1:], dtype=bool)
    for g in bits:
        binary ^= g  # binary bit i = XOR of Gray bits 0..i
        value = (value << 1) | binary
    return value


def decode_gray_code(
    pattern_images: Sequence[ArrayLike] | NDArray,
    projector_size: tuple[int, int],
    white: ArrayLike | None = None,
    black: ArrayLike | None = None,
    *,
    white_threshold: float = 5.0,
    black_threshold: float = 40.0,
    step: int = 1,
) -> GrayCodeDecoding:
    """Decode Gray-code captures with inverses (OpenCV ``GrayCodePattern`` order), vectorised.

    Parameters
    ----------
    pattern_images : sequence of (H, W) arrays, length 2 n_c + 2 n_r
        Camera images of the patterns and their inverses (any numeric dtype, grey levels).
    projector_size : (width, height)
        Size of the decoded code grid: the projector size divided by ``step`` (rounded up).
    white, black : (H, W) arrays, optional
        Images under full and no illumination; with both, pixels whose contrast
        ``white - black`` is at most ``black_threshold`` are invalid (procam-calibration's rule).
    white_threshold : float
        Smallest accepted difference between a pattern and its inverse (OpenCV's rule).
    black_threshold : float
        See ``white, black``.
    step : int
        Gray-code step (projector pixels per code); the codes are multiplied by it.

    Returns
    -------
    GrayCodeDecoding
    """
    width, height = (int(v) for v in projector_size)
    gc_w, gc_h = (width - 1) // step + 1, (height - 1) // step + 1
    n_c, n_r = gray_code_bit_counts(gc_w, gc_h)
    imgs = np.asarray(pattern_images, dtype=np.float32) if not isinstance(pattern_images, np.ndarray) else pattern_images.astype(np.float32, copy=False)
    if imgs.ndim != 3 or imgs.shape[0] != 2 * (n_c + n_r):
        raise CalibrationError(
            f"Gray-code decoding for a {gc_w}x{gc_h} code grid needs {2 * (n_c + n_r)} images "
            f"({n_c} column and {n_r} row bits, each with its inverse), got {imgs.shape[0] if imgs.ndim == 3 else imgs.shape}"
        )
    diff = imgs[0::2] - imgs[1::2]  # (n_c + n_r, H, W)
    reliable = np.all(np.abs(diff) >= white_threshold, axis=0)
    bits = diff > 0
    column = _gray_bits_to_int(bits[:n_c])
    row = _gray_bits_to_int(bits[n_c:])
    valid = reliable & (column < gc_w) & (row < gc_h)
    if white is not None and black is not None:
        contrast = np.asarray(white, dtype=np.float32) - np.asarray(black, dtype=np.float32)
        if contrast.shape != valid.shape:
            raise CalibrationError(f"white/black images are {contrast.shape}, the patterns {valid.shape}")
        valid &= contrast > black_threshold
    column = np.where(valid, column * step, -1).astype(np.int32)
    row = np.where(valid, row * step, -1).astype(np.int32)
    return GrayCodeDecoding(column=column, row=row, valid=valid)


def read_graycode_capture(folder: str | os.PathLike[str], projector_size: tuple[int, int], step: int = 1) -> tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]:
    """Read one procam-calibration pose folder: ``graycode_00.png`` ... in capture order.

    Returns ``(patterns (2 n_c + 2 n_r, H, W), white (H, W), black (H, W))`` uint8: the Gray-code
    images, then the white and the black image (the last two files).
    """
    folder = Path(folder)
    files = sorted(folder.glob("graycode_*.png"))
    gc_w, gc_h = ((v - 1) // step + 1 for v in projector_size)
    n_c, n_r = gray_code_bit_counts(gc_w, gc_h)
    need = 2 * (n_c + n_r) + 2
    if len(files) != need:
        raise CalibrationError(f"{folder}: {len(files)} graycode_*.png images, a {projector_size[0]}x{projector_size[1]} projector (step {step}) needs {need} (patterns with inverses, white, black)")
    images = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"{f}: not a readable image")
        if images and img.shape != images[0].shape:
            raise CalibrationError(f"{f}: size {img.shape[::-1]} differs from {files[0].name}'s {images[0].shape[::-1]}")
        images.append(img)
    stack = np.stack(images)
    return stack[:-2], stack[-2], stack[-1]
