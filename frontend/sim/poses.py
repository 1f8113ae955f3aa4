"""Rotations and sensor poses of the virtual FPP sensor: look-at poses and small rotation helpers.

Frames: the sensor frame is the camera frame (x right, y down, z forward); a pose
``T_world_sensor`` maps sensor points into the world. Angles in radians.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError


def look_at_rotation(forward: NDArray, down_hint: NDArray) -> NDArray:
    """Rotation whose columns are camera x (right), y (down), z (forward) in the parent frame.

    ``down_hint`` is the parent-frame direction that should appear as image "down" (+y).
    """
    z = forward / np.linalg.norm(forward)
    y = down_hint - np.dot(down_hint, z) * z
    ny = np.linalg.norm(y)
    if ny < 1e-9:
        raise ConfigError("look-at direction is parallel to the up hint; choose another viewing direction")
    y /= ny
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


def rotation_between(a: NDArray, b: NDArray) -> NDArray:
    """Smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-15:
        return np.eye(3) if c > 0 else -np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def look_at_pose(position_world: NDArray, target_world: NDArray, up_world: NDArray | None = None) -> NDArray[np.float64]:
    """``T_world_sensor`` of a sensor at ``position_world`` looking at ``target_world``.

    The sensor frame is the camera frame (x right, y down, z forward); ``up_world`` (default
    +z) appears upwards in the image.
    """
    up = np.array([0.0, 0.0, 1.0]) if up_world is None else np.asarray(up_world, float)
    R = look_at_rotation(np.asarray(target_world, float) - np.asarray(position_world, float), -up)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = position_world
    return T


def axis_rotation(axis: str, angle_rad: float) -> NDArray:
    """Rotation by ``angle_rad`` about the coordinate axis ``"x"``, ``"y"`` or (any other) z."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rotation_z_to(z: NDArray) -> NDArray:
    """A rotation whose third column is the direction ``z`` (the other two axes arbitrary)."""
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])
