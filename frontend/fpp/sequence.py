"""Recorded FPP sequences on disk: writing (simulator, or a real sensor's capture tool) and reading.

Folder layout (DESIGN.md)::

    sequence.yaml            format, units, sensor calibration, pattern set, frame list
    frame_000000/000.png     pattern images of frame 0, in capture order (8- or 16-bit grey)
    frame_000000/001.png
    ...
    groundtruth.tum          optional: timestamp tx ty tz qx qy qz qw of T_world_sensor (metres)
    groundtruth_mesh.ply     optional: the scene in the world frame (metres)
    groundtruth_calibration.yaml  optional: the rig's true parameters when sequence.yaml holds an
                             estimate (simulated sequences); only evaluation reads it

``sequence.yaml``::

    format: fpp-graph sequence v1
    units: {length: m, time: s, calibration_length: mm}
    calibration: {...}         # RigCalibration.to_dict(): states its own length_unit
    patterns: {...}            # PatternSpec.to_dict()
    image_count: 11            # images per frame
    frames:
      - {id: 0, timestamp: 0.0, folder: frame_000000, images: [000.png, 001.png, ...]}
    groundtruth: {trajectory: groundtruth.tum, mesh: groundtruth_mesh.ply, calibration: ...}   # optional
    source: {...}              # free-form provenance (simulator settings, capture software)

A real sensor's recording fits this format as is: the frame folders hold whatever the camera
captured, in capture order, and the calibration comes from the rig calibration. A frame's
``folder`` is relative to the sequence folder and may lie outside it (``fpp-slam import
--reference`` refers to the capture folders where they are, e.g. ``../captures/view1``).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from collections import Counter
from collections.abc import Sequence as _Seq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_write_bytes, atomic_write_text
from fpp_graph.errors import CalibrationError, InputDataError, OutputError
from fpp_graph.outputs import LOCK_NAME
from fpp_graph.trajectory import Trajectory, read_tum, write_tum
from fpp_graph.yaml_files import read_yaml_file
from frontend.fpp.images import check_images_match_calibration, image_size, load_image_stack
from frontend.fpp.pattern_file import pattern_spec_from_dict
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import RigCalibration

log = logging.getLogger(__name__)

FORMAT = "fpp-graph sequence v1"
SEQUENCE_FILE = "sequence.yaml"
GT_TRAJECTORY_FILE = "groundtruth.tum"
GT_MESH_FILE = "groundtruth_mesh.ply"
GT_CALIBRATION_FILE = "groundtruth_calibration.yaml"


def frame_folder_name(frame_id: int) -> str:
    return f"frame_{int(frame_id):06d}"


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a sequence: id, capture time (s), folder and image file names in capture order."""

    id: int
    timestamp: float
    folder: str
    images: tuple[str, ...]


