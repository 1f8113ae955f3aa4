"""Side by side: fpp-graph vs Open3D's multiway registration on the same simulated sequences.

    .venv/bin/python scripts/compare_open3d_multiway.py [--scenes turntable corridor] [--full] [--frames N]

For each scene the sequence is simulated (640x400 preview unless ``--full``), then:

* **ours**: ``fpp-slam run`` (the same :func:`fpp_graph.slam.pipeline.run_sequence`), evaluated with
  ``fpp-slam eval`` (:func:`fpp_graph.evaluation.results.evaluate_results`);
* **Open3D** (the user's obvious alternative, the multiway-registration tutorial): on the *same
  decoded frames* (our run's frame cache, so the peer pays no decoding), each cloud voxel-
  downsampled to our ICP voxel with normals (radius 2 voxels); pairwise multiscale point-to-plane
  ICP (coarse 15 voxels then fine 1.5 voxels, the tutorial's settings), information from
  ``get_information_matrix_from_point_clouds``; each pair starts both from a guess and from the
  global-registration tutorial's FPFH + RANSAC result (features on a 5-voxel cloud), keeping the
  ICP result of higher fitness; odometry edges between consecutive frames
  (initialised by constant velocity), loop edges (``uncertain=True``) on exactly the candidate
  pairs our loop detector proposed (``loops.json``), initialised from the odometry chain;
  ``global_optimization`` (Levenberg-Marquardt, ``max_correspondence_distance`` 1.5 voxels,
  ``edge_prune_threshold`` 0.25, ``preference_loop_closure`` 2.0, reference node 0); then a
  TSDF ``VoxelBlockGrid`` (our TSDF voxel and truncation) integrating every frame's depth, whose
  extracted point cloud is the peer's map.

Both are scored by the same evaluation (SE(3)-aligned ATE, map RMS distance to the GT mesh after
the same alignment). Times: wall and CPU (this process + its worker processes). Ours includes
fringe decoding and feature detection; the peer's does not (it starts from decoded clouds).
The table is printed and written to ``--out``/compare.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import sys
import time
from pathlib import Path

import numpy as np


def cpu_seconds() -> float:
    """CPU of this process and of its finished children (worker processes)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def run_ours(seq: Path, out: Path, config_path: Path | None = None) -> dict:
    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.pipeline import run_sequence
    from fpp_graph.slam.sources import open_source

    wall0, cpu0 = time.perf_counter(), cpu_seconds()
    run_sequence(seq, load_config(config_path), out, resume=False, overwrite=True, kind=None, analyses=run_analyses())
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    metrics = evaluate_results(out, open_source(seq, load_config(None)))
    return {"wall_s": wall, "cpu_s": cpu, **metrics}


# -- the peer: Open3D multiway registration ----------------------------------------------------
def open3d_multiway(ours_dir: Path, seq: Path, out: Path) -> dict:
    """Open3D's multiway registration and TSDF on our frames and loop candidates; its metrics."""
    import open3d as o3d

    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.fusion.tsdf_mesh import TSDF_TRUNCATION_VOXELS
    from fpp_graph.slam.frame_store import load_frame
    from fpp_graph.slam.sources import open_source
    from fpp_graph.trajectory import Trajectory, write_tum

    config = load_config(ours_dir / "config.yaml")
    out.mkdir(parents=True, exist_ok=True)
    loops = json.loads((ours_dir / "loops.json").read_text())
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

    wall0, cpu0 = time.perf_counter(), cpu_seconds()
    frames = [load_frame(p) for p in sorted((ours_dir / "frames").glob("frame_*.npz"))]
    poses, pairs, kept_loops = _open3d_pose_graph(frames, loops, config.registration.lengths.icp_voxel_m)
    t_graph = time.perf_counter() - wall0
    cloud = _open3d_tsdf(frames, poses, config.fusion.tsdf_voxel_m, TSDF_TRUNCATION_VOXELS * config.fusion.tsdf_voxel_m)
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    if not o3d.io.write_point_cloud(str(out / "map.ply"), cloud):
        raise RuntimeError(f"Open3D could not write {out / 'map.ply'} ({len(cloud.points)} points)")
    write_tum(out / "trajectory.tum", Trajectory.from_poses([f.timestamp for f in frames], poses))
    (out / "metrics.json").write_text(json.dumps({"seconds": wall, "loop_candidates": pairs}))
    metrics = evaluate_results(out, open_source(seq, load_config(None)))
    return {"wall_s": wall, "cpu_s": cpu, "graph_s": t_graph, "loop_edges": pairs, "loop_edges_kept": kept_loops, **metrics}


