"""One capture (a folder of pattern images) -> point cloud, xyz map, texture, depth image, report.

:func:`capture_image_paths` picks a capture's images in the order the pattern file states,
:func:`decode_capture` decodes and triangulates them exactly as the SLAM pipeline does
(:class:`frontend.fpp.sensor.FppSensor`: decoder, triangulation, mixed-pixel edge filter) and
:func:`write_capture_outputs` writes the results, each whole and all written before any appears:

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
    thresholds used, depth range, seconds per step; ``thresholds.edge_filter`` states the edge
    filter's noise model (:meth:`frontend.fpp.sensor.EdgeFilterStats.as_dict`: the measured
    image noise ``image_noise_grey``, the median expected depth noise ``median_depth_sigma_m``,
    the multiples of it the two tests allow, ``range_sigma_multiple`` and
    ``gradient_sigma_multiple``, at ``false_drop_probability``, the ``noise_floor_m``, and the
    ``removed_pixels`` of the ``triangulated_pixels``).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_open, atomic_write_bytes
from fpp_graph.errors import InputDataError, OutputError
from fpp_graph.outputs import (
    LOCK_NAME,
    FolderLock,
    make_folder,
    refuse_input_overlap,
    translated_os_errors,
)
from frontend.config import DecodeConfig
from frontend.fpp.images import load_image_stack
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import DecodeResult
from frontend.fpp.rig import RigCalibration

if TYPE_CHECKING:
    from frontend.fpp.sensor import EdgeFilterStats

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
        Gray code alone, whose stripe staircase it would reject entirely). Its noise allowances
        follow the capture's measured noise; when it removes more than half of the triangulated
        pixels one warning says so (and how to keep them).
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
    xyz, edge_stats = sensor.filtered_points(result)
    seconds["triangulate"] = time.perf_counter() - t0
    _report(progress, 3)
    report = _capture_report(result, xyz, edge_stats, config, spec, depth_range_m)
    report["seconds"] = seconds
    return CaptureResult(xyz_map_m=xyz, texture=result.texture, decoding=result, report=report)


def _report(progress: Progress | None, done: int) -> None:
    if progress is not None:
        progress("decode", done, 4)


def _capture_report(result: DecodeResult, xyz: NDArray, edge_stats: EdgeFilterStats, config: DecodeConfig, spec: PatternSpec, depth_range_m: tuple[float, float]) -> dict[str, Any]:
    valid = np.isfinite(xyz[..., 2])
    edge_rejected = edge_stats.removed
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
            "edge_filter": edge_stats.as_dict(),
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


def write_capture_outputs(out_dir: str | os.PathLike[str], capture: CaptureResult, overwrite: bool = False) -> dict[str, Path]:
    """Write :data:`OUTPUT_FILES` into ``out_dir``; returns their paths.

    Every file is written whole (and synced) under a temporary name before any is renamed into
    place, so a write that fails (a full disk, no permission) leaves none of them and no
    temporary file: an OutputError names the file and what to do. Without ``overwrite`` an
    existing output is never replaced (OutputError; one made meanwhile by another program stops
    the renaming at that file). Other files in ``out_dir`` are left alone.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out} is a file, not a folder: choose another --out")
    contents = _encoded_outputs(capture)
    paths = {name: out / name for name in OUTPUT_FILES}
    with contextlib.ExitStack() as stack:
        # entered last, published first: decode.json, the report, appears after the data it describes
        handles = {name: stack.enter_context(atomic_open(paths[name], "wb", replace=overwrite)) for name in reversed(OUTPUT_FILES)}
        for name in OUTPUT_FILES:
            handle = handles[name]
            handle.write(contents[name])
            handle.flush()
            os.fsync(handle.fileno())  # on disk before any file is published: no half set on a full disk
    return paths


def _encoded_outputs(capture: CaptureResult) -> dict[str, bytes]:
    """The bytes of each of :data:`OUTPUT_FILES`."""
    xyz = capture.xyz_map_m
    valid = capture.valid
    npy = io.BytesIO()
    np.save(npy, xyz.astype(np.float32))
    depth_units = np.where(valid, np.rint(np.where(valid, xyz[..., 2], 0.0) / DEPTH_UNIT_M), 0.0)
    too_far = depth_units > np.iinfo(np.uint16).max
    depth_units[too_far] = 0
    report = {**capture.report, "depth_png": {"unit_m": DEPTH_UNIT_M, "invalid": 0, "too_far_written_as_0": int(np.count_nonzero(too_far))}}
    return {
        "points.ply": _ply_bytes(xyz[valid], capture.texture[valid]),
        "xyz_map.npy": npy.getvalue(),
        "texture.png": png_bytes(capture.texture, "texture.png"),
        "depth.png": png_bytes(depth_units.astype(np.uint16), "depth.png"),
        "decode.json": (json.dumps(report, indent=1) + "\n").encode("utf-8"),
    }


