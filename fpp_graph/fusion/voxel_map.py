"""Global map fusion: frames under (optimised) poses into a coloured voxel map and a TSDF mesh.

:class:`VoxelMapFuser` implements :class:`fpp_graph.types.MapFuser`. It streams: call
:meth:`VoxelMapFuser.integrate` once per frame, then :meth:`VoxelMapFuser.result`. Memory is
bounded by the size of the map (per-voxel sums), not by the number of frames, because each frame
is reduced to its occupied voxels before it is merged.

- Points: every voxel of edge ``voxel_size_m`` holds the weighted mean of the points (and
  colours) that fell in it, weight = number of points (or the sum of the per-point weights the
  caller passes), each point down-weighted by ``cos`` of its surface's angle to the viewing ray
  when the frame has an organised ``xyz_map`` (``grazing_weight``). Averaging the overlapping views of a surface reduces the sensor noise by about
  ``sqrt(weight)``.
- Mesh: Open3D's TSDF ``VoxelBlockGrid`` (sparse, grows with the scene). Each frame's organised ``xyz_map`` is rendered into a
  pinhole depth image (intrinsics from the frame's camera model or fitted to the map), so FPP maps
  whose pixels follow a distorted lens still land on the right rays.

After a pose-graph update, :meth:`VoxelMapFuser.fuse` rebuilds the map from the frames (their
``points``/``xyz_map``/``texture``, e.g. from the :class:`~fpp_graph.slam.frame_store.FrameStore`);
the raw fringe images are not needed again.

Results are :class:`FusedMap`: numpy arrays only, so they pickle across processes; the PLY
writers are in :mod:`fpp_graph.fusion.ply` (re-exported here).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError

# the PLY writers, re-exported: they lived here
from fpp_graph.fusion.ply import write_mesh_ply as write_mesh_ply
from fpp_graph.fusion.ply import write_point_cloud_ply as write_point_cloud_ply
from fpp_graph.fusion.tsdf_mesh import (
    TSDF_INITIAL_VOXELS,
    TSDF_TRUNCATION_VOXELS,
    TsdfMesher,
    tsdf_block_voxels,
)
from fpp_graph.fusion.voxel_grid import _reduce, project_to_local_planes, voxel_keys
from fpp_graph.geometry import (
    finite_box,
    finite_points,
    in_row_bands,
    masked_pixels,
    transform_points,
)
from fpp_graph.types import (  # FusedMap: the MapFuser protocol's result type, re-exported here
    Frame,
    FusedMap,
    FusedMesh,
)

log = logging.getLogger(__name__)


class VoxelMapFuser:
    """Streams frames into a voxel-averaged coloured point cloud and, optionally, a TSDF mesh.

    Parameters
    ----------
    voxel_size_m : float
        Edge of the voxels of the point map, metres.
    tsdf_voxel_m : float
        Edge of the TSDF voxels of the mesh, metres; the truncation band is
        :data:`TSDF_TRUNCATION_VOXELS` of them (``tsdf_truncation_m``).
    mesh : bool
        Build the TSDF mesh as well (needs frames with ``xyz_map``).
    tsdf_depth_max_m : float
        Depths beyond this are ignored by the TSDF.
    tsdf_min_weight : float
        Mesh only voxels observed with at least this TSDF weight (frames).
    tsdf_block_count : int, optional
        Initial capacity of the TSDF block hash map (it grows on demand); default: blocks for
        :data:`~fpp_graph.fusion.tsdf_mesh.TSDF_INITIAL_VOXELS` voxels.
    max_depth_m : float
        Points farther along the optical axis (sensor ``z``) stay out of the point map and the
        TSDF (``points_beyond_max_depth`` counts them): a depth camera's error grows with range
        (Kinect: ``1.4e-3 z^2``), and beyond the TSDF truncation band its points smear surfaces.
    surface_smoothing : bool
        After averaging, move each voxel's point onto the weighted plane fitted to its 3x3x3
        voxel neighbourhood (:func:`project_to_local_planes`). The voxel grid sorts noisy points
        by the sign of their error where the noise is not far below the voxel size (a point
        too far along its ray lands in the voxel behind the surface), so plain voxel means keep
        about the per-point noise; the plane fit averages across those voxels. Voxels whose
        neighbourhood is not planar (edges, thin parts) or too sparse keep their mean.
    grazing_weight : bool
        Weight each point of a frame with an organised ``xyz_map`` by ``cos(angle)`` between its
        surface normal and the viewing ray (:func:`grazing_weights`), so head-on views of a surface
        dominate its voxels over grazing ones (whose points are the least accurate). Points
        without a normal (no ``xyz_map``, hole edges) keep weight 1.
    """

    def __init__(
        self,
        voxel_size_m: float,
        tsdf_voxel_m: float,
        mesh: bool,
        tsdf_depth_max_m: float = 10.0,
        tsdf_min_weight: float = 1.0,
        tsdf_block_count: int | None = None,
        grazing_weight: bool = True,
        surface_smoothing: bool = True,
        max_depth_m: float = math.inf,
    ) -> None:
        for name, value in (("voxel_size_m", voxel_size_m), ("tsdf_voxel_m", tsdf_voxel_m)):
            if not (np.isfinite(value) and value > 0):
                raise InputDataError(f"map fusion: {name} must be a positive number of metres, got {value!r}")
        self.voxel_size_m = float(voxel_size_m)
        self.tsdf_voxel_m = float(tsdf_voxel_m)
        self.tsdf_truncation_m = TSDF_TRUNCATION_VOXELS * self.tsdf_voxel_m
        self.mesh = bool(mesh)
        self.tsdf_depth_max_m = float(tsdf_depth_max_m)
        self.tsdf_min_weight = float(tsdf_min_weight)
        self.tsdf_block_voxels = tsdf_block_voxels(self.tsdf_truncation_m, self.tsdf_voxel_m)
        self.tsdf_block_count = int(tsdf_block_count) if tsdf_block_count is not None else -(-TSDF_INITIAL_VOXELS // self.tsdf_block_voxels**3)
        self.grazing_weight = bool(grazing_weight)
        self.surface_smoothing = bool(surface_smoothing)
        if not max_depth_m > 0:
            raise InputDataError(f"map fusion: max_depth_m must be a positive number of metres, got {max_depth_m!r}")
        self.max_depth_m = float(max_depth_m)
        self.reset()

    def reset(self) -> None:
        """Forget everything integrated so far."""
        self._keys = np.zeros(0, dtype=np.int64)
        # one contiguous plane per sum, a value per voxel: w*x, w*y, w*z, w*r, w*g, w*b, w
        self._sums = np.zeros((7, 0))
        self._pending: list[tuple[NDArray[np.int64], NDArray[np.float64]]] = []
        self._pending_rows = 0
        self._tsdf: TsdfMesher | None = None
        self.frames_integrated = 0
        self.points_beyond_max_depth = 0

    # -- streaming -----------------------------------------------------------------------------
    def integrate(
        self,
        frame: Frame,
        T_world_sensor: NDArray[np.float64],
        point_weights: NDArray[np.float64] | None = None,
    ) -> None:
        """Add one frame seen from ``T_world_sensor`` (4x4, sensor to world).

        Parameters
        ----------
        frame : Frame
            Uses ``points`` and ``colors`` (grey 0.5 when absent) for the point map and
            ``xyz_map`` plus ``texture`` (or ``colors``) for the mesh.
        T_world_sensor : (4, 4) float64
            Pose of the frame.
        point_weights : (N,) float64, optional
            Per-point weights (e.g. FPP modulation); default 1 per point, times the grazing-angle
            weight when ``grazing_weight`` is on and the frame has an ``xyz_map``.
        """
        self.add(self.preparer()(frame, T_world_sensor, point_weights))

    def preparer(self) -> FramePreparer:
        """The per-frame half of :meth:`integrate`, apart from this fuser's state: a picklable
        callable ``(frame, T_world_sensor) -> PreparedFrame`` a worker process can run; fold its
        results in with :meth:`add` (implements :class:`~fpp_graph.types.ParallelMapFuser`)."""
        return FramePreparer(self.voxel_size_m, self.mesh, self.grazing_weight, self.max_depth_m)

    def add(self, prepared: PreparedFrame) -> None:
        """Fold in one frame's :class:`PreparedFrame` (from :meth:`preparer`, in this or another process)."""
        self.points_beyond_max_depth += prepared.points_beyond_max_depth
        if len(prepared.keys):
            self._pending.append((prepared.keys, prepared.sums))
            self._pending_rows += len(prepared.keys)
            # merge when the pending chunks outgrow the map: amortised O(map log map) per merge
            # and peak memory about twice the map
            if self._pending_rows > max(len(self._keys), 1_000_000):
                self._merge()
        if self.mesh:
            if prepared.depth_m is None:
                log.warning("frame %d has %s; it is left out of the TSDF mesh", prepared.frame_id, prepared.no_depth_reason)
            else:
                self._mesher().integrate(prepared.depth_m, prepared.rgb, prepared.K, prepared.T_world_sensor)
        self.frames_integrated += 1

    def _merge(self) -> None:
        if not self._pending:
            return
        keys = np.concatenate([self._keys, *(k for k, _ in self._pending)])
        sums = np.concatenate([self._sums, *(s for _, s in self._pending)], axis=1)
        self._keys, self._sums = _reduce(keys, sums, sorted_runs=True)
        self._pending = []
        self._pending_rows = 0

    def _mesher(self) -> TsdfMesher:
        if self._tsdf is None:
            self._tsdf = TsdfMesher(*self._tsdf_settings())
        return self._tsdf

    @property
    def frames_meshed(self) -> int:
        """Frames in the TSDF mesh so far."""
        return 0 if self._tsdf is None else self._tsdf.frames_meshed

    def split_mesh(self) -> FrameMesher | None:
        """The mesh as a job of its own (:class:`FrameMesher`, picklable: one process can mesh
        the frames while others fuse their points); this fuser then makes no mesh (its
        :meth:`preparer` renders no depth images, its :meth:`result` has no mesh). None when it
        makes none anyway, or has meshed frames already (implements
        :class:`~fpp_graph.types.MeshSplittingMapFuser`)."""
        if not self.mesh or self.frames_integrated:
            return None
        self.mesh = False
        return FrameMesher(*self._tsdf_settings())

    def _tsdf_settings(self) -> tuple[float, float, float, float, int, int]:
        """:class:`TsdfMesher`'s arguments (and :class:`FrameMesher`'s fields), in their order."""
        return (self.tsdf_voxel_m, self.tsdf_truncation_m, min(self.tsdf_depth_max_m, self.max_depth_m), self.tsdf_min_weight,
                self.tsdf_block_voxels, self.tsdf_block_count)

    def result(self, map_chunks: Callable[[Callable[[tuple], Any], Iterable[tuple]], Iterable[Any]] = map) -> FusedMap:
        """The map fused so far (the fuser can keep integrating afterwards). ``map_chunks``
        (builtin ``map``, or a worker pool's) runs the surface smoothing's chunks: a room-sized
        FPP map's 7.4 M voxels take 57 s in one process. The result does not depend on it."""
        self._merge()
        w = self._sums[6]
        points = np.ascontiguousarray((self._sums[:3] / w).T)
        if self.surface_smoothing and len(points):
            points = project_to_local_planes(self._keys, points, w, self.voxel_size_m, map_chunks=map_chunks)
        colors = np.ascontiguousarray(np.clip(self._sums[3:6] / w, 0.0, 1.0).T)
        vertices = triangles = vertex_colors = None
        if self.mesh:
            vertices, triangles, vertex_colors = self._mesher().mesh()
        return FusedMap(points, colors, w.copy(), vertices, triangles, vertex_colors)

    # -- MapFuser protocol -------------------------------------------------------------------
    def fuse(self, frames: Sequence[Frame], poses_world_sensor: Mapping[int, NDArray[np.float64]]) -> FusedMap:
        """Fuse ``frames`` from scratch under ``poses_world_sensor`` (frame id -> 4x4)."""
        missing = [f.id for f in frames if f.id not in poses_world_sensor]
        if missing:
            raise InputDataError(
                f"map fusion: no pose for frames {missing[:10]}{' ...' if len(missing) > 10 else ''}; "
                "pass a pose for every frame to fuse (or leave those frames out)"
            )
        self.reset()
        for frame in frames:
            self.integrate(frame, poses_world_sensor[frame.id])
        return self.result()


