"""Core data types and plug-in protocols of the back-end.

Any front-end (FPP, RGB-D, LiDAR, a g2o file) feeds the back-end through these: it makes
:class:`Frame` objects, implements :class:`PairRegistrar` to turn two frames into a
:class:`Constraint`, and may bring its own :class:`LoopDetector` or :class:`MapFuser`.
Everything here is numpy arrays and frozen dataclasses, so it pickles across processes.
"""

from __future__ import annotations

import enum
import numbers
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import is_rigid


class ConstraintKind(enum.StrEnum):
    """What a constraint links: consecutive keyframes (odometry) or a revisit (loop)."""

    ODOMETRY = "odometry"
    LOOP = "loop"


def _readonly(array: NDArray | None) -> NDArray | None:
    if array is not None:
        array.setflags(write=False)
    return array


def grey_colors(grey: np.ndarray) -> np.ndarray:
    """(N, 3) colours of (N,) grey values: a read-only view repeating the one column (both sensors'
    colours are their grey texture; three float64 copies of it were 48 MB a 1920x1200 frame)."""
    return np.broadcast_to(grey[:, None], (len(grey), 3))


def _checked_prepared(prepared: Mapping[str, Any], where: str) -> dict[str, NDArray[Any]]:
    """:attr:`Frame.prepared` as read-only arrays, its names and contents checked (the frame store
    saves each as an ``.npz`` member)."""
    checked = {}
    for name, value in dict(prepared).items():
        if not isinstance(name, str) or not name or not all(c.isalnum() or c in "_." for c in name):
            raise InputDataError(f"{where}: prepared array name {name!r} must be letters, digits, '_' and '.'")
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise InputDataError(f"{where}: prepared array {name!r} holds Python objects; only numeric, bool and string arrays are stored")
        checked[name] = _readonly(array)
    return checked


@dataclass(frozen=True, eq=False)
class CameraModel:
    """The pinhole camera a frame's organised data was taken with (what the back-end's view
    change, loop ranking and TSDF projection read).

    Attributes
    ----------
    K : (3, 3) float64
        Intrinsic matrix in pixels (``fx, fy`` on the diagonal, ``cx, cy`` in the last column).
    width_px, height_px : int
        Image size in pixels (``xyz_map`` and ``texture`` are ``height_px`` x ``width_px``).
    readout_s : float
        A rolling shutter's row readout time in seconds: the keyframe manager widens a moving
        camera's constraints by its motion over it; 0: a global shutter or a still capture.
    """

    K: NDArray[np.float64]
    width_px: int
    height_px: int
    readout_s: float = 0.0

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputDataError(f"camera model: K must be a 3x3 pinhole matrix with positive focal lengths, got {K.tolist()}")
        if int(self.width_px) <= 0 or int(self.height_px) <= 0:
            raise InputDataError(f"camera model: image size must be positive pixels, got {self.width_px} x {self.height_px}")
        readout_s = float(self.readout_s) if isinstance(self.readout_s, numbers.Real) else float("nan")
        if not (np.isfinite(readout_s) and readout_s >= 0):
            raise InputDataError(f"camera model: readout_s must be the rolling shutter's readout time in seconds (0: a global shutter), got {self.readout_s!r}")
        object.__setattr__(self, "K", _readonly(K))
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))
        object.__setattr__(self, "readout_s", readout_s)


