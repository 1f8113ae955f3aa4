"""One capture (a folder of pattern images) -> point cloud, xyz map, texture, depth image, report.

:func:`capture_image_paths` picks a capture's images in the order the pattern file states,
:func:`decode_capture` decodes and triangulates them exactly as the SLAM pipeline does
(:class:`frontend.fpp.sensor.FppSensor`: decoder, triangulation, mixed-pixel edge filter) and
:func:`write_capture_outputs` writes the results atomically:

``points.ply``
    Binary little-endian PLY, ``x y z`` float64 metres in the camera frame, ``red green blue``
    uchar (the texture grey), valid pixels in row-major order.
``xyz_map.npy``
    (H, W, 3) float32, metres, camera frame, NaN where invalid.
``texture.png``
    (H, W) 8-bit: the background ``a`` of the fringes.
``depth.png``
    (H, W) 16-bit, depth ``z`` along the camera axis in 0.1 mm units, 0 where invalid (depths
    beyond 6.5535 m do not fit and are written as 0, counted in ``decode.json``).
``decode.json``
    Valid pixel count, invalid counts per reason, modulation statistics (grey levels), the mask
    thresholds used, depth range, seconds per step.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_open, atomic_write_bytes, atomic_write_text
from fpp_graph.errors import InputDataError, OutputError
from frontend.config import DecodeConfig
from frontend.fpp.images import load_image_stack
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import DecodeResult
from frontend.fpp.rig import RigCalibration

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg", ".pgm")
DEPTH_UNIT_M = 1e-4  # depth.png: 0.1 mm per count
OUTPUT_FILES = ("points.ply", "xyz_map.npy", "texture.png", "depth.png", "decode.json")

#: progress(stage, done, total), as the pipeline's ProgressCallback
Progress = Callable[[str, int, int], None]


def natural_key(path: Path) -> list[Any]:
    """``img2.png`` before ``img10.png``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def capture_image_paths(folder: str | os.PathLike[str], spec: PatternSpec, pattern: str | None = None) -> list[Path]:
    """The capture's image files, in natural name order, checked against the spec's image count.

    Parameters
    ----------
    folder : path
        The capture folder.
    spec : PatternSpec
        What the images show, in capture order.
    pattern : str, optional
        Glob that picks the images (default: every image file in the folder).

    Raises
    ------
    InputDataError
        No such folder, or a number of images different from the spec's.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputDataError(f"capture folder {folder} does not exist (or is not a folder)")
    files = sorted((p for p in folder.glob(pattern or "*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
    n = spec.image_count()
    if len(files) != n:
        which = f"matching {pattern!r}" if pattern else "(all image files)"
        raise InputDataError(
            f"{folder}: {len(files)} images {which} but the pattern spec describes {n} "
            f"({describe_order(spec)}); pick the images with --images GLOB or fix the spec's order"
        )
    return files


def describe_order(spec: PatternSpec, keep: int = 4) -> str:
    """The spec's image roles in order, the middle elided for long sets."""
    tokens = [im.token() for im in spec.layout()]
    if len(tokens) <= 2 * keep + 1:
        return ", ".join(tokens)
    return ", ".join(tokens[:keep]) + f", ... ({len(tokens) - 2 * keep} more), " + ", ".join(tokens[-keep:])


@dataclass(frozen=True, eq=False)
class CaptureResult:
    """A decoded and triangulated capture.

    Attributes
    ----------
    xyz_map_m : (H, W, 3) float64
        Metres, camera frame, NaN where invalid.
    texture : (H, W) uint8
    decoding : DecodeResult
    report : dict
        What ``decode.json`` holds.
    """

    xyz_map_m: NDArray[np.float64]
    texture: NDArray[np.uint8]
    decoding: DecodeResult
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def valid(self) -> NDArray[np.bool_]:
        return np.isfinite(self.xyz_map_m[..., 2])


