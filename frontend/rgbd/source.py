"""A depth-image front-end: RGB-D sequences (7-Scenes and TUM RGB-D layouts) as Frames.

It shows the back-end working under a non-FPP sensor: depth images become organised xyz maps,
the colour image becomes the texture, and the same 2D-keypoint + RANSAC + ICP registration of
:mod:`frontend.registration` produces the constraints. Depth cameras are noisier than FPP by an
order of magnitude and more: the registration reads the Kinect's noise model
(:data:`KINECT_V1_NOISE`), and its thresholds, multiples of that noise, follow.

Layouts
-------
7-Scenes: ``frame-XXXXXX.color.png`` (or ``.color.jpg``), ``frame-XXXXXX.depth.png`` (uint16 millimetres, 0 and
65535 invalid), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world = ``T_world_sensor``, metres),
optional ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240). Colour and
depth are not registered to each other in 7-Scenes (two cameras of a Kinect v1, different focal
lengths, about 2.5 cm apart): the colour image is resampled onto the depth grid through the
colour camera model :data:`KINECT_V1_COLOR_K` / :data:`KINECT_V1_T_COLOR_DEPTH` (optional
``color-intrinsics.txt``, 3x3, overrides the former), so a keypoint found in the texture lifts to
the depth pixel that saw the same surface point. Pasting the colour pixel-for-pixel onto the
depth grid instead puts image corners ~30 px (~10 cm at 2 m) away from their depth.

TUM RGB-D: ``rgb.txt`` and ``depth.txt`` (``timestamp path`` lines; colour and depth are
associated by nearest timestamp within 20 ms, as the benchmark's tools do), depth uint16 with
factor 5000 per metre, optional ``groundtruth.txt`` (TUM trajectory at 100 Hz, interpolated to
each frame's time: slerp in rotation, linear in position), optional ``intrinsics.txt`` (``fx fy
cx cy [k1 k2 p1 p2 k3]``). TUM depth is registered to the colour image, so both share the colour
camera's model: without ``intrinsics.txt`` it is the benchmark's published calibration of the
camera named in ``rgb.txt``'s header or the folder name (freiburg1/2/3, :data:`TUM_CAMERAS`,
with lens distortion), else the ROS default 525, 525, 319.5, 239.5 with a warning. Depth
pixels are lifted along the undistorted rays of that model.

Configuration
-------------
The registration's length thresholds are multiples of ``registration.noise``
(:mod:`frontend.config`); :meth:`RgbdSource.resolve_config` fills the noise values a config leaves
null with :data:`KINECT_V1_NOISE` (a user's own noise values win) and raises the fusion voxels to
:data:`RGBD_FUSION_FLOORS` (a scene-scale matter, not noise: a 1 mm TSDF over a 3 m room is ~10^10
voxels) and the dense refinement's pixel stride to :data:`RGBD_DENSE_STRIDE_FLOOR_PX` (the
depth's correlation window). Where the config leaves them null it also sets the fusion's depth range
(``fusion.max_depth_m``: where :data:`KINECT_DEPTH_SIGMA_PER_M2` reaches the TSDF truncation) and
turns on tracking from motion (``keyframes.track_from_motion``: 30 Hz frames move a few millimetres
apart). The pipeline runs on the resolved config and writes it to the results folder.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fpp_graph.config import Config, refuse_reference_time_offset
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import masked_pixels
from fpp_graph.trajectory import Trajectory, read_tum
from fpp_graph.types import Frame, grey_colors
from frontend.config import SensorNoise

log = logging.getLogger(__name__)

KINECT_V1_NOISE = SensorNoise(point_sigma_m=0.0075, voxel_m=0.01, information_correlation=3e-4, shared_depth_sigma_per_m2=1.4e-3, readout_s=1.0 / 30.0)
"""The Kinect v1 depth camera's noise model (see ``registration.noise``).