@dataclass(frozen=True, eq=False)
class Frame:
    """One 3D frame of a sensor.

    Attributes
    ----------
    id : int
        Unique, increasing frame index within a sequence.
    timestamp : float
        Capture time in seconds.
    points : (N, 3) float64
        Valid 3D points in metres, in the sensor frame.
    colors : (N, 3) float64 or None
        Per-point colours in [0, 1].
    xyz_map : (H, W, 3) float64 or None
        Organised points in metres, sensor frame, NaN where invalid; row/column are camera pixels.
    texture : (H, W) uint8 or None
        Grey texture image registered to ``xyz_map`` (the FPP background term ``a``).
    keypoints_uv : (K, 2) float64 or None
        Keypoint pixel coordinates (u = column, v = row) on ``texture``.
    descriptors : (K, D) array or None
        Descriptors of ``keypoints_uv`` (float32 or uint8 for binary descriptors).
    T_world_sensor_guess : (4, 4) float64 or None
        Prior pose (e.g. from wheel odometry or the simulator), if any.
    camera : CameraModel or None
        The pinhole camera of ``xyz_map`` (its size must match): the keyframe rule
        (``keyframes.min_view_change``) measures view change in its pixels and refuses a frame
        without one; the loop detector ranks candidates and the TSDF projects depth with it.
    metadata : mapping
        JSON-serialisable facts the front-end keeps with the frame (sensor name, decoder
        counts, ...). The back-end stores it and never reads it.
    prepared : mapping of str to array
        The registrar's own per-frame arrays: what its ``prepare(frame) -> Frame`` derived from
        the frame where the source made it (a decode worker), so that no process that later
        registers the frame recomputes them. The registrar owns the names (letters, digits, ``_`` and
        ``.``; a dotted prefix groups one part's arrays); the back-end stores them with the
        frame and hands them back unchanged, and never reads them.
    xyz_map_stored : (H, W, 3) float32 or None
        The float32 map ``xyz_map`` was widened from when the frame was read from the frame
        store (which keeps maps as float32); code that works on float32 maps takes it instead
        of narrowing ``xyz_map`` again. None for a frame not read from storage.
    """

    id: int
    timestamp: float
    points: NDArray[np.float64]
    colors: NDArray[np.float64] | None = None
    xyz_map: NDArray[np.float64] | None = None
    texture: NDArray[np.uint8] | None = None
    keypoints_uv: NDArray[np.float64] | None = None
    descriptors: NDArray[Any] | None = None
    T_world_sensor_guess: NDArray[np.float64] | None = None
    camera: CameraModel | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    prepared: Mapping[str, NDArray[Any]] = field(default_factory=dict)
    xyz_map_stored: NDArray[np.float32] | None = None
    _stored_xyz_map_of: NDArray[np.float64] | None = field(default=None, repr=False)  # the xyz_map it belongs to

    def __post_init__(self) -> None:
        where = f"frame {self.id}"
        object.__setattr__(self, "prepared", _checked_prepared(self.prepared, where))
        points = np.asarray(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputDataError(f"{where}: points must be N x 3, got shape {points.shape}")
        object.__setattr__(self, "points", _readonly(points))
        if self.colors is not None:
            colors = np.asarray(self.colors, dtype=np.float64)
            if colors.shape != points.shape:
                raise InputDataError(
                    f"{where}: colors shape {colors.shape} does not match points {points.shape}"
                )
            object.__setattr__(self, "colors", _readonly(colors))
        if self.xyz_map is not None:
            xyz = np.asarray(self.xyz_map, dtype=np.float64)
            if xyz.ndim != 3 or xyz.shape[2] != 3:
                raise InputDataError(f"{where}: xyz_map must be H x W x 3, got {xyz.shape}")
            object.__setattr__(self, "xyz_map", _readonly(xyz))
            if self.camera is not None and xyz.shape[:2] != (self.camera.height_px, self.camera.width_px):
                raise InputDataError(
                    f"{where}: xyz_map is {xyz.shape[1]} x {xyz.shape[0]} pixels but its camera model "
                    f"{self.camera.width_px} x {self.camera.height_px}; both must come from the same camera"
                )
            if self.texture is not None and np.shape(self.texture) != xyz.shape[:2]:
                raise InputDataError(
                    f"{where}: texture shape {np.shape(self.texture)} does not match "
                    f"xyz_map {xyz.shape[:2]}; both must come from the same camera"
                )
        if self.xyz_map_stored is not None:
            if self.xyz_map is None or np.shape(self.xyz_map_stored) != self.xyz_map.shape:
                raise InputDataError(f"{where}: xyz_map_stored shape {np.shape(self.xyz_map_stored)} does not match xyz_map")
            # a frame made from this one with another xyz_map (dataclasses.replace) leaves it behind
            belongs = self._stored_xyz_map_of is None or self._stored_xyz_map_of is self.xyz_map
            object.__setattr__(self, "xyz_map_stored", self.xyz_map_stored if belongs else None)
        object.__setattr__(self, "_stored_xyz_map_of", self.xyz_map if self.xyz_map_stored is not None else None)
        if self.texture is not None:
            texture = np.asarray(self.texture)
            if texture.ndim != 2 or texture.dtype != np.uint8:
                raise InputDataError(
                    f"{where}: texture must be an H x W uint8 image, got {texture.dtype} {texture.shape}"
                )
            object.__setattr__(self, "texture", _readonly(texture))
        if (self.keypoints_uv is None) != (self.descriptors is None):
            raise InputDataError(f"{where}: keypoints_uv and descriptors must be given together")
        if self.keypoints_uv is not None:
            kp = np.asarray(self.keypoints_uv, dtype=np.float64).reshape(-1, 2)
            desc = np.asarray(self.descriptors)
            if desc.shape[0] != kp.shape[0]:
                raise InputDataError(
                    f"{where}: {kp.shape[0]} keypoints but {desc.shape[0]} descriptors"
                )
            object.__setattr__(self, "keypoints_uv", _readonly(kp))
            object.__setattr__(self, "descriptors", _readonly(desc))
        if self.T_world_sensor_guess is not None:
            T = np.asarray(self.T_world_sensor_guess, dtype=np.float64)
            if not is_rigid(T, atol=1e-5):
                raise InputDataError(f"{where}: T_world_sensor_guess is not a rigid 4x4 transform")
            object.__setattr__(self, "T_world_sensor_guess", _readonly(T))

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True, eq=False)
class Constraint:
    """A relative-pose measurement between two frames.

    ``T_target_source`` maps points of the source frame into the target frame. ``information``
    is 6x6 in ``[rotation, translation]`` order (GTSAM's), the inverse of the covariance of the
    error ``Log(T_target_source_true^-1 * T_target_source)``. A rejected constraint has
    ``accepted == False`` and says why in ``rejection_reason``; its pose must not be used.
    """

    source_id: int
    target_id: int
    T_target_source: NDArray[np.float64]
    information: NDArray[np.float64]
    kind: ConstraintKind = ConstraintKind.ODOMETRY
    fitness: float = float("nan")
    inlier_rmse_m: float = float("nan")
    inlier_count: int = 0
    overlap: float = float("nan")
    rejection_reason: str | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", ConstraintKind(self.kind))
        T = np.asarray(self.T_target_source, dtype=np.float64)
        info = np.asarray(self.information, dtype=np.float64)
        where = f"constraint {self.source_id}->{self.target_id}"
        if T.shape != (4, 4):
            raise InputDataError(f"{where}: T_target_source must be 4x4, got {T.shape}")
        if info.shape != (6, 6):
            raise InputDataError(f"{where}: information must be 6x6 [rot, trans], got {info.shape}")
        if self.rejection_reason is None:
            if not is_rigid(T, atol=1e-5):
                raise InputDataError(f"{where}: T_target_source is not a rigid transform")
            if not np.allclose(info, info.T, rtol=1e-8, atol=1e-12 * max(1.0, np.abs(info).max())):
                raise InputDataError(f"{where}: information matrix is not symmetric")
            if np.linalg.eigvalsh(0.5 * (info + info.T)).min() <= 0:
                raise InputDataError(
                    f"{where}: information matrix is not positive definite; "
                    "a constraint must constrain all 6 degrees of freedom (reject it instead)"
                )
        object.__setattr__(self, "T_target_source", _readonly(T))
        object.__setattr__(self, "information", _readonly(info))

    @property
    def accepted(self) -> bool:
        return self.rejection_reason is None

    @classmethod
    def rejected(
        cls, source_id: int, target_id: int, reason: str, kind: ConstraintKind = ConstraintKind.ODOMETRY, **quality: Any
    ) -> Constraint:
        """A rejected constraint with identity pose, zero information and the reason."""
        return cls(
            source_id=source_id,
            target_id=target_id,
            T_target_source=np.eye(4),
            information=np.zeros((6, 6)),
            kind=kind,
            rejection_reason=reason,
            **quality,
        )


