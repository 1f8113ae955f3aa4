"""Frame sources: how a recorded sequence of any sensor reaches the back-end.

A front-end plugs in by providing a :class:`FrameSource` class and registering it under the
``fpp_graph.sources`` entry-point group of its distribution (this project registers the FPP and
RGB-D sources of ``frontend`` in ``pyproject.toml``). ``fpp_graph`` discovers sources through the
entry points and never imports a front-end by name.
"""

from __future__ import annotations

import logging
import os
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from fpp_graph.config import Config
from fpp_graph.errors import InputDataError
from fpp_graph.outputs import os_error
from fpp_graph.trajectory import Trajectory
from fpp_graph.types import Frame, PairRegistrar

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "fpp_graph.sources"  # the group third-party sources register under: fixed


@runtime_checkable
class FrameSource(Protocol):
    """A recorded sequence that yields :class:`~fpp_graph.types.Frame` objects.

    Implementations must pickle (they are sent to worker processes): hold paths and config,
    and build heavy state lazily.
    """

    name: str

    @classmethod
    def detect(cls, path: Path) -> bool:
        """True when ``path`` looks like a sequence this source reads."""
        ...

    def frame_ids(self) -> list[int]:
        """Ids of the frames in capture order."""
        ...

    def load_frame(self, frame_id: int) -> Frame:
        """Decode one frame; InputDataError when it is unusable. With keypoints and descriptors,
        unless the registrar is a :class:`~fpp_graph.types.FrameDescriber` (then the keyframe
        manager has keyframes described, and ``register`` describes what it needs)."""
        ...

    def make_registrar(self) -> PairRegistrar:
        """The pairwise registration this sensor's frames need (its random draws, e.g. RANSAC's,
        seeded by the run's ``run.seed`` so that a run is reproducible for a seed)."""
        ...

    def ground_truth(self) -> Trajectory | None:
        """Ground-truth ``T_world_sensor`` trajectory if the sequence has one, at the frames'
        timestamps. A timestamped reference (a motion capture) is read there plus the config's
        ``evaluation.reference_time_offset_s``; a source whose reference poses belong to its frames
        refuses a non-zero offset (:func:`fpp_graph.config.refuse_reference_time_offset`)."""
        ...

    def ground_truth_mesh(self) -> Path | None:
        """Path of a ground-truth mesh in the world frame, if any."""
        ...

    def describe(self) -> dict[str, Any]:
        """A few facts for the results (sensor, image size, frame count)."""
        ...

    def resolve_config(self, config: Config) -> Config:
        """The run's configuration for this sensor: ``config`` with the source's own values where
        the config leaves them null (the sensor's noise model, which the registration thresholds
        are multiples of; ``fusion.voxel_size_m``, ``tsdf_voxel_m`` and ``max_depth_m``: an RGB-D
        room is metres wide, an FPP scene centimetres; ``keyframes.track_from_motion``;
        ``run.keep_frames``), or ``config`` itself when the sensor needs none. Called once, before
        any frame is loaded; a value the user set is never changed."""
        ...


def check_frame_source(source: object) -> None:
    """Raise :class:`InputDataError` naming what ``source`` lacks of the :class:`FrameSource`
    declaration (a plug-in written against an older or partial declaration)."""
    members = sorted({n for n in vars(FrameSource) if not n.startswith("_")} | set(FrameSource.__annotations__))
    missing = [n for n in members if not hasattr(source, n)]
    if missing:
        raise InputDataError(
            f"frame source {type(source).__name__} lacks {', '.join(missing)} of the FrameSource protocol: "
            "implement every member declared in fpp_graph.slam.sources.FrameSource"
        )


def available_sources() -> dict[str, type]:
    """Registered source classes by name."""
    found: dict[str, type] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            found[ep.name] = ep.load()
        except Exception as exc:  # a broken plug-in must not hide the others
            log.warning("frame source %r could not be loaded: %s", ep.name, exc)
    return found


def open_source(path: str | os.PathLike[str], config: Config, kind: str | None = None) -> FrameSource:
    """Open the sequence at ``path`` with the first registered source that recognises it."""
    path = Path(path)
    if not path.exists():
        raise InputDataError(f"sequence {path} does not exist")
    if path.is_dir():
        try:  # an unreadable folder would otherwise read as no known layout
            next(os.scandir(path), None)
        except OSError as exc:
            raise os_error(exc, path, reading=True) from exc
    sources = available_sources()
    if kind is not None:
        if kind not in sources:
            raise InputDataError(f"unknown sequence kind {kind!r}; registered: {', '.join(sorted(sources)) or 'none'}")
        return sources[kind](path, config)
    for name, cls in sources.items():
        if cls.detect(path):
            log.debug("%s detected as a %s sequence", path, name)  # the run logs it once its results folder is claimed
            return cls(path, config)
    inside = _sequences_inside(path, sources)
    hint = (f"; it holds {len(inside)} sequence folder(s) ({', '.join(inside[:4])}{', ...' if len(inside) > 4 else ''}): "
            "run one of them, or `fpp-slam batch` on them all") if inside else ""
    raise InputDataError(
        f"{path}: not a recognised sequence layout (registered: {', '.join(sorted(sources)) or 'none'}); "
        f"an FPP sequence holds sequence.yaml, an RGB-D one 7-Scenes frame-*.color.png/depth.png or TUM rgb.txt/depth.txt{hint}"
    )


def _sequences_inside(path: Path, sources: dict[str, type]) -> list[str]:
    """Names of ``path``'s sub-folders a registered source recognises (a 7-Scenes scene holds
    ``seq-01``, ``seq-02``, ...; a download of TUM sequences holds ``rgbd_dataset_*``)."""
    if not path.is_dir():
        return []
    found = []
    for sub in sorted(p for p in path.iterdir() if p.is_dir()):
        try:
            if any(cls.detect(sub) for cls in sources.values()):
                found.append(sub.name)
        except OSError:  # an unreadable sub-folder is not a sequence we can offer
            continue
    return found