- ``point_sigma_m``: its random depth error is ~1.4e-3 z^2 m (Khoshelham and Elberink, Sensors
  2012), 7.5 mm at z = 2.3 m, the far half of an indoor scene; a keypoint's pixel error adds
  ~3.5 mm per pixel at 2 m, inside that.
- ``voxel_m``: 1 cm holds ~3 x 3 depth pixels at 2 m, above the noise, so a voxel's normal is the
  surface's; finer voxels give ICP the speckle's noise as normals.
- ``information_correlation``: ICP's information assumes independent residuals; Kinect depth errors
  are correlated over the image (quantisation steps, structured-light speckle, low-frequency depth
  distortion), so its raw information is ~10^3-10^4 times too confident and the robust back-end
  rejected every true loop as inconsistent with odometry. The keypoint and dense parts are not
  scaled by it; ``shared_depth_sigma_per_m2`` bounds the whole pair instead (the depth error a
  view shares). ``scripts/rgbd_nees.py`` on 8 pairs of the 7-Scenes chess frames now gives mean
  NEES / 6 of 0.22 (median 0.09: conservative); the TUM fr1_rpy edges are over-confident (issue 22).
- ``readout_s``: both its cameras are rolling shutters that read their rows over the frame period
  (1/30 s); frames record it (``metadata["readout_s"]``) and the keyframe manager widens the
  constraints of a moving camera by its motion over it (:func:`fpp_graph.slam.motion.with_readout_motion`).
"""
KINECT_DEPTH_SIGMA_PER_M2 = 1.425e-3
"""A Kinect v1 depth's random error over the square of its range (1/m): ``sigma = 1.425e-3 z^2``
(Khoshelham and Elberink, Sensors 2012; the simulator's :class:`~frontend.sim.rgbd.KinectModel`
reproduces it). Sets how far its depth is fused (:meth:`RgbdSource.resolve_config`)."""

RGBD_FUSION_FLOORS = {
    "voxel_size_m": 0.01,
    "tsdf_voxel_m": 0.01,
    "tsdf_truncation_m": 0.04,
}
# The Kinect v1 computes disparity over a 9 x 9 pixel correlation window, so neighbouring depth
# pixels share most of their error: the dense refinement samples every 4th pixel (half the
# window; its coarse iterations every 8th), where FPP's finer-grained errors want every 2nd.
# Pixels in between add cost, not information (with the ICP stop: chess ATE 6.8 -> 5.6 mm,
# TUM fr1_rpy 29.3 -> 29.2 mm).
RGBD_DENSE_STRIDE_FLOOR_PX = 4
# Kinect v1 colour camera (the ROS/OpenNI defaults) and its offset from the depth camera: the
# colour camera sits ~2.5 cm along +x of the depth (IR) camera.
KINECT_V1_COLOR_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
KINECT_V1_T_COLOR_DEPTH = np.array([[1.0, 0, 0, -0.025], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])
# The TUM RGB-D benchmark's published colour-camera calibrations (fx, fy, cx, cy, OpenCV k1 k2 p1
# p2 k3), https://vision.in.tum.de/data/datasets/rgbd-dataset/file_formats; freiburg3's images
# are undistorted already.
TUM_CAMERAS = {
    "freiburg1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
# the TUM RGB-D benchmark's association bound (associate.py --max_difference): colour and depth
# run at 30 Hz each, so a pair further apart than 20 ms is a dropped image's neighbour
TUM_MAX_ASSOCIATION_S = 0.02
ROS_DEFAULT_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
# 7-Scenes is distributed with PNG colour and, in common re-packagings, JPEG colour
_SEVEN_SCENES = re.compile(r"frame-(\d+)\.color\.(?:png|jpe?g)$", re.IGNORECASE)


def pixel_rays(K: np.ndarray, shape: tuple[int, int], distortion: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 2) normalised image coordinates (x/z, y/z) of every pixel centre: ``K^-1 [u v 1]``
    with the lens ``distortion`` (OpenCV k1 k2 p1 p2 k3) undone when given."""
    h, w = shape
    if distortion is None or not np.any(distortion):
        u = np.arange(w, dtype=np.float64)
        v = np.arange(h, dtype=np.float64)[:, None]
        rays = np.empty((h, w, 2))
        rays[..., 0] = (u - K[0, 2]) / K[0, 0]
        rays[..., 1] = (v - K[1, 2]) / K[1, 1]
        return rays
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), axis=-1)
    # iterated to convergence: the default 5 iterations leave ~0.1 px in the image corners
    # under freiburg1's strong k1..k3
    undistorted = cv2.undistortPoints(grid.reshape(-1, 1, 2), K, np.asarray(distortion, np.float64), None, None, None,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))
    return undistorted.reshape(h, w, 2)


