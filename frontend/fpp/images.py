"""Loading a frame's pattern images from image files, with checks that name the bad file: every
image read to its end, one size for a frame's images, and that size the calibration's camera's."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import CalibrationError, InputDataError

if TYPE_CHECKING:
    from frontend.fpp.rig import RigCalibration


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


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and CRC, the last bytes a PNG writer writes
JPEG_START = b"\xff\xd8\xff"
JPEG_START_OF_SCAN = b"\xff\xda"
JPEG_END = b"\xff\xd9"


def load_image(path: str | os.PathLike[str]) -> NDArray:
    """One image as a single-channel uint8 or uint16 array (colour converted to grey).

    Raises
    ------
    InputDataError
        Missing, unreadable, corrupt or truncated file, or a pixel type other than 8/16-bit unsigned.
    """
    path = Path(path)
    data = np.frombuffer(_read_bytes(path), dtype=np.uint8)
    # imdecode on the bytes instead of imread: works for any path encoding and reports a
    # non-image file as None rather than a partial image with a warning
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputDataError(f"{path}: not a readable image (corrupt, truncated or unsupported format); re-export it as PNG")
    _check_complete(data.tobytes(), path)
    image = _to_grey(image, path)
    if image.dtype not in (np.uint8, np.uint16):
        raise InputDataError(f"{path}: pixel type {image.dtype} is not supported; pattern images must be 8- or 16-bit unsigned")
    return image


def _read_bytes(path: Path) -> bytes:
    """The file's bytes; every OSError as an InputDataError naming the file and what to do."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputDataError(f"{path}: image file not found; restore it, or correct the list or folder that names it") from None
    except IsADirectoryError:
        raise InputDataError(f"{path}: a folder, not an image file; correct the list or folder that names it") from None
    except OSError as exc:
        raise InputDataError(f"{path}: cannot read image file ({exc.strerror or exc}); check its permissions") from None


def _check_complete(data: bytes, path: Path) -> None:
    """A PNG or JPEG whose end is missing (an interrupted copy or capture) is refused, although a
    decoder may return its first rows and leave the rest grey without an error (libjpeg pads a
    truncated scan and only warns). A PNG ends with its IEND chunk; a JPEG's last scan ends with
    the EOI marker, which the entropy-coded data cannot contain (0xFF is stuffed there)."""
    if data.startswith(PNG_SIGNATURE):
        complete, kind = data.rfind(PNG_END) > 0, "PNG"
    elif data.startswith(JPEG_START):
        last_scan = data.rfind(JPEG_START_OF_SCAN)
        complete, kind = last_scan > 0 and data.find(JPEG_END, last_scan) > 0, "JPEG"
    else:
        return
    if not complete:
        raise InputDataError(f"{path}: truncated {kind} file (its end is missing: an interrupted copy or capture); copy or capture it again")


def image_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """(width, height) of an image file: from a PNG's header alone, else by decoding it.

    Raises
    ------
    InputDataError
        As :func:`load_image`.
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            head = handle.read(24)
    except OSError:
        head = b""  # load_image says why
    if head.startswith(PNG_SIGNATURE) and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    image = load_image(path)
    return image.shape[1], image.shape[0]


def check_images_match_calibration(stack_shape: tuple[int, ...], rig: RigCalibration, where: str) -> None:
    """Raise CalibrationError unless images of ``stack_shape`` ((M, H, W) or (H, W)) are the size
    of ``rig``'s camera: a calibration of another camera (or of resized images) would decode
    nothing and say only that no pixel is valid.

    ``where`` names the images (a frame's folder, a capture) at the start of the message.
    """
    height, width = (int(n) for n in stack_shape[-2:])
    camera = rig.camera
    if (width, height) != (camera.width, camera.height):
        raise CalibrationError(
            f"{where}: images are {width}x{height} but the calibration's camera is {camera.width}x{camera.height} pixels; "
            "the calibration is of another camera (or the images were resized or cropped): use the calibration of the camera "
            "that took these images"
        )


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
