"""The TSDF mesh of a map (used by :class:`~fpp_graph.fusion.voxel_map.VoxelMapFuser`): the
surface built from depth images one frame at a time (:class:`TsdfMesher`), its blocks as thick
as the truncation band (:func:`tsdf_block_voxels`), the hash map's first capacity
(:data:`TSDF_INITIAL_VOXELS`), and the mesh listed in an order of its own content
(:func:`canonical_mesh`)."""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError

log = logging.getLogger(__name__)

TSDF_INITIAL_VOXELS = 1000 * 16**3
"""The TSDF hash map's first capacity in voxels: Open3D's customary 1000 blocks of 16^3 (82 MB
of tsdf, weight and colour), whatever the block size. It doubles when full
(:meth:`TsdfMesher._make_room`: a new grid and a copy of the blocks)."""

TSDF_TRUNCATION_VOXELS = 4
"""The TSDF's truncation band in TSDF voxels: it covers the voxel discretisation (half a voxel
either side) and the depth noise on both sides of a surface, which the voxel is chosen to match
(the registration's ICP voxel, a few standard deviations of the sensor's depth noise)."""


def tsdf_block_voxels(truncation_m: float, voxel_m: float) -> int:
    """Edge of a TSDF block in voxels: as thick as the truncation band (``2 * truncation``), 8 to
    16 voxels. Integration updates every voxel of each block the band touches; in a block much
    thicker than the band most voxels are free space in front of the surface (each view sets
    them to +1, which the mesh does not use). The defaults' band is 8 voxels (FPP: 2 mm voxels,
    8 mm truncation; RGB-D: 1 cm, 4 cm). 8^3 blocks integrate a keyframe 2-2.5x faster than
    Open3D's default 16^3 on RGB-D sequences (views of walls metres away: most of a 16 cm block
    is empty) and make the same surface (vertex distances to the true surface equal within
    0.01 mm RMS on simulated sequences; on walls 4-5 m away 4 % more vertices stay that wide
    blocks' free-space updates carve away). Below 8 the hash map's per-block work grows."""
    if not (math.isfinite(truncation_m) and math.isfinite(voxel_m) and truncation_m > 0 and voxel_m > 0):
        raise InputDataError(f"map fusion: the TSDF's truncation and voxel must be positive lengths in metres, got {truncation_m!r} and {voxel_m!r}")
    return int(min(max(math.ceil(2.0 * truncation_m / voxel_m - 1e-9), 8), 16))