def decode_capture(
    images: NDArray | Sequence[NDArray],
    calibration: RigCalibration,
    spec: PatternSpec,
    decode_config: DecodeConfig | None = None,
    *,
    edge_filter: bool = True,
    depth_range_m: tuple[float, float] = (0.05, 10.0),
    where: str = "capture",
    progress: Progress | None = None,
) -> CaptureResult:
    """Decode and triangulate one capture as the pipeline does (:class:`FppSensor`).

    Parameters
    ----------
    images : (M, H, W) uint8/uint16
        In the spec's capture order.
    calibration, spec, decode_config
        Rig, pattern set and decoder thresholds (default: the packaged ones).
    edge_filter : bool
        The mixed-pixel / discontinuity filter of the pipeline (on by default; never applied to
        Gray code alone, whose stripe staircase it would reject entirely).
    depth_range_m : (near, far)
        Accepted depths along the camera axis, metres.
    where : str
        Names the capture in error messages (e.g. its folder).

    Raises
    ------
    InputDataError
        Wrong image count or a frame without any valid pixel.
    CalibrationError
        The images' size differs from the calibration's camera.
    """
    from frontend.fpp.sensor import FppSensor

    config = decode_config or DecodeConfig()
    if spec.kind == "gray_code" and edge_filter:
        # A stripe-quantised map is a staircase of projector stripe planes: its local normals
        # are those planes', seen at grazing angles, so the filter would drop every pixel.
        log.info("%s: Gray code alone gives a staircase depth map; the mixed-pixel edge filter is not applied", where)
        edge_filter = False
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    sensor = FppSensor(calibration, spec, config, depth_range_m=depth_range_m, edge_max_angle_deg=75.0 if edge_filter else None)
    seconds["set_up"] = time.perf_counter() - t0
    _report(progress, 1)
    t0 = time.perf_counter()
    result = sensor.decode(images, where)
    seconds["decode"] = time.perf_counter() - t0
    _report(progress, 2)
    t0 = time.perf_counter()
    xyz, edge_rejected = sensor.points_from_decoding(result)
    seconds["triangulate"] = time.perf_counter() - t0
    _report(progress, 3)
    report = _capture_report(result, xyz, edge_rejected, config, spec, depth_range_m, edge_filter)
    report["seconds"] = seconds
    return CaptureResult(xyz_map_m=xyz, texture=result.texture, decoding=result, report=report)


def _report(progress: Progress | None, done: int) -> None:
    if progress is not None:
        progress("decode", done, 4)


def _capture_report(result: DecodeResult, xyz: NDArray, edge_rejected: int, config: DecodeConfig, spec: PatternSpec, depth_range_m: tuple[float, float], edge_filter: bool) -> dict[str, Any]:
    valid = np.isfinite(xyz[..., 2])
    mod = result.modulation
    decoded = result.mask
    z = xyz[..., 2][valid]
    finite_mod = mod[np.isfinite(mod)]
    return {
        "image_size": [int(valid.shape[1]), int(valid.shape[0])],
        "pattern_kind": spec.kind,
        "valid_pixels": int(np.count_nonzero(valid)),
        "decoded_pixels": int(np.count_nonzero(decoded)),
        "invalid_counts": {**{k: int(v) for k, v in result.invalid_counts.items()}, "edge_filter": int(edge_rejected),
                           "triangulation": int(np.count_nonzero(decoded)) - int(np.count_nonzero(valid)) - int(edge_rejected)},
        "modulation_grey": {
            "all_pixels": _stats(finite_mod),
            "valid_pixels": _stats(mod[valid]),
        },
        "thresholds": {
            "min_modulation_grey": config.min_modulation,
            "min_background_grey": config.min_background,
            "saturation_level_grey": config.saturation_level,
            "min_code_contrast_grey": config.min_code_contrast,
            "depth_range_m": list(depth_range_m),
            "edge_filter": {"enabled": edge_filter, "max_angle_deg": 75.0, "noise_floor_m": 0.0005} if edge_filter else {"enabled": False},
        },
        "depth_m": _stats(z),
        "pitch_px": float(result.pitch_px),
    }


def _stats(values: NDArray) -> dict[str, float]:
    if values.size == 0:
        return {"count": 0}
    p = np.percentile(values, [1, 50, 99])
    return {"count": int(values.size), "min": float(values.min()), "p01": float(p[0]), "median": float(p[1]), "p99": float(p[2]), "max": float(values.max()), "mean": float(values.mean())}


def read_capture(folder: str | os.PathLike[str], spec: PatternSpec, pattern: str | None = None) -> NDArray:
    """The capture's images as one (M, H, W) stack in the spec's order (see :func:`capture_image_paths`)."""
    return load_image_stack(capture_image_paths(folder, spec, pattern))


