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
- :mod:`~frontend.sim.sequences`: scene YAML -> :class:`~frontend.sim.sequences.SimulationSetup` -> sequence folder.
"""

from frontend.sim.calibration import (
    calibration_errors,
    estimate_rig_calibration,
)
from frontend.sim.poses import look_at_pose
from frontend.sim.render import (
    FppSimulator,
    RenderSettings,
)
from frontend.sim.rig import (
    RigParameters,
    binned_calibration,
    build_rig,
    default_pattern_spec,
    default_rig,
    with_camera_resolution,
)
from frontend.sim.scenes import (
    Scene,
    build_corridor,
    plane_scene,
    sphere_scene,
)
from frontend.sim.sequences import load_simulation, simulate_sequence

__all__ = [
    "FppSimulator",
    "RenderSettings",
    "RigParameters",
    "Scene",
    "binned_calibration",
    "calibration_errors",
    "build_corridor",
    "build_rig",
    "default_pattern_spec",
    "default_rig",
    "estimate_rig_calibration",
    "load_simulation",
    "look_at_pose",
    "plane_scene",
    "simulate_sequence",
    "sphere_scene",
    "with_camera_resolution",
]