def depth_to_xyz_map(depth_m: np.ndarray, K: np.ndarray, rays: np.ndarray | None = None) -> np.ndarray:
    """Organised points (H, W, 3) in metres, camera frame, NaN where depth is invalid (<= 0).

    ``rays`` (from :func:`pixel_rays`, e.g. with lens distortion) replaces the pinhole ``K``."""
    if rays is None:
        rays = pixel_rays(K, depth_m.shape)
    z = np.where(depth_m > 0, depth_m, np.nan).astype(np.float64)
    xyz = np.empty((*depth_m.shape, 3))
    xyz[..., 0] = rays[..., 0] * z
    xyz[..., 1] = rays[..., 1] * z
    xyz[..., 2] = z
    return xyz


def register_color_to_depth(color: np.ndarray, xyz_map: np.ndarray, K_color: np.ndarray, T_color_depth: np.ndarray) -> np.ndarray:
    """Resample ``color`` onto the depth grid: each depth pixel takes the colour where its 3D point
    projects in the colour camera (bilinear; 0 where it projects outside or has no depth).

    Occlusion between the two viewpoints (a few cm apart) is ignored.
    """
    p = xyz_map @ T_color_depth[:3, :3].T + T_color_depth[:3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        map_u = (K_color[0, 0] * p[..., 0] / p[..., 2] + K_color[0, 2]).astype(np.float32)
        map_v = (K_color[1, 1] * p[..., 1] / p[..., 2] + K_color[1, 2]).astype(np.float32)
    bad = ~(np.isfinite(map_u) & np.isfinite(map_v))
    map_u[bad] = -1.0
    map_v[bad] = -1.0
    return cv2.remap(color, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def associate_timestamps(first_s: list[float], second_s: list[float], max_difference_s: float) -> list[tuple[int, int]]:
    """One-to-one pairs ``(i, j)`` of ``first_s[i]`` and ``second_s[j]`` within ``max_difference_s``,
    in the order of ``first_s``: the closest pairs first, each timestamp used once, as the TUM RGB-D
    benchmark's ``associate.py`` does (a dropped depth image leaves its colour image alone instead of
    lending it the neighbour's depth, taken up to a frame period earlier or later)."""
    a, b = np.asarray(first_s, dtype=np.float64), np.asarray(second_s, dtype=np.float64)
    if not len(a) or not len(b):
        return []
    # candidates: each first timestamp against its neighbours in the sorted second list (the
    # nearest on either side holds every pair within the bound when max_difference_s is below the
    # streams' periods; two on each side cover jittered streams)
    order = np.argsort(b, kind="stable")
    at = np.searchsorted(b[order], a)
    candidates = []
    for i, k in enumerate(at):
        for m in range(max(k - 2, 0), min(k + 2, len(b))):
            j = int(order[m])
            d = abs(a[i] - b[j])
            if d <= max_difference_s:
                candidates.append((d, i, j))
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in sorted(candidates):
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def interpolate_pose(trajectory: Trajectory, t: float, max_gap_s: float) -> np.ndarray | None:
    """``T_world_sensor`` of ``trajectory`` at time ``t``: slerp in rotation and linear in position
    between the two samples around ``t`` (a motion-capture stream at 100 Hz: the nearest sample
    can be 5 ms off, 2-3 mm and 0.25 deg at hand-held speeds). None outside the trajectory or
    across a gap longer than ``max_gap_s``."""
    from scipy.spatial.transform import Rotation, Slerp

    times = trajectory.timestamps_s
    k = int(np.searchsorted(times, t))
    if k < len(times) and times[k] == t:
        return trajectory.poses_world_sensor[k]
    if k == 0 or k == len(times) or times[k] - times[k - 1] > max_gap_s:
        return None
    poses = trajectory.poses_world_sensor[k - 1:k + 1]
    a = (t - times[k - 1]) / (times[k] - times[k - 1])
    T = np.eye(4)
    T[:3, :3] = Slerp(times[k - 1:k + 1], Rotation.from_matrix(poses[:, :3, :3]))([t]).as_matrix()[0]
    T[:3, 3] = (1 - a) * poses[0, :3, 3] + a * poses[1, :3, 3]
    return T


@dataclass
class _Entry:
    frame_id: int
    timestamp: float
    color: Path
    depth: Path
    T_world_sensor: np.ndarray | None


class RgbdSource:
    """:class:`fpp_graph.slam.sources.FrameSource` for 7-Scenes and TUM RGB-D folders."""

    name = "rgbd"

    def __init__(self, path: Path, config: Config) -> None:
        self.path = Path(path)
        self.config = config
        self.K_color: np.ndarray | None = None  # None: colour already on the depth grid
        self.distortion: np.ndarray | None = None  # lens distortion of the depth grid's camera
        self._rays: np.ndarray | None = None  # pixel_rays of the depth grid, computed on first use
        self._preparer = None  # the registrar whose per-frame work load_frame does (made on first use)
        self.T_color_depth = KINECT_V1_T_COLOR_DEPTH
        # TUM: colour and depth images the one-to-one association left alone (7-Scenes pairs by name)
        self.unassociated = {"color": 0, "depth": 0}
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
        self.config = self.resolve_config(config)

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
        self.K_color = KINECT_V1_COLOR_K
        cfile = self.path / "color-intrinsics.txt"
        if cfile.exists():
            try:
                self.K_color = np.loadtxt(cfile).reshape(3, 3)
            except ValueError as exc:
                raise InputDataError(f"{cfile}: expected a 3x3 matrix ({exc})") from None
        refuse_reference_time_offset(self.config, f"the 7-Scenes folder {self.path}")
        entries = []
        for p in sorted(self.path.iterdir()):
            m = _SEVEN_SCENES.search(p.name)
            if not m:
                continue
            stem = p.name[: m.start() + len(f"frame-{m.group(1)}")]
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
        K, self.distortion = self._tum_camera()
        gt = read_tum(self.path / "groundtruth.txt") if (self.path / "groundtruth.txt").exists() else None
        offset_s = self.config.evaluation.reference_time_offset_s
        pairs = associate_timestamps([t for t, _ in rgb], [t for t, _ in depth], TUM_MAX_ASSOCIATION_S)
        self.unassociated = {"color": len(rgb) - len(pairs), "depth": len(depth) - len(pairs)}
        if self.unassociated["color"]:
            paired = {i for i, _ in pairs}
            alone = [f"{rgb[i][0]:.6f}" for i in range(len(rgb)) if i not in paired]
            log.warning("%s: %d of %d colour images have no depth image within %.0f ms of their own and are left out "
                        "(timestamps %s%s)", self.path, len(alone), len(rgb), 1e3 * TUM_MAX_ASSOCIATION_S,
                        ", ".join(alone[:5]), ", ..." if len(alone) > 5 else "")
        entries = []
        for i, j in pairs:
            t = rgb[i][0]
            T = None if gt is None else interpolate_pose(gt, t + offset_s, max_gap_s=0.05)
            entries.append(_Entry(len(entries), t, self.path / rgb[i][1], self.path / depth[j][1], T))
        return entries, K, 5000.0

    def _tum_camera(self) -> tuple[np.ndarray, np.ndarray | None]:
        """K and lens distortion of a TUM folder: intrinsics.txt, else the published calibration
        of the camera its rgb.txt header or its name mentions, else the ROS default."""
        kfile = self.path / "intrinsics.txt"
        if kfile.exists():
            try:
                values = np.loadtxt(kfile).reshape(-1)
            except ValueError as exc:
                raise InputDataError(f"{kfile}: expected 'fx fy cx cy [k1 k2 p1 p2 k3]' ({exc})") from None
            if len(values) not in (4, 8, 9):
                raise InputDataError(f"{kfile}: expected 'fx fy cx cy [k1 k2 p1 p2 k3]', got {len(values)} numbers")
            fx, fy, cx, cy = values[:4]
            return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), (values[4:] if len(values) > 4 else None)
        header = "\n".join(line for line in (self.path / "rgb.txt").read_text().splitlines()[:5] if line.startswith("#"))
        for name, ((fx, fy, cx, cy), distortion) in TUM_CAMERAS.items():
            if name in header or name in self.path.name or name.replace("freiburg", "fr") in self.path.name:
                log.info("%s: %s camera, the benchmark's published intrinsics and distortion", self.path, name)
                return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), np.array(distortion)
        log.warning("%s: camera not named (freiburg1/2/3) and no intrinsics.txt; using the ROS default "
                    "intrinsics 525/525/319.5/239.5 without distortion: add intrinsics.txt for accurate depth", self.path)
        return ROS_DEFAULT_K.copy(), None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_preparer"] = None  # its caches stay in the process that made it
        return state

    # -- FrameSource -----------------------------------------------------------------------
    def frame_ids(self) -> list[int]:
        return [e.frame_id for e in self.entries]

    def load_frame(self, frame_id: int) -> Frame:
        from frontend.features.detect import detect_and_describe

        e = self._by_id[frame_id]
        depth = cv2.imread(str(e.depth), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.ndim != 2 or depth.dtype != np.uint16:
            raise InputDataError(f"{e.depth}: missing, corrupt or not a 16-bit depth image")
        color = cv2.imread(str(e.color), cv2.IMREAD_GRAYSCALE)
        if color is None:
            raise InputDataError(f"{e.color}: missing or corrupt colour image")
        depth_m = depth.astype(np.float64) / self.depth_per_m
        depth_m[depth == 65535] = 0.0
        if self._rays is None or self._rays.shape[:2] != depth_m.shape:
            self._rays = pixel_rays(self.K, depth_m.shape, self.distortion)
        xyz = depth_to_xyz_map(depth_m, self.K, self._rays)
        valid = np.isfinite(xyz[..., 2])
        if not valid.any():
            raise InputDataError(f"{e.depth}: no valid depth")
        if self.K_color is not None:
            color = register_color_to_depth(color, xyz, self.K_color, self.T_color_depth)
        elif color.shape != depth.shape:
            raise InputDataError(
                f"{e.color}: colour {color.shape[1]}x{color.shape[0]} but depth {depth.shape[1]}x{depth.shape[0]}; "
                "TUM RGB-D colour must be registered to depth (same size)"
            )
        frame = Frame(
            id=e.frame_id,
            timestamp=e.timestamp,
            points=masked_pixels(xyz, valid),
            colors=grey_colors(color[valid] / 255.0),
            xyz_map=xyz,
            texture=color,
            metadata={"K": self.K.tolist(), "sensor": "rgbd", "readout_s": self.config.registration.sensor_noise().readout_s,
                      **({"distortion": self.distortion.tolist()} if self.distortion is not None else {})},
        )
        # the registrar's per-frame work that every pair of this frame needs (its dense surface),
        # done here once, on a decode worker, and handed on with the frame
        if self._preparer is None:
            self._preparer = self.make_registrar()
        frame = self._preparer.prepare(frame)
        if self.config.keyframes.track_from_motion:
            # tracked frames follow their keyframe's keypoints and need none of their own; the
            # keyframe manager has keyframes described (FrameDescriber): SURF on a 640x480
            # frame costs about as much as tracking it
            return frame
        return detect_and_describe(frame, self.config.registration)

    @staticmethod
    def resolve_config(config: Config) -> Config:
        """``config`` with the Kinect's noise model where ``registration.noise`` is left null, the
        RGB-D floors on fusion voxels and on the dense refinement's pixel stride, and the fusion's
        depth range, tracking from motion and keyframes-only frame storage (``run.keep_frames``)
        unless the config sets them (idempotent)."""
        reg = config.registration.with_noise(KINECT_V1_NOISE)
        dense = reg.dense
        stride = max(dense.stride_px, RGBD_DENSE_STRIDE_FLOOR_PX)
        reg = reg.model_copy(update={"dense": dense.model_copy(update={"stride_px": stride, "coarse_stride_px": max(dense.coarse_stride_px, 2 * stride)})})
        fus = config.fusion
        fus = fus.model_copy(update={k: max(getattr(fus, k), v) for k, v in RGBD_FUSION_FLOORS.items()})
        if fus.max_depth_m is None:
            # beyond the range where the depth error reaches the TSDF's truncation band a
            # surface's points scatter over more than the band (5.3 m with the 4 cm floor)
            fus = fus.model_copy(update={"max_depth_m": math.sqrt(fus.tsdf_truncation_m / KINECT_DEPTH_SIGMA_PER_M2)})
        keyframes = config.keyframes
        if keyframes.track_from_motion is None:  # 30 Hz video: the previous motion predicts the next
            keyframes = keyframes.model_copy(update={"track_from_motion": True})
        run = config.run
        if run.keep_frames is None:
            # a 640x480 frame is 4.4 MB in the results folder and 30-60 ms to decode again: 30 Hz
            # video keeps its keyframes (2000 frames of which 496 keyframes: 8.7 -> 2.2 GB)
            run = run.model_copy(update={"keep_frames": "keyframes"})
        return config.model_copy(update={"registration": reg, "fusion": fus, "keyframes": keyframes, "run": run})

    def make_registrar(self):
        from frontend.registration import FppPairRegistrar

        return FppPairRegistrar(self.config.registration, seed=self.config.run.seed)

    def ground_truth(self) -> Trajectory | None:
        """The reference poses of the frames that have one (None when none has): a motion capture
        that starts after the camera or drops out (TUM's ``groundtruth.txt``) leaves the frames it
        does not cover out of the evaluation, said in a warning, instead of the whole reference."""
        covered = [e for e in self.entries if e.T_world_sensor is not None]
        if not covered:
            return None
        if len(covered) < len(self.entries):
            log.warning("%s: the reference poses cover %d of %d frames; the other %d are left out of the evaluation",
                        self.path, len(covered), len(self.entries), len(self.entries) - len(covered))
        return Trajectory.from_poses([e.timestamp for e in covered], [e.T_world_sensor for e in covered])

    def ground_truth_mesh(self) -> Path | None:
        return None

    def describe(self) -> dict[str, Any]:
        return {"sensor": "rgbd", "layout": self.layout, "frames": len(self.entries), "K": self.K.tolist(),
                "distortion": None if self.distortion is None else self.distortion.tolist(),
                "unassociated_images": dict(self.unassociated),
                "frames_with_reference": sum(e.T_world_sensor is not None for e in self.entries),
                "reference_time_offset_s": self.config.evaluation.reference_time_offset_s}
