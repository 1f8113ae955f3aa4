"""Small synthetic FPP-like frames for registration tests and benchmarks (no fringe decoding).

The full virtual sensor (:mod:`frontend.sim`) renders fringe images that are decoded into
frames; that is the path accuracy figures of the whole front-end come from. Registration tests
need something smaller and independent of the decoder: a textured surface ray-cast straight into
an ``xyz_map`` + ``texture`` :class:`~fpp_graph.types.Frame`, with Gaussian depth noise along the
ray. This module does that with Open3D's ``RaycastingScene``.

Scenes (world frame, metres, the surface faces -z towards a sensor at z < 0.5):

* :func:`bumpy_wall_scene`: a wall at z = 0.5 m with Gaussian bumps and boxes (well-conditioned
  geometry), solid procedural albedo (fractal value noise sharpened into blobs);
* ``flat=True``: the same wall without relief (one plane, geometrically degenerate);
* ``texture_period_m``: the albedo repeats along x with that period, so two places one period
  apart look alike (and, on a flat wall, are indistinguishable).

Sensor frame = camera frame: x right, y down, z forward; pixel ``(u, v)`` centred at ``(u, v)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy import ndimage

from fpp_graph.types import CameraModel, Frame


def camera_matrix(width: int, height: int, focal_px: float | None = None) -> NDArray[np.float64]:
    """Pinhole K of the paper-like camera (2048 px focal at 1920 wide), scaled to ``width``."""
    f = focal_px if focal_px is not None else 2048.0 * width / 1920.0
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass
class ProceduralAlbedo:
    """Solid 3D albedo: sum of value-noise octaves (trilinear on a random lattice), sharpened.

    ``period_x_m`` makes the pattern periodic along world x (look-alike places).
    """

    seed: int = 0
    cell_m: tuple[float, ...] = (0.005, 0.012, 0.03)
    period_x_m: float | None = None
    lattice: int = 64

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self._grids = [rng.random((self.lattice,) * 3).astype(np.float32) for _ in self.cell_m]
        self._offsets = [rng.random(3) * self.lattice for _ in self.cell_m]

    def __call__(self, points_world: NDArray) -> NDArray[np.float64]:
        p = np.asarray(points_world, dtype=np.float64)
        total = np.zeros(p.shape[0])
        weights = (0.25, 0.4, 0.35)
        for grid, off, cell, w in zip(self._grids, self._offsets, self.cell_m, weights, strict=False):
            scale = np.full(3, 1.0 / cell)
            if self.period_x_m is not None:
                # an integer number of lattice wraps per period keeps the pattern periodic in x
                scale[0] = self.lattice * max(1, round(self.period_x_m / (cell * self.lattice))) / self.period_x_m
            coords = (p * scale + off).T
            total += w * ndimage.map_coordinates(grid, coords, order=1, mode="grid-wrap")
        return 0.5 + 0.45 * np.tanh(3.0 * (total - 0.5))


@dataclass
class SyntheticScene:
    """A triangle mesh in the world frame plus its albedo function."""

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]
    albedo: ProceduralAlbedo

    def __post_init__(self) -> None:
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)), o3d.core.Tensor(self.triangles.astype(np.uint32))
        )

    def cast(self, origins: NDArray, directions: NDArray) -> tuple[NDArray, NDArray]:
        """Distance along each (unit) ray and the unit normal at the hit (inf / NaN on a miss)."""
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        ans = self._scene.cast_rays(o3d.core.Tensor(rays))
        return ans["t_hit"].numpy().astype(np.float64), ans["primitive_normals"].numpy().astype(np.float64)


def bumpy_wall_scene(
    seed: int = 0,
    flat: bool = False,
    size_m: tuple[float, float] = (2.4, 1.2),
    texture_period_m: float | None = None,
    resolution_m: float = 0.004,
) -> SyntheticScene:
    """A wall at z = 0.5 m (facing -z) with bumps and boxes unless ``flat``; see module doc."""
    rng = np.random.default_rng(seed + 1000)
    nx = int(size_m[0] / resolution_m) + 1
    ny = int(size_m[1] / resolution_m) + 1
    xs = np.linspace(-size_m[0] / 2, size_m[0] / 2, nx)
    ys = np.linspace(-size_m[1] / 2, size_m[1] / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    Z = np.full_like(X, 0.5)
    if not flat:
        n_bumps = int(40 * size_m[0] * size_m[1])
        for _ in range(n_bumps):
            cx, cy = rng.uniform(-size_m[0] / 2, size_m[0] / 2), rng.uniform(-size_m[1] / 2, size_m[1] / 2)
            sigma = rng.uniform(0.02, 0.08)
            amp = rng.uniform(-0.03, 0.03)
            Z += amp * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * sigma**2))
    vertices = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    triangles = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    parts_v, parts_t = [vertices], [triangles]
    if not flat:
        offset = vertices.shape[0]
        for _ in range(int(8 * size_m[0] * size_m[1])):
            w, h, depth = rng.uniform(0.03, 0.12, size=3)
            cx, cy = rng.uniform(-size_m[0] / 2, size_m[0] / 2), rng.uniform(-size_m[1] / 2, size_m[1] / 2)
            box = o3d.geometry.TriangleMesh.create_box(w, h, depth)
            v = np.asarray(box.vertices) + np.array([cx - w / 2, cy - h / 2, 0.47 - depth / 2])
            t = np.asarray(box.triangles) + offset
            parts_v.append(v)
            parts_t.append(t)
            offset += v.shape[0]
    albedo = ProceduralAlbedo(seed=seed, period_x_m=texture_period_m)
    return SyntheticScene(np.concatenate(parts_v), np.concatenate(parts_t).astype(np.int32), albedo)


def render_frame(
    scene: SyntheticScene,
    T_world_sensor: NDArray,
    width: int = 640,
    height: int = 400,
    K: NDArray | None = None,
    depth_noise_m: float = 5e-5,
    image_noise_grey: float = 1.0,
    frame_id: int = 0,
    seed: int = 0,
    max_range_m: float = 2.0,
    supersampling: int = 2,
    shading: float = 0.3,
) -> Frame:
    """Ray-cast one frame: ``xyz_map`` (sensor frame, noisy along the ray), ``texture``, ``points``.

    The texture is ``albedo * (1 - shading + shading cos(incidence))`` (a light at the camera),
    integrated over each pixel with ``supersampling``^2 rays, as 8-bit grey with Gaussian noise; pixels that miss the scene are NaN / 0. ``T_world_sensor_guess`` is left
    empty; the true pose goes to ``metadata["T_world_sensor_true"]``.
    """
    K = camera_matrix(width, height) if K is None else np.asarray(K, float)
    T = np.asarray(T_world_sensor, float)
    rng = np.random.default_rng([seed, frame_id])
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays_c /= np.linalg.norm(rays_c, axis=1, keepdims=True)
    dirs_w = rays_c @ np.ascontiguousarray(T[:3, :3].T)
    origins = np.broadcast_to(T[:3, 3], dirs_w.shape)
    t_hit, normals_w = scene.cast(np.ascontiguousarray(origins), dirs_w)
    hit = np.isfinite(t_hit) & (t_hit < max_range_m)
    t_noisy = t_hit + rng.normal(0.0, depth_noise_m, t_hit.shape)
    xyz = np.full((width * height, 3), np.nan)
    xyz[hit] = rays_c[hit] * t_noisy[hit, None]
    # the texture is integrated over each pixel (supersampling x supersampling rays): point
    # sampling would alias the albedo and make the two views disagree at sub-pixel level
    ss = max(1, int(supersampling))
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    img = np.zeros(width * height)
    for dv in offs:
        for du in offs:
            r = np.stack([(u + du - K[0, 2]) / K[0, 0], (v + dv - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1).reshape(-1, 3)
            r /= np.linalg.norm(r, axis=1, keepdims=True)
            d_w = r @ np.ascontiguousarray(T[:3, :3].T)
            t_s, n_s = scene.cast(np.ascontiguousarray(origins), d_w)
            h = np.isfinite(t_s) & (t_s < max_range_m)
            p_world = T[:3, 3] + d_w[h] * t_s[h, None]
            cos_inc = np.abs(np.einsum("ij,ij->i", n_s[h], d_w[h]))
            img[h] += 235.0 * scene.albedo(p_world) * (1.0 - shading + shading * cos_inc) / (ss * ss)
    img += rng.normal(0.0, image_noise_grey, img.shape)
    texture = np.clip(np.round(img), 0, 255).astype(np.uint8).reshape(height, width)
    xyz_map = xyz.reshape(height, width, 3)
    return Frame(
        id=frame_id,
        timestamp=float(frame_id),
        points=xyz[hit],
        xyz_map=xyz_map,
        texture=texture,
        camera=CameraModel(K, width, height),
        metadata={"T_world_sensor_true": T.copy(), "K": K.copy()},
    )


def wall_pose(x_m: float, y_m: float = 0.0, yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0, distance_m: float = 0.5) -> NDArray[np.float64]:
    """``T_world_sensor`` of a sensor ``distance_m`` in front of the wall point ``(x, y, 0.5)``, then rotated."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, 3] = [x_m, y_m, 0.5 - distance_m]
    T[:3, :3] = Rotation.from_euler("yxz", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    return T
