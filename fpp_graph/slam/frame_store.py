"""Frames on disk and a bounded in-memory keyframe store.

A dense FPP frame at 1920x1200 holds ~55 MB of xyz map, so a sequence cannot stay in memory.
:func:`save_frame` / :func:`load_frame` write a frame as one ``.npz`` (atomically; xyz maps as
float32, ~30 nm resolution at 1 m, far below the sensor's noise); :class:`FrameStore` keeps the
most recently used frames in memory and reloads the rest from disk on demand, so peak memory
does not grow with the number of frames.

Both sensors make ``points`` the finite pixels of ``xyz_map`` in row-major order and ``colors``
the grey ``texture`` at those pixels, so storing them next to the map would double the file
(8.8 MB instead of 4.7 MB for a 640x480 RGB-D frame). When a frame's arrays are exactly that,
they are not stored: ``derived_from_map`` lists them and :func:`load_frame` rebuilds them, equal
to what storing them would have given (points from the float32 map, colours as texture / 255).
Any other frame (points filtered differently, no map, ...) stores them as they are. Files
written before ``derived_from_map`` existed load unchanged.
"""

from __future__ import annotations

import json
import logging
import os
import weakref
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np

from fpp_graph.atomic import atomic_open
from fpp_graph.errors import InputDataError, OutputError
from fpp_graph.geometry import masked_pixels
from fpp_graph.mapped_npz import mapped_npz
from fpp_graph.types import CameraModel, Frame, grey_colors

log = logging.getLogger(__name__)


def save_frame(path: str | os.PathLike[str], frame: Frame) -> None:
    """Write ``frame`` to ``path`` (``.npz``) atomically: its :func:`stored_arrays`.

    Raises
    ------
    OutputError
        The file cannot be written (a full disk, no permission); the partial file is removed
        and the frames cached before it stay whole, so the run can be resumed.
    """
    arrays = stored_arrays(frame)
    try:
        with atomic_open(path, "wb") as handle:
            np.savez(handle, **arrays)
    except OutputError as exc:  # atomic_open's OSError, said with what a run can do about it
        if not isinstance(exc.__cause__, OSError):
            raise
        cause = exc.__cause__
        size_mb = sum(a.nbytes for a in arrays.values()) / 1e6
        raise OutputError(
            f"cannot write the frame cache {path}: {cause.strerror or cause}; free space on that disk (a frame like this one "
            f"takes ~{size_mb:.0f} MB) or keep fewer frames (run.keep_frames: keyframes), then run again with --resume"
        ) from exc


def stored_arrays(frame: Frame) -> dict[str, np.ndarray]:
    """The arrays :func:`save_frame` writes for ``frame`` and :func:`frame_from_stored` reads.

    ``points`` / ``colors`` that can be rebuilt from ``xyz_map`` / ``texture`` are left out (see
    the module docstring); everything else is kept as it is. A decode worker hands a frame over
    in this form when it need not be written (``fpp_graph.slam.workers.decode``): a quarter
    of the bytes, and the tracking process sees the same numbers as from the cache.
    """
    arrays: dict[str, np.ndarray] = {
        "id": np.array(frame.id),
        "timestamp": np.array(frame.timestamp),
    }
    for name in ("texture", "keypoints_uv", "descriptors", "T_world_sensor_guess"):
        value = getattr(frame, name)
        if value is not None:
            arrays[name] = value
    colors_u8 = _colors_u8(frame.colors)
    derived: list[str] = []
    if frame.xyz_map is None:
        arrays["points"] = frame.points
    else:
        xyz32 = frame.xyz_map.astype(np.float32)
        arrays["xyz_map"] = xyz32
        points32 = frame.points.astype(np.float32)
        valid = np.isfinite(xyz32[..., 2])
        n_valid = int(np.count_nonzero(valid))
        if points32.shape[0] == n_valid and np.array_equal(points32, masked_pixels(xyz32, valid)):
            derived.append("points")
        else:
            arrays["points"] = points32
        texture = frame.texture
        if (
            colors_u8 is not None
            and texture is not None
            and texture.ndim == 2
            and texture.dtype == np.uint8
            and colors_u8.shape[0] == n_valid
            and _grey_equal(colors_u8, texture[valid])
        ):
            derived.append("colors")
            colors_u8 = None
    if colors_u8 is not None:
        arrays["colors"] = colors_u8
    if derived:
        arrays["derived_from_map"] = np.array(derived)
    if frame.camera is not None:
        camera = frame.camera
        arrays["camera_K"] = camera.K
        arrays["camera_size_px"] = np.array([camera.width_px, camera.height_px])
        arrays["camera_readout_s"] = np.array(camera.readout_s)
    arrays["metadata_json"] = np.array(json.dumps(dict(frame.metadata), default=_json_default))
    for name, value in frame.prepared.items():
        arrays[PREPARED_PREFIX + name] = value
    return arrays


