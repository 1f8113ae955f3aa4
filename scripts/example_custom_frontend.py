"""Plug the fpp-graph back-end under your own front-end, from Python.

Your front-end supplies two things: ``Frame`` objects (points in metres, sensor frame; optionally
an organised xyz map, a texture and keypoint descriptors) and a ``PairRegistrar`` whose
``register(target, source, T_guess)`` returns a ``Constraint`` (``T_target_source`` + 6x6
information in [rot, trans] order, or a rejected constraint with a reason). The back-end does
keyframes, loop detection and verification, the robust pose graph, and writes the trajectory.

Run: .venv/bin/python scripts/example_custom_frontend.py [--out results/example]
Here the "front-end" is a toy: a sensor circling a scene twice, its registrar returning the
true relative pose plus noise when the views overlap, and rejecting otherwise.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fpp_graph.config import config_from_dict
from fpp_graph.geometry import invert, make_pose, se3_exp
from fpp_graph.slam.keyframes import KeyframeManager
from fpp_graph.trajectory import Trajectory, write_tum
from fpp_graph.types import Constraint, ConstraintKind, Frame


class NoisyOracleRegistrar:
    """A stand-in for your registration: true relative pose + noise, or a reasoned rejection."""

    def __init__(self, truth: dict[int, np.ndarray], sigma_rot: float = 1e-3, sigma_trans: float = 1e-3, seed: int = 0) -> None:
        self.truth, self.rng = truth, np.random.default_rng(seed)
        self.sigmas = np.array([sigma_rot] * 3 + [sigma_trans] * 3)

    def register(self, target: Frame, source: Frame, T_guess=None, kind=ConstraintKind.ODOMETRY) -> Constraint:
        # the protocol passes kind (odometry or loop); this stand-in verifies both alike
        T_true = invert(self.truth[target.id]) @ self.truth[source.id]
        if np.linalg.norm(Rotation.from_matrix(T_true[:3, :3]).as_rotvec()) > math.radians(45):
            return Constraint.rejected(source.id, target.id, "low overlap (views more than 45 deg apart)")
        noisy = T_true @ se3_exp(self.rng.normal(size=6) * self.sigmas)
        return Constraint(source.id, target.id, noisy, np.diag(1 / self.sigmas**2), fitness=0.8, inlier_count=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/example_custom_frontend"))
    args = parser.parse_args()

    views, turns, radius = 16, 2, 1.0
    truth = {}
    for i in range(views * turns):
        theta = 2 * math.pi * (i % views) / views
        truth[i] = make_pose(Rotation.from_euler("y", -theta).as_matrix(), [radius * math.sin(theta), 0, -radius * math.cos(theta)])
    rng = np.random.default_rng(1)
    place_descriptors = [rng.normal(size=(200, 32)).astype(np.float32) for _ in range(views)]

    # these frames carry no camera model (Frame.camera), which the keyframe rule measures view
    # change with: every frame is made a keyframe (views 22.5 degrees apart are distinct anyway)
    config = config_from_dict({"keyframes": {"min_view_change": 0}, "loop_closure": {"proximity_radius_m": 0.2}})
    manager = KeyframeManager(NoisyOracleRegistrar(truth), config)
    for i in range(views * turns):
        # your front-end would make this Frame from its sensor data
        frame = Frame(
            id=i, timestamp=0.1 * i, points=rng.normal(size=(100, 3)),
            keypoints_uv=rng.uniform(0, 640, (200, 2)),
            descriptors=place_descriptors[i % views] + rng.normal(scale=0.2, size=(200, 32)).astype(np.float32),
        )
        manager.process(frame)
    result = manager.finish()

    # the first pose is anchored at identity: express the truth relative to it to compare
    T0 = truth[0]
    errors = [np.linalg.norm((invert(T0) @ truth[i])[:3, 3] - T[:3, 3]) for i, T in result.poses_world_sensor.items()]
    accepted = sum(r.verified and not r.rejected_by_backend for r in result.loop_records)
    ids = sorted(result.poses_world_sensor)
    write_tum(args.out / "trajectory.tum", Trajectory.from_poses([0.1 * i for i in ids], [result.poses_world_sensor[i] for i in ids]))
    print(f"{len(ids)} poses, {accepted} loops accepted of {len(result.loop_records)} candidates")
    print(f"position error after loop closure: max {max(errors) * 1e3:.2f} mm, rms {math.sqrt(np.mean(np.square(errors))) * 1e3:.2f} mm")
    print(f"trajectory written to {args.out / 'trajectory.tum'}")


if __name__ == "__main__":
    main()
