"""A frame with a pinhole model and an image size over a flat scene, for the view and loop-window tests."""

from __future__ import annotations

import numpy as np

from fpp_graph.types import CameraModel, Frame


def camera_frame(frame_id: int, depth_m: float = 2.0, width: int = 640, height: int = 480, f_px: float = 500.0) -> Frame:
    """A frame with a pinhole model and an image size (a flat scene at ``depth_m``)."""
    K = np.array([[f_px, 0, width / 2], [0, f_px, height / 2], [0, 0, 1.0]])
    xyz = np.full((height, width, 3), np.nan)
    points = np.column_stack([np.zeros(50), np.zeros(50), np.full(50, depth_m)])
    return Frame(id=frame_id, timestamp=float(frame_id), points=points, xyz_map=xyz, camera=CameraModel(K, width, height))
