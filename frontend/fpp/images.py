"""Loading a frame's pattern images from image files, with checks that name the bad file."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError


def _to_grey(image: NDArray, path: Path) -> NDArray:
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise InputDataError(f"{path}: unsupported image layout {image.shape}; expected grey, BGR or BGRA")


def load_image(path: str | os.PathLike[str]) -> NDArray:
    """One image as a single-channel uint8 or uint16 array (colour converted to grey).

    Raises
    ------
    InputDataError
        Missing, unreadable or corrupt file, or a pixel type other than 8/16-bit unsigned.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: image file not found")
    # imdecode on the bytes instead of imread: works for any path encoding and reports a
    # truncated or non-image file as None rather than a partial image with a warning.
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputDataError(f"{path}: cannot read image file ({exc.strerror})") from exc
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputDataError(f"{path}: not a readable image (corrupt, truncated or unsupported format); re-export it as PNG")
    image = _to_grey(image, path)
    if image.dtype not in (np.uint8, np.uint16):
        raise InputDataError(f"{path}: pixel type {image.dtype} is not supported; pattern images must be 8- or 16-bit unsigned")
    return image


def load_image_stack(paths: Sequence[str | os.PathLike[str]]) -> NDArray:
    """A frame's pattern images as one (M, H, W) stack, in the order given.

    Parameters
    ----------
    paths : sequence of paths
        Image files (PNG, TIFF, BMP, ...) in capture order.

    Returns
    -------
    (M, H, W) uint8 or uint16
        Colour images are converted to grey (OpenCV's BGR weights).

    Raises
    ------
    InputDataError
        No paths, an unreadable/corrupt file (named), or images of mixed sizes or pixel types.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise InputDataError("no image files given for the pattern stack")
    images = [load_image(p) for p in paths]
    first, first_path = images[0], paths[0]
    for image, path in zip(images[1:], paths[1:], strict=True):
        if image.shape != first.shape:
            raise InputDataError(
                f"{path}: size {image.shape[1]}x{image.shape[0]} differs from {first_path.name} "
                f"({first.shape[1]}x{first.shape[0]}); all images of a frame must have the same size"
            )
        if image.dtype != first.dtype:
            raise InputDataError(f"{path}: pixel type {image.dtype} differs from {first_path.name} ({first.dtype}); all images of a frame must share one bit depth")
    return np.stack(images)