def write_capture_outputs(out_dir: str | os.PathLike[str], capture: CaptureResult) -> dict[str, Path]:
    """Write :data:`OUTPUT_FILES` into ``out_dir`` (each atomically); returns their paths."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a folder; choose another --out")
    xyz = capture.xyz_map_m
    valid = capture.valid
    paths = {name: out / name for name in OUTPUT_FILES}
    _write_ply(paths["points.ply"], xyz[valid], capture.texture[valid])
    with atomic_open(paths["xyz_map.npy"], "wb") as handle:
        np.save(handle, xyz.astype(np.float32))
    write_png(paths["texture.png"], capture.texture)
    depth_units = np.where(valid, np.rint(np.where(valid, xyz[..., 2], 0.0) / DEPTH_UNIT_M), 0.0)
    too_far = depth_units > np.iinfo(np.uint16).max
    depth_units[too_far] = 0
    write_png(paths["depth.png"], depth_units.astype(np.uint16))
    report = {**capture.report, "depth_png": {"unit_m": DEPTH_UNIT_M, "invalid": 0, "too_far_written_as_0": int(np.count_nonzero(too_far))}}
    atomic_write_text(paths["decode.json"], json.dumps(report, indent=1) + "\n")
    return paths


def write_png(path: str | os.PathLike[str], image: NDArray) -> None:
    """Write an 8- or 16-bit image as PNG, atomically."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OutputError(f"cannot encode {Path(path).name} as PNG")
    atomic_write_bytes(path, buf.tobytes())


def _write_ply(path: Path, points_m: NDArray, grey: NDArray) -> None:
    """Binary little-endian PLY of coloured points (float64 metres, uchar grey as RGB)."""
    n = len(points_m)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment fpp-graph decode: metres, camera frame\n"
        f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    rows = np.empty(n, dtype=[("xyz", "<f8", 3), ("rgb", "u1", 3)])
    rows["xyz"] = points_m
    rows["rgb"] = np.repeat(np.asarray(grey, np.uint8)[:, None], 3, axis=1)
    buf = io.BytesIO()
    buf.write(header.encode("ascii"))
    buf.write(rows.tobytes())
    atomic_write_bytes(path, buf.getvalue())


def import_captures(
    root: str | os.PathLike[str],
    spec: PatternSpec,
    calibration: RigCalibration,
    out: str | os.PathLike[str],
    *,
    images: str | None = None,
    frames: str = "*",
    copy: bool = True,
    frame_period_s: float = 1.0,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> Path:
    """A folder with one sub-folder of images per frame -> a sequence folder ``fpp-slam run`` reads.

    Parameters
    ----------
    root : path
        Capture root; its sub-folders matching ``frames`` (natural name order) are the frames.
    spec, calibration
        The pattern set (image order within a frame) and the rig, written into ``sequence.yaml``.
    out : path
        The sequence folder (:mod:`frontend.fpp.sequence`).
    images : str, optional
        Glob picking each frame's images.
    copy : bool
        True: the images are re-written as grey PNGs into the sequence. False: ``sequence.yaml``
        refers to the capture folders where they are (relative paths: keep both folders together).
    frame_period_s : float
        Timestamps are ``frame index * frame_period_s``.

    Raises
    ------
    InputDataError
        No frame folders, a frame with the wrong image count, unreadable images.
    CalibrationError
        A frame's image size differs from the calibration's camera.
    """
    from frontend.fpp.sequence import FrameRecord, SequenceWriter

    root = Path(root)
    if not root.is_dir():
        raise InputDataError(f"capture root {root} does not exist (or is not a folder)")
    folders = sorted((p for p in root.glob(frames) if p.is_dir()), key=natural_key)
    if not folders:
        raise InputDataError(f"{root} has no frame sub-folders matching {frames!r}; put each frame's images in a sub-folder of its own")
    writer = SequenceWriter(out, calibration, spec, overwrite=overwrite, source={"imported_from": str(root.resolve()), "copied": copy})
    out_path = Path(out).resolve()
    for k, folder in enumerate(folders):
        paths = capture_image_paths(folder, spec, images)
        if copy:
            writer.add_frame(k, k * frame_period_s, load_image_stack(paths))
        else:
            first = load_image_stack(paths[:1])  # one image per frame: size and type (all are checked on reading)
            calibration.check_image_size(first.shape[2], first.shape[1], f"{folder} (calibration camera)")
            rel = os.path.relpath(folder.resolve(), out_path)
            writer.frames.append(FrameRecord(k, k * frame_period_s, rel, tuple(p.name for p in paths)))
        if progress is not None:
            progress("import", k + 1, len(folders))
    return writer.close()