def _open3d_pose_graph(frames: list, loops: list[dict], voxel: float) -> tuple[list[np.ndarray], int, int]:
    """The tutorial's multiway registration: poses (T_world_frame), loop pairs tried, loop edges kept."""
    import open3d as o3d

    from fpp_graph.geometry import invert

    reg = o3d.pipelines.registration
    index = {f.id: k for k, f in enumerate(frames)}
    clouds = []
    for f in frames:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(f.points, dtype=np.float64)))
        pcd = pcd.voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        clouds.append(pcd)
    coarse, fine = 15 * voxel, 1.5 * voxel
    # global registration (the tutorial's FPFH + RANSAC, features on a 5x coarser cloud) gives
    # every pair a second starting point: the peer does not depend on our odometry being right
    feature_voxel = 5 * voxel
    feature_clouds, features = [], []
    for pcd in clouds:
        down = pcd.voxel_down_sample(feature_voxel)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * feature_voxel, max_nn=30))
        feature_clouds.append(down)
        features.append(reg.compute_fpfh_feature(down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * feature_voxel, max_nn=100)))

    def global_guess(s: int, t: int):
        d = 1.5 * feature_voxel
        return reg.registration_ransac_based_on_feature_matching(
            feature_clouds[s], feature_clouds[t], features[s], features[t], True, d,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(d)],
            reg.RANSACConvergenceCriteria(100000, 0.999),
        ).transformation

    def pairwise(s: int, t: int, init):
        """The tutorial's multiscale point-to-plane ICP of source s into target t, from ``init``
        and from the global guess; the result with the higher fine fitness wins."""
        source, target = clouds[s], clouds[t]
        best = None
        for start in (init, global_guess(s, t)):
            icp_coarse = reg.registration_icp(source, target, coarse, start, reg.TransformationEstimationPointToPlane())
            icp_fine = reg.registration_icp(source, target, fine, icp_coarse.transformation, reg.TransformationEstimationPointToPlane())
            if best is None or icp_fine.fitness > best.fitness:
                best = icp_fine
        info = reg.get_information_matrix_from_point_clouds(source, target, fine, best.transformation)
        return best.transformation, info

    graph = reg.PoseGraph()
    T_world_k = [np.eye(4)]
    graph.nodes.append(reg.PoseGraphNode(np.eye(4)))
    velocity = np.eye(4)  # T_{k}_{k-1} of the previous step
    for k in range(1, len(frames)):
        # edge source k-1 -> target k (the tutorial's order: transformation maps source into target)
        T_k_km1, info = pairwise(k - 1, k, velocity)
        velocity = T_k_km1
        T_world_k.append(T_world_k[-1] @ invert(T_k_km1))
        graph.nodes.append(reg.PoseGraphNode(T_world_k[-1]))
        graph.edges.append(reg.PoseGraphEdge(k - 1, k, T_k_km1, info, uncertain=False))
    pairs = sorted({(r["match"], r["query"]) for r in loops if r["match"] in index and r["query"] in index})
    for match, query in pairs:
        s, t = index[match], index[query]  # source = the earlier frame, target = the revisit
        init = invert(T_world_k[t]) @ T_world_k[s]
        T, info = pairwise(s, t, init)
        graph.edges.append(reg.PoseGraphEdge(s, t, T, info, uncertain=True))
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=fine, edge_prune_threshold=0.25, preference_loop_closure=2.0, reference_node=0
    )
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option)
    kept_loops = sum(1 for e in graph.edges if e.uncertain)
    return [np.asarray(graph.nodes[k].pose) for k in range(len(frames))], len(pairs), kept_loops