def _colors_u8(colors: np.ndarray | None) -> np.ndarray | None:
    """``colors`` in [0, 1] as uint8 (N, 3); a :func:`grey_colors` view converts its one column."""
    if colors is None:
        return None
    if colors.ndim == 2 and colors.shape[1] == 3 and colors.strides[1] == 0:
        return grey_colors((np.clip(colors[:, 0], 0, 1) * 255).round().astype(np.uint8))
    return (np.clip(colors, 0, 1) * 255).round().astype(np.uint8)


def _grey_equal(colors_u8: np.ndarray, grey: np.ndarray) -> bool:
    """Whether every row of ``colors_u8`` (N, 3) is ``grey`` (N,) three times."""
    if colors_u8.strides[1] == 0:
        return np.array_equal(colors_u8[:, 0], grey)
    return np.array_equal(colors_u8, np.repeat(grey[:, None], 3, axis=1))


PREPARED_PREFIX = "prepared."
"""Stored name of a :attr:`Frame.prepared` array: this prefix and its name."""


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in frame metadata")


_UNREADABLE = (OSError, ValueError, zipfile.BadZipFile, EOFError)
"""What ``np.load`` raises on a missing, truncated or foreign cache file."""


def _unreadable(path: Path, exc: BaseException) -> InputDataError:
    return InputDataError(f"cannot read cached frame {path}: {exc}; delete it to recompute")


def load_frame(path: str | os.PathLike[str]) -> Frame:
    """Read a frame written by :func:`save_frame`."""
    path = Path(path)
    try:  # views of the mapped file: no copy, no checksum pass, pages shared by every process reading it
        get = mapped_npz(path)
    except _UNREADABLE as exc:
        raise _unreadable(path, exc) from None
    return frame_from_stored(get, f"cached frame {path}")


def frame_from_stored(get: dict[str, np.ndarray], origin: str) -> Frame:
    """The :class:`Frame` whose :func:`stored_arrays` are ``get`` (``origin`` names them in errors)."""
    try:
        derived = set(get["derived_from_map"].tolist()) if "derived_from_map" in get else set()
        xyz32 = get["xyz_map"] if derived or "xyz_map" in get else None
        xyz = None if xyz32 is None else xyz32.astype(np.float64)
        valid = np.isfinite(xyz32[..., 2]) if derived else None
        # the points picked from the float64 map: the same numbers as picking float32 ones and
        # widening them, one frame-sized array and pass fewer
        points = masked_pixels(xyz, valid) if "points" in derived else get["points"]
        if "colors" in derived:
            colors = grey_colors(get["texture"][valid] / 255.0)
        else:
            colors = get.get("colors")
            colors = None if colors is None else colors.astype(np.float64) / 255.0
        frame = Frame(
            id=int(get["id"]),
            timestamp=float(get["timestamp"]),
            points=points.astype(np.float64, copy=False),
            colors=colors,
            xyz_map=xyz,
            texture=get.get("texture"),
            keypoints_uv=get.get("keypoints_uv"),
            descriptors=get.get("descriptors"),
            T_world_sensor_guess=get.get("T_world_sensor_guess"),
            camera=_stored_camera(get),
            metadata=json.loads(str(get["metadata_json"])),
            prepared={k[len(PREPARED_PREFIX):]: v for k, v in get.items() if k.startswith(PREPARED_PREFIX)},
            # widening is exact, so the float32 map equals xyz_map narrowed again: code that works
            # on float32 maps (the dense alignment's surfaces) takes it instead of narrowing the
            # 55 MB float64 map of a 1920x1200 frame (~10 ms each time, and a run builds a surface
            # for every pair it registers)
            xyz_map_stored=xyz32 if xyz32 is not None and xyz32.dtype == np.float32 else None,
        )
    except KeyError as exc:
        raise InputDataError(f"{origin} lacks {exc.args[0]!r}; delete it to recompute") from None
    return frame


def _stored_camera(get: dict[str, np.ndarray]) -> CameraModel | None:
    if "camera_K" not in get:
        return None
    width_px, height_px = (int(v) for v in get["camera_size_px"])
    return CameraModel(get["camera_K"], width_px, height_px, float(get["camera_readout_s"]))