def canonical_mesh(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], vertex_colors: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """The mesh in an order of its own content: vertices sorted by position (then colour), the
    few exact duplicates (same position and colour) merged, each triangle starting at its
    smallest vertex (its winding kept) and the triangles sorted, repeats and collapsed ones
    dropped. Open3D's threaded extraction lists the same vertices and triangles in an order that
    differs from run to run (two runs of 7-Scenes chess: the same 128,653 vertices, other
    files), and a run's outputs are otherwise the same bytes every time. It costs 0.7 s for
    TUM fr1_rpy's 686k vertices (two sorts), about 2 % of that run."""
    if not len(vertices):
        return vertices, triangles, vertex_colors
    keys = np.concatenate([vertices, vertex_colors], axis=1)
    order = np.lexsort(keys.T[::-1])  # by x, then y, z and the colour
    keys = keys[order]
    first_of_kind = np.ones(len(keys), dtype=bool)
    first_of_kind[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.cumsum(first_of_kind) - 1
    tri = rank[triangles]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
    tri = np.take_along_axis(tri, (tri.argmin(axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    tri = tri[np.lexsort(tri.T[::-1])]
    repeat = np.zeros(len(tri), dtype=bool)
    repeat[1:] = np.all(tri[1:] == tri[:-1], axis=1)
    keys, tri = keys[first_of_kind], tri[~repeat]
    if len(keys) < len(vertices) or len(tri) < len(triangles):  # identical copies: no surface is lost
        log.debug("TSDF mesh: %d duplicate vertices merged, %d collapsed or repeated triangles dropped", len(vertices) - len(keys), len(triangles) - len(tri))
    return keys[:, :3], tri, keys[:, 3:]


# the TSDF grid's voxel attributes (name, channels), float32 each; growing the grid copies each
_TSDF_ATTRIBUTES = (("tsdf", 1), ("weight", 1), ("color", 3))


class TsdfMesher:
    """A TSDF surface built from pinhole depth images, one frame at a time, and its mesh.

    Open3D's tensor ``VoxelBlockGrid`` on the CPU (sparse: it grows with the scene; the legacy
    ``ScalableTSDFVolume`` of open3d 0.20 returns empty meshes here, checked against
    ``UniformTSDFVolume`` on the same images). Open3D is imported with the first frame.

    Parameters
    ----------
    voxel_m, truncation_m : float
        TSDF voxel edge and truncation distance, metres.
    depth_max_m : float
        Depths beyond this are left out.
    min_weight : float
        :meth:`mesh` keeps only voxels observed with at least this weight (frames).
    block_voxels : int
        Edge of a block in voxels (:func:`tsdf_block_voxels`).
    block_count : int
        The hash map's first capacity in blocks; it grows on demand (:meth:`_make_room`).
    """

    def __init__(self, voxel_m: float, truncation_m: float, depth_max_m: float, min_weight: float, block_voxels: int, block_count: int) -> None:
        self.voxel_m, self.truncation_m, self.depth_max_m = float(voxel_m), float(truncation_m), float(depth_max_m)
        self.min_weight, self.block_voxels, self.block_count = float(min_weight), int(block_voxels), int(block_count)
        self._volume = None
        self.frames_meshed = 0

    def _new_volume(self, block_count: int):
        import open3d as o3d

        return o3d.t.geometry.VoxelBlockGrid(
            attr_names=tuple(name for name, _ in _TSDF_ATTRIBUTES),
            attr_dtypes=tuple(o3d.core.float32 for _ in _TSDF_ATTRIBUTES),
            attr_channels=tuple(channels for _, channels in _TSDF_ATTRIBUTES),
            voxel_size=self.voxel_m,
            block_resolution=self.block_voxels,
            block_count=block_count,
            device=o3d.core.Device("CPU:0"),
        )

    def integrate(self, depth_m: NDArray[np.float32], rgb: NDArray[np.uint8], K: NDArray[np.float64], T_world_sensor: NDArray[np.float64]) -> None:
        """Fuse one view: its depth image (float32 metres, 0 where empty), colours and pinhole ``K``."""
        import open3d as o3d

        from fpp_graph.geometry import invert

        if self._volume is None:
            self._volume = self._new_volume(self.block_count)
        depth = o3d.t.geometry.Image(o3d.core.Tensor(depth_m))
        # one pass from the bytes (the same float32 quotients as astype(float32) / 255: 2.4 against 9.9 ms at 1920x1200)
        color = o3d.t.geometry.Image(o3d.core.Tensor(np.divide(rgb, np.float32(255.0), dtype=np.float32)))
        intrinsic = o3d.core.Tensor(K, dtype=o3d.core.float64)
        # Open3D wants the extrinsic world -> camera, the inverse of our T_world_sensor
        extrinsic = o3d.core.Tensor(invert(T_world_sensor), dtype=o3d.core.float64)
        band_voxels = self.truncation_m / self.voxel_m
        blocks = self._volume.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, self.depth_max_m, band_voxels)
        self._make_room(len(blocks))
        self._volume.integrate(blocks, depth, color, intrinsic, extrinsic, 1.0, self.depth_max_m, band_voxels)
        self.frames_meshed += 1

    def _make_room(self, incoming_blocks: int) -> None:
        """Grow the TSDF's hash map before ``incoming_blocks`` are activated in it, where Open3D
        would grow it itself (when its size plus the blocks asked for exceed its capacity).

        Open3D 0.20 grows a filled map (``HashMap.reserve``) at ~0.1-0.2 ms a block, over half of
        a room-sized FPP map's TSDF integration. A new grid of twice the capacity, its blocks activated at
        once and their voxels copied through numpy, holds the same blocks and voxel values (the
        mesh is the same: :func:`canonical_mesh` lists it by content, not by the hash map's slots)."""
        hashmap = self._volume.hashmap()
        size, capacity = hashmap.size(), hashmap.capacity()
        if size + incoming_blocks <= capacity:
            return
        import open3d as o3d

        grown = self._new_volume(max(2 * capacity, size + incoming_blocks))
        grown_map = grown.hashmap()
        slots = hashmap.active_buf_indices().numpy()
        new_slots, activated = grown_map.activate(o3d.core.Tensor(hashmap.key_tensor().numpy()[slots]))
        if not bool(activated.numpy().all()):
            raise RuntimeError("map fusion: the TSDF's blocks did not all move to its grown hash map")
        new_slots = new_slots.numpy()
        for attribute in range(len(_TSDF_ATTRIBUTES)):  # one at a time: a copy of one, not of all, at any moment
            grown_map.value_tensor(attribute).numpy()[new_slots] = hashmap.value_tensor(attribute).numpy()[slots]
        log.debug("TSDF hash map grown from %d to %d blocks (%d in use)", capacity, grown_map.capacity(), size)
        self._volume = grown

    def mesh(self) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        """``(vertices, triangles, vertex_colors)`` of the surface so far (:func:`canonical_mesh`
        order; empty arrays before the first frame)."""
        if self._volume is None:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3))
        mesh = self._volume.extract_triangle_mesh(weight_threshold=self.min_weight)
        vertices = mesh.vertex.positions.numpy().astype(np.float64)
        triangles = mesh.triangle.indices.numpy().astype(np.int64)
        if "colors" in mesh.vertex:
            vertex_colors = np.clip(mesh.vertex.colors.numpy().astype(np.float64), 0.0, 1.0)
        else:
            vertex_colors = np.full(vertices.shape, 0.5)
        return canonical_mesh(vertices, triangles, vertex_colors)


__all__ = ["TSDF_INITIAL_VOXELS", "TsdfMesher", "canonical_mesh", "tsdf_block_voxels"]
