"""Real RGB-D sequences end to end, ours against the Open3D RGB-D recipe on the same frames.

    .venv/bin/python -m scripts.rgbd_acceptance [SEQUENCE ...] [--out results/rgbd_acceptance] [--no-peer] [--config YAML] [--seeds 0 1 2 3]

Default sequences: ../shared/data/rgbd/7scenes_chess_150_199 and ../shared/data/rgbd/tum_fr1_rpy_subset.
Per sequence:

* **ours**: ``fpp-slam run`` (:func:`fpp_graph.slam.pipeline.run_sequence`, the default worker
  pool) and ``fpp-slam eval``: ATE, loops verified / accepted (share kept), frames/s over the
  whole run, the split by stage, CPU utilisation (CPU seconds of this process and its workers
  over wall seconds times the cores), and the NEES of the run's own constraints
  (``graph.g2o``: every accepted odometry and loop edge against the reference poses,
  ``e^T I e`` with ``e = Log(T_gt^-1 T_edge)``, 6 on average when the information is right);
* **Open3D** (the user's obvious alternative): on the same decoded frames (our reader's, decoded
  before its clock starts, so the peer pays no decoding), ``compute_rgbd_odometry`` (hybrid colour + depth term, the
  pinhole ``K`` of the frames) between consecutive frames, initialised by constant velocity; a
  keyframe every 5 frames registered to the 3 keyframes before the last as uncertain edges;
  ``global_optimization`` (Levenberg-Marquardt, ``preference_loop_closure`` 0.1 as in Open3D's
  RGB-D reconstruction system for odometry-based edges). Its trajectory gets the same evaluation.

Frames/s of the peer exclude decoding, ours include it.

``--seeds``: ours once per ``run.seed`` (RANSAC's samples, the appearance vocabulary), each printed,
then the spread (min / median / max) of ATE, share of loops kept and NEES: a figure one seed
meets and another misses is a property of the draws, not of the method. The peer runs on the
first seed's frames.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from fpp_graph.slam.heap import keep_large_blocks_in_heap
from scripts.compare_open3d_multiway import cpu_seconds

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"
DEFAULT_SEQUENCES = [SHARED / "7scenes_chess_150_199", SHARED / "tum_fr1_rpy_subset"]


def constraint_nees(results: Path, gt_by_id: dict[int, np.ndarray]) -> dict[str, float]:
    """Mean and median NEES / 6 of the run's accepted edges (``graph.g2o``) against the reference."""
    from fpp_graph.backend.g2o import read_g2o
    from fpp_graph.geometry import invert, se3_log

    values: dict[str, list[float]] = {"odometry": [], "loop": []}
    for edge in read_g2o(results / "graph.g2o").edges():
        gt_t, gt_s = gt_by_id.get(edge.target_id), gt_by_id.get(edge.source_id)
        if gt_t is None or gt_s is None:
            continue
        e = se3_log(invert(invert(gt_t) @ gt_s) @ edge.T_target_source)
        values[str(edge.kind)].append(float(e @ edge.information_rot_trans @ e))
    every = values["odometry"] + values["loop"]
    return {
        "nees6_mean": float(np.mean(every) / 6) if every else float("nan"),
        "nees6_median": float(np.median(every) / 6) if every else float("nan"),
        "nees6_odometry_mean": float(np.mean(values["odometry"]) / 6) if values["odometry"] else float("nan"),
        "nees6_loops_mean": float(np.mean(values["loop"]) / 6) if values["loop"] else float("nan"),
        "edges": len(every),
    }


def run_ours(seq: Path, out: Path, config_path: Path | None = None, seed: int | None = None) -> dict:
    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.pipeline import run_sequence
    from fpp_graph.slam.sources import open_source

    wall0, cpu0 = time.perf_counter(), cpu_seconds()
    config = load_config(config_path)
    if seed is not None:
        config = config.model_copy(update={"run": config.run.model_copy(update={"seed": seed})})
    report = run_sequence(seq, config, out, overwrite=True, analyses=run_analyses())
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    # the run's config: its evaluation section (the reference's time offset) reads the reference
    source = open_source(seq, config)
    evaluation = evaluate_results(out, source)
    gt_by_id = {e.frame_id: e.T_world_sensor for e in source.entries}
    m = report.metrics
    return {
        "seed": config.run.seed, "frames": report.frames_used, "keyframes": m["keyframes"], "wall_s": wall, "cpu_s": cpu,
        "fps": report.frames_used / wall, "cpu_utilisation": cpu / (wall * (os.cpu_count() or 1)),
        "stages_s": m["seconds_by_stage"], "loop_candidates": m["loop_candidates"],
        "loops_verified": m["loops_verified"], "loops_accepted": m["loops_accepted"],
        "ate_rmse_mm": evaluation["ate_rmse_mm"], "ate_max_mm": evaluation["ate_max_mm"],
        **constraint_nees(out, gt_by_id),
    }