def _open3d_tsdf(frames: list, poses: list[np.ndarray], voxel_m: float, truncation_m: float):
    """Open3D's TSDF: the tensor VoxelBlockGrid (the legacy ScalableTSDFVolume of open3d 0.20
    extracts nothing here, see fpp_graph/fusion/voxel_map.py), our TSDF voxel and truncation."""
    import open3d as o3d

    from fpp_graph.fusion.voxel_map import intrinsics_of, render_depth
    from fpp_graph.geometry import invert

    trunc_voxels = truncation_m / voxel_m
    volume = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
        attr_channels=((1), (1), (3)), voxel_size=voxel_m, block_resolution=16, block_count=50000,
        device=o3d.core.Device("CPU:0"),
    )
    for f, T in zip(frames, poses, strict=True):
        K = intrinsics_of(f)
        depth_m, rgb = render_depth(f, K)
        depth = o3d.t.geometry.Image(o3d.core.Tensor(depth_m.astype(np.float32)))
        color = o3d.t.geometry.Image(o3d.core.Tensor(rgb.astype(np.float32) / 255.0))
        intrinsic = o3d.core.Tensor(K, dtype=o3d.core.float64)
        extrinsic = o3d.core.Tensor(invert(T), dtype=o3d.core.float64)
        depth_max = float(depth_m.max()) + 1.0
        blocks = volume.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, depth_max, trunc_voxels)
        volume.integrate(blocks, depth, color, intrinsic, extrinsic, 1.0, depth_max, trunc_voxels)
    return volume.extract_point_cloud().to_legacy()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["turntable", "corridor"], choices=["turntable", "bunny", "corridor"])
    parser.add_argument("--full", action="store_true", help="1920x1200 instead of the 640x400 preview")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames of each sequence")
    parser.add_argument("--config", type=Path, default=None, help="fpp-slam config file for our runs (e.g. preview-sized registration gates)")
    parser.add_argument("--out", type=Path, default=Path("results/compare_open3d"))
    parser.add_argument("--reuse-ours", action="store_true", help="keep an earlier run of ours in --out (its time is then read from metrics.json)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("compare").setLevel(logging.INFO)
    from frontend.demo import simulate_once

    rows = []
    for name in args.scenes:
        folder = args.out / name
        seq = simulate_once(name, folder / "sequence", args.full, args.frames)
        if args.reuse_ours and (folder / "ours" / "metrics.json").exists():
            from fpp_graph.config import load_config
            from fpp_graph.evaluation.results import evaluate_results
            from fpp_graph.slam.sources import open_source

            ours = evaluate_results(folder / "ours", open_source(seq, load_config(None)))
            ours.update(wall_s=ours["run_seconds"], cpu_s=float("nan"))
        else:
            ours = run_ours(seq, folder / "ours", args.config)
        peer = open3d_multiway(folder / "ours", seq, folder / "open3d")
        rows.append((name, ours, peer))
        print(f"{name}: ours ATE {ours['ate_rmse_mm']:.4f} mm, map {ours.get('map_rmse_mm', float('nan')):.4f} mm, "
              f"{ours['wall_s']:.1f} s | Open3D ATE {peer['ate_rmse_mm']:.4f} mm, map {peer.get('map_rmse_mm', float('nan')):.4f} mm, "
              f"{peer['wall_s']:.1f} s", flush=True)
    res = "1920x1200" if args.full else "640x400 preview"
    lines = [
        f"# fpp-graph vs Open3D multiway registration ({res})", "",
        "| scene | frames | method | ATE RMSE mm | map RMSE mm | map p95 mm | wall s | CPU s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, ours, peer in rows:
        for label, m in (("fpp-graph", ours), ("Open3D multiway", peer)):
            lines.append(
                f"| {name} | {m['frames']} | {label} | {m['ate_rmse_mm']:.4f} | {m.get('map_rmse_mm', float('nan')):.4f} | "
                f"{m.get('map_p95_mm', float('nan')):.4f} | {m['wall_s']:.1f} | {m['cpu_s']:.1f} |"
            )
    lines += ["", "Ratios Open3D / ours (> 1: ours better or faster):", "",
              "| scene | ATE | map RMSE | wall time | CPU time |", "|---|---|---|---|---|"]
    for name, ours, peer in rows:
        def ratio(key, ours=ours, peer=peer):
            a, b = peer.get(key, float("nan")), ours.get(key, float("nan"))
            return a / b if b else float("nan")
        lines.append(f"| {name} | {ratio('ate_rmse_mm'):.2f} | {ratio('map_rmse_mm'):.2f} | {ratio('wall_s'):.2f} | {ratio('cpu_s'):.2f} |")
    if args.config:
        lines += ["", f"Our runs used the config {args.config}: {' '.join(args.config.read_text().split())}"]
    counts = ", ".join(f"{n}: {p['loop_edges']} proposed, {p['loop_edges_kept']} kept" for n, _, p in rows)
    lines += ["", "Ours includes decoding and features; the peer starts from our decoded clouds. "
              f"Open3D loop edges on the same candidate pairs as ours ({counts})."]
    text = "\n".join(lines) + "\n"
    print(text)
    (args.out / "compare.md").write_text(text)
    (args.out / "compare.json").write_text(json.dumps([{"scene": n, "ours": o, "open3d": p} for n, o, p in rows], default=float, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
