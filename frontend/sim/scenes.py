"""Scenes for the virtual FPP sensor: scene configs and builders, sensor trajectories, overlap.

A :class:`Scene` is a list of :class:`frontend.sim.parts.SurfacePart` (triangle mesh in the
world frame, metres, plus a material giving the albedo at any surface point,
:mod:`frontend.sim.materials`).

Scenes built here (parameters in pydantic models, loaded from the YAML files in ``datasets/``):

* turntable (:func:`build_turntable`): an object on a table, world frame = table frame (z up,
  table top at z = 0). The table turns the object by ``-theta``, which is the same as the sensor
  orbiting by ``+theta``: the renderer moves the sensor on a circle looking at the object. The
  default object is a procedural textured doll (:func:`frontend.sim.parts.make_doll`); any
  mesh file can replace it.
* corridor (:func:`build_corridor`): a textured corridor (walls, floor, ceiling, door frames,
  pilasters, a handrail, posters, clutter) with a cart trajectory along it and back.
* plane and sphere (:func:`plane_scene`, :func:`sphere_scene`) for accuracy checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pydantic import Field

from fpp_graph.errors import ConfigError, InputDataError
from fpp_graph.geometry import transform_points
from frontend.sim.config import StrictModel
from frontend.sim.materials import ImageMaterial, ProceduralMaterial, VertexColorMaterial
from frontend.sim.parts import (
    SurfacePart,
    box,
    cylinder,
    load_mesh,
    make_doll,
    place_mesh,
    quad,
    sphere,
)
from frontend.sim.poses import axis_rotation, look_at_pose


@dataclass(eq=False)
class Scene:
    """Surfaces in the world frame."""

    parts: list[SurfacePart]

    def __post_init__(self) -> None:
        if not self.parts:
            raise InputDataError("scene has no surfaces")

    def bounds(self) -> tuple[NDArray, NDArray]:
        v = np.concatenate([p.vertices for p in self.parts])
        return v.min(axis=0), v.max(axis=0)

    def to_open3d(self) -> o3d.geometry.TriangleMesh:
        """One legacy mesh (world frame, metres) with grey vertex colours from the albedo."""
        out = o3d.geometry.TriangleMesh()
        for part in self.parts:
            m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(part.vertices), o3d.utility.Vector3iVector(part.triangles.astype(np.int32)))
            grey = _vertex_albedo(part)
            m.vertex_colors = o3d.utility.Vector3dVector(np.repeat(grey[:, None], 3, axis=1))
            out += m
        out.compute_vertex_normals()
        return out


def _vertex_albedo(part: SurfacePart) -> NDArray[np.float64]:
    mat = part.material
    if isinstance(mat, VertexColorMaterial):
        return mat.vertex_albedo
    if isinstance(mat, ProceduralMaterial):
        return mat.albedo(part.vertices)
    return np.full(part.vertices.shape[0], 0.6)


# ---------------------------------------------------------------------------------------------
# Config models
# ---------------------------------------------------------------------------------------------
class TextureConfig(StrictModel):
    """Albedo of a loaded mesh: ``procedural`` (solid texture), ``vertex_colors`` or ``image``."""

    kind: Literal["procedural", "vertex_colors", "image"] = "procedural"
    base: float = Field(0.6, ge=0, le=1)
    contrast: float = Field(0.6, ge=0, le=2)
    scale_m: float = Field(0.015, gt=0, description="largest feature size of the solid texture")
    octaves: int = Field(3, ge=1, le=6)
    seed: int = 3
    image: str | None = Field(None, description="texture image path (kind=image; the mesh must carry UVs)")


class TurntableConfig(StrictModel):
    """An object on a turntable in front of a fixed sensor (the paper's doll protocol)."""

    object: str = Field("doll", description="'doll' (built-in) or a mesh file path (relative to the YAML file)")
    object_size_m: float = Field(0.22, gt=0, description="largest extent of the object after scaling")
    up_axis: Literal["z", "y", "-y", "x", "-z"] = "z"
    texture: TextureConfig = TextureConfig()
    turns: int = Field(3, ge=0)
    views_per_turn: int = Field(13, ge=0)
    turn_offset_deg: float = Field(0.0, description="table angle added per turn (0: every turn repeats the same stops)")
    distance_m: float = Field(0.5, gt=0, description="sensor to the look-at point")
    elevation_deg: float = Field(20.0, ge=-89, le=89)
    target_height_fraction: float = Field(0.5, ge=0, le=1, description="look-at point height as a fraction of the object height")
    table_radius_m: float = Field(0.16, ge=0, description="0: no table top")
    frame_interval_s: float = Field(1.0, gt=0)


class CorridorConfig(StrictModel):
    """A textured corridor; the sensor rides a cart along one wall, turns, and back along the other."""

    length_m: float = Field(6.0, gt=1.0)
    width_m: float = Field(1.2, gt=0.4)
    height_m: float = Field(2.4, gt=1.0)
    sensor_height_m: float = Field(0.95, gt=0)
    wall_distance_m: float = Field(0.5, gt=0, description="sensor to the wall it faces")
    step_m: float = Field(0.31, gt=0, description="cart advance between frames along a wall")
    turn_step_deg: float = Field(30.0, gt=0, le=90)
    passes: int = Field(5, ge=0, description="straight passes (out, back, out, ...); a turn joins consecutive passes")
    margin_m: float = Field(0.5, ge=0, description="cart stops this far from the end walls")
    poster_repeats: int = Field(2, ge=1, description="copies of the look-alike poster on each wall (false-loop bait)")
    clutter_seed: int = 11
    frame_interval_s: float = Field(1.0, gt=0)


# ---------------------------------------------------------------------------------------------
# Turntable
# ---------------------------------------------------------------------------------------------
def _object_parts(cfg: TurntableConfig, base_dir: Path | None) -> list[SurfacePart]:
    if cfg.object == "doll":
        parts = make_doll(cfg.object_size_m)
        return parts
    path = Path(cfg.object)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    mesh = load_mesh(path)
    v, t = place_mesh(mesh, cfg.object_size_m, cfg.up_axis)
    tex = cfg.texture
    if tex.kind == "vertex_colors":
        if not mesh.has_vertex_colors():
            raise InputDataError(f"mesh {path} has no vertex colours; use texture.kind: procedural")
        rgb = np.asarray(mesh.vertex_colors)
        material: Any = VertexColorMaterial(rgb @ np.array([0.299, 0.587, 0.114]), t)
    elif tex.kind == "image":
        if tex.image is None or not mesh.has_triangle_uvs():
            raise InputDataError(f"texture.kind image needs texture.image and a mesh with UVs ({path})")
        img_path = Path(tex.image) if Path(tex.image).is_absolute() or base_dir is None else base_dir / tex.image
        img = cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputDataError(f"cannot read texture image {img_path}")
        uvs = np.asarray(mesh.triangle_uvs).reshape(-1, 3, 2)
        # Open3D's OBJ UVs have v up; image rows go down.
        uvs = np.stack([uvs[..., 0], 1.0 - uvs[..., 1]], axis=-1)
        material = ImageMaterial(img.astype(np.float32) / 255.0, uvs)
    else:
        material = ProceduralMaterial(base=tex.base, contrast=tex.contrast, scale_m=tex.scale_m, octaves=tex.octaves, seed=tex.seed)
    return [SurfacePart(path.stem, v, t, material)]


def build_turntable(cfg: TurntableConfig, base_dir: Path | None = None) -> tuple[Scene, NDArray, NDArray]:
    """Scene and ground-truth trajectory of the turntable protocol.

    Returns
    -------
    scene : Scene
        Object (and table top) in the world = table frame, z up, table top at z = 0.
    poses_world_sensor : (N, 4, 4)
        ``N = turns * views_per_turn`` sensor poses on a circle around the object; view ``k``
        of every turn is at angle ``2 pi k / views_per_turn`` (plus ``turn * turn_offset``), so
        the trajectory returns to its start after each turn.
    timestamps_s : (N,)
    """
    parts = _object_parts(cfg, base_dir)
    top = max(float(p.vertices[:, 2].max()) for p in parts)
    if cfg.table_radius_m > 0:
        table = cylinder("table", [0, 0, -0.02], [0, 0, 0.0], cfg.table_radius_m, ProceduralMaterial(base=0.45, contrast=0.5, scale_m=0.02, seed=99), resolution=96)
        parts.append(table)
    target = np.array([0.0, 0.0, cfg.target_height_fraction * top])
    el = math.radians(cfg.elevation_deg)
    poses = []
    for turn in range(cfg.turns):
        for k in range(cfg.views_per_turn):
            theta = 2 * math.pi * k / cfg.views_per_turn + math.radians(cfg.turn_offset_deg) * turn
            pos = target + cfg.distance_m * np.array([math.cos(el) * math.cos(theta), math.cos(el) * math.sin(theta), math.sin(el)])
            poses.append(look_at_pose(pos, target))
    poses_arr = np.array(poses).reshape(-1, 4, 4)
    return Scene(parts), poses_arr, np.arange(len(poses_arr)) * cfg.frame_interval_s


# ---------------------------------------------------------------------------------------------
# Corridor
# ---------------------------------------------------------------------------------------------
def make_poster(seed: int, width_px: int = 480, height_px: int = 640) -> NDArray[np.float32]:
    """A procedural poster (grey, [0, 1]): blocks, circles, a title and 'text' lines."""
    rng = np.random.default_rng(seed)

    def grey(lo: float, hi: float) -> int:
        return int(255 * rng.uniform(lo, hi))

    img = np.full((height_px, width_px), grey(0.65, 0.85), dtype=np.uint8)
    for _ in range(6):
        x0, y0 = int(rng.integers(0, width_px - 60)), int(rng.integers(0, height_px - 60))
        x1, y1 = x0 + int(rng.integers(40, 220)), y0 + int(rng.integers(30, 200))
        cv2.rectangle(img, (x0, y0), (x1, y1), grey(0.05, 0.7), -1)
    for _ in range(5):
        c = (int(rng.integers(0, width_px)), int(rng.integers(0, height_px)))
        cv2.circle(img, c, int(rng.integers(15, 90)), grey(0.0, 0.95), -1)
    y = int(height_px * 0.72)
    while y < height_px - 20:
        x = 25
        while x < width_px - 40:
            w = int(rng.integers(12, 60))
            cv2.rectangle(img, (x, y), (min(x + w, width_px - 25), y + 9), 25, -1)
            x += w + int(rng.integers(8, 16))
        y += 22
    cv2.putText(img, f"No.{seed % 97:02d}", (30, 80), cv2.FONT_HERSHEY_DUPLEX, 2.0, 15, 4)
    return cv2.GaussianBlur(img.astype(np.float32) / 255.0, (0, 0), 1.0)


def build_corridor(cfg: CorridorConfig) -> tuple[Scene, NDArray, NDArray]:
    """Corridor scene and the cart trajectory.

    World frame: x along the corridor (0..length), y across (left wall at +width/2), z up,
    floor at z = 0. The cart drives along the centre line; the sensor looks at the left wall
    (+y) on "out" passes and at the right wall on "back" passes, at ``wall_distance_m``;
    between passes it turns in place by ``turn_step_deg`` steps, looking at the end wall
    midway. Later passes revisit earlier ones (loops); the same poster hangs at several places
    on both walls (look-alike places).
    """
    parts = _corridor_shell(cfg)
    parts += _door_frames(cfg)
    parts += _pilasters(cfg)
    parts += _handrail(cfg)
    parts += _posters(cfg)
    parts += _clutter(cfg)
    scene = Scene(parts)
    poses = corridor_trajectory(cfg)
    return scene, poses, np.arange(len(poses)) * cfg.frame_interval_s


def _facing(part: SurfacePart, direction: NDArray) -> SurfacePart:
    """Flip a flat part's winding so its front (right-handed normal) points along ``direction``."""
    v0, v1, v2 = part.vertices[part.triangles[0]]
    if np.dot(np.cross(v1 - v0, v2 - v0), direction) < 0:
        part.triangles = part.triangles[:, ::-1].copy()
        mat = part.material
        if isinstance(mat, ImageMaterial):
            part.material = ImageMaterial(mat.image, mat.triangle_uvs[:, ::-1].copy())
    return part


def _wall_side(cfg: CorridorConfig, side: int) -> tuple[float, float]:
    """(wall y, sign of +y into the corridor) of the left (``side`` > 0) or right wall."""
    return (cfg.width_m / 2, -1.0) if side > 0 else (-cfg.width_m / 2, 1.0)


def _corridor_shell(cfg: CorridorConfig) -> list[SurfacePart]:
    """Floor, ceiling, side walls and end walls, all facing the corridor's inside."""
    L, Wd, Hc = cfg.length_m, cfg.width_m, cfg.height_m
    yl, yr = Wd / 2, -Wd / 2
    wall = ProceduralMaterial(base=0.62, contrast=0.45, scale_m=0.05, octaves=4, seed=21)
    wall_r = ProceduralMaterial(base=0.58, contrast=0.5, scale_m=0.045, octaves=4, seed=22)
    parts: list[SurfacePart] = [
        quad("floor", [0, yr, 0], [L, 0, 0], [0, Wd, 0], ProceduralMaterial(base=0.4, contrast=0.5, scale_m=0.06, seed=23)),
        quad("ceiling", [0, yr, Hc], [0, Wd, 0], [L, 0, 0], ProceduralMaterial(base=0.8, contrast=0.2, scale_m=0.1, seed=24)),
        quad("wall_left", [0, yl, 0], [L, 0, 0], [0, 0, Hc], wall),
        quad("wall_right", [0, yr, 0], [0, 0, Hc], [L, 0, 0], wall_r),
        quad("end_wall_far", [L, yr, 0], [0, 0, Hc], [0, Wd, 0], ProceduralMaterial(base=0.55, contrast=0.5, scale_m=0.05, seed=25)),
        quad("end_wall_near", [0, yr, 0], [0, Wd, 0], [0, 0, Hc], ProceduralMaterial(base=0.55, contrast=0.5, scale_m=0.05, seed=26)),
    ]
    # The shell's faces must face the corridor's inside (the renderer's inside-geometry check
    # counts back faces).
    centre = np.array([L / 2, 0, Hc / 2])
    return [_facing(p, centre - p.vertices[0]) for p in parts]


def _door_frames(cfg: CorridorConfig) -> list[SurfacePart]:
    """Door frames (jambs + head protruding from the wall) with a recessed, striped door leaf."""
    parts: list[SurfacePart] = []
    door_mat = ProceduralMaterial(base=0.45, contrast=0.5, scale_m=0.03, seed=31, stripes_m=0.012)
    frame_mat = ProceduralMaterial(base=0.85, contrast=0.25, scale_m=0.02, seed=32)
    for side, x0 in ((1, 2.1), (-1, 3.7)):
        yw, inward = _wall_side(cfg, side)
        depth = 0.025
        lo_y, hi_y = sorted([yw, yw + inward * depth])
        parts.append(box(f"door{side}_jamb_a", [x0 - 0.08, lo_y, 0], [x0, hi_y, 2.05], frame_mat))
        parts.append(box(f"door{side}_jamb_b", [x0 + 0.85, lo_y, 0], [x0 + 0.93, hi_y, 2.05], frame_mat))
        parts.append(box(f"door{side}_head", [x0 - 0.08, lo_y, 2.05], [x0 + 0.93, hi_y, 2.13], frame_mat))
        # The leaf hangs 4 mm in front of the wall plane, framed by the protruding jambs.
        leaf_y = yw + inward * 0.004
        parts.append(_facing(quad(f"door{side}_leaf", [x0, leaf_y, 0], [0.85, 0, 0], [0, 0, 2.05], door_mat), np.array([0.0, inward, 0.0])))
        hx = x0 + 0.75
        parts.append(box(f"door{side}_handle", [hx, min(leaf_y, leaf_y + inward * 0.06), 0.98], [hx + 0.12, max(leaf_y, leaf_y + inward * 0.06), 1.01], ProceduralMaterial(base=0.3, contrast=0.2, seed=33)))
    return parts


def _pilasters(cfg: CorridorConfig) -> list[SurfacePart]:
    """Pilasters every ~1.4 m on both walls (geometry that pins the along-corridor position)."""
    parts: list[SurfacePart] = []
    for side in (1, -1):
        yw, inward = _wall_side(cfg, side)
        for x in np.arange(0.7 if side > 0 else 1.2, cfg.length_m - 0.3, 1.4):
            if any(abs(x - d) < 1.1 for d in (2.5, 4.1)):
                continue
            lo_y, hi_y = sorted([yw, yw + inward * 0.06])
            parts.append(box(f"pilaster{side}_{x:.1f}", [x, lo_y, 0], [x + 0.18, hi_y, cfg.height_m], ProceduralMaterial(base=0.7, contrast=0.4, scale_m=0.03, seed=int(40 + 10 * x))))
    return parts


def _handrail(cfg: CorridorConfig) -> list[SurfacePart]:
    """A handrail on brackets along part of the left wall."""
    yl = cfg.width_m / 2
    rail_mat = ProceduralMaterial(base=0.5, contrast=0.3, scale_m=0.01, seed=51)
    parts = [cylinder("handrail", [0.9, yl - 0.07, 0.9], [1.9, yl - 0.07, 0.9], 0.02, rail_mat, resolution=32)]
    for bx in (1.0, 1.8):
        parts.append(box(f"rail_bracket_{bx}", [bx - 0.01, yl - 0.07, 0.86], [bx + 0.01, yl, 0.89], rail_mat))
    return parts


def _posters(cfg: CorridorConfig) -> list[SurfacePart]:
    """Posters 2 mm proud of the walls: poster "A" repeated (look-alike places), plus unique ones."""
    parts: list[SurfacePart] = []
    look_alike = make_poster(1000)
    slots = {1: [1.3, 3.05, 4.9, 5.6], -1: [0.5, 2.0, 4.6, 5.4]}
    for side, xs in slots.items():
        yw, inward = _wall_side(cfg, side)
        for i, x in enumerate(xs):
            img = look_alike if i < cfg.poster_repeats else make_poster(2000 + 10 * i + (side > 0))
            y = yw + inward * 0.002
            w, h, z0 = 0.36, 0.48, 0.72
            # Image u runs to the viewer's right: +x when looking at the left wall, -x on the right.
            if side > 0:
                poster = quad(f"poster{side}_{i}", [x, y, z0 + h], [w, 0, 0], [0, 0, -h], image=img)
            else:
                poster = quad(f"poster{side}_{i}", [x + w, y, z0 + h], [-w, 0, 0], [0, 0, -h], image=img)
            parts.append(_facing(poster, np.array([0.0, inward, 0.0])))
    return parts


def _clutter(cfg: CorridorConfig) -> list[SurfacePart]:
    """Boxes stacked against the walls (sizes from ``clutter_seed``), a bin, a radiator, a fire extinguisher."""
    yl, yr = cfg.width_m / 2, -cfg.width_m / 2
    rng = np.random.default_rng(cfg.clutter_seed)
    parts: list[SurfacePart] = []
    for side, x in ((1, 4.2), (-1, 1.4), (-1, 5.0)):
        yw, inward = _wall_side(cfg, side)
        z = 0.0
        for k in range(int(rng.integers(2, 4))):
            dx, dy, dz = rng.uniform(0.25, 0.45), rng.uniform(0.2, 0.35), rng.uniform(0.25, 0.4)
            xo = x + rng.uniform(-0.05, 0.05)
            lo_y, hi_y = sorted([yw + inward * 0.01, yw + inward * (0.01 + dy)])
            parts.append(box(f"box{side}_{x}_{k}", [xo, lo_y, z], [xo + dx, hi_y, z + dz], ProceduralMaterial(base=0.5, contrast=0.6, scale_m=0.03, seed=int(60 + 7 * k + 10 * x))))
            z += dz
    parts.append(cylinder("bin", [2.9, yr + 0.2, 0], [2.9, yr + 0.2, 0.95], 0.15, ProceduralMaterial(base=0.3, contrast=0.5, scale_m=0.02, seed=71), resolution=64))
    parts.append(cylinder("extinguisher", [0.3, yl - 0.1, 0.7], [0.3, yl - 0.1, 1.15], 0.08, ProceduralMaterial(base=0.35, contrast=0.4, scale_m=0.015, seed=72), resolution=48))
    rad_mat = ProceduralMaterial(base=0.82, contrast=0.2, scale_m=0.02, seed=73)
    for k in range(14):
        x = 3.3 + 0.05 * k
        parts.append(box(f"radiator_fin_{k}", [x, yr + 0.03, 0.15], [x + 0.03, yr + 0.11, 0.85], rad_mat))
    return parts


def corridor_trajectory(cfg: CorridorConfig) -> NDArray[np.float64]:
    """(N, 4, 4) ``T_world_sensor`` of the cart: passes along the walls joined by in-place turns."""
    L, Wd = cfg.length_m, cfg.width_m
    x_start, x_end = cfg.margin_m, L - cfg.margin_m
    if x_end <= x_start:
        raise ConfigError(f"corridor of {L} m is too short for margins of {cfg.margin_m} m")
    # The cart runs along y = y_out on out passes (left wall at +Wd/2 is wall_distance away) and
    # y = -y_out on back passes.
    y_out = Wd / 2 - cfg.wall_distance_m
    n_steps = max(1, round((x_end - x_start) / cfg.step_m))
    xs = np.linspace(x_start, x_end, n_steps + 1)
    n_turn = max(1, math.ceil(180.0 / cfg.turn_step_deg))
    z = cfg.sensor_height_m
    poses: list[NDArray] = []

    def pose(x: float, y: float, heading: float) -> NDArray:
        pos = np.array([x, y, z])
        return look_at_pose(pos, pos + np.array([math.cos(heading), math.sin(heading), 0.0]))

    for p in range(cfg.passes):
        out = p % 2 == 0
        heading = math.pi / 2 if out else -math.pi / 2
        y = y_out if out else -y_out
        seq = xs if out else xs[::-1]
        for i, x in enumerate(seq):
            if p > 0 and i == 0:
                continue  # the turn's last pose is this pass's first
            poses.append(pose(float(x), y, heading))
        if p + 1 < cfg.passes:
            # Turn in place at the end (out: heading +90 -> 0 -> -90; back: -90 -> -180 -> -270),
            # drifting across to the next pass's lane.
            x_t = float(seq[-1])
            for k in range(1, n_turn + 1):
                f = k / n_turn
                h = heading - math.pi * f
                yy = y + (-2 * y) * f
                poses.append(pose(x_t, yy, h))
    return np.array(poses).reshape(-1, 4, 4)


# ---------------------------------------------------------------------------------------------
# Accuracy targets
# ---------------------------------------------------------------------------------------------
def plane_scene(distance_m: float = 0.5, size_m: float = 1.0, tilt_deg: float = 10.0, albedo: float = 0.8, contrast: float = 0.0) -> Scene:
    """A flat plate facing the sensor at the origin (sensor looks along world +z, y down).

    The plate is tilted by ``tilt_deg`` about the vertical axis; ``contrast`` 0 makes it uniformly
    white-ish (like a calibration flat), > 0 gives it a solid texture.
    """
    t = math.radians(tilt_deg)
    R = axis_rotation("y", t)
    eu = R @ np.array([size_m, 0, 0])
    ev = R @ np.array([0, size_m, 0])
    c = np.array([0, 0, distance_m]) - 0.5 * eu - 0.5 * ev
    part = quad("plane", c, ev, eu, ProceduralMaterial(base=albedo, contrast=contrast, scale_m=0.02, seed=5))
    return Scene([part])


def sphere_scene(distance_m: float = 0.5, radius_m: float = 0.05, albedo: float = 0.8, resolution: int = 400) -> Scene:
    """A matte sphere whose front is ``distance_m`` in front of the sensor (world = sensor frame)."""
    part = sphere("sphere", [0, 0, distance_m + radius_m], np.full(3, radius_m), ProceduralMaterial(base=albedo, contrast=0.0, seed=6), resolution=resolution)
    return Scene([part])


def frame_overlap(xyz_a_sensor: NDArray, T_world_a: NDArray, depth_b: NDArray, T_world_b: NDArray, K: NDArray, tolerance_m: float = 0.01) -> float:
    """Fraction of frame a's valid points that frame b also sees (same surface, within tolerance).

    Uses the pinhole part of ``K`` only (ground-truth bookkeeping, not measurement).
    """
    pts = xyz_a_sensor.reshape(-1, 3)
    pts = pts[np.isfinite(pts[:, 0])]
    if pts.shape[0] == 0:
        return 0.0
    T_b_a = np.linalg.inv(T_world_b) @ T_world_a
    p = transform_points(T_b_a, pts)
    H, W = depth_b.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
        v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
    ok = (p[:, 2] > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    ui = np.rint(u[ok]).astype(int)
    vi = np.rint(v[ok]).astype(int)
    d = depth_b[vi, ui]
    seen = np.abs(d - p[ok, 2]) < tolerance_m
    return float(np.count_nonzero(seen)) / pts.shape[0]