def load_frame_points(path: str | os.PathLike[str], max_points: int, seed: int = 0) -> np.ndarray:
    """Up to ``max_points`` of a saved frame's points, drawn uniformly without replacement (seeded),
    in their order, float64 (N, 3): what an evaluation over hundreds of frames needs, without
    building each :class:`Frame` (its maps and textures) as :func:`load_frame` does."""
    path = Path(path)
    try:
        data = mapped_npz(path)
    except _UNREADABLE as exc:
        raise _unreadable(path, exc) from None
    if "points" in data:
        points = data["points"]
    elif "xyz_map" in data:
        xyz = data["xyz_map"]
        points = masked_pixels(xyz, np.isfinite(xyz[..., 2]))
    else:
        raise InputDataError(f"cached frame {path} has neither points nor an xyz map; delete it to recompute")
    points = points.reshape(-1, 3)
    if len(points) > max_points:
        points = points[np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))]
    return points.astype(np.float64)


class FrameStore:
    """Frames by id: the ``max_in_memory`` most recently used in memory, all of them on disk.

    With ``directory=None`` every frame stays in memory (small sequences, tests).

    A frame evicted from the cache but still referenced elsewhere (e.g. by a registrar's
    per-frame cache) is handed out again rather than loaded as a second copy, so there is never
    more than one copy of a frame in memory.
    """

    def __init__(self, directory: str | os.PathLike[str] | None = None, max_in_memory: int = 8) -> None:
        self.directory = Path(directory) if directory is not None else None
        self.max_in_memory = max(1, int(max_in_memory))
        self._cache: OrderedDict[int, Frame] = OrderedDict()
        self._alive: weakref.WeakValueDictionary[int, Frame] = weakref.WeakValueDictionary()
        self._ids: list[int] = []
        self.loads = 0  # frames read back from disk (cache misses)
        if self.directory is not None:
            self.directory.mkdir(parents=True, exist_ok=True)

    @classmethod
    def open(cls, directory: str | os.PathLike[str], max_in_memory: int = 8) -> FrameStore:
        """A store over the frames already saved in ``directory`` (e.g. a results folder's ``frames/``)."""
        directory = Path(directory)
        if not directory.is_dir():
            raise InputDataError(f"frame store {directory} does not exist")
        store = cls(directory, max_in_memory)
        for path in sorted(directory.glob("frame_*.npz")):
            try:
                store._ids.append(int(path.stem.split("_", 1)[1]))
            except ValueError:
                log.warning("ignoring %s: not a frame_<id>.npz file", path)
        return store

    def path_of(self, frame_id: int) -> Path:
        if self.directory is None:
            raise InputDataError("this FrameStore keeps frames in memory only")
        return self.directory / f"frame_{frame_id:06d}.npz"

    def __contains__(self, frame_id: int) -> bool:
        return frame_id in self._cache or frame_id in self._ids

    def __len__(self) -> int:
        return len(self._ids)

    @property
    def ids(self) -> list[int]:
        return list(self._ids)

    def put(self, frame: Frame, rewrite: bool = False) -> None:
        """Keep ``frame`` (on disk unless it is there already; ``rewrite``: replace the stored
        copy, e.g. by the same frame with its keypoints added)."""
        if self.directory is not None and (rewrite or not self.path_of(frame.id).exists()):
            save_frame(self.path_of(frame.id), frame)
        if frame.id not in self._ids:
            self._ids.append(frame.id)
        self._remember(frame)

    def discard_unstored(self, frame_id: int) -> bool:
        """Delete the file of a frame that was written to this folder (a worker's decode cache)
        but never :meth:`put` (not a keyframe); whether a file went. A stored frame is kept."""
        if self.directory is None or frame_id in self._ids:  # every frame in memory was put or read from _ids
            return False
        path = self.path_of(frame_id)
        existed = path.exists()
        path.unlink(missing_ok=True)
        return existed

    def get(self, frame_id: int) -> Frame:
        if frame_id in self._cache:
            self._cache.move_to_end(frame_id)
            return self._cache[frame_id]
        if self.directory is None or frame_id not in self._ids:
            raise KeyError(frame_id)
        frame = self._alive.get(frame_id)
        if frame is None:
            frame = load_frame(self.path_of(frame_id))
            self.loads += 1
        self._remember(frame)
        return frame

    def _remember(self, frame: Frame) -> None:
        self._cache[frame.id] = frame
        self._alive[frame.id] = frame
        self._cache.move_to_end(frame.id)
        limit = self.max_in_memory if self.directory is not None else len(self._cache)
        while len(self._cache) > limit:
            self._cache.popitem(last=False)