@runtime_checkable
class PairRegistrar(Protocol):
    """Estimates the relative pose of two frames (the FPP and RGB-D front-ends implement it).

    The keyframe manager calls ``register(target, source, T_guess, kind=...)`` with ``kind``
    always given (keyword): ``ODOMETRY`` for a new frame against a recent keyframe, ``LOOP``
    for a revisit candidate. An implementation that treats both alike still takes the argument.
    """

    def register(
        self,
        target: Frame,
        source: Frame,
        T_guess: NDArray[np.float64] | None = None,
        kind: ConstraintKind = ConstraintKind.ODOMETRY,
    ) -> Constraint:
        """Return a Constraint ``T_target_source``; a rejected one says why, never raises on bad overlap.

        ``T_guess`` is ``T_target_source`` from the current estimate (None when unknown, e.g. an
        appearance-only loop candidate). ``kind`` tells the registrar what the pair is for: a
        loop candidate may deserve stricter verification (look-alike places) than consecutive
        frames.
        """
        ...


@runtime_checkable
class FrameTracker(Protocol):
    """Optional second capability of a :class:`PairRegistrar`: a cheap pose from a prediction.

    With ``keyframes.track_from_motion`` on, the keyframe manager predicts each new frame's pose
    relative to the last keyframe (constant velocity) and calls ``track(keyframe, frame,
    T_predicted)`` first. An accepted result is the frame's pose, and the odometry edge if the
    frame becomes a keyframe, so its information must be as honest as ``register``'s. A rejected
    result (with its reason) makes the manager make the last frame tracked against that keyframe
    (when there is one) a keyframe and track the frame against it, and then fall back to
    ``register`` for the frame, with the prediction as ``T_guess``.
    """

    def track(self, target: Frame, source: Frame, T_predicted: NDArray[np.float64]) -> Constraint:
        """Return an ODOMETRY Constraint ``T_target_source`` near ``T_predicted`` (4x4), or a
        rejected one saying why (never raises on bad overlap)."""
        ...


