"""The camera + projector rig model: intrinsics, lens distortion, relative pose, image sizes.

The projector is modelled as an inverse camera. The *sensor frame* is the camera frame: the
camera sits at the origin looking along +z, and ``T_projector_camera`` maps camera-frame points
into the projector frame. Distortion coefficients follow OpenCV's order
``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``. Lengths are metres in memory; files state their unit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_write_text
from fpp_graph.errors import CalibrationError
from fpp_graph.geometry import is_rigid
from fpp_graph.yaml_files import read_yaml_file

_UNIT_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


@dataclass(frozen=True, eq=False)
class PinholeModel:
    """A pinhole device with OpenCV lens distortion.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    K : (3, 3) float64
        Intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
    dist : (k,) float64
        OpenCV distortion coefficients (k = 0, 4, 5, 8, 12 or 14); empty means none.
    """

    width: int
    height: int
    K: NDArray[np.float64]
    dist: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"intrinsic matrix must be a finite 3x3 with positive focal lengths, got {K.tolist()}")
        if dist.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise CalibrationError(f"distortion must hold 0, 4, 5, 8, 12 or 14 finite OpenCV coefficients, got {dist.size}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def has_distortion(self) -> bool:
        return bool(self.dist.size and np.any(self.dist != 0))

    def to_dict(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "K": self.K.tolist(), "dist": self.dist.tolist()}

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str) -> PinholeModel:
        try:
            return cls(width=data["width"], height=data["height"], K=np.array(data["K"], dtype=float), dist=np.array(data.get("dist", []), dtype=float))
        except KeyError as exc:
            raise CalibrationError(f"{where}: missing key {exc.args[0]!r} (need width, height, K, dist)") from None
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: malformed device model ({exc})") from None


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """Calibration of an FPP rig: camera, projector (inverse camera) and their relative pose.

    ``T_projector_camera`` (4x4, metres) maps camera-frame (= sensor-frame) points into the
    projector frame. ``reprojection_rms_px`` holds per-device RMS reprojection errors when the
    calibration was estimated.
    """

    camera: PinholeModel
    projector: PinholeModel
    T_projector_camera: NDArray[np.float64]
    reprojection_rms_px: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        T = np.asarray(self.T_projector_camera, dtype=np.float64)
        if not is_rigid(T, atol=1e-6):
            raise CalibrationError("T_projector_camera is not a rigid 4x4 transform (check rotation orthonormality and units)")
        object.__setattr__(self, "T_projector_camera", T)

    @property
    def A_camera(self) -> NDArray[np.float64]:
        """3x4 camera projection matrix ``A^c = K_c [I | 0]`` (sensor frame = camera frame)."""
        return self.camera.K @ np.hstack([np.eye(3), np.zeros((3, 1))])

    @property
    def A_projector(self) -> NDArray[np.float64]:
        """3x4 projector projection matrix ``A^p = K_p [R | t]`` with ``T_projector_camera``."""
        return self.projector.K @ self.T_projector_camera[:3, :]

    @property
    def baseline_m(self) -> float:
        """Distance between the camera and projector centres in metres."""
        R, t = self.T_projector_camera[:3, :3], self.T_projector_camera[:3, 3]
        return float(np.linalg.norm(-R.T @ t))

    def check_image_size(self, width: int, height: int, where: str) -> None:
        """Raise CalibrationError when images of ``width x height`` do not fit the camera model."""
        if (width, height) != (self.camera.width, self.camera.height):
            raise CalibrationError(
                f"{where}: images are {width}x{height} but the calibration's camera is "
                f"{self.camera.width}x{self.camera.height}; use the calibration of this camera or resize consistently"
            )

    def to_dict(self, unit: str = "mm") -> dict[str, Any]:
        """A YAML-ready dict with lengths in ``unit`` (translations only; pixels stay pixels)."""
        scale = 1.0 / _UNIT_TO_M[unit]
        T = self.T_projector_camera.copy()
        T[:3, 3] *= scale
        return {
            "format": "fpp-graph rig calibration v1",
            "length_unit": unit,
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "T_projector_camera": T.tolist(),
            "A_camera": self.A_camera.tolist(),
            "A_projector": (self.projector.K @ T[:3, :]).tolist(),
            "reprojection_rms_px": dict(self.reprojection_rms_px),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "<calibration>") -> RigCalibration:
        if not isinstance(data, dict):
            raise CalibrationError(f"{where}: a calibration must be a mapping")
        unit = data.get("length_unit")
        if unit not in _UNIT_TO_M:
            raise CalibrationError(f"{where}: length_unit must be one of {sorted(_UNIT_TO_M)}, got {unit!r}; calibration files must state their unit")
        try:
            T = np.array(data["T_projector_camera"], dtype=np.float64)
        except KeyError:
            raise CalibrationError(f"{where}: missing key 'T_projector_camera'") from None
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: T_projector_camera is malformed ({exc})") from None
        if T.shape != (4, 4):
            raise CalibrationError(f"{where}: T_projector_camera must be 4x4, got {T.shape}")
        T[:3, 3] *= _UNIT_TO_M[unit]
        for key in ("camera", "projector"):
            if key not in data:
                raise CalibrationError(f"{where}: missing key {key!r}")
        return cls(
            camera=PinholeModel.from_dict(data["camera"], f"{where}: camera"),
            projector=PinholeModel.from_dict(data["projector"], f"{where}: projector"),
            T_projector_camera=T,
            reprojection_rms_px={str(k): float(v) for k, v in (data.get("reprojection_rms_px") or {}).items()},
        )


def save_calibration(path: str | os.PathLike[str], calibration: RigCalibration, unit: str = "mm", replace: bool = True) -> None:
    """Write a calibration YAML atomically, lengths in ``unit``, floats at full precision.

    With ``replace=False`` an existing file is never replaced (OutputError instead); a failed
    write (a full disk, no permission) is an OutputError naming ``path`` and leaves no file.
    """
    # yaml.safe_dump writes floats with repr, i.e. full precision.
    atomic_write_text(path, yaml.safe_dump(calibration.to_dict(unit), sort_keys=False), replace=replace)


def load_calibration(path: str | os.PathLike[str]) -> RigCalibration:
    """Read a calibration YAML written by :func:`save_calibration` (any stated length unit)."""
    data = read_yaml_file(path, CalibrationError, "calibration")
    return RigCalibration.from_dict(data, where=str(path))
