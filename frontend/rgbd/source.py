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

Checks
------
What cannot be read as a whole is refused when the source opens (:class:`InputDataError`): a
folder holding both layouts, an unreadable list, intrinsics or pose file, impossible intrinsics
(a focal length not finite and positive, a principal point not finite), intrinsics made for
another image size than the sequence's images (judged from the principal point, since neither
layout's intrinsics file states a size: :meth:`RgbdSource._check_camera_fits`), TUM colour of
another size than its depth, a malformed ``groundtruth.txt`` line. What concerns one frame is
that frame's: a missing, unreadable, truncated or corrupt image, or one of another size than the
sequence's, makes :meth:`RgbdSource.load_frame` raise, and the pipeline skips the frame with the
reason; a 7-Scenes frame that lost an image is still counted. A 7-Scenes pose file holding no
rigid pose leaves its frame out of the reference, said and counted in :meth:`RgbdSource.describe`,
which also records where the intrinsics came from (a default is said in a warning).

Configuration
-------------
The registration's length thresholds are multiples of ``registration.noise``
(:mod:`frontend.config`); :meth:`RgbdSource.resolve_config` fills the noise values a config leaves
null with :data:`KINECT_V1_NOISE` (a user's own noise values win; its dense refinement's pixel
stride is the depth's correlation window).
Where the config leaves them null it also sets the fusion voxels to :data:`RGBD_FUSION_VOXELS_M`
(a scene-scale matter, not noise: a 1 mm TSDF over a 3 m room is ~10^10 voxels), the fusion's
depth range (``fusion.max_depth_m``: where :data:`KINECT_DEPTH_SIGMA_PER_M2` reaches the TSDF
truncation band) and turns on tracking from motion (``keyframes.track_from_motion``: 30 Hz frames move a few millimetres
apart). The pipeline runs on the resolved config and writes it to the results folder.
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np

from fpp_graph.config import Config, refuse_reference_time_offset
from fpp_graph.errors import InputDataError
from fpp_graph.fusion.tsdf_mesh import TSDF_TRUNCATION_VOXELS
from fpp_graph.geometry import masked_pixels
from fpp_graph.trajectory import Trajectory, read_tum
from fpp_graph.types import CameraModel, Frame, grey_colors
from frontend.config import SensorNoise

log = logging.getLogger(__name__)

KINECT_V1_NOISE = SensorNoise(
    point_sigma_m=0.0075, voxel_m=0.01, information_correlation=3e-4, shared_depth_sigma_per_m2=1.4e-3, readout_s=1.0 / 30.0, dense_stride_px=4,
)
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
  NEES / 6 of 0.22 (median 0.09: conservative); the TUM fr1_rpy edges are over-confident.
- ``readout_s``: both its cameras are rolling shutters that read their rows over the frame period
  (1/30 s); frames record it (``CameraModel.readout_s``) and the keyframe manager widens the
  constraints of a moving camera by its motion over it (:func:`fpp_graph.slam.motion.with_readout_motion`).
- ``dense_stride_px``: it computes disparity over a 9 x 9 pixel correlation window, so neighbouring
  depth pixels share most of their error: the dense refinement samples every 4th pixel (half the
  window; its coarse iterations every 8th); pixels in between add cost, not information.
"""
KINECT_DEPTH_SIGMA_PER_M2 = 1.425e-3
"""A Kinect v1 depth's random error over the square of its range (1/m): ``sigma = 1.425e-3 z^2``
(Khoshelham and Elberink, Sensors 2012; the simulator's :class:`~frontend.sim.rgbd.KinectModel`
reproduces it). Sets how far its depth is fused (:meth:`RgbdSource.resolve_config`)."""

RGBD_FUSION_VOXELS_M = {"voxel_size_m": 0.01, "tsdf_voxel_m": 0.01}
"""The fusion voxels of a room-scale depth camera (where the configuration leaves them null): the
registration's ICP voxel, a few standard deviations of the Kinect's depth error at 1-2 m."""
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
# 7-Scenes frame files: colour (PNG as distributed, JPEG in common re-packagings), depth, pose
_SEVEN_SCENES_FILE = re.compile(r"^(?P<stem>.*frame-(?P<index>\d+))\.(?P<kind>color\.(?:png|jpe?g)|depth\.png|pose\.txt)$", re.IGNORECASE)
# the dataset's published depth camera (its web page: focal length 585, principal point (320,
# 240), 640x480 images), used when a folder has no camera-intrinsics.txt (the download has none)
SEVEN_SCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
# how far (a fraction of the image's width or height) the principal point may sit from the image
# centre before the intrinsics count as another image size's: RgbdSource._check_camera_fits
PRINCIPAL_POINT_OFF_CENTRE = 0.1
# |R^T R - I| a reference pose's rotation may show: the real 7-Scenes pose files (KinectFusion's
# poses, 8 significant digits) show up to 1.6e-4 (chess frames 150-199); text rounded to 4
# decimals adds ~1e-4. Beyond 1e-3 the matrix scales or shears (a 0.1 % stretch), not rotates.
ROTATION_TOLERANCE = 1e-3
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and its (fixed) CRC


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


def _cannot_read(path: Path, exc: OSError) -> InputDataError:
    """An OSError met reading ``path`` as a one-line error: what, where and what to do."""
    if isinstance(exc, PermissionError):
        todo = "check the file's permissions (the user running fpp-slam must be able to read it)"
    elif isinstance(exc, FileNotFoundError):
        todo = "restore the file"
    else:
        todo = "check the file and the disk it is on"
    return InputDataError(f"cannot read {path}: {exc.strerror or exc}; {todo}")


def _read_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise _cannot_read(path, exc) from None


def _read_text(path: Path) -> str:
    try:
        return _read_bytes(path).decode("utf-8")
    except UnicodeDecodeError:
        raise InputDataError(f"{path}: not a text file (not UTF-8); replace it with the dataset's text file") from None


def _numbers(path: Path, counts: tuple[int, ...], form: str) -> np.ndarray:
    """The whitespace-separated numbers of the text file ``path``, as many as one of ``counts``."""
    try:
        values = np.array(_read_text(path).split(), dtype=np.float64)
    except ValueError as exc:
        raise InputDataError(f"{path}: expected {form} ({exc})") from None
    if values.size not in counts:
        raise InputDataError(f"{path}: expected {form}, got {values.size} numbers; correct the file")
    return values


def _listing(path: Path) -> list[str]:
    """The names in the folder ``path``, sorted."""
    try:
        return sorted(os.listdir(path))
    except NotADirectoryError:
        raise InputDataError(f"{path}: not a folder; an RGB-D sequence is a folder of 7-Scenes or TUM RGB-D files") from None
    except OSError as exc:
        raise InputDataError(f"cannot list the folder {path}: {exc.strerror}; check its permissions (it must be readable and searchable)") from None


def _layout(names: list[str]) -> tuple[bool, list[str]]:
    """Whether the names make a TUM RGB-D folder (rgb.txt and depth.txt), and its 7-Scenes images."""
    images = [n for n in names if (m := _SEVEN_SCENES_FILE.match(n)) and not m["kind"].lower().startswith("pose")]
    return "rgb.txt" in names and "depth.txt" in names, images


def _camera_matrix(K: np.ndarray, where: str) -> np.ndarray:
    """``K`` when it is a pinhole ``[[fx 0 cx] [0 fy cy] [0 0 1]]`` with finite positive focal
    lengths and a finite principal point (where the principal point must lie needs the image
    size: :meth:`RgbdSource._check_camera_fits`); an InputDataError naming ``where`` otherwise."""
    for name, value in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not (np.isfinite(value) and value > 0):
            raise InputDataError(f"{where}: {name} = {value:g} is not a focal length (a finite number of pixels > 0); "
                                 "write the camera's calibration there")
    for name, value in (("cx", K[0, 2]), ("cy", K[1, 2])):
        if not np.isfinite(value):
            raise InputDataError(f"{where}: {name} = {value:g} is not a finite pixel position; write the camera's calibration there")
    # the depth is lifted along K^-1 [u v 1] with no skew term: a skew would be silently dropped
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise InputDataError(f"{where}: expected a camera matrix [[fx 0 cx] [0 fy cy] [0 0 1]], got "
                             f"{' / '.join(' '.join(f'{v:g}' for v in row) for row in K)}; write the camera's calibration there")
    return K


def _image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's or a JPEG's header, without decoding it; None when the file
    cannot be read or is neither (the frame's decoding says why, when it is loaded)."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
            if head.startswith(_PNG_SIGNATURE) and head[12:16] == b"IHDR":
                return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            if head.startswith(b"\xff\xd8"):
                return _jpeg_size(f)
    except OSError:
        pass
    return None


def _jpeg_size(f: BinaryIO) -> tuple[int, int] | None:
    """(width, height) from the frame header (SOFn) of the JPEG open in ``f``."""
    f.seek(2)
    while len(marker := f.read(4)) == 4 and marker[0] == 0xFF:
        kind, length = marker[1], int.from_bytes(marker[2:], "big")
        if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):  # SOF0..15; not DHT, JPG, DAC
            sof = f.read(5)  # precision, height, width
            return (int.from_bytes(sof[3:5], "big"), int.from_bytes(sof[1:3], "big")) if len(sof) == 5 else None
        f.seek(length - 2, os.SEEK_CUR)
    return None


def _truncation(data: bytes) -> str | None:
    """How the bytes of a PNG or a JPEG file show it cut short, or None when they end as the
    format ends. Decoders fill a truncated image's missing rows (libjpeg with grey, after a
    warning of its own on stderr) rather than fail, so the end is checked before decoding."""
    if data.startswith(_PNG_SIGNATURE):
        # IEND (with its fixed CRC) is the last chunk; the 8 bytes inside compressed data by
        # chance: one file in 2^64
        return None if data.rfind(_PNG_END) >= 0 else "it has no IEND chunk"
    if data.startswith(b"\xff\xd8"):
        # the end-of-image marker follows the last scan; entropy-coded data holds neither
        # 0xFF 0xD9 nor 0xFF 0xDA (a data byte 0xFF is followed by 0x00)
        return None if data.rfind(b"\xff\xd9") > data.rfind(b"\xff\xda") else "it has no end-of-image marker after its last scan"
    return None


def _decode(path: Path, flags: int, what: str) -> np.ndarray:
    """The image at ``path`` decoded whole (cv2 ``flags``); an InputDataError saying why not."""
    data = _read_bytes(path)
    if not data:
        raise InputDataError(f"{path}: empty {what} image file; copy it again from the dataset")
    cut = _truncation(data)
    if cut:
        raise InputDataError(f"{path}: truncated {what} image ({len(data)} bytes; {cut}): an interrupted copy or download; "
                             "copy it again from the dataset")
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error:
        image = None
    if image is None:
        raise InputDataError(f"{path}: corrupt or not an image file ({what}); copy it again from the dataset")
    return image


def _check_size(path: Path, image: np.ndarray, size: tuple[int, int], what: str) -> None:
    """A frame's image must have the sequence's size (the one its camera model is checked for)."""
    h, w = image.shape[:2]
    if (w, h) != tuple(size):
        raise InputDataError(f"{path}: {what} image is {w}x{h} but the sequence's {what} images (and their intrinsics) are "
                             f"{size[0]}x{size[1]}; resize it to {size[0]}x{size[1]} to use this frame")


def _rigid_pose_problem(T: np.ndarray) -> str | None:
    """Why the 4x4 ``T`` is not a rigid transform, or None."""
    if not np.isfinite(T).all():
        return "it holds non-finite values (nan or inf)"
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        return f"its last row is {' '.join(f'{v:g}' for v in T[3])}, not 0 0 0 1"
    R = T[:3, :3]
    error = np.abs(R.T @ R - np.eye(3)).max()
    if error > ROTATION_TOLERANCE:
        return f"its rotation is not orthonormal (|R^T R - I| = {error:.1e} > {ROTATION_TOLERANCE:g})"
    if np.linalg.det(R) < 0:
        return "its rotation is a reflection (det R < 0)"
    return None


def _reference_pose(path: Path) -> tuple[np.ndarray | None, str | None]:
    """A 7-Scenes pose file's ``T_world_sensor``, or None and why it is not a rigid pose. A file
    that cannot be read raises: that is the user's to fix (a permission), not the recording's."""
    try:
        values = np.array(_read_text(path).split(), dtype=np.float64)
    except ValueError as exc:
        return None, f"it is not a 4x4 matrix of numbers ({exc})"
    if values.size != 16:
        return None, f"it holds {values.size} numbers, not a 4x4 matrix"
    T = values.reshape(4, 4)
    problem = _rigid_pose_problem(T)
    return (None, problem) if problem else (T, None)


def _listed(items: dict[str, str], limit: int = 5) -> str:
    """``name: reason`` for the first ``limit`` items, '...' after."""
    shown = "; ".join(f"{name}: {why}" for name, why in list(items.items())[:limit])
    return shown + ("; ..." if len(items) > limit else "")


def _seven_scenes_frames(path: Path, names: list[str]) -> list[tuple[int, str, dict[str, str]]]:
    """``(index, stem, {"color"|"depth"|"pose": file name})`` of each 7-Scenes frame that has any
    of its files, by index: a frame that lost an image is still a frame of the sequence."""
    frames: dict[tuple[int, str], dict[str, list[str]]] = {}
    for name in names:
        if m := _SEVEN_SCENES_FILE.match(name):
            frames.setdefault((int(m["index"]), m["stem"]), {}).setdefault(m["kind"].split(".")[0].lower(), []).append(name)
    out: list[tuple[int, str, dict[str, str]]] = []
    for (index, stem), files in sorted(frames.items()):
        if out and out[-1][0] == index:
            raise InputDataError(f"{path}: {out[-1][1]} and {stem} are both frame {index}: keep one sequence per folder")
        if len(files.get("color", [])) > 1:
            raise InputDataError(f"{path}: frame {stem} has {len(files['color'])} colour images ({', '.join(files['color'])}): keep one")
        out.append((index, stem, {part: found[0] for part, found in files.items()}))
    return out


def _colour_suffix(names: list[str]) -> str:
    """The colour images' suffix most of the folder's frames use (``.color.png`` without any)."""
    suffixes = Counter(m[0][len(m["stem"]):] for n in names if (m := _SEVEN_SCENES_FILE.match(n)) and m["kind"].lower().startswith("color"))
    return suffixes.most_common(1)[0][0] if suffixes else ".color.png"


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
        self.intrinsics: dict[str, Any] = {}  # where the depth grid's camera model came from
        self.color_intrinsics: dict[str, Any] | None = None  # 7-Scenes: where the colour camera's came from
        self.incomplete_frames: dict[str, str] = {}  # 7-Scenes frame -> the image it lacks
        self.references_left_out: dict[str, str] = {}  # 7-Scenes pose file -> why it is no rigid pose
        names = _listing(self.path)
        tum, seven_scenes = _layout(names)
        if tum and seven_scenes:
            raise InputDataError(
                f"{self.path}: holds both a TUM RGB-D sequence (rgb.txt, depth.txt) and a 7-Scenes one ({len(seven_scenes)} "
                f"frame images such as {seven_scenes[0]}), and which one to read cannot be told (--kind rgbd reads both "
                "layouts): move one set of files into a folder of its own"
            )
        if tum:
            self.layout = "tum"
            self.entries, self.K, self.depth_per_m = self._read_tum(names)
        elif seven_scenes:
            self.layout = "7scenes"
            self.entries, self.K, self.depth_per_m = self._read_7scenes(names)
        else:
            half = [n for n in ("rgb.txt", "depth.txt") if n in names]
            lacking = f"; it has {half[0]} but no {({'rgb.txt', 'depth.txt'} - set(half)).pop()}" if half else ""
            raise InputDataError(f"{self.path}: neither a 7-Scenes folder (frame-XXXXXX.color.png, .depth.png) nor a TUM RGB-D "
                                 f"folder (rgb.txt and depth.txt){lacking}")
        if not self.entries:
            raise InputDataError(f"{self.path}: no RGB-D frames found")
        self._by_id = {e.frame_id: e for e in self.entries}
        self.depth_size, self.color_size = self._image_sizes()
        self.config = self.resolve_config(config)

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        try:
            names = os.listdir(path) if path.is_dir() else []
        except OSError:  # an unreadable folder is nobody's layout; --kind rgbd says why it cannot be read
            return False
        tum, seven_scenes = _layout(names)
        return tum or bool(seven_scenes)  # both: the constructor refuses the folder as ambiguous

    # -- layouts ---------------------------------------------------------------------------
    def _camera_file(self, names: list[str], name: str, default: np.ndarray, default_name: str) -> tuple[np.ndarray, dict[str, Any]]:
        """The 3x3 camera matrix in the folder's file ``name``, or ``default`` (said, and recorded)."""
        if name in names:
            kfile = self.path / name
            return _camera_matrix(_numbers(kfile, (9,), "a 3x3 camera matrix").reshape(3, 3), str(kfile)), {"source": str(kfile)}
        source = f"default {default_name} (fx=fy={default[0, 0]:g}, cx={default[0, 2]:g}, cy={default[1, 2]:g})"
        return default.copy(), {"source": source}

    def _read_7scenes(self, names: list[str]):
        self.K, self.intrinsics = self._camera_file(names, "camera-intrinsics.txt", SEVEN_SCENES_K, "7-Scenes")
        if "camera-intrinsics.txt" not in names:
            log.warning("%s: no camera-intrinsics.txt; using the 7-Scenes intrinsics fx=fy=585, cx=320, cy=240 (the dataset's "
                        "published depth camera, 640x480): add camera-intrinsics.txt (3x3) for another camera", self.path)
        # the colour camera's model is always the Kinect's unless the folder gives one (7-Scenes has none)
        self.K_color, self.color_intrinsics = self._camera_file(names, "color-intrinsics.txt", KINECT_V1_COLOR_K, "Kinect v1 colour")
        refuse_reference_time_offset(self.config, f"the 7-Scenes folder {self.path}")
        entries: list[_Entry] = []
        for index, stem, files in _seven_scenes_frames(self.path, names):
            color = self.path / files.get("color", f"{stem}{_colour_suffix(names)}")
            depth = self.path / files.get("depth", f"{stem}.depth.png")
            lacking = [what for part, what in (("color", "colour"), ("depth", "depth")) if part not in files]
            if lacking:
                self.incomplete_frames[stem] = f"no {' and no '.join(lacking)} image"
            T = None
            if "pose" in files:
                T, problem = _reference_pose(self.path / files["pose"])
                if problem:
                    self.references_left_out[files["pose"]] = problem
            # 7-Scenes is recorded at 30 Hz; the frame index stands in for time
            entries.append(_Entry(index, index / 30.0, color, depth, T))
        if self.incomplete_frames:
            log.warning("%s: %d of %d frames lack an image and are skipped: %s", self.path, len(self.incomplete_frames),
                        len(entries), _listed(self.incomplete_frames))
        if self.references_left_out:
            # a pose file of the recording that holds no rigid pose (a lost tracking written as
            # nan or inf, a damaged file) leaves its frame out of the reference, as a motion
            # capture's gap does, instead of refusing the run: the reference only scores it
            log.warning("%s: %d pose file(s) hold no rigid pose and are left out of the reference (the evaluation scores "
                        "the other frames): %s", self.path, len(self.references_left_out), _listed(self.references_left_out))
        return entries, self.K, 1000.0

    def _read_list(self, name: str) -> list[tuple[float, str]]:
        """The ``timestamp path`` lines of the TUM list ``name``."""
        path = self.path / name
        rows = []
        for lineno, line in enumerate(_read_text(path).splitlines(), 1):
            if not line.strip() or line.startswith("#"):
                continue
            parts = line.split()
            try:
                rows.append((float(parts[0]), parts[1]))
            except (ValueError, IndexError):
                raise InputDataError(f"{path}:{lineno}: expected 'timestamp path', got {line.strip()[:80]!r}") from None
            if not math.isfinite(rows[-1][0]):
                raise InputDataError(f"{path}:{lineno}: timestamp {parts[0]} is not finite; correct the line")
        return rows

    def _reference(self, names: list[str]) -> Trajectory | None:
        """groundtruth.txt, when the folder has one. It is a single file interpolated at the frame
        times, so a malformed line (non-finite, a quaternion off unit norm) refuses it with the
        line's number rather than being interpolated across."""
        if "groundtruth.txt" not in names:
            return None
        path = self.path / "groundtruth.txt"
        _read_bytes(path)  # an OSError here says what to do; read_tum only says what happened
        try:
            return read_tum(path)
        except InputDataError as exc:
            raise InputDataError(f"{exc}; correct or delete that line (the reference only scores the run)") from None

    def _read_tum(self, names: list[str]):
        rgb, depth = self._read_list("rgb.txt"), self._read_list("depth.txt")
        if not depth:
            return [], None, 5000.0
        K, self.distortion = self._tum_camera(names)
        gt = self._reference(names)
        offset_s = self.config.evaluation.reference_time_offset_s
        pairs = associate_timestamps([t for t, _ in rgb], [t for t, _ in depth], TUM_MAX_ASSOCIATION_S)
        self.unassociated = {"color": len(rgb) - len(pairs), "depth": len(depth) - len(pairs)}
        if self.unassociated["color"]:
            paired = {i for i, _ in pairs}
            alone = [f"{rgb[i][0]:.6f}" for i in range(len(rgb)) if i not in paired]
            log.warning("%s: %d of %d colour images have no depth image within %.0f ms of their own and are left out "
                        "(timestamps %s%s)", self.path, len(alone), len(rgb), 1e3 * TUM_MAX_ASSOCIATION_S,
                        ", ".join(alone[:5]), ", ..." if len(alone) > 5 else "")
        entries: list[_Entry] = []
        for i, j in pairs:
            t = rgb[i][0]
            T = None if gt is None else interpolate_pose(gt, t + offset_s, max_gap_s=0.05)
            entries.append(_Entry(len(entries), t, self.path / rgb[i][1], self.path / depth[j][1], T))
        return entries, K, 5000.0

    def _tum_camera(self, names: list[str]) -> tuple[np.ndarray, np.ndarray | None]:
        """K and lens distortion of a TUM folder: intrinsics.txt, else the published calibration
        of the camera its rgb.txt header or its name mentions, else the ROS default."""
        kfile = self.path / "intrinsics.txt"
        if "intrinsics.txt" in names:
            values = _numbers(kfile, (4, 8, 9), "'fx fy cx cy [k1 k2 p1 p2 k3]'")
            fx, fy, cx, cy = values[:4]
            K = _camera_matrix(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), str(kfile))
            if not np.isfinite(values[4:]).all():
                raise InputDataError(f"{kfile}: the lens distortion {' '.join(f'{v:g}' for v in values[4:])} is not finite; "
                                     "write the camera's calibration there")
            self.intrinsics = {"source": str(kfile)}
            return K, (values[4:] if len(values) > 4 else None)
        header = "\n".join(line for line in _read_text(self.path / "rgb.txt").splitlines()[:5] if line.startswith("#"))
        for name, ((fx, fy, cx, cy), distortion) in TUM_CAMERAS.items():
            if name in header or name in self.path.name or name.replace("freiburg", "fr") in self.path.name:
                log.debug("%s: %s camera, the benchmark's published intrinsics and distortion", self.path, name)
                self.intrinsics = {"source": f"published calibration of the TUM {name} camera"}
                return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), np.array(distortion)
        log.warning("%s: camera not named (freiburg1/2/3) and no intrinsics.txt; using the ROS default "
                    "intrinsics 525/525/319.5/239.5 without distortion: add intrinsics.txt for accurate depth", self.path)
        self.intrinsics = {"source": "default ROS (fx=fy=525, cx=319.5, cy=239.5)"}
        return ROS_DEFAULT_K.copy(), None

    # -- image sizes -----------------------------------------------------------------------
    def _image_sizes(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """The sequence's depth and colour image sizes (the most common ones: a frame of another
        size is skipped when it is loaded), each checked against its camera model."""
        depth = self._common_size([e.depth for e in self.entries], cv2.IMREAD_UNCHANGED, "depth")
        color = self._common_size([e.color for e in self.entries], cv2.IMREAD_GRAYSCALE, "colour")
        tum = self.layout == "tum"
        self._check_camera_fits(self.K, depth, self.intrinsics["source"], "depth", "intrinsics.txt" if tum else "camera-intrinsics.txt")
        if self.K_color is not None and self.color_intrinsics is not None:  # 7-Scenes: a colour camera of its own
            self._check_camera_fits(self.K_color, color, self.color_intrinsics["source"], "colour", "color-intrinsics.txt")
        elif color != depth:
            raise InputDataError(f"{self.path}: its colour images are {color[0]}x{color[1]} but its depth images {depth[0]}x{depth[1]}; "
                                 "TUM RGB-D colour must be registered to depth (the same size): register or resize them")
        return depth, color

    def _common_size(self, paths: list[Path], flags: int, what: str) -> tuple[int, int]:
        """The most common (width, height) of the images at ``paths``, read from their headers."""
        sizes = Counter(size for size in map(_image_size, paths) if size is not None)
        if sizes:
            return sizes.most_common(1)[0][0]
        # no PNG or JPEG header among them: another format decodes, or the first says why not
        try:
            shape = _decode(paths[0], flags, what).shape
        except InputDataError as exc:
            raise InputDataError(f"{self.path}: none of its {len(paths)} {what} images can be read (the first: {exc})") from None
        return shape[1], shape[0]

    def _check_camera_fits(self, K: np.ndarray, size: tuple[int, int], where: str, what: str, remedy: str) -> None:
        """Refuse a camera model made for images of another size than the sequence's.

        Neither layout's intrinsics file states an image size, so it is judged from the principal
        point: a calibrated principal point sits near the image centre (TUM freiburg1's is 3.2 %
        of the height off it, the farthest of the published calibrations), while images resized
        by a factor s put it W/2 |1 - 1/s| off: beyond :data:`PRINCIPAL_POINT_OFF_CENTRE` (10 %
        of the size) for any resize by more than ~20 %, e.g. 640x480 intrinsics on 320x240
        images (the principal point at the image's edge) or on a Kinect v2's 512x424 (12.5 %)."""
        (w, h), cx, cy = size, K[0, 2], K[1, 2]
        outside = not (0 <= cx <= w and 0 <= cy <= h)
        if outside or max(abs(cx - w / 2) / w, abs(cy - h / 2) / h) > PRINCIPAL_POINT_OFF_CENTRE:
            raise InputDataError(
                f"{self.path}: the {what} images are {w}x{h} but the intrinsics ({where}) put the principal point at "
                f"cx={cx:g}, cy={cy:g}, {'outside them' if outside else 'far off their centre'}: intrinsics of about "
                f"{2 * cx:.0f}x{2 * cy:.0f} images; give {remedy} for {w}x{h} images, or resize the images to the calibrated size"
            )

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
        depth = _decode(e.depth, cv2.IMREAD_UNCHANGED, "depth")
        if depth.ndim != 2 or depth.dtype != np.uint16:
            raise InputDataError(f"{e.depth}: not a 16-bit depth image ({depth.dtype}, {depth.shape[2] if depth.ndim == 3 else 1} "
                                 "channel(s)); copy it again from the dataset")
        _check_size(e.depth, depth, self.depth_size, "depth")
        color = _decode(e.color, cv2.IMREAD_GRAYSCALE, "colour")
        if self.K_color is None and color.shape != depth.shape:
            raise InputDataError(
                f"{e.color}: colour {color.shape[1]}x{color.shape[0]} but depth {depth.shape[1]}x{depth.shape[0]}; "
                "TUM RGB-D colour must be registered to depth (same size)"
            )
        _check_size(e.color, color, self.color_size, "colour")
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
        frame = Frame(
            id=e.frame_id,
            timestamp=e.timestamp,
            points=masked_pixels(xyz, valid),
            colors=grey_colors(color[valid] / 255.0),
            xyz_map=xyz,
            texture=color,
            camera=CameraModel(self.K, xyz.shape[1], xyz.shape[0], readout_s=self.config.registration.sensor_noise().readout_s),
            # the front-end's own record of the camera, as FPP frames keep theirs (the back-end reads ``camera``)
            metadata={"K": self.K.tolist(), "sensor": "rgbd", **({"distortion": self.distortion.tolist()} if self.distortion is not None else {})},
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
        """``config`` with the Kinect's noise model (its dense pixel stride included) where
        ``registration.noise`` is left null, and the fusion voxels and depth range,
        tracking from motion and keyframes-only frame storage (``run.keep_frames``) where the
        config leaves them null (idempotent; a value the user set is kept)."""
        reg = config.registration.with_noise(KINECT_V1_NOISE)  # the dense stride included: a user's value wins
        fus = config.fusion
        fus = fus.model_copy(update={k: v for k, v in RGBD_FUSION_VOXELS_M.items() if getattr(fus, k) is None})
        if fus.max_depth_m is None:
            # beyond the range where the depth error reaches the TSDF's truncation band a
            # surface's points scatter over more than the band (5.3 m with 1 cm voxels)
            truncation_m = TSDF_TRUNCATION_VOXELS * fus.tsdf_voxel_m
            fus = fus.model_copy(update={"max_depth_m": math.sqrt(truncation_m / KINECT_DEPTH_SIGMA_PER_M2)})
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
        from frontend.registration import TexturedSurfaceRegistrar

        return TexturedSurfaceRegistrar(self.config.registration, seed=self.config.run.seed)

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
        left_out = self.references_left_out
        return {"sensor": "rgbd", "layout": self.layout, "frames": len(self.entries), "K": self.K.tolist(),
                "distortion": None if self.distortion is None else self.distortion.tolist(),
                "intrinsics": {**self.intrinsics, "image_size": list(self.depth_size)},
                "color_intrinsics": None if self.color_intrinsics is None else {**self.color_intrinsics, "image_size": list(self.color_size)},
                "unassociated_images": dict(self.unassociated),
                "incomplete_frames": dict(self.incomplete_frames),
                "frames_with_reference": sum(e.T_world_sensor is not None for e in self.entries),
                # the first 20 pose files by name: a recording that lost tracking for long has hundreds
                "reference_poses_left_out": {"count": len(left_out), "files": dict(list(left_out.items())[:20])},
                "reference_time_offset_s": self.config.evaluation.reference_time_offset_s}