def png_bytes(image: NDArray, name: str) -> bytes:
    """An 8- or 16-bit image encoded as PNG; ``name`` for the error message."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OutputError(f"cannot encode {name} as PNG")
    return buf.tobytes()


def write_png(path: str | os.PathLike[str], image: NDArray, replace: bool = False) -> None:
    """Write an 8- or 16-bit image as PNG, atomically; an existing file is replaced only with ``replace``."""
    atomic_write_bytes(path, png_bytes(image, Path(path).name), replace=replace)


def _ply_bytes(points_m: NDArray, grey: NDArray) -> bytes:
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
    return buf.getvalue()


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
    inputs: Iterable[str | os.PathLike[str] | None] = (),
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
        The sequence folder (:mod:`frontend.fpp.sequence`), written as :func:`sequence_output`
        says: never into an input, never over a folder that is not an imported sequence.
    images : str, optional
        Glob picking each frame's images.
    copy : bool
        True: the images are re-written as grey PNGs into the sequence. False: ``sequence.yaml``
        refers to the capture folders where they are (relative paths: keep both folders together).
    frame_period_s : float
        Timestamps are ``frame index * frame_period_s``.
    overwrite : bool
        Replace a sequence an earlier import wrote into ``out``.
    inputs : paths
        The other files read (pattern file, calibration): ``out`` must not overlap them.

    Raises
    ------
    InputDataError
        No frame folders, a frame with the wrong image count, unreadable images.
    CalibrationError
        A frame's image size differs from the calibration's camera.
    OutputError
        ``out`` cannot be written (see :func:`sequence_output`).
    """
    from frontend.fpp.sequence import FrameRecord

    root = Path(root)
    if not root.is_dir():
        raise InputDataError(f"capture root {root} does not exist (or is not a folder)")
    all_inputs = [root, *inputs]
    refuse_sequence_output(out, overwrite, all_inputs, IMPORTED)
    folders = sorted((p for p in root.glob(frames) if p.is_dir()), key=natural_key)
    if not folders:
        raise InputDataError(f"{root} has no frame sub-folders matching {frames!r}; put each frame's images in a sub-folder of its own")
    frame_images = [capture_image_paths(folder, spec, images) for folder in folders]  # every count checked before writing
    source = {"imported_from": str(root.resolve()), "copied": copy}
    with sequence_output(out, calibration, spec, overwrite=overwrite, inputs=all_inputs, source=source, made_by=IMPORTED) as writer:
        out_path = Path(out).resolve()
        for k, (folder, paths) in enumerate(zip(folders, frame_images, strict=True)):
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


# ---------------------------------------------------------------------------- sequence folders

#: ``made_by`` of :func:`sequence_output`: the key of ``sequence.yaml``'s ``source`` that the
#: writer records, and what a sequence without it is not
IMPORTED = ("imported_from", "imported by fpp-slam import")
SIMULATED = ("simulator", "simulated by fpp-slam simulate")


def _sequence_folder_files() -> tuple[str, ...]:
    from frontend.fpp.sequence import (
        GT_CALIBRATION_FILE,
        GT_MESH_FILE,
        GT_TRAJECTORY_FILE,
        SEQUENCE_FILE,
    )

    return (SEQUENCE_FILE, GT_TRAJECTORY_FILE, GT_MESH_FILE, GT_CALIBRATION_FILE)


def _is_sequence_entry(path: Path) -> bool:
    """A frame folder, a file a sequence writer writes, or the temporary file of one of its writes."""
    if path.is_dir() and not path.is_symlink():
        return path.name.startswith("frame_")
    return path.name in _sequence_folder_files() or (path.name.startswith(".") and ".tmp" in path.name)