def open3d_rgbd(seq: Path, out: Path, keyframe_every: int = 5, keyframe_links: int = 3, config_path: Path | None = None) -> dict:
    """Open3D's RGB-D odometry + keyframe pose graph + global optimisation on our decoded frames."""
    import open3d as o3d

    from fpp_graph.config import load_config
    from fpp_graph.evaluation.results import evaluate_results
    from fpp_graph.slam.sources import open_source
    from fpp_graph.trajectory import Trajectory, write_tum

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    odo = o3d.pipelines.odometry
    # every frame decoded by our reader (the numbers our run tracked), before the peer's clock starts
    source = open_source(seq, load_config(config_path))
    frames = [source.load_frame(fid) for fid in source.frame_ids()]
    wall0, cpu0 = time.perf_counter(), cpu_seconds()
    K = np.asarray(frames[0].metadata["K"], dtype=np.float64)
    h, w = frames[0].xyz_map.shape[:2]
    intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    images = []
    for f in frames:
        depth = np.nan_to_num(f.xyz_map[..., 2].astype(np.float32), nan=0.0)
        rgb = np.repeat(f.texture[..., None], 3, axis=2) if f.texture.ndim == 2 else f.texture
        rgb = (np.clip(rgb.astype(np.float32) / (255.0 if rgb.max() > 1.5 else 1.0), 0, 1) * 255).astype(np.uint8)
        # Open3D's odometry needs the float intensity image its RGB conversion makes
        images.append(o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb)), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=4.0,
            convert_rgb_to_intensity=True))
    option = odo.OdometryOption()

    def pair(s: int, t: int, init: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:
        ok, T, info = odo.compute_rgbd_odometry(images[s], images[t], intrinsic, init, odo.RGBDOdometryJacobianFromHybridTerm(), option)
        return ok, np.asarray(T), np.asarray(info)

    graph = reg.PoseGraph()
    T_world = [np.eye(4)]
    graph.nodes.append(reg.PoseGraphNode(np.eye(4)))
    step = np.eye(4)
    for k in range(1, len(frames)):
        ok, T_prev_k, info = pair(k, k - 1, step)  # maps frame k's points into frame k-1
        if not ok:
            T_prev_k, info = step, np.eye(6)
        step = T_prev_k
        T_world.append(T_world[-1] @ T_prev_k)
        graph.nodes.append(reg.PoseGraphNode(T_world[-1]))
        graph.edges.append(reg.PoseGraphEdge(k, k - 1, T_prev_k, info, uncertain=False))
    keyframes = list(range(0, len(frames), keyframe_every))
    links = 0
    for i, t in enumerate(keyframes):
        for s in keyframes[max(0, i - 1 - keyframe_links): max(0, i - 1)]:
            ok, T, info = pair(t, s, np.linalg.inv(T_world[s]) @ T_world[t])
            if ok:
                graph.edges.append(reg.PoseGraphEdge(t, s, T, info, uncertain=True))
                links += 1
    reg.global_optimization(
        graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(),
        reg.GlobalOptimizationOption(max_correspondence_distance=0.03, edge_prune_threshold=0.25, preference_loop_closure=0.1, reference_node=0),
    )
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", Trajectory.from_poses([f.timestamp for f in frames], [np.asarray(n.pose) for n in graph.nodes]))
    evaluation = evaluate_results(out, open_source(seq, load_config(config_path)))  # against the same reference as ours
    return {"frames": len(frames), "wall_s": wall, "cpu_s": cpu, "fps": len(frames) / wall, "keyframe_links": links,
            "ate_rmse_mm": evaluation["ate_rmse_mm"], "ate_max_mm": evaluation["ate_max_mm"]}


def kept_share(ours: dict) -> float:
    """Share of the verified loops the back-end kept (NaN without verified loops)."""
    return ours["loops_accepted"] / ours["loops_verified"] if ours["loops_verified"] else float("nan")


def print_ours(ours: dict, multiple: bool) -> None:
    stages = ", ".join(f"{k} {v:.1f} s ({100 * v / ours['wall_s']:.0f} %)" for k, v in ours["stages_s"].items())
    label = f"seed {ours['seed']}" if multiple else "ours"
    print(f"{label:7s}: ATE {ours['ate_rmse_mm']:.1f} mm (max {ours['ate_max_mm']:.1f}); loops {ours['loop_candidates']} proposed, "
          f"{ours['loops_verified']} verified, {ours['loops_accepted']} accepted ({100 * kept_share(ours):.0f} % kept); "
          f"{ours['fps']:.2f} frames/s ({ours['wall_s']:.1f} s wall, CPU utilisation {100 * ours['cpu_utilisation']:.0f} % of "
          f"{os.cpu_count()} cores); NEES/6 of its {ours['edges']} edges: mean {ours['nees6_mean']:.2f}, median "
          f"{ours['nees6_median']:.2f}; odometry {ours['nees6_odometry_mean']:.2f}, loops {ours['nees6_loops_mean']:.2f}")
    print(f"         stages: {stages}")


def spread(runs: list[dict]) -> dict[str, dict[str, float]]:
    """Min / median / max over the seeds' runs of the figures the acceptance lines name."""
    figures = {
        "ATE mm": [r["ate_rmse_mm"] for r in runs],
        "% kept": [100 * kept_share(r) for r in runs],
        "NEES/6": [r["nees6_mean"] for r in runs],
        "frames/s": [r["fps"] for r in runs],
    }
    return {k: {"min": float(np.min(v)), "median": float(np.median(v)), "max": float(np.max(v))} for k, v in figures.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="*", type=Path, default=DEFAULT_SEQUENCES)
    parser.add_argument("--out", type=Path, default=Path("results/rgbd_acceptance"))
    parser.add_argument("--no-peer", action="store_true", help="skip the Open3D recipe")
    parser.add_argument("--config", type=Path, default=None, help="fpp-slam config YAML for our runs (default: the defaults)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="run ours once per run.seed and print the spread (default: the config's seed)")
    args = parser.parse_args(argv)
    keep_large_blocks_in_heap()  # as fpp-slam run does in its own process
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows = {}
    for seq in args.sequences:
        if not seq.is_dir():
            print(f"{seq}: not found, skipped", file=sys.stderr)
            continue
        runs = []
        for i, seed in enumerate(args.seeds or [None]):
            ours_dir = args.out / seq.name / ("ours" if i == 0 else f"ours_seed{seed}")
            runs.append(run_ours(seq, ours_dir, args.config, seed))
            if i == 0:
                print(f"== {seq.name}: {runs[0]['frames']} frames, {runs[0]['keyframes']} keyframes")
            print_ours(runs[-1], multiple=len(args.seeds or []) > 1)
        ours = runs[0]
        row = {"ours": ours}
        if len(runs) > 1:
            row["seeds"] = runs
            row["spread"] = spread(runs)
            print("spread : " + "; ".join(f"{k} {v['min']:.2f} / {v['median']:.2f} / {v['max']:.2f}" for k, v in row["spread"].items())
                  + f" (min / median / max over seeds {', '.join(str(r['seed']) for r in runs)})")
        if not args.no_peer:
            peer = open3d_rgbd(seq, args.out / seq.name / "open3d", config_path=args.config)
            row["open3d"] = peer
            print(f"open3d : ATE {peer['ate_rmse_mm']:.1f} mm (max {peer['ate_max_mm']:.1f}); {peer['keyframe_links']} keyframe edges; "
                  f"{peer['fps']:.2f} frames/s ({peer['wall_s']:.1f} s wall, decoded frames given)")
            print(f"ratio  : ATE ours/open3d {ours['ate_rmse_mm'] / peer['ate_rmse_mm']:.2f}; frames/s ours/open3d {ours['fps'] / peer['fps']:.2f}")
        rows[seq.name] = row
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rgbd_acceptance.json").write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
