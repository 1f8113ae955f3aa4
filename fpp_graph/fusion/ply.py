"""Binary little-endian PLY writers for the fused map and mesh: a few lines of numpy, points as
``double`` (a write/read round trip is exact), colours as ``uchar``, written atomically through
:func:`fpp_graph.atomic.atomic_open`. Open3D, MeshLab and CloudCompare read them."""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_open
from fpp_graph.errors import InputDataError, OutputError


def _color_bytes(colors: NDArray | None, n: int, what: str) -> NDArray[np.uint8]:
    if colors is None:
        return np.full((n, 3), 128, dtype=np.uint8)
    c = np.asarray(colors)
    if c.shape != (n, 3):
        raise InputDataError(f"{what}: colors shape {c.shape} does not match {n} x 3")
    if c.dtype == np.uint8:
        return c
    return (np.clip(np.nan_to_num(c.astype(np.float64)), 0.0, 1.0) * 255.0).round().astype(np.uint8)


# a vertex as both files store it: position as double (an exact round trip), colour as uchar
_VERTEX_RECORD = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_VERTEX_PROPERTIES = (
    "property double x\nproperty double y\nproperty double z\n"
    "property uchar red\nproperty uchar green\nproperty uchar blue\n"
)


def _vertex_records(points: NDArray[np.float64], colors: NDArray | None, what: str) -> NDArray:
    """``points`` (N, 3) and their colours as :data:`_VERTEX_RECORD` rows."""
    data = np.empty(len(points), dtype=_VERTEX_RECORD)
    data["x"], data["y"], data["z"] = points[:, 0], points[:, 1], points[:, 2]
    rgb = _color_bytes(colors, len(points), what)
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    return data


def write_point_cloud_ply(
    path: str | os.PathLike[str], points: NDArray[np.float64], colors: NDArray | None = None
) -> None:
    """Write a coloured point cloud as binary little-endian PLY, atomically.

    Points are stored as ``double`` (exact round trip); colours as ``uchar`` red/green/blue
    (floats in [0, 1] are rounded to 1/255; uint8 colours are kept as they are).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputDataError(f"point cloud for {path}: points must be N x 3, got {pts.shape}")
    data = _vertex_records(pts, colors, f"point cloud for {path}")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment fpp-graph map, metres, world frame\n"
        f"element vertex {len(pts)}\n{_VERTEX_PROPERTIES}end_header\n"
    )
    _write_ply(path, header, [data.tobytes()])


def write_mesh_ply(
    path: str | os.PathLike[str],
    vertices: NDArray[np.float64],
    triangles: NDArray[np.integer],
    colors: NDArray | None = None,
) -> None:
    """Write a triangle mesh as binary little-endian PLY, atomically (vertices as ``double``)."""
    verts = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(triangles)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise InputDataError(f"mesh for {path}: vertices must be V x 3, got {verts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise InputDataError(f"mesh for {path}: triangles must be F x 3, got {tris.shape}")
    if tris.size and (tris.min() < 0 or tris.max() >= len(verts)):
        raise InputDataError(f"mesh for {path}: triangle indices out of range 0..{len(verts) - 1}")
    vdata = _vertex_records(verts, colors, f"mesh for {path}")
    frec = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    fdata = np.empty(len(tris), dtype=frec)
    fdata["n"] = 3
    fdata["i"] = tris.astype(np.int32)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment fpp-graph TSDF mesh, metres, world frame\n"
        f"element vertex {len(verts)}\n{_VERTEX_PROPERTIES}"
        f"element face {len(tris)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    _write_ply(path, header, [vdata.tobytes(), fdata.tobytes()])


def _write_ply(path: str | os.PathLike[str], header: str, blocks: list[bytes]) -> None:
    try:
        with atomic_open(path, "wb") as handle:
            handle.write(header.encode("ascii"))
            for block in blocks:
                handle.write(block)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror}; check the folder and free space") from exc