@dataclass(frozen=True, eq=False)
class PreparedFrame:
    """One frame's share of a :class:`VoxelMapFuser` map, computed without the fuser's state.

    ``keys`` / ``sums``: the frame's occupied voxels and their weighted sums (7, voxels: planes
    w*x, w*y, w*z, w*r, w*g, w*b, w); ``depth_m`` / ``rgb`` / ``K``: its pinhole depth image (float32,
    metres), colours and intrinsics for the TSDF, None without a mesh or a depth
    (``no_depth_reason`` says which).
    """

    frame_id: int
    T_world_sensor: NDArray[np.float64]
    keys: NDArray[np.int64]
    sums: NDArray[np.float64]
    points_beyond_max_depth: int
    depth_m: NDArray[np.float32] | None = None
    rgb: NDArray[np.uint8] | None = None
    K: NDArray[np.float64] | None = None
    no_depth_reason: str | None = None


@dataclass(frozen=True)
class FramePreparer:
    """The per-frame work of :meth:`VoxelMapFuser.integrate` (grazing weights, voxel sums, the
    depth rendering): a function of the frame, its pose and these settings alone, so the run's
    worker processes can do it for several keyframes at once (:meth:`VoxelMapFuser.preparer`)."""

    voxel_size_m: float
    mesh: bool
    grazing_weight: bool
    max_depth_m: float

    def __call__(self, frame: Frame, T_world_sensor: NDArray[np.float64], point_weights: NDArray[np.float64] | None = None) -> PreparedFrame:
        T = _checked_pose(frame, T_world_sensor)
        points = frame.points
        colors = frame.colors if frame.colors is not None else np.full(points.shape, 0.5)
        weights = np.ones(len(points)) if point_weights is None else np.asarray(point_weights, dtype=np.float64).reshape(-1)
        if weights.shape[0] != points.shape[0]:
            raise InputDataError(
                f"map fusion: frame {frame.id} has {points.shape[0]} points but {weights.shape[0]} weights"
            )
        # the map's finite pixels, found once for the grazing weights and the depth rendering
        # (each pass over a 1920x1200 map costs ~30 ms), and only when one of them is made
        needs_finite = frame.xyz_map is not None and (self.grazing_weight or self.mesh)
        finite_map = finite_points(frame.xyz_map) if needs_finite else None
        if self.grazing_weight and finite_map is not None:
            # front-ends build points as xyz_map[valid] in row-major order; use it when it fits
            if np.count_nonzero(finite_map) == len(points):
                weights = weights * grazing_weights(frame.xyz_map, finite=finite_map)[finite_map]
        keep = finite_points(points) & (weights > 0)
        beyond = 0
        if math.isfinite(self.max_depth_m):
            far = keep & (points[:, 2] > self.max_depth_m)
            beyond = int(np.count_nonzero(far))
            keep &= ~far
        # (every point is kept, as a rule: the masked copies of 2.3 M points, colours and weights
        # are skipped then)
        kept = slice(None) if keep.all() else keep
        points_world = transform_points(T, points[kept])
        w = weights[kept]
        keys, sums = np.zeros(0, dtype=np.int64), np.zeros((7, 0))
        if len(points_world):
            planes = np.empty((7, len(w)))
            np.multiply(points_world.T, w, out=planes[:3])
            np.multiply(colors[kept].T, w, out=planes[3:6])
            planes[6] = w
            keys, sums = _reduce(voxel_keys(points_world, self.voxel_size_m), planes)
        prepared = PreparedFrame(frame.id, T, keys, sums, beyond)
        if not self.mesh:
            return prepared
        view = depth_view(frame, finite_map)
        if isinstance(view, str):
            return dataclasses.replace(prepared, no_depth_reason=view)
        depth_m, rgb, K = view
        return dataclasses.replace(prepared, depth_m=depth_m, rgb=rgb, K=K)