def recorded_source(folder: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``source`` section of ``folder/sequence.yaml`` ({} when absent or unreadable)."""
    from fpp_graph.errors import FppError
    from fpp_graph.yaml_files import read_yaml_file
    from frontend.fpp.sequence import SEQUENCE_FILE

    try:
        meta = read_yaml_file(Path(folder) / SEQUENCE_FILE, InputDataError, "sequence")
    except FppError:
        return {}
    source = meta.get("source") if isinstance(meta, dict) else None
    return source if isinstance(source, dict) else {}


def refuse_sequence_output(
    out: str | os.PathLike[str], overwrite: bool, inputs: Iterable[str | os.PathLike[str] | None] = (),
    made_by: tuple[str, str] | None = None,
) -> None:
    """Raise OutputError, changing nothing, when a sequence may not be written into ``out``.

    Refused: ``out`` overlaps an input, is a file, holds anything a sequence writer does not
    write, holds a sequence and ``overwrite`` is false, holds one whose ``sequence.yaml`` lacks the
    ``source`` key ``made_by[0]`` (another command's or a real sensor's recording: never
    replaced), or frame folders without ``sequence.yaml`` that no fpp-slam writer left.
    """
    out = Path(out)
    refuse_input_overlap(out, inputs)
    if not out.exists():
        return
    if not out.is_dir():
        raise OutputError(f"--out {out} is a file, not a folder: choose another --out")
    with translated_os_errors(out, reading=True):
        entries = [p for p in out.iterdir() if p.name != LOCK_NAME]
        _refuse_replacing(out, entries, overwrite, made_by, interrupted=(out / LOCK_NAME).exists())


def _refuse_replacing(out: Path, entries: list[Path], overwrite: bool, made_by: tuple[str, str] | None, interrupted: bool) -> None:
    from frontend.fpp.sequence import SEQUENCE_FILE

    if not entries:
        return
    foreign = sorted(p.name for p in entries if not _is_sequence_entry(p))
    if foreign:
        shown = ", ".join(foreign[:4]) + (", ..." if len(foreign) > 4 else "")
        raise OutputError(f"--out {out} holds files that are not part of a sequence ({shown}); they are never deleted: choose a new or empty --out")
    if not overwrite:
        raise OutputError(f"--out {out} exists and holds a sequence: pass --overwrite to replace it, or choose another --out")
    if not (out / SEQUENCE_FILE).exists():
        if not interrupted:  # frame folders no fpp-slam writer left: a recording of the user's
            raise OutputError(f"--out {out} holds frame folders but no {SEQUENCE_FILE}, and no fpp-slam command wrote them: choose another --out")
        return
    if made_by is not None and made_by[0] not in recorded_source(out):
        raise OutputError(f"--out {out} holds a sequence that was not {made_by[1]}; it is never replaced: choose another --out")


@contextlib.contextmanager
def sequence_output(
    out: str | os.PathLike[str], calibration: RigCalibration, spec: PatternSpec, *, overwrite: bool = False,
    inputs: Iterable[str | os.PathLike[str] | None] = (), source: dict[str, Any] | None = None,
    made_by: tuple[str, str] | None = None,
) -> Iterator[Any]:
    """A :class:`~frontend.fpp.sequence.SequenceWriter` on ``out``, the folder locked for the block.

    Refused as :func:`refuse_sequence_output` says (nothing changed), or when another process is
    writing ``out`` (the message names its PID). An earlier sequence is deleted only after those
    checks. When the block fails (an unreadable image, a full disk, a stop) what it wrote is
    removed, and ``out`` too if it was made here; OSErrors become OutputErrors naming the path.
    """
    from frontend.fpp.sequence import SequenceWriter

    out = Path(out)
    refuse_sequence_output(out, overwrite, list(inputs), made_by)
    made_here = not out.exists()
    interrupted = (out / LOCK_NAME).exists()  # an fpp-slam writer has been here (its frame folders are no recording of the user's)
    make_folder(out)
    lock = FolderLock(out)
    lock.acquire()  # a second writer that got here meanwhile: refused, naming the first one's PID
    try:
        with translated_os_errors(out):
            _empty_earlier_sequence(out, overwrite, made_by, interrupted)
            writer = SequenceWriter(out, calibration, spec, source=source)
        try:
            with translated_os_errors(out):
                yield writer
        except BaseException:
            _remove_written(out, made_here)
            raise
    finally:
        lock.release()


def _empty_earlier_sequence(out: Path, overwrite: bool, made_by: tuple[str, str] | None, interrupted: bool) -> None:
    """Delete the sequence in ``out`` (its lock held; checked again under it), leaving ``out`` empty."""
    entries = [p for p in out.iterdir() if p.name != LOCK_NAME]
    _refuse_replacing(out, entries, overwrite, made_by, interrupted)
    if entries:
        log.info("replacing the sequence in %s", out)
    for entry in entries:
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def _remove_written(out: Path, made_here: bool) -> None:
    """What a failed sequence write left in ``out`` (all of it is the write's own)."""
    with contextlib.suppress(OSError):
        for entry in out.iterdir():
            if entry.name == LOCK_NAME:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink()
        if made_here:
            (out / LOCK_NAME).unlink()
            out.rmdir()