@runtime_checkable
class FrameDescriber(Protocol):
    """Optional third capability of a :class:`PairRegistrar`: keypoints and descriptors on demand.

    A source whose frames are tracked from motion may decode them without keypoints (a tracked
    frame never needs its own: :class:`FrameTracker` follows the keyframe's). The keyframe
    manager then has each new keyframe described once, before it is indexed for loop detection
    and stored for loop verification; ``register`` describes what it is given as it needs.
    """

    def describe(self, frame: Frame) -> Frame:
        """``frame`` with ``keypoints_uv`` and ``descriptors`` (the same object when it has them)."""
        ...


@runtime_checkable
class PairVerifier(Protocol):
    """Registers pairs of stored keyframes off the tracking path (loop verification).

    The keyframe manager submits every loop candidate of a keyframe as soon as it is proposed and
    reads the results a few keyframes later (:data:`~fpp_graph.slam.keyframes.VERIFY_LAG_KEYFRAMES`), in submission order, so a run's
    outcome does not depend on which worker finished first. An implementation may run the
    registration at once (in-process) or on any executor; both frames are keyframes already
    put in the manager's :class:`~fpp_graph.slam.frame_store.FrameStore`.
    """

    def submit(self, target_id: int, source_id: int, T_guess: NDArray[np.float64] | None, kind: ConstraintKind) -> Future[Constraint]:
        """Start ``register(target, source, T_guess, kind=kind)`` of the two stored keyframes; its
        result (a Constraint, accepted or rejected with a reason) or exception through the future."""
        ...


@dataclass(frozen=True)
class LoopCandidate:
    """A proposed revisit: ``query_id`` may see the same place as ``match_id``."""

    query_id: int
    match_id: int
    score: float
    source: str  # which stage proposed it, e.g. "proximity", "appearance"; "proximity" in it means
    # the pose estimate is trusted enough to serve as the registration's initial guess


@runtime_checkable
class LoopDetector(Protocol):
    """Proposes revisit candidates for a new keyframe (the keyframe manager verifies them)."""

    def add(self, frame: Frame) -> None:
        """Remember a keyframe so later frames can be matched against it (called once per keyframe,
        after :meth:`candidates` for that keyframe)."""
        ...

    def candidates(
        self,
        frame: Frame,
        poses_world_sensor: Mapping[int, NDArray[np.float64]],
        position_sigma_m: float = 0.0,
    ) -> Sequence[LoopCandidate]:
        """Candidates for ``frame`` among remembered keyframes, best first.

        ``poses_world_sensor`` holds the current estimate of the keyframes that may be matched
        by position (it may include ``frame.id``); ``position_sigma_m`` is the standard deviation
        of the query's position relative to its last loop closure (drift), for a proximity gate
        that widens with it. A detector that does not use positions ignores both.
        """
        ...


