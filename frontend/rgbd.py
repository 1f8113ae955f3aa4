"""A depth-image front-end: RGB-D sequences (7-Scenes and TUM RGB-D layouts) as Frames.

It shows the back-end working under a non-FPP sensor: depth images become organised xyz maps,
the colour image becomes the texture, and the same 2D-keypoint + RANSAC + ICP registration of
:mod:`frontend.registration` produces the constraints. Depth cameras are noisier than FPP by two
orders of magnitude, so registration thresholds below centimetre floors are raised (see
:data:`RGBD_REGISTRATION_FLOORS`).

Layouts
-------
7-Scenes: ``frame-XXXXXX.color.png``, ``frame-XXXXXX.depth.png`` (uint16 millimetres, 0 and
65535 invalid), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world = ``T_world_sensor``, metres),
optional ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240). Colour and
depth are not registered to each other in 7-Scenes; the colour is resized onto the depth grid.

TUM RGB-D: ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines), depth uint16 with factor
5000 per metre, optional ``groundtruth.txt`` (TUM trajectory), optional ``intrinsics.txt``
(``fx fy cx cy``; default the ROS default 525, 525, 319.5, 239.5).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fpp_graph.config import Config, RegistrationConfig
from fpp_graph.errors import InputDataError
from fpp_graph.trajectory import Trajectory, read_tum
from fpp_graph.types import Frame

log = logging.getLogger(__name__)

RGBD_REGISTRATION_FLOORS = {
    "ransac_threshold_m": 0.03,
    "icp_voxel_m": 0.01,
    "icp_max_correspondence_m": 0.05,
    "max_inlier_rmse_m": 0.03,
    "max_icp_shift_m": 0.05,
    "max_weak_sigma_m": 0.005,
}
_SEVEN_SCENES = re.compile(r"frame-(\d+)\.color\.png$")


def depth_to_xyz_map(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Organised points (H, W, 3) in metres, camera frame, NaN where depth is invalid (<= 0)."""
    h, w = depth_m.shape
    u = np.arange(w, dtype=np.float64)
    v = np.arange(h, dtype=np.float64)[:, None]
    z = np.where(depth_m > 0, depth_m, np.nan).astype(np.float64)
    xyz = np.empty((h, w, 3))
    xyz[..., 0] = (u - K[0, 2]) / K[0, 0] * z
    xyz[..., 1] = (v - K[1, 2]) / K[1, 1] * z
    xyz[..., 2] = z
    return xyz


@dataclass
class _Entry:
    frame_id: int
    timestamp: float
    color: Path
    depth: Path
    T_world_sensor: np.ndarray | None


