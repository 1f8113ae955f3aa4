"""The peer: a plain gtsam script (chordal initialisation + Levenberg-Marquardt) on a g2o file.

A planar file (``VERTEX_SE2``, ``EDGE_SE2``) is solved as gtsam Pose2 from LAGO's start (gtsam's
Pose2 initialiser), with SE-Sync's planar ``tau = 2 / trace(inv(I_xy))`` and ``kappa = I_theta``
and ``F = sum kappa ||R_j - R_i R_ij||_F^2 + tau ||t_j - t_i - R_i t_ij||^2`` over 2x2 rotations.

It does not import fpp_graph: it is what a user would write in 25 lines, and what the back-end's
default ``fpp-slam optimize`` is measured against (``scripts/bench_pose_graph_peer.py``). The
noise model is SE-Sync's isotropic one (tau, kappa from the information blocks, the same model as
``--noise-model isotropic``); the file is parsed with numpy because ``gtsam.readG2o`` alters
information matrices that are not positive definite. Prints one JSON line: poses, edges, the
SE-Sync objective F at the solution, the LM iterations and the solve time.

    python scripts/plain_gtsam_g2o.py GRAPH.g2o [--prior-sigma 1e-6] [--max-iterations 100]

``--prior-sigma`` is the gauge prior on the first pose (it does not move the optimum; the
benchmark varies it to show how far a run that stops at its iteration limit depends on it).
"""

import json
import sys
import time

import gtsam
import numpy as np

options = dict(zip(sys.argv[2::2], sys.argv[3::2], strict=True))  # no argparse: ~3 ms of import
prior_sigma, max_iterations = float(options.pop("--prior-sigma", 1e-6)), int(options.pop("--max-iterations", 100))
assert not options, f"unknown options {options}"
start = time.perf_counter()
rows = [line.split() for line in open(sys.argv[1]) if line.strip()]


def planar() -> dict:
    """Pose2: LAGO + LM, SE-Sync's planar tau and kappa; the JSON fields as for 3D."""
    vertices = {int(r[1]): np.array(r[2:5], float) for r in rows if r[0] == "VERTEX_SE2"}
    edges = [(int(r[1]), int(r[2]), np.array(r[3:12], float)) for r in rows if r[0] == "EDGE_SE2"]
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for key, (x, y, theta) in vertices.items():
        initial.insert(key, gtsam.Pose2(x, y, theta))
    weights = []
    for i, j, v in edges:
        info = np.zeros((3, 3))
        info[np.triu_indices(3)] = v[3:]
        info = info + np.triu(info, 1).T  # g2o order [x, y, theta], as gtsam's Pose2 tangent
        tau, kappa = 2.0 / np.trace(np.linalg.inv(info[:2, :2])), info[2, 2]
        weights.append((tau, kappa))
        graph.add(gtsam.BetweenFactorPose2(i, j, gtsam.Pose2(*v[:3]), gtsam.noiseModel.Diagonal.Precisions([2 * tau, 2 * tau, 4 * kappa])))
    first = min(vertices)
    graph.add(gtsam.PriorFactorPose2(first, initial.atPose2(first), gtsam.noiseModel.Isotropic.Sigma(3, prior_sigma)))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, gtsam.lago.initialize(graph), lm_params())
    result = optimizer.optimize()
    F = 0.0
    for (i, j, v), (tau, kappa) in zip(edges, weights, strict=True):
        Ti, Tj = result.atPose2(i), result.atPose2(j)
        Ri = Ti.rotation().matrix()
        F += kappa * np.sum((Tj.rotation().matrix() - Ri @ gtsam.Rot2(v[2]).matrix()) ** 2)
        F += tau * np.sum((Tj.translation() - Ti.translation() - Ri @ v[:2]) ** 2)
    return {"poses": len(vertices), "edges": len(edges), "sesync_objective": F, "iterations": optimizer.iterations()}


def lm_params() -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    params.setErrorTol(0.0)
    params.setMaxIterations(max_iterations)
    return params


if any(r[0] == "VERTEX_SE2" for r in rows):
    print(json.dumps({**planar(), "seconds": time.perf_counter() - start}))
    sys.exit(0)
importing = time.perf_counter()  # 3D only: a planar script has no use for scipy's ~0.4 s import
from scipy.spatial.transform import Rotation  # noqa: E402

start += time.perf_counter() - importing  # the solve time excludes the import, as at the top of the script

vertices = {int(r[1]): np.array(r[2:9], float) for r in rows if r[0] == "VERTEX_SE3:QUAT"}
edges = [(int(r[1]), int(r[2]), np.array(r[3:31], float)) for r in rows if r[0] == "EDGE_SE3:QUAT"]
graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
for key, v in vertices.items():
    initial.insert(key, gtsam.Pose3(gtsam.Rot3(Rotation.from_quat(v[3:]).as_matrix()), v[:3]))
upper, tau, kappa, measured = np.triu_indices(6), [], [], []
for i, j, v in edges:
    info = np.zeros((6, 6))
    info[upper] = v[7:]
    info = info + np.triu(info, 1).T  # g2o order [trans, rot]
    tau.append(3.0 / np.trace(np.linalg.inv(info[:3, :3])))
    kappa.append(3.0 / (2.0 * np.trace(np.linalg.inv(info[3:, 3:]))))
    measured.append((Rotation.from_quat(v[3:7]).as_matrix(), v[:3]))
    precisions = np.array([4 * kappa[-1]] * 3 + [2 * tau[-1]] * 3)  # GTSAM [rot, trans]
    graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(gtsam.Rot3(measured[-1][0]), measured[-1][1]),
                                       gtsam.noiseModel.Diagonal.Precisions(precisions)))
graph.add(gtsam.PriorFactorPose3(min(vertices), initial.atPose3(min(vertices)), gtsam.noiseModel.Isotropic.Sigma(6, prior_sigma)))
optimizer = gtsam.LevenbergMarquardtOptimizer(graph, gtsam.InitializePose3.initialize(graph), lm_params())
result = optimizer.optimize()
F = 0.0
for (i, j, _), (R_ij, t_ij), ta, ka in zip(edges, measured, tau, kappa, strict=True):
    Ti, Tj = result.atPose3(i), result.atPose3(j)
    F += ka * np.sum((Tj.rotation().matrix() - Ti.rotation().matrix() @ R_ij) ** 2)
    F += ta * np.sum((Tj.translation() - Ti.translation() - Ti.rotation().matrix() @ t_ij) ** 2)
print(json.dumps({"poses": len(vertices), "edges": len(edges), "sesync_objective": F,
                  "iterations": optimizer.iterations(), "seconds": time.perf_counter() - start}))
