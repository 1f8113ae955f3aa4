"""Surface parts of a virtual FPP scene: triangle meshes with a material, primitives, mesh files, the doll.

A :class:`SurfacePart` is a triangle mesh in the world frame (metres) plus a material
(:mod:`frontend.sim.materials`). Primitives (:func:`box`, :func:`quad`, :func:`sphere`,
:func:`cylinder`), mesh files (:func:`load_mesh`, :func:`place_mesh`) and the default turntable
object (:func:`make_doll`) all produce them.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError, InputDataError
from frontend.sim.materials import ImageMaterial, ProceduralMaterial
from frontend.sim.poses import axis_rotation, rotation_z_to


@dataclass(eq=False)
class SurfacePart:
    """A triangle mesh in the world frame (metres) with its material."""

    name: str
    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    material: Any = field(default_factory=ProceduralMaterial)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        if self.vertices.shape[0] == 0 or self.triangles.shape[0] == 0:
            raise InputDataError(f"surface {self.name!r} is empty ({self.vertices.shape[0]} vertices, {self.triangles.shape[0]} triangles)")
        if not np.all(np.isfinite(self.vertices)):
            raise InputDataError(f"surface {self.name!r} has non-finite vertex coordinates")
        if self.triangles.min() < 0 or self.triangles.max() >= self.vertices.shape[0]:
            raise InputDataError(f"surface {self.name!r} has triangle indices outside its {self.vertices.shape[0]} vertices")


# ---------------------------------------------------------------------------------------------
# Primitives
# ---------------------------------------------------------------------------------------------
def _o3d_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[NDArray, NDArray]:
    return np.asarray(mesh.vertices, dtype=np.float64).copy(), np.asarray(mesh.triangles, dtype=np.int64).copy()


def box(name: str, min_xyz: Any, max_xyz: Any, material: Any) -> SurfacePart:
    """Axis-aligned closed box with outward faces."""
    lo, hi = np.asarray(min_xyz, float), np.asarray(max_xyz, float)
    m = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    v, t = _o3d_arrays(m)
    return SurfacePart(name, v + lo, t, material)


def quad(name: str, corner: Any, edge_u: Any, edge_v: Any, material: Any = None, image: NDArray | None = None) -> SurfacePart:
    """A rectangle ``corner + a edge_u + b edge_v`` (a, b in [0, 1]); its front is ``edge_u x edge_v``.

    With ``image``, UV (0,0) is at ``corner`` (image top-left), u along ``edge_u``.
    """
    c, eu, ev = (np.asarray(x, float) for x in (corner, edge_u, edge_v))
    verts = np.array([c, c + eu, c + eu + ev, c + ev])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    if image is not None:
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
        material = ImageMaterial(image.astype(np.float32), uv[tris])
    return SurfacePart(name, verts, tris, material if material is not None else ProceduralMaterial())


def sphere(name: str, centre: Any, radii: Any, material: Any, resolution: int = 40) -> SurfacePart:
    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
    v, t = _o3d_arrays(m)
    return SurfacePart(name, v * np.asarray(radii, float) + np.asarray(centre, float), t, material)


def cylinder(name: str, start: Any, end: Any, radius: float, material: Any, resolution: int = 40, closed: bool = True) -> SurfacePart:
    """A cylinder from ``start`` to ``end`` (capped)."""
    a, b = np.asarray(start, float), np.asarray(end, float)
    length = float(np.linalg.norm(b - a))
    m = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=length, resolution=resolution, split=max(1, int(length / (radius * 0.5))))
    v, t = _o3d_arrays(m)
    z = (b - a) / length
    R = rotation_z_to(z)
    return SurfacePart(name, v @ R.T + (a + b) / 2.0, t, material)


# ---------------------------------------------------------------------------------------------
# Mesh files
# ---------------------------------------------------------------------------------------------
def load_mesh(path: str | os.PathLike[str]) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh file (PLY, OBJ, STL, OFF, GLB...) with Open3D.

    Raises
    ------
    InputDataError
        The file is missing, unreadable, not a mesh, or has no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"mesh file {path} does not exist; give the path to a PLY/OBJ/STL/OFF mesh")
    try:
        with open(path, "rb") as handle:
            handle.read(1)
    except OSError as exc:
        raise InputDataError(f"cannot read mesh {path}: {exc.strerror}") from exc
    mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False, print_progress=False)
    if len(mesh.vertices) == 0 or len(mesh.triangles) == 0:
        raise InputDataError(
            f"mesh {path} has {len(mesh.vertices)} vertices and {len(mesh.triangles)} triangles: it is empty or not a "
            "triangle-mesh format Open3D reads (PLY, OBJ, STL, OFF, GLB); convert it or point to another file"
        )
    v = np.asarray(mesh.vertices)
    if not np.all(np.isfinite(v)):
        raise InputDataError(f"mesh {path} has non-finite vertex coordinates")
    if float(np.ptp(v, axis=0).max()) <= 0:
        raise InputDataError(f"mesh {path} is degenerate: all vertices coincide")
    return mesh


_UP_AXES = {"z": np.eye(3), "y": axis_rotation("x", math.pi / 2), "-y": axis_rotation("x", -math.pi / 2), "x": axis_rotation("y", -math.pi / 2), "-z": axis_rotation("x", math.pi)}


def place_mesh(mesh: o3d.geometry.TriangleMesh, size_m: float, up_axis: str = "z") -> tuple[NDArray, NDArray]:
    """Rotate the mesh's ``up_axis`` to +z, scale its largest extent to ``size_m``, stand it on z = 0.

    Returns vertices (V,3) in metres and triangles (T,3), centred on x = y = 0.
    """
    if up_axis not in _UP_AXES:
        raise ConfigError(f"up_axis {up_axis!r} unknown; use one of {sorted(_UP_AXES)}")
    if not size_m > 0:
        raise ConfigError(f"object size must be positive, got {size_m}")
    v, t = _o3d_arrays(mesh)
    v = v @ _UP_AXES[up_axis].T
    extent = np.ptp(v, axis=0)
    v = v * (size_m / float(extent.max()))
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    return v, t


# ---------------------------------------------------------------------------------------------
# The default doll
# ---------------------------------------------------------------------------------------------
def make_doll(height_m: float = 0.22, seed: int = 7) -> list[SurfacePart]:
    """A procedural textured doll standing on z = 0, centred on the z axis, facing +x.

    Head, hair cap, eyes and nose, body, arms, legs and feet; each part has its own solid texture
    (different base albedo, scale and seed) so 2D keypoints have something to match everywhere.
    """
    s = height_m / 0.22

    def mat(base: float, scale: float, k: int, contrast: float = 0.55) -> ProceduralMaterial:
        return ProceduralMaterial(base=base, contrast=contrast, scale_m=scale * s, seed=seed + k)

    parts = [
        cylinder("leg_left", [0, 0.02 * s, 0.012 * s], [0, 0.02 * s, 0.075 * s], 0.016 * s, mat(0.35, 0.02, 1)),
        cylinder("leg_right", [0, -0.02 * s, 0.012 * s], [0, -0.02 * s, 0.075 * s], 0.016 * s, mat(0.35, 0.02, 1)),
        sphere("foot_left", [0.012 * s, 0.02 * s, 0.012 * s], np.array([0.03, 0.018, 0.012]) * s, mat(0.25, 0.01, 2)),
        sphere("foot_right", [0.012 * s, -0.02 * s, 0.012 * s], np.array([0.03, 0.018, 0.012]) * s, mat(0.25, 0.01, 2)),
        sphere("body", [0, 0, 0.115 * s], np.array([0.035, 0.048, 0.055]) * s, mat(0.6, 0.03, 3, 0.7), resolution=60),
        cylinder("arm_left", [0, 0.045 * s, 0.145 * s], [0.03 * s, 0.075 * s, 0.085 * s], 0.011 * s, mat(0.55, 0.015, 4)),
        cylinder("arm_right", [0, -0.045 * s, 0.145 * s], [0.0, -0.085 * s, 0.09 * s], 0.011 * s, mat(0.55, 0.015, 4)),
        sphere("hand_left", [0.03 * s, 0.075 * s, 0.08 * s], np.full(3, 0.014) * s, mat(0.75, 0.01, 5, 0.3)),
        sphere("hand_right", [0.0, -0.085 * s, 0.085 * s], np.full(3, 0.014) * s, mat(0.75, 0.01, 5, 0.3)),
        sphere("head", [0, 0, 0.19 * s], np.array([0.032, 0.033, 0.035]) * s, mat(0.78, 0.012, 6, 0.3), resolution=60),
        sphere("hair", [-0.006 * s, 0, 0.2 * s], np.array([0.031, 0.035, 0.03]) * s, mat(0.2, 0.008, 7, 0.35)),
        sphere("nose", [0.032 * s, 0, 0.188 * s], np.full(3, 0.006) * s, mat(0.7, 0.01, 8, 0.2)),
        sphere("eye_left", [0.027 * s, 0.012 * s, 0.197 * s], np.full(3, 0.0055) * s, mat(0.1, 0.01, 9, 0.1)),
        sphere("eye_right", [0.027 * s, -0.012 * s, 0.197 * s], np.full(3, 0.0055) * s, mat(0.1, 0.01, 9, 0.1)),
        cylinder("belt", [0, 0, 0.085 * s], [0, 0, 0.095 * s], 0.04 * s, mat(0.15, 0.01, 10, 0.3)),
    ]
    top = max(float(p.vertices[:, 2].max()) for p in parts)
    for p in parts:  # exact requested height
        p.vertices = p.vertices * (height_m / top)
    return parts
