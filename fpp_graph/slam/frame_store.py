"""Frames on disk and a bounded in-memory keyframe store.

A dense FPP frame at 1920x1200 holds ~55 MB of xyz map, so a sequence cannot stay in memory.
:func:`save_frame` / :func:`load_frame` write a frame as one ``.npz`` (atomically; xyz maps as
float32, ~30 nm resolution at 1 m, far below the sensor's noise); :class:`FrameStore` keeps the
most recently used frames in memory and reloads the rest from disk on demand, so peak memory
does not grow with the number of frames.
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
from fpp_graph.errors import InputDataError
from fpp_graph.types import Frame

log = logging.getLogger(__name__)


def save_frame(path: str | os.PathLike[str], frame: Frame) -> None:
    """Write ``frame`` to ``path`` (``.npz``) atomically."""
    arrays: dict[str, np.ndarray] = {
        "id": np.array(frame.id),
        "timestamp": np.array(frame.timestamp),
        "points": frame.points.astype(np.float32) if frame.xyz_map is not None else frame.points,
    }
    for name in ("texture", "keypoints_uv", "descriptors", "T_world_sensor_guess"):
        value = getattr(frame, name)
        if value is not None:
            arrays[name] = value
    if frame.colors is not None:
        arrays["colors"] = (np.clip(frame.colors, 0, 1) * 255).round().astype(np.uint8)
    if frame.xyz_map is not None:
        arrays["xyz_map"] = frame.xyz_map.astype(np.float32)
    arrays["metadata_json"] = np.array(json.dumps(dict(frame.metadata), default=_json_default))
    with atomic_open(path, "wb") as handle:
        np.savez(handle, **arrays)


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in frame metadata")


def load_frame(path: str | os.PathLike[str]) -> Frame:
    """Read a frame written by :func:`save_frame`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            get = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputDataError(f"cannot read cached frame {path}: {exc}; delete it to recompute") from None
    try:
        colors = get.get("colors")
        return Frame(
            id=int(get["id"]),
            timestamp=float(get["timestamp"]),
            points=get["points"].astype(np.float64),
            colors=None if colors is None else colors.astype(np.float64) / 255.0,
            xyz_map=None if "xyz_map" not in get else get["xyz_map"].astype(np.float64),
            texture=get.get("texture"),
            keypoints_uv=get.get("keypoints_uv"),
            descriptors=get.get("descriptors"),
            T_world_sensor_guess=get.get("T_world_sensor_guess"),
            metadata=json.loads(str(get["metadata_json"])),
        )
    except KeyError as exc:
        raise InputDataError(f"cached frame {path} lacks {exc.args[0]!r}; delete it to recompute") from None


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

    def put(self, frame: Frame) -> None:
        if self.directory is not None and not self.path_of(frame.id).exists():
            save_frame(self.path_of(frame.id), frame)
        if frame.id not in self._ids:
            self._ids.append(frame.id)
        self._remember(frame)

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