@dataclass(frozen=True, eq=False)
class FusedMap:
    """A fused global map in the world frame (numpy arrays only: it pickles across processes).

    Attributes
    ----------
    points_world_m : (N, 3) float64
        Map points, metres, world frame (e.g. the weighted mean point of each occupied voxel).
    colors : (N, 3) float64
        Colour of each point, RGB in [0, 1].
    weights : (N,) float64 or None
        Evidence behind each point (e.g. the number of points that fell in its voxel), if known.
    mesh_vertices : (V, 3) float64 or None
        Surface mesh vertices, metres, world frame (None without a mesh).
    mesh_triangles : (F, 3) int64 or None
        Vertex indices of each triangle.
    mesh_vertex_colors : (V, 3) float64 or None
        Vertex colours, RGB in [0, 1].
    """

    points_world_m: NDArray[np.float64]
    colors: NDArray[np.float64]
    weights: NDArray[np.float64] | None = None
    mesh_vertices: NDArray[np.float64] | None = None
    mesh_triangles: NDArray[np.int64] | None = None
    mesh_vertex_colors: NDArray[np.float64] | None = None

    @property
    def num_points(self) -> int:
        return int(self.points_world_m.shape[0])


@dataclass(frozen=True, eq=False)
class FusedMesh:
    """A map's surface mesh made apart from its points (:class:`MeshSplittingMapFuser`).

    Attributes
    ----------
    vertices : (V, 3) float64
        Metres, world frame.
    triangles : (F, 3) int64
        Vertex indices of each triangle.
    vertex_colors : (V, 3) float64
        RGB in [0, 1].
    frames_meshed : int
        Frames whose depth went into the mesh.
    frames_left_out : tuple of (frame id, reason)
        Frames that could not be meshed (e.g. no ``xyz_map``), with why.
    """

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    vertex_colors: NDArray[np.float64]
    frames_meshed: int
    frames_left_out: tuple[tuple[int, str], ...] = ()


@runtime_checkable
class MapFuser(Protocol):
    """Fuses frames under (optimised) poses into a global map, one frame at a time.

    The pipeline streams keyframes from its frame store (a long sequence does not fit in
    memory at once): ``integrate`` each, then ``result`` once.
    """

    def integrate(self, frame: Frame, T_world_sensor: NDArray[np.float64]) -> None:
        """Add one frame's points (``frame.points``, sensor frame) under ``T_world_sensor``."""
        ...

    def result(self) -> FusedMap:
        """The map fused so far."""
        ...


@runtime_checkable
class ParallelMapFuser(MapFuser, Protocol):
    """A :class:`MapFuser` whose per-frame work can run in the run's worker processes.

    ``preparer()`` returns a picklable callable ``(frame, T_world_sensor) -> prepared`` that
    depends on the fuser's settings only (not on what it has fused); ``add(prepared)`` folds one
    result in. The pipeline prepares several keyframes at once on its executor and adds them in
    keyframe order, so the map is the same as from ``integrate`` one by one
    (``integrate(f, T)`` must equal ``add(preparer()(f, T))``). ``result(map_chunks)`` gets
    the pool's map too.
    """

    def preparer(self) -> Callable[[Frame, NDArray[np.float64]], Any]:
        """The per-frame work, picklable, independent of this fuser's state."""
        ...

    def add(self, prepared: Any) -> None:
        """Fold in one frame's prepared result."""
        ...

    def result(self, map_chunks: Callable[[Callable[[Any], Any], Iterable[Any]], Iterable[Any]] = map) -> FusedMap:
        """The map fused so far; ``map_chunks`` (builtin ``map`` or the pool's, with the same
        meaning) may run a final pass over the map in chunks elsewhere, or be ignored."""
        ...


@runtime_checkable
class MeshSplittingMapFuser(ParallelMapFuser, Protocol):
    """A :class:`ParallelMapFuser` whose surface mesh can be made apart from its points.

    A mesh (a TSDF, say) is one state updated frame after frame, which the per-frame
    ``preparer`` cannot share out; made in a process of its own while the points are prepared
    and folded elsewhere, it is off the path of the rest. ``split_mesh()`` returns a picklable
    callable that meshes ``(frame, T_world_sensor)`` pairs given in keyframe order and returns a
    :class:`FusedMesh`; from then on the fuser itself makes no mesh (``result()`` has none).
    It returns None when there is no mesh to split off (the fuser makes none, or has begun).
    """

    def split_mesh(self) -> Callable[[Iterable[tuple[Frame, NDArray[np.float64]]]], FusedMesh] | None:
        """Hand the mesh over: the job that makes it, or None."""
        ...