class RgbdSource:
    """:class:`fpp_graph.sources.FrameSource` for 7-Scenes and TUM RGB-D folders."""

    name = "rgbd"

    def __init__(self, path: Path, config: Config) -> None:
        self.path = Path(path)
        self.config = config
        if (self.path / "rgb.txt").exists() and (self.path / "depth.txt").exists():
            self.layout = "tum"
            self.entries, self.K, self.depth_per_m = self._read_tum()
        elif any(_SEVEN_SCENES.search(p.name) for p in self.path.iterdir()):
            self.layout = "7scenes"
            self.entries, self.K, self.depth_per_m = self._read_7scenes()
        else:
            raise InputDataError(f"{self.path}: neither a 7-Scenes nor a TUM RGB-D folder")
        if not self.entries:
            raise InputDataError(f"{self.path}: no RGB-D frames found")
        self._by_id = {e.frame_id: e for e in self.entries}

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        if not path.is_dir():
            return False
        if (path / "rgb.txt").exists() and (path / "depth.txt").exists():
            return True
        return any(_SEVEN_SCENES.search(p.name) for p in path.iterdir())

    # -- layouts ---------------------------------------------------------------------------
    def _read_7scenes(self):
        K = np.array([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
        kfile = self.path / "camera-intrinsics.txt"
        if kfile.exists():
            try:
                K = np.loadtxt(kfile).reshape(3, 3)
            except ValueError as exc:
                raise InputDataError(f"{kfile}: expected a 3x3 matrix ({exc})") from None
        entries = []
        for p in sorted(self.path.iterdir()):
            m = _SEVEN_SCENES.search(p.name)
            if not m:
                continue
            stem = p.name[: -len(".color.png")]
            index = int(m.group(1))
            pose_file = self.path / f"{stem}.pose.txt"
            T = None
            if pose_file.exists():
                try:
                    T = np.loadtxt(pose_file).reshape(4, 4)
                except ValueError as exc:
                    raise InputDataError(f"{pose_file}: expected a 4x4 matrix ({exc})") from None
            # 7-Scenes is recorded at 30 Hz; the frame index stands in for time
            entries.append(_Entry(index, index / 30.0, p, self.path / f"{stem}.depth.png", T))
        return entries, K, 1000.0

    def _read_tum(self):
        def read_list(name):
            rows = []
            for lineno, line in enumerate((self.path / name).read_text().splitlines(), 1):
                if not line.strip() or line.startswith("#"):
                    continue
                parts = line.split()
                try:
                    rows.append((float(parts[0]), parts[1]))
                except (ValueError, IndexError):
                    raise InputDataError(f"{self.path / name}:{lineno}: expected 'timestamp path'") from None
            return rows

        rgb, depth = read_list("rgb.txt"), read_list("depth.txt")
        if not depth:
            return [], None, 5000.0
        depth_t = np.array([t for t, _ in depth])
        K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
        kfile = self.path / "intrinsics.txt"
        if kfile.exists():
            fx, fy, cx, cy = np.loadtxt(kfile).reshape(-1)[:4]
            K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        gt = read_tum(self.path / "groundtruth.txt") if (self.path / "groundtruth.txt").exists() else None
        entries = []
        for t, rgb_name in rgb:
            j = int(np.argmin(np.abs(depth_t - t)))
            if abs(depth_t[j] - t) > 0.02:
                continue
            T = None
            if gt is not None and len(gt):
                k = int(np.argmin(np.abs(gt.timestamps_s - t)))
                if abs(gt.timestamps_s[k] - t) < 0.02:
                    T = gt.poses_world_sensor[k]
            entries.append(_Entry(len(entries), t, self.path / rgb_name, self.path / depth[j][1], T))
        return entries, K, 5000.0

    # -- FrameSource -----------------------------------------------------------------------
    def frame_ids(self) -> list[int]:
        return [e.frame_id for e in self.entries]

    def load_frame(self, frame_id: int) -> Frame:
        from frontend.features import detect_and_describe

        e = self._by_id[frame_id]
        depth = cv2.imread(str(e.depth), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.ndim != 2 or depth.dtype != np.uint16:
            raise InputDataError(f"{e.depth}: missing, corrupt or not a 16-bit depth image")
        color = cv2.imread(str(e.color), cv2.IMREAD_GRAYSCALE)
        if color is None:
            raise InputDataError(f"{e.color}: missing or corrupt colour image")
        if color.shape != depth.shape:
            color = cv2.resize(color, (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_AREA)
        depth_m = depth.astype(np.float64) / self.depth_per_m
        depth_m[depth == 65535] = 0.0
        xyz = depth_to_xyz_map(depth_m, self.K)
        valid = np.isfinite(xyz[..., 2])
        if not valid.any():
            raise InputDataError(f"{e.depth}: no valid depth")
        frame = Frame(
            id=e.frame_id,
            timestamp=e.timestamp,
            points=xyz[valid],
            colors=np.repeat(color[valid][:, None] / 255.0, 3, axis=1),
            xyz_map=xyz,
            texture=color,
            metadata={"K": self.K.tolist(), "sensor": "rgbd"},
        )
        return detect_and_describe(frame, self.registration_config())

    def registration_config(self) -> RegistrationConfig:
        cfg = self.config.registration
        raised = {k: max(getattr(cfg, k), v) for k, v in RGBD_REGISTRATION_FLOORS.items()}
        return cfg.model_copy(update=raised)

    def make_registrar(self):
        from frontend.registration import FppPairRegistrar

        return FppPairRegistrar(self.registration_config())

    def ground_truth(self) -> Trajectory | None:
        if any(e.T_world_sensor is None for e in self.entries):
            return None
        return Trajectory.from_poses([e.timestamp for e in self.entries], [e.T_world_sensor for e in self.entries])

    def ground_truth_mesh(self) -> Path | None:
        return None

    def describe(self) -> dict[str, Any]:
        return {"sensor": "rgbd", "layout": self.layout, "frames": len(self.entries), "K": self.K.tolist()}