@dataclass(eq=False)
class Sequence:
    """A recorded FPP sequence read from disk (images are loaded on demand).

    Attributes
    ----------
    path : Path
    calibration : RigCalibration
    spec : PatternSpec
    frames : list of FrameRecord
    ground_truth : Trajectory or None
        ``T_world_sensor`` per frame (same order and timestamps as ``frames``).
    ground_truth_mesh_path : Path or None
    source : dict
        Provenance recorded by the writer.
    """

    path: Path
    calibration: RigCalibration
    spec: PatternSpec
    frames: list[FrameRecord]
    ground_truth: Trajectory | None = None
    ground_truth_mesh_path: Path | None = None
    source: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def image_paths(self, i: int) -> list[Path]:
        rec = self.frames[i]
        return [self.path / rec.folder / name for name in rec.images]

    def load_frame_images(self, i: int) -> NDArray:
        """The pattern images of the ``i``-th frame (list position), (M, H, W) uint8 or uint16.

        Raises
        ------
        InputDataError
            A missing, unreadable, corrupt or truncated image (the message names the file), or
            images of different sizes: a pipeline skips the frame and records why.
        CalibrationError
            The images' size differs from the calibration's camera.
        """
        if not 0 <= i < len(self.frames):
            raise InputDataError(f"{self.path}: frame index {i} out of range (0..{len(self.frames) - 1})")
        rec = self.frames[i]
        stack = load_image_stack(self.image_paths(i))
        check_images_match_calibration(stack.shape, self.calibration, f"{self.path / rec.folder}")
        return stack

    def check_frames_match_calibration(self) -> None:
        """Raise CalibrationError when no frame's images are the size of the calibration's camera
        (the calibration of another camera: every frame would be skipped, or decode to nothing).

        One readable image per frame is looked at, until one has the camera's size: a PNG's size
        is in its header, so a good sequence costs one small read. A frame that differs alone is
        left to :meth:`load_frame_images`, which refuses it (a pipeline skips it, saying why).
        """
        sizes: Counter[tuple[int, int]] = Counter()
        camera = (self.calibration.camera.width, self.calibration.camera.height)
        for i in range(len(self.frames)):
            try:
                size = image_size(self.image_paths(i)[0])
            except InputDataError:  # a missing or broken image is that frame's own reason to be skipped
                continue
            if size == camera:
                return
            sizes[size] += 1
        if sizes:
            (width, height), count = sizes.most_common(1)[0]
            raise CalibrationError(
                f"{self.path}: the frames' images are {width}x{height} ({count} of {len(self.frames)} frames, none "
                f"{camera[0]}x{camera[1]}) but the calibration's camera in {SEQUENCE_FILE} is {camera[0]}x{camera[1]} pixels; the "
                f"calibration is of another camera (or the images were resized or cropped): put the calibration of the camera "
                f"that took these images in {SEQUENCE_FILE}"
            )


def read_sequence(path: str | os.PathLike[str]) -> Sequence:
    """Read ``sequence.yaml`` of a sequence folder (images stay on disk).

    Raises
    ------
    InputDataError
        Missing or malformed ``sequence.yaml``, a frame list inconsistent with the pattern set,
        a ground-truth trajectory that does not match the frames.
    CalibrationError
        Malformed calibration.
    ConfigError
        Malformed pattern section.
    """
    path = Path(path)
    meta_path = path / SEQUENCE_FILE
    meta = _read_meta(meta_path)
    calibration = RigCalibration.from_dict(meta["calibration"], where=f"{meta_path}: calibration")
    spec = pattern_spec_from_dict(meta["patterns"], where=f"{meta_path}: patterns")
    m = spec.image_count()
    if "image_count" in meta and meta["image_count"] != m:
        raise InputDataError(f"{meta_path}: image_count {meta['image_count']!r} but the pattern set has {m} images; set it to {m}")
    frames = _frame_records(meta["frames"], meta_path, m)
    gt_meta = meta.get("groundtruth") or {}
    if not isinstance(gt_meta, dict) or not all(isinstance(v, str) for v in gt_meta.values()):
        raise InputDataError(f"{meta_path}: groundtruth must map trajectory / mesh / calibration to file names, got {gt_meta!r}")
    ground_truth = None
    gt_traj = path / gt_meta.get("trajectory", GT_TRAJECTORY_FILE)
    if _is_file(gt_traj):
        ground_truth = read_tum(gt_traj)
        if len(ground_truth) != len(frames):
            raise InputDataError(f"{gt_traj}: {len(ground_truth)} poses for {len(frames)} frames; one pose per frame is required")
        if frames and not np.allclose(ground_truth.timestamps_s, [f.timestamp for f in frames], atol=1e-9):
            raise InputDataError(f"{gt_traj}: timestamps differ from the frame list in {SEQUENCE_FILE}")
    gt_mesh = path / gt_meta.get("mesh", GT_MESH_FILE)
    source = meta.get("source") or {}
    if not isinstance(source, dict):
        raise InputDataError(f"{meta_path}: source must be a mapping (free-form provenance), got {type(source).__name__}")
    return Sequence(
        path=path,
        calibration=calibration,
        spec=spec,
        frames=frames,
        ground_truth=ground_truth,
        ground_truth_mesh_path=gt_mesh if _is_file(gt_mesh) else None,
        source=dict(source),
    )


