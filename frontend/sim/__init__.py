"""The virtual FPP sensor: scenes, a camera + projector rig, and a renderer of its raw fringe images.

Modules, each depending only on those before it:

- :mod:`~frontend.sim.poses`: look-at sensor poses and rotation helpers.
- :mod:`~frontend.sim.materials`: surface albedo (solid procedural texture, vertex colours, images).
- :mod:`~frontend.sim.parts`: textured triangle meshes: primitives, mesh files, the default doll.
- :mod:`~frontend.sim.config`: the strict pydantic base of every config section.
- :mod:`~frontend.sim.scenes`: :class:`Scene`, the turntable / corridor / plane / sphere builders,
  trajectories, frame overlap.
- :mod:`~frontend.sim.rig`: the simulated rig's physical parameters into a calibration.
- :mod:`~frontend.sim.render`: :class:`FppSimulator` (ray cast, shading, camera model) and its
  ground truth.
- :mod:`~frontend.sim.calibration`: the rig calibrated from simulated chessboard captures (what a
  sequence stores by default), cached per rig and seed.
- :mod:`~frontend.sim.sequences`: scene YAML -> :class:`SimulationSetup` -> sequence folder.
"""

from frontend.sim.calibration import (
    BoardCalibrationSettings,
    EstimatedCalibration,
    calibration_errors,
    estimate_rig_calibration,
)
from frontend.sim.materials import ImageMaterial, Material, ProceduralMaterial, VertexColorMaterial
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
from frontend.sim.poses import look_at_pose
from frontend.sim.render import (
    FppSimulator,
    GroundTruth,
    RenderedFrame,
    RenderSettings,
    camera_ray_directions,
    project_points,
)
from frontend.sim.rig import (
    PREVIEW_SIZE,
    RigParameters,
    binned_calibration,
    build_rig,
    default_pattern_spec,
    default_rig,
    with_camera_resolution,
)
from frontend.sim.scenes import (
    CorridorConfig,
    Scene,
    TextureConfig,
    TurntableConfig,
    build_corridor,
    build_turntable,
    corridor_trajectory,
    frame_overlap,
    make_poster,
    plane_scene,
    sphere_scene,
)
from frontend.sim.sequences import SimulationSetup, load_simulation, simulate_sequence

__all__ = [
    "PREVIEW_SIZE",
    "BoardCalibrationSettings",
    "EstimatedCalibration",
    "CorridorConfig",
    "FppSimulator",
    "GroundTruth",
    "ImageMaterial",
    "Material",
    "ProceduralMaterial",
    "RenderSettings",
    "RenderedFrame",
    "RigParameters",
    "Scene",
    "SimulationSetup",
    "SurfacePart",
    "TextureConfig",
    "TurntableConfig",
    "VertexColorMaterial",
    "binned_calibration",
    "box",
    "calibration_errors",
    "build_corridor",
    "build_rig",
    "build_turntable",
    "camera_ray_directions",
    "corridor_trajectory",
    "cylinder",
    "default_pattern_spec",
    "default_rig",
    "estimate_rig_calibration",
    "frame_overlap",
    "load_mesh",
    "load_simulation",
    "look_at_pose",
    "make_doll",
    "make_poster",
    "place_mesh",
    "plane_scene",
    "project_points",
    "quad",
    "simulate_sequence",
    "sphere",
    "sphere_scene",
    "with_camera_resolution",
]
