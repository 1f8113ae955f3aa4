"""How far a sensor's view moved: the keyframe policy's and the loop window's common measure.

:func:`view_change` is the pixel flow of a keyframe's view seen from another pose, as a fraction
of the image's smaller side, so one threshold means the same loss of overlap for a 60-degree
RGB-D camera and a narrow FPP camera; :meth:`ViewModel.overlap` is the share of the other pose's
image the view still covers (the loop detector's ranking). :class:`ViewModel` keeps what it needs of a keyframe
(intrinsics, image size, median depth), a few numbers instead of the frame.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import invert
from fpp_graph.types import Frame


def median_depth_m(frame: Frame) -> float:
    """Median depth (z, metres) of a frame's points; NaN without points. Computed once per frame
    object: the keyframe policy and the loop detector's view of a keyframe each ask for it, and
    it is a median over ~2 M points of a 1920x1200 FPP frame (~35 ms, asked about twice per frame)."""
    depth = _MEDIAN_DEPTHS_M.get(frame)
    if depth is None:
        depth = float(np.median(np.asarray(frame.points)[:, 2])) if len(frame.points) else math.nan
        _MEDIAN_DEPTHS_M[frame] = depth
    return depth


_MEDIAN_DEPTHS_M: weakref.WeakKeyDictionary[Frame, float] = weakref.WeakKeyDictionary()
""":func:`median_depth_m` of each frame while it lives (frames are immutable)."""


@dataclass(frozen=True)
class ViewModel:
    """A keyframe's pinhole view: ``K`` (3x3), image ``height_px`` x ``width_px``, median scene depth."""

    K: NDArray[np.float64]
    height_px: int
    width_px: int
    depth_m: float

    @classmethod
    def of(cls, frame: Frame, depth_m: float | None = None) -> ViewModel | None:
        """The frame's view; None without a camera model (:attr:`Frame.camera`) or points in
        front of the sensor. ``depth_m``: its :func:`median_depth_m`, when known."""
        camera = frame.camera
        if camera is None or len(frame.points) == 0:
            return None
        depth = median_depth_m(frame) if depth_m is None else depth_m
        if not depth > 0:
            return None
        return cls(camera.K, camera.height_px, camera.width_px, float(depth))

    def change(self, T_keyframe_frame: NDArray[np.float64]) -> float:
        """See :func:`view_change`."""
        K, h, w = self.K, self.height_px, self.width_px
        u, v = np.meshgrid(np.array([1, 3, 5]) * w / 6.0, np.array([1, 3, 5]) * h / 6.0)
        pixels = np.stack([u.ravel(), v.ravel()], axis=1)
        rays = np.column_stack([(pixels - K[:2, 2]) / np.diag(K)[:2], np.ones(9)])
        T_frame_keyframe = invert(T_keyframe_frame)
        seen = (self.depth_m * rays) @ T_frame_keyframe[:3, :3].T + T_frame_keyframe[:3, 3]
        if np.any(seen[:, 2] <= 0):
            return 1.0  # part of the view is now behind the sensor
        projected = seen[:, :2] / seen[:, 2:] * np.diag(K)[:2] + K[:2, 2]
        return float(np.max(np.linalg.norm(projected - pixels, axis=1)) / min(h, w))

    def overlap(self, T_keyframe_frame: NDArray[np.float64]) -> float:
        """Share of the image of a camera with this model at ``T_keyframe_frame`` that this view
        covers: the view's rectangle at its median depth (the plane the scene is taken to lie
        on), cut to the half-space in front of that camera, projected into its image and
        intersected with it. 1 for the same pose, 0 once the view has left the image; it varies
        continuously with the pose, so round-off in the poses moves it by round-off."""
        import cv2

        K, h, w = self.K, self.height_px, self.width_px
        corners_px = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        rays = np.column_stack([(corners_px - K[:2, 2]) / np.diag(K)[:2], np.ones(4)])
        T_frame_keyframe = invert(T_keyframe_frame)
        corners = (self.depth_m * rays) @ T_frame_keyframe[:3, :3].T + T_frame_keyframe[:3, 3]
        # a point 1/100 of the depth ahead projects 100 focal lengths out: far enough beyond the
        # image that the cut changes no area inside it
        polygon = _in_front_of(corners, 0.01 * self.depth_m)
        if len(polygon) < 3:
            return 0.0
        projected = polygon[:, :2] / polygon[:, 2:] * np.diag(K)[:2] + K[:2, 2]
        image = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]], dtype=np.float32)
        area, _ = cv2.intersectConvexConvex(projected.astype(np.float32), image)
        return float(min(1.0, max(0.0, area / (w * h))))


def _in_front_of(polygon: NDArray[np.float64], z_min: float) -> NDArray[np.float64]:
    """The part of a convex 3D polygon (its vertices in order) with ``z >= z_min``
    (Sutherland-Hodgman against one plane)."""
    kept = []
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        if a[2] >= z_min:
            kept.append(a)
        if (a[2] >= z_min) != (b[2] >= z_min):
            kept.append(a + (z_min - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(kept).reshape(-1, 3)


def view_change(keyframe: Frame, T_keyframe_frame: NDArray[np.float64], depth_m: float | None = None) -> float | None:
    """How far the image content moved from ``keyframe`` to a frame at ``T_keyframe_frame``, as
    a fraction of the image's smaller side: the largest pixel displacement of nine points of the
    keyframe's view (a 3x3 grid over the image at the keyframe's median depth) seen from the
    frame. Rotation, translation against the scene's depth and roll all count, in the sensor's
    own pixels, so the same fraction means the same loss of overlap for a 60-degree RGB-D camera
    and a narrow FPP camera. None when the keyframe has no camera model (:attr:`Frame.camera`)
    or no points in front of it. ``depth_m``: the keyframe's :func:`median_depth_m`, when known."""
    view = ViewModel.of(keyframe, depth_m)
    return None if view is None else view.change(T_keyframe_frame)