@dataclass(frozen=True)
class FrameMesher:
    """The TSDF mesh of :class:`VoxelMapFuser` as a job of its own (:meth:`VoxelMapFuser.split_mesh`):
    its settings alone, picklable, so that one process meshes the frames while others fuse their
    points. Call it with the frames and their poses in order; each frame's depth image is
    rendered as :class:`FramePreparer` renders it, so the mesh is the fuser's own."""

    voxel_m: float
    truncation_m: float
    depth_max_m: float
    min_weight: float
    block_voxels: int
    block_count: int

    def __call__(self, frames: Iterable[tuple[Frame, NDArray[np.float64]]]) -> FusedMesh:
        mesher = TsdfMesher(*dataclasses.astuple(self))
        left_out = []
        for frame, T_world_sensor in frames:
            T = _checked_pose(frame, T_world_sensor)
            view = depth_view(frame)
            if isinstance(view, str):
                left_out.append((frame.id, view))
            else:
                mesher.integrate(*view, T)
        vertices, triangles, vertex_colors = mesher.mesh()
        return FusedMesh(vertices, triangles, vertex_colors, mesher.frames_meshed, tuple(left_out))


def _checked_pose(frame: Frame, T_world_sensor: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.asarray(T_world_sensor, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputDataError(f"map fusion: pose of frame {frame.id} must be a finite 4x4, got shape {T.shape}")
    return T


def depth_view(frame: Frame, finite: NDArray[np.bool_] | None = None) -> tuple[NDArray[np.float32], NDArray[np.uint8], NDArray[np.float64]] | str:
    """What the TSDF takes of a frame: its pinhole depth image (float32 metres), RGB image and
    ``K`` (:func:`render_depth`, :func:`intrinsics_of`), or why there is none."""
    if frame.xyz_map is None:
        return "no xyz_map"
    K = intrinsics_of(frame)
    depth_m, rgb = render_depth(frame, K, finite=finite)
    if not np.any(depth_m > 0):
        return "no valid depth"
    return depth_m.astype(np.float32), rgb, K


def grazing_weights(xyz_map: NDArray[np.float64], floor: float = 0.05, finite: NDArray[np.bool_] | None = None) -> NDArray[np.float64]:
    """Per-pixel ``|cos|`` of the angle between the surface normal and the viewing ray.

    The normal is the cross product of the organised map's central differences (one-sided at
    the image border). Pixels whose normal is unknown (a NaN neighbour) get 1; the weight is at
    least ``floor`` so no valid point is dropped here (rejecting points is the front-end's job).
    ``finite``: the map's :func:`~fpp_graph.geometry.finite_points`, when the caller has it.
    """
    xyz = np.asarray(xyz_map, dtype=np.float64)
    weights = np.ones(xyz.shape[:2])
    # Only the box around the finite pixels, one pixel wider, is computed: every pixel outside
    # it has a NaN coordinate (weight 1), and inside it each finite pixel's differences take
    # the same neighbours as over the whole map (a scanned object often fills a third of the
    # view). np.gradient is one-sided only at the box's sides that are the
    # image's own.
    rows, cols = finite_box(xyz, finite)
    if rows.stop - rows.start >= 2 and cols.stop - cols.start >= 2:
        # in bands of rows (the same cosines): ~40 % faster on 1920x1200 maps (cache-resident bands)
        in_row_bands(lambda band: _grazing_cos(band, floor), xyz[rows, cols], weights[rows, cols], GRAZING_BAND_ROWS)
    return weights


GRAZING_BAND_ROWS = 16
"""Rows per band of :func:`grazing_weights`: 16 rows of a 1920-pixel map are 0.25 MB per float64
plane, so a band's ~10 planes fit a 4 MB L2 cache (8 and 64 rows were 10-20 % slower on 1920x1200 maps)."""


def _grazing_cos(xyz: NDArray[np.float64], floor: float) -> NDArray[np.float64]:
    # per coordinate plane, contiguous: arithmetic on the strided channels of an (H, W, 3) map
    # ran slower. The differences are np.gradient's times 2 (its interior halving and its
    # one-sided border steps differ from these by exactly 2, a power of two): every product
    # below then carries exact powers of two that the ratio cancels, so the cosines are
    # np.gradient's bit for bit, without its temporaries (140 -> 113 ms a 1920 x 1200 map)
    # copies, always: the products below overwrite them (a map stored as coordinate planes has
    # contiguous channels, which ascontiguousarray would hand back as views of the caller's map)
    x, y, z = (np.array(xyz[..., k], dtype=np.float64, order="C", copy=True) for k in range(3))
    bx, ax = _twice_gradient(x)  # (rows, columns)
    by, ay = _twice_gradient(y)
    bz, az = _twice_gradient(z)
    # the cross product, dot product and norms written per component, in place: np.cross and
    # np.linalg.norm over a 1920 x 1200 map took 0.5 s a frame
    with np.errstate(invalid="ignore", divide="ignore"):
        nx = np.multiply(ay, bz)
        scratch = np.multiply(az, by)
        nx -= scratch
        ny = np.multiply(az, bx, out=az)
        ny -= np.multiply(ax, bz, out=scratch)
        nz = np.multiply(ax, by, out=ax)
        nz -= np.multiply(ay, bx, out=scratch)
        dot = np.multiply(nx, x, out=bx)
        dot += np.multiply(ny, y, out=scratch)
        dot += np.multiply(nz, z, out=scratch)
        np.abs(dot, out=dot)
        n2 = np.multiply(nx, nx, out=nx)
        n2 += np.multiply(ny, ny, out=ny)
        n2 += np.multiply(nz, nz, out=nz)
        r2 = np.multiply(x, x, out=x)
        r2 += np.multiply(y, y, out=y)
        r2 += np.multiply(z, z, out=z)
        n2 *= r2
        np.sqrt(n2, out=n2)
        cos = np.divide(dot, n2, out=dot)
        # NaN (an unknown normal) stays NaN through the clip; +inf (never, in practice) clips to 1
        np.clip(cos, floor, 1.0, out=cos)
    cos[np.isnan(cos)] = 1.0
    return cos


def _twice_gradient(f: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``2 * np.gradient(f)`` of a 2-D array (at least 2 x 2), exactly: central differences
    inside, one-sided steps doubled at the border."""
    along_rows, along_columns = np.empty_like(f), np.empty_like(f)
    for out, g in ((along_rows, f), (along_columns.T, f.T)):
        np.subtract(g[2:], g[:-2], out=out[1:-1])
        np.subtract(g[1], g[0], out=out[0])
        np.subtract(g[-1], g[-2], out=out[-1])
        out[0] *= 2.0
        out[-1] *= 2.0
    return along_rows, along_columns


# -- intrinsics and depth rendering ---------------------------------------------------------
def intrinsics_of(frame: Frame) -> NDArray[np.float64]:
    """Pinhole ``K`` (3x3) of a frame's ``xyz_map``: its camera model's or a least-squares fit.

    The fit solves ``u = fx x/z + cx`` and ``v = fy y/z + cy`` over the valid pixels
    (u = column, v = row). A lens with distortion gives a K that is right on average; the
    depth rendering then puts each point at its pinhole pixel, so the TSDF stays consistent.
    """
    if frame.camera is not None:
        return np.array(frame.camera.K)
    if frame.xyz_map is None:
        raise InputDataError(f"frame {frame.id}: no camera model and no xyz_map to estimate intrinsics from")
    xyz = frame.xyz_map
    valid = finite_points(xyz) & (xyz[..., 2] > 0)
    v, u = np.nonzero(valid)
    if len(u) < 10:
        raise InputDataError(f"frame {frame.id}: only {len(u)} valid pixels, too few to estimate intrinsics")
    pts = xyz[valid]
    # subsample: a few thousand pixels pin down four numbers
    if len(u) > 20000:
        pick = np.linspace(0, len(u) - 1, 20000).astype(np.int64)
        u, v, pts = u[pick], v[pick], pts[pick]
    x_over_z = pts[:, 0] / pts[:, 2]
    y_over_z = pts[:, 1] / pts[:, 2]
    fx, cx = np.linalg.lstsq(np.column_stack([x_over_z, np.ones_like(x_over_z)]), u.astype(np.float64), rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.column_stack([y_over_z, np.ones_like(y_over_z)]), v.astype(np.float64), rcond=None)[0]
    if not (fx > 0 and fy > 0):
        raise InputDataError(
            f"frame {frame.id}: the xyz_map does not look like a camera's organised map "
            f"(fitted fx={fx:.4g}, fy={fy:.4g}); give the frame a camera model (Frame.camera)"
        )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def render_depth(frame: Frame, K: NDArray[np.float64], finite: NDArray[np.bool_] | None = None) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """Project a frame's ``xyz_map`` into a pinhole depth image (z-buffered) and its RGB image
    (``finite``: the map's :func:`~fpp_graph.geometry.finite_points`, when the caller has it).

    Returns
    -------
    depth_m : (H, W) float64
        Depth (z in the sensor frame) in metres, 0 where empty.
    rgb : (H, W, 3) uint8
        Colour from ``texture`` (grey) or ``colors`` at the same pixels.
    """
    xyz = frame.xyz_map
    assert xyz is not None
    h, w = xyz.shape[:2]
    with np.errstate(invalid="ignore"):
        valid = (finite_points(xyz) if finite is None else finite) & (xyz[..., 2] > 0)
    pixel_of_point = np.flatnonzero(valid)
    x, y, z = masked_pixels(np.asarray(xyz), valid).T
    # A grey texture is carried as one byte per point and spread to RGB at the end (moving
    # (N, 3) colour rows through the masks and the scatter took a third of the rendering)
    if frame.texture is not None:
        colors = np.asarray(frame.texture).reshape(-1)[pixel_of_point].astype(np.uint8)
    elif frame.colors is not None and len(frame.colors) == len(z):
        # front-ends build points as xyz_map[valid] (row-major), so colours line up
        colors = (np.clip(frame.colors, 0, 1) * 255).round().astype(np.uint8)
    else:
        colors = np.full(len(z), 128, dtype=np.uint8)
    # (without skew its term adds only zeros: the same sums)
    u_px = K[0, 0] * x / z + K[0, 1] * y / z if K[0, 1] != 0.0 else K[0, 0] * x / z
    u = np.rint(u_px + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * y / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    pixel = v * w + u
    if inside.all() and np.array_equal(pixel, pixel_of_point):
        # a pinhole map under its own K (an undistorted depth camera): every point lands on its
        # own pixel, one per pixel, so there is nothing to z-buffer
        return _depth_and_rgb(h, w, pixel_of_point, z, colors)
    if not inside.all():
        # (a pinhole fit of a distorted map keeps nearly every point inside: copying 2.3 M
        # points, depths and colours through the mask took a quarter of a 1920x1200 frame's time)
        pixel, z, colors = pixel[inside], z[inside], colors[inside]
    # z-buffer: the nearest point of each pixel wins (a per-pixel minimum instead of sorting
    # 2.3 M depths: 195 -> 112 ms a 1920 x 1200 frame); its colour with it
    nearest = np.full(h * w, np.inf)
    np.minimum.at(nearest, pixel, z)
    wins = z == nearest[pixel]
    return _depth_and_rgb(h, w, pixel[wins], z[wins], colors[wins])


def _depth_and_rgb(h: int, w: int, pixel: NDArray[np.int64], z: NDArray[np.float64], colors: NDArray[np.uint8]) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """Depth and RGB images with ``z`` and ``colors`` (grey (N,) or RGB (N, 3)) at flat ``pixel``s, 0 elsewhere."""
    depth_m = np.zeros((h, w))
    depth_m.reshape(-1)[pixel] = z
    if colors.ndim == 1:
        grey = np.zeros((h, w), dtype=np.uint8)
        grey.reshape(-1)[pixel] = colors
        return depth_m, np.repeat(grey[..., None], 3, axis=2)
    rgb = np.zeros((h, w, 3), dtype=np.uint8)
    rgb.reshape(-1, 3)[pixel] = colors
    return depth_m, rgb