def _is_file(path: Path) -> bool:
    """``path.is_file()``, with a folder that cannot be looked into as an InputDataError."""
    try:
        return path.is_file()
    except OSError as exc:
        raise InputDataError(f"cannot look for {path}: {exc.strerror or exc}; check the permissions of {path.parent}") from None


def _read_meta(meta_path: Path) -> dict[str, Any]:
    """``sequence.yaml``'s top-level mapping, with its format and required keys checked."""
    try:
        present = meta_path.exists()
    except OSError as exc:
        raise InputDataError(f"cannot look for {meta_path}: {exc.strerror or exc}; check the permissions of {meta_path.parent}") from None
    if not present:
        raise InputDataError(f"{meta_path.parent} is not an FPP sequence folder: {SEQUENCE_FILE} is missing")
    meta = read_yaml_file(meta_path, InputDataError, "sequence file")
    if not isinstance(meta, dict):
        raise InputDataError(f"{meta_path}: expected a mapping at the top level")
    if meta.get("format") != FORMAT:
        raise InputDataError(f"{meta_path}: format is {meta.get('format')!r}, expected {FORMAT!r}")
    for key in ("calibration", "patterns", "frames"):
        if key not in meta:
            raise InputDataError(f"{meta_path}: missing key {key!r}")
    return meta


