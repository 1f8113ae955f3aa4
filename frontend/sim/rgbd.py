"""A virtual Kinect-class RGB-D camera: depth and grey images of a simulated scene, 30 Hz sequences.

It exists to test the back-end's behaviour on long 30 Hz hand-held sequences (thousands of
frames, revisits) that no real recording here has ground truth for. The noise is the published
behaviour of a structured-light depth camera of the Kinect v1 kind, stated in its own units:

* depth comes from disparity ``d = f b / z`` (``f`` focal length in pixels, ``b`` the
  projector-camera baseline, 7.5 cm); the error is constant in disparity, ``k f b`` with
  ``k = 1.425e-3 /m`` (Khoshelham and Elberink, Sensors 2012, measured ``sigma_z = k z^2``
  on plane fits, quantisation included), so depth error grows with the square of range;
* the disparity comes from a correlation window (9 x 9 pixels): neighbouring pixels share most
  of their error, so the noise is a white field averaged over that window and rescaled to
  ``sigma_d`` (pixel errors correlate, as on the real sensor);
* disparity is quantised to 1/8 pixel (the sensor's sub-pixel resolution), which gives the
  depth steps real Kinect maps show (3 mm at 1 m, 13 mm at 2 m); the random part is what the
  measured total leaves after the quantisation's ``step^2 / 12``;
* no depth outside 0.5-4 m or at grazing incidence (beyond 75 degrees).

The grey image is the scene's albedo under diffuse light (a head-lamp term plus ambient) with
2 grey levels of noise, on the depth camera's grid (TUM RGB-D style, colour registered to
depth). Not modelled: motion blur, rolling shutter, colour-depth time offset, lens distortion.

Sequences are written in the TUM RGB-D layout (``rgb.txt``, ``depth.txt``, depth factor 5000,
``groundtruth.txt``, ``intrinsics.txt``) that :class:`frontend.rgbd.source.RgbdSource` reads.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from fpp_graph.errors import OutputError
from fpp_graph.trajectory import Trajectory, write_tum
from frontend.sim.poses import look_at_pose
from frontend.sim.scenes import CorridorConfig, Scene, build_corridor

log = logging.getLogger(__name__)

DEPTH_PER_M = 5000.0  # TUM RGB-D depth factor


@dataclass(frozen=True)
class KinectModel:
    """Intrinsics and noise of a Kinect v1-class depth camera (defaults: TUM's ROS defaults)."""

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    baseline_m: float = 0.075
    depth_sigma_per_m: float = 1.425e-3  # sigma_z = k z^2 (Khoshelham and Elberink 2012)
    correlation_window_px: int = 9
    disparity_step_px: float = 1.0 / 8.0
    min_depth_m: float = 0.5
    max_depth_m: float = 4.0
    max_incidence_deg: float = 75.0
    grey_noise: float = 2.0

    @property
    def K(self) -> NDArray[np.float64]:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def disparity_sigma_px(self) -> float:
        """The random part of the disparity error: the measured total less the quantisation's."""
        total = self.depth_sigma_per_m * self.fx * self.baseline_m
        return math.sqrt(max(total**2 - self.disparity_step_px**2 / 12.0, 0.0))


class RgbdRenderer:
    """Renders ``(depth_m, grey)`` of a :class:`~frontend.sim.scenes.Scene` from a pose."""

    def __init__(self, scene: Scene, model: KinectModel | None = None) -> None:
        self.model = model or KinectModel()
        m = self.model
        self._parts = list(scene.parts)
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._gid_to_part: dict[int, int] = {}
        for i, part in enumerate(self._parts):
            gid = self._raycaster.add_triangles(o3d.core.Tensor(part.vertices.astype(np.float32)), o3d.core.Tensor(part.triangles.astype(np.uint32)))
            self._gid_to_part[int(gid)] = i
        u, v = np.meshgrid(np.arange(m.width, dtype=np.float64), np.arange(m.height, dtype=np.float64))
        rays = np.stack([(u - m.cx) / m.fx, (v - m.cy) / m.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        self._rays_sensor = rays  # z = 1: the hit distance along a ray is the depth

    def render(self, T_world_sensor: NDArray, rng: np.random.Generator) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
        """Noisy depth (H, W) in metres (0 = no depth) and the grey image (H, W) uint8."""
        m = self.model
        R = np.asarray(T_world_sensor, dtype=np.float64)[:3, :3]
        origin = np.asarray(T_world_sensor, dtype=np.float64)[:3, 3]
        d_world = self._rays_sensor @ R.T
        rays = np.empty((d_world.shape[0], 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = d_world
        ans = self._raycaster.cast_rays(o3d.core.Tensor(rays))
        z = ans["t_hit"].numpy().astype(np.float64)  # rays have unit z, so t is the depth
        hit = np.isfinite(z)
        normals = ans["primitive_normals"].numpy()
        unit = d_world / np.linalg.norm(d_world, axis=1, keepdims=True)
        cos_view = np.abs(np.einsum("ij,ij->i", normals, unit))
        pts_world = origin + z[:, None] * d_world
        albedo = self._albedo(ans, hit, pts_world)
        grey = albedo * (0.45 + 0.55 * cos_view) * 255.0 + rng.normal(0.0, m.grey_noise, z.shape)
        grey = np.clip(np.where(hit, grey, 0.0), 0, 255).round().astype(np.uint8).reshape(m.height, m.width)
        depth = self._noisy_depth(np.where(hit, z, np.inf).reshape(m.height, m.width), rng)
        too_oblique = (cos_view < math.cos(math.radians(m.max_incidence_deg))).reshape(m.height, m.width)
        depth[too_oblique] = 0.0
        return depth, grey

    def _albedo(self, ans: dict, hit: NDArray, pts_world: NDArray) -> NDArray[np.float64]:
        gids = ans["geometry_ids"].numpy()
        tris = ans["primitive_ids"].numpy().astype(np.int64)
        bary = ans["primitive_uvs"].numpy()
        albedo = np.zeros(hit.size)
        for gid in np.unique(gids[hit]):
            sel = np.flatnonzero(hit & (gids == gid))
            part = self._parts[self._gid_to_part[int(gid)]]
            albedo[sel] = part.material.albedo(pts_world[sel], tris[sel], bary[sel])
        return albedo

    def _noisy_depth(self, z_true_m: NDArray, rng: np.random.Generator) -> NDArray[np.float64]:
        """Depth through the disparity: correlated noise, quantisation, range limits."""
        m = self.model
        fb = m.fx * m.baseline_m
        with np.errstate(divide="ignore"):
            disparity = fb / z_true_m  # 0 where nothing was hit
        w = m.correlation_window_px
        white = rng.standard_normal(z_true_m.shape)
        # averaging over the window divides the standard deviation by w; rescale to sigma_d
        correlated = cv2.blur(white, (w, w), borderType=cv2.BORDER_REFLECT) * w
        noisy = disparity + m.disparity_sigma_px * correlated
        quantised = np.round(noisy / m.disparity_step_px) * m.disparity_step_px
        with np.errstate(divide="ignore"):
            depth = np.where(quantised > 0, fb / quantised, 0.0)
        depth[(z_true_m < m.min_depth_m) | (z_true_m > m.max_depth_m) | ~np.isfinite(depth)] = 0.0
        return depth


def handheld_corridor_trajectory(cfg: CorridorConfig, rate_hz: float = 30.0, speed_m_s: float = 0.35,
                                 turn_deg_s: float = 45.0, yaw_to_wall_deg: float = 50.0,
                                 passes: int = 5, seed: int = 0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A hand-held walk along the corridor's centre line at ``rate_hz``: ``(poses, timestamps_s)``.

    Each pass walks the corridor at ``speed_m_s`` with the camera turned ``yaw_to_wall_deg`` from
    the walking direction towards one wall (it sees that wall, the floor and the corridor ahead);
    between passes it turns round on the spot at ``turn_deg_s``. Pass ``p + 2`` walks pass ``p``'s
    path again (revisits). A hand's sway (a few mm and tenths of a degree at 0.5-1.5 Hz) rides on
    top.
    """
    rng = np.random.default_rng(seed)
    x0, x1 = cfg.margin_m, cfg.length_m - cfg.margin_m
    dt = 1.0 / rate_hz
    n_walk = max(2, round((x1 - x0) / speed_m_s * rate_hz))
    n_turn = max(2, round(180.0 / turn_deg_s * rate_hz))
    heading_yaw: list[tuple[float, float]] = []  # (x, yaw of the optical axis in the world)
    look = math.radians(yaw_to_wall_deg)
    for p in range(passes):
        out = p % 2 == 0
        # out passes walk +x and see the +y wall, back passes walk -x and see the -y wall
        yaw = (0.0 if out else math.pi) + look
        xs = np.linspace(x0, x1, n_walk) if out else np.linspace(x1, x0, n_walk)
        heading_yaw += [(float(x), yaw) for x in (xs if p == 0 else xs[1:])]
        if p + 1 < passes:
            # turn round clockwise (seen from above), through the end wall ahead
            heading_yaw += [(float(xs[-1]), yaw - math.pi * k / n_turn) for k in range(1, n_turn + 1)]
    n = len(heading_yaw)
    t = np.arange(n) * dt
    freqs = rng.uniform(0.5, 1.5, size=6)
    phases = rng.uniform(0, 2 * np.pi, size=6)
    sway = np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases[None, :])
    poses = np.empty((n, 4, 4))
    for i, (x, yaw) in enumerate(heading_yaw):
        position = np.array([x, 0.0, cfg.sensor_height_m]) + 0.004 * sway[i, :3]
        pitch = math.radians(-8.0) + math.radians(0.4) * sway[i, 3]
        yaw_i = yaw + math.radians(0.4) * sway[i, 4]
        forward = np.array([math.cos(yaw_i) * math.cos(pitch), math.sin(yaw_i) * math.cos(pitch), math.sin(pitch)])
        poses[i] = look_at_pose(position, position + forward)
    return poses, t


def default_rgbd_corridor() -> CorridorConfig:
    """The corridor for RGB-D: twice as wide as the FPP cart's (2.4 m), so the walls sit in
    the Kinect's range (0.5-4 m) from the centre line, and the walk turns round 1.2 m from the
    end walls."""
    return CorridorConfig(width_m=2.4, wall_distance_m=1.2, margin_m=1.2)


_WORKER: dict = {}


def _init_render_worker(scene: Scene, model: KinectModel) -> None:
    _WORKER["renderer"] = RgbdRenderer(scene, model)


def _render_to_files(index: int, T_world_sensor: NDArray, seed: int, rgb_path: str, depth_path: str) -> None:
    renderer: RgbdRenderer = _WORKER["renderer"]
    depth_m, grey = renderer.render(T_world_sensor, np.random.default_rng([seed, index]))
    depth_u16 = np.clip(np.round(depth_m * DEPTH_PER_M), 0, 65535).astype(np.uint16)
    if not (cv2.imwrite(depth_path, depth_u16) and cv2.imwrite(rgb_path, grey)):
        raise OutputError(f"could not write frame {index} to {Path(rgb_path).parent.parent}: check free disk space")


def write_rgbd_sequence(out: Path, scene: Scene, poses: NDArray, timestamps_s: NDArray, model: KinectModel | None = None,
                        seed: int = 0, workers: int = 0, progress: Callable[[int, int], None] | None = None) -> Path:
    """Render every pose and write a TUM RGB-D folder at ``out`` (built in a sibling temp folder
    and renamed into place, so an interrupted render leaves no half sequence behind)."""
    model = model or KinectModel()
    out = Path(out)
    if out.exists():
        raise OutputError(f"{out} exists; remove it or choose another folder")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "rgb").mkdir(parents=True)
    (tmp / "depth").mkdir()
    # the lists carry 6 decimals: the ground truth gets the same times, or the last frame falls
    # after the trajectory's end by a rounding error and loses its reference pose
    timestamps_s = np.round(np.asarray(timestamps_s, dtype=np.float64), 6)
    names = [f"{t:.6f}.png" for t in timestamps_s]
    workers = workers or os.cpu_count() or 1
    # spawned, not forked: a child forked from a process whose OpenCV thread pool has run holds
    # that pool's state without its threads, and its first cv2.remap waited forever (a test
    # suite hung there after earlier tests had used OpenCV)
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_render_worker,
                             initargs=(scene, model)) as pool:
        futures = [pool.submit(_render_to_files, i, poses[i], seed, str(tmp / "rgb" / name), str(tmp / "depth" / name)) for i, name in enumerate(names)]
        for done, future in enumerate(futures, 1):
            future.result()
            if progress:
                progress(done, len(futures))
    header = "# simulated Kinect-class RGB-D (frontend.sim.rgbd)\n# timestamp filename\n"
    (tmp / "rgb.txt").write_text(header + "".join(f"{t:.6f} rgb/{n}\n" for t, n in zip(timestamps_s, names, strict=True)))
    (tmp / "depth.txt").write_text(header + "".join(f"{t:.6f} depth/{n}\n" for t, n in zip(timestamps_s, names, strict=True)))
    (tmp / "intrinsics.txt").write_text(f"{model.fx} {model.fy} {model.cx} {model.cy}\n")
    write_tum(tmp / "groundtruth.txt", Trajectory.from_poses(list(timestamps_s), list(poses)))
    tmp.rename(out)
    return out


def simulate_rgbd_corridor(out: Path, frames: int | None = 2000, seed: int = 0, workers: int = 0,
                           progress: Callable[[int, int], None] | None = None) -> Path:
    """The default long RGB-D sequence: :func:`handheld_corridor_trajectory` through
    :func:`default_rgbd_corridor` (5 passes, 2021 frames at 30 Hz, 67 s), first ``frames`` only."""
    cfg = default_rgbd_corridor()
    scene, _, _ = build_corridor(cfg)
    poses, t = handheld_corridor_trajectory(cfg, seed=seed)
    if frames is not None:
        poses, t = poses[:frames], t[:frames]
    return write_rgbd_sequence(out, scene, poses, t, seed=seed, workers=workers, progress=progress)