def _frame_records(entries: Any, meta_path: Path, image_count: int) -> list[FrameRecord]:
    """The ``frames`` list: ids increasing, finite timestamps, ``image_count`` image names each."""
    if not isinstance(entries, list):
        raise InputDataError(f"{meta_path}: frames must be a list")
    frames: list[FrameRecord] = []
    for k, fr in enumerate(entries):
        where = f"{meta_path}: frames[{k}]"
        try:
            rec = FrameRecord(int(fr["id"]), float(fr["timestamp"]), str(fr["folder"]), tuple(str(n) for n in fr["images"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputDataError(f"{where}: malformed frame entry ({exc!r}); need id, timestamp, folder, images") from None
        if not math.isfinite(rec.timestamp):
            raise InputDataError(f"{where}: timestamp {rec.timestamp} is not a finite number of seconds; give the capture time")
        if len(rec.images) != image_count:
            raise InputDataError(f"{where}: {len(rec.images)} images listed but the pattern set has {image_count}")
        if frames and rec.id <= frames[-1].id:
            raise InputDataError(f"{where}: frame ids must increase (id {rec.id} after {frames[-1].id})")
        frames.append(rec)
    return frames


class SequenceWriter:
    """Writes a sequence folder frame by frame; ``close()`` writes ``sequence.yaml`` last.

    Every file is written atomically. ``sequence.yaml`` appears only when the sequence is
    complete, so a folder without it is an interrupted write, never a short sequence.

    Parameters
    ----------
    path : path
        Output folder; must not exist or be empty unless ``overwrite``.
    calibration, spec
        Written into ``sequence.yaml``.
    overwrite : bool
        Replace an existing sequence folder.
    source : dict, optional
        Provenance (e.g. the simulator's scene and noise settings).
    """

    def __init__(self, path: str | os.PathLike[str], calibration: RigCalibration, spec: PatternSpec, overwrite: bool = False, source: dict[str, Any] | None = None):
        self.path = Path(path)
        # a folder held by fpp_graph.outputs.FolderLock holds its lock file: empty all the same
        if self.path.exists() and (not self.path.is_dir() or any(p.name != LOCK_NAME for p in self.path.iterdir())):
            if not overwrite:
                raise OutputError(f"{self.path} exists and is not empty; choose another folder or pass overwrite")
            if (self.path / SEQUENCE_FILE).is_file() or all(p.name.startswith("frame_") or p.name.startswith("groundtruth") for p in self.path.iterdir()):
                shutil.rmtree(self.path)
            else:
                raise OutputError(f"{self.path} holds files that are not a sequence; refusing to delete it")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create {self.path}: {exc.strerror}") from exc
        self.calibration = calibration
        self.spec = spec
        self.source = dict(source or {})
        self.frames: list[FrameRecord] = []
        self._has_gt_traj = False
        self._has_gt_mesh = False
        self._has_gt_calibration = False

    def add_frame(self, frame_id: int, timestamp: float, images: NDArray | _Seq[NDArray]) -> FrameRecord:
        """Write one frame's images (M, H, W) uint8/uint16 as PNGs ``000.png``.. in capture order."""
        stack = np.asarray(images)
        if stack.ndim != 3 or stack.shape[0] != self.spec.image_count():
            raise InputDataError(f"frame {frame_id}: expected ({self.spec.image_count()}, H, W) images, got {stack.shape}")
        if stack.dtype not in (np.uint8, np.uint16):
            raise InputDataError(f"frame {frame_id}: images must be uint8 or uint16, got {stack.dtype}")
        self.calibration.check_image_size(stack.shape[2], stack.shape[1], f"frame {frame_id}")
        if self.frames and frame_id <= self.frames[-1].id:
            raise InputDataError(f"frame ids must increase: {frame_id} after {self.frames[-1].id}")
        folder = frame_folder_name(frame_id)
        names = tuple(f"{k:03d}.png" for k in range(stack.shape[0]))
        for name, img in zip(names, stack, strict=True):
            ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise OutputError(f"cannot encode {folder}/{name} as PNG")
            atomic_write_bytes(self.path / folder / name, buf.tobytes())
        rec = FrameRecord(int(frame_id), float(timestamp), folder, names)
        self.frames.append(rec)
        return rec

    def write_ground_truth(self, poses_world_sensor: NDArray | None = None, mesh: Any = None) -> None:
        """Write ``groundtruth.tum`` (one T_world_sensor per written frame) and/or the mesh (Open3D legacy)."""
        if poses_world_sensor is not None:
            poses = np.asarray(poses_world_sensor, dtype=np.float64).reshape(-1, 4, 4)
            if len(poses) != len(self.frames):
                raise InputDataError(f"{len(poses)} ground-truth poses for {len(self.frames)} written frames")
            write_tum(self.path / GT_TRAJECTORY_FILE, Trajectory.from_poses([f.timestamp for f in self.frames], poses))
            self._has_gt_traj = True
        if mesh is not None:
            import open3d as o3d

            tmp = self.path / f".{GT_MESH_FILE}.tmp.ply"
            if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False, print_progress=False):
                raise OutputError(f"cannot write {self.path / GT_MESH_FILE}")
            os.replace(tmp, self.path / GT_MESH_FILE)
            self._has_gt_mesh = True

    def write_ground_truth_calibration(self, true_calibration: RigCalibration) -> None:
        """Write the rig's true parameters to ``groundtruth_calibration.yaml`` (mm, full precision).

        For sequences whose ``sequence.yaml`` holds an *estimated* calibration: the decoder never
        reads this file, evaluation may.
        """
        atomic_write_text(self.path / GT_CALIBRATION_FILE, yaml.safe_dump(true_calibration.to_dict("mm"), sort_keys=False))
        self._has_gt_calibration = True

    def close(self) -> Path:
        """Write ``sequence.yaml``; returns the sequence folder."""
        if not self.frames:
            raise InputDataError(f"{self.path}: a sequence needs at least one frame; nothing was written")
        meta: dict[str, Any] = {
            "format": FORMAT,
            "units": {"length": "m", "time": "s", "calibration_length": "mm", "note": "ground truth in metres; the calibration states its own length_unit"},
            "calibration": self.calibration.to_dict("mm"),
            "patterns": self.spec.to_dict(),
            "image_count": self.spec.image_count(),
            "frames": [{"id": f.id, "timestamp": f.timestamp, "folder": f.folder, "images": list(f.images)} for f in self.frames],
        }
        gt: dict[str, str] = {}
        if self._has_gt_traj:
            gt["trajectory"] = GT_TRAJECTORY_FILE
        if self._has_gt_mesh:
            gt["mesh"] = GT_MESH_FILE
        if self._has_gt_calibration:
            gt["calibration"] = GT_CALIBRATION_FILE
        if gt:
            meta["groundtruth"] = gt
        if self.source:
            meta["source"] = self.source
        atomic_write_text(self.path / SEQUENCE_FILE, yaml.safe_dump(meta, sort_keys=False))
        log.info("wrote sequence %s with %d frames", self.path, len(self.frames))
        return self.path

