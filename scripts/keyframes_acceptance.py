"""Acceptance figures of issue 7 (keyframes, loop closure, map re-fusion), printed.

    .venv/bin/python scripts/keyframes_acceptance.py --preview                 # 640x400, all parts
    .venv/bin/python scripts/keyframes_acceptance.py --resolution mid --only corridor
    .venv/bin/python scripts/keyframes_acceptance.py --preview --only turntable13,turntable24,badinput

Sequences are simulated into ``datasets/generated/<scene>_<resolution>`` when missing (reused
otherwise): ``turntable13`` is the paper's doll protocol (``datasets/turntable.yaml``, 3 turns x
13 views), ``turntable24`` the demo's (``fpp-slam demo``: 3 x 24 views, finer texture),
``corridor`` ``datasets/corridor.yaml`` (105 frames, a revisit and look-alike posters).
Resolutions: ``preview`` 640x400, ``mid`` 960x600 (the default rig with the camera binned by 2),
``full`` 1920x1200.

For each sequence it runs the whole pipeline in this process (one worker, so the peak RSS is
the run's) and prints: chain breaks and connected parts; loop candidates scored against ground
truth per stage (:mod:`fpp_graph.evaluation.loops`); for turntables the same-angle revisit pairs
found; ATE; map accuracy against the ground-truth mesh (Open3D RaycastingScene) before
(odometry only) and after loop closure; RSS at frame counts and per stage. ``badinput`` re-runs
the turntable24 keyframes with a block of views left out (no overlap across the gap).
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MID_RIG = {"camera_width": 960, "camera_height": 600, "camera_focal_px": 1024.0, "camera_principal_offset_px": [1.6, -1.35]}


def scene_config(name: str, resolution: str) -> dict:
    import yaml

    if name == "turntable24":
        from frontend.demo import DEFAULT_SCENE

        cfg = json.loads(json.dumps(DEFAULT_SCENE))
    else:
        cfg = yaml.safe_load((ROOT / "datasets" / f"{name.rstrip('0123456789')}.yaml").read_text())
    if resolution == "mid":
        cfg["rig"] = {**(cfg.get("rig") or {}), **MID_RIG}
    return cfg


def sequence_dir(name: str, resolution: str) -> Path:
    from frontend.sim import simulate_sequence

    path = ROOT / "datasets" / "generated" / f"{name}_{resolution}"
    if not (path / "sequence.yaml").exists():
        start = time.perf_counter()
        print(f"simulating {name} at {resolution} into {path} ...", flush=True)
        simulate_sequence(scene_config(name, resolution), path, preview=resolution == "preview", overwrite=True)
        print(f"  simulated in {time.perf_counter() - start:.0f} s", flush=True)
    return path


def _rss_mb(process) -> float:
    """RSS of a psutil process in MB, 0 when it has just ended."""
    import psutil

    try:
        return process.memory_info().rss / 2**20
    except psutil.Error:
        return 0.0


class RssSampler:
    """Peak RSS per stage and RSS at frame counts, sampled every 20 ms in a thread; at frame
    counts also the RSS of this process and all its children (the run's worker pool)."""

    def __init__(self) -> None:
        import psutil

        self.proc = psutil.Process()
        self.stage = "start"
        self.peak_mb: dict[str, float] = {}
        self.at_frames_mb: dict[int, float] = {}
        self.tree_at_frames_mb: dict[int, float] = {}
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop:
            rss = self.proc.memory_info().rss / 2**20
            self.peak_mb[self.stage] = max(self.peak_mb.get(self.stage, 0.0), rss)
            time.sleep(0.02)

    def progress(self, stage: str, done: int, total: int) -> None:
        self.stage = stage
        if stage == "frames" and (done % 10 == 0 or done == total):
            self.at_frames_mb[done] = self.proc.memory_info().rss / 2**20
            self.tree_at_frames_mb[done] = self.at_frames_mb[done] + sum(_rss_mb(c) for c in self.proc.children(recursive=True))

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop = True
        self._thread.join()


def map_figures(out: Path, source, slam, voxel_m: float) -> dict:
    """Map accuracy against the ground-truth mesh before (odometry only) and after loop closure."""
    from fpp_graph.evaluation.metrics import ate_rpe, load_mesh, point_to_mesh_distances
    from fpp_graph.evaluation.plots import plot_map_before_after
    from fpp_graph.slam.frame_store import FrameStore
    from fpp_graph.slam.map_fusion import fuse_points_only
    from fpp_graph.slam.pipeline import odometry_only_poses
    from fpp_graph.trajectory import read_tum

    estimate = read_tum(out / "trajectory.tum")
    err = ate_rpe(estimate, source.ground_truth())
    T = err.T_gt_estimate
    V, F = load_mesh(source.ground_truth_mesh())
    store = FrameStore.open(out / "frames", max_in_memory=2)
    figures: dict = {"ate_rmse_mm": err.ate_rmse_m * 1e3}
    clouds: dict = {}
    gt = dict(zip(source.frame_ids(), source.ground_truth().poses_world_sensor, strict=True))
    # "gt_poses": the same keyframes fused under the ground-truth poses, i.e. the map's accuracy
    # with registration taken out (what the front-end's points and the fusion give)
    for name, poses in (("before", odometry_only_poses(slam)), ("after", slam.poses_world_sensor), ("gt_poses", gt)):
        fused = fuse_points_only(poses, slam.keyframe_ids, store, voxel_m)
        A = np.eye(4) if name == "gt_poses" else T
        pts = fused.points_world_m @ A[:3, :3].T + A[:3, 3]
        d = point_to_mesh_distances(pts, V, F)
        clouds[name] = (pts, d)
        figures[name] = {
            "rms_mm": float(np.sqrt(np.mean(d**2))) * 1e3, "mean_mm": float(d.mean()) * 1e3,
            "p95_mm": float(np.percentile(d, 95)) * 1e3, "max_mm": float(d.max()) * 1e3, "points": int(len(d)),
        }
    png = out / "map_error_before_after.png"
    plot_map_before_after(
        png, clouds["before"][0], clouds["after"][0], errors_before_m=clouds["before"][1], errors_after_m=clouds["after"][1],
        titles=("before loop closure (odometry only)", "after loop closure"), error_max_mm=1.0,
    )
    png_gt = out / "map_error_after_vs_gt_poses.png"
    plot_map_before_after(
        png_gt, clouds["after"][0], clouds["gt_poses"][0], errors_before_m=clouds["after"][1], errors_after_m=clouds["gt_poses"][1],
        titles=("after loop closure", "same keyframes under ground-truth poses"), error_max_mm=1.0,
    )
    figures["png"] = [str(png), str(png_gt), str(out / "map_before_after.png"), str(out / "trajectory_top.png")]
    return figures


def same_angle_pairs(slam, views: int) -> dict:
    """Turntable revisits of the same table angle (frame ids differ by a multiple of ``views``)."""
    kf = slam.keyframe_ids
    truth = {(a, b) for i, a in enumerate(kf) for b in kf[i + 1:] if (b - a) % views == 0}
    rows = slam.loop_records
    pair = lambda r: (min(r.query_id, r.match_id), max(r.query_id, r.match_id))  # noqa: E731
    proposed = {pair(r) for r in rows} & truth
    verified = {pair(r) for r in rows if r.verified} & truth
    accepted = {pair(r) for r in rows if r.verified and not r.rejected_by_backend} & truth
    reasons: dict[str, int] = {}
    for r in rows:
        if pair(r) in truth and not r.verified:
            key = (r.reason or "").split("(")[0].split(":")[0].strip()
            reasons[key] = reasons.get(key, 0) + 1
    return {"true": len(truth), "proposed": len(proposed), "verified": len(verified), "accepted": len(accepted), "refused_because": reasons}


def run_sequence(name: str, resolution: str, results_root: Path, voxel_mm: float | None = None) -> dict:
    from fpp_graph.config import load_config
    from fpp_graph.evaluation.run_analyses import run_analyses
    from fpp_graph.slam.pipeline import Pipeline
    from fpp_graph.slam.sources import open_source

    seq = sequence_dir(name, resolution)
    cfg = load_config(None)
    cfg = cfg.model_copy(update={"run": cfg.run.model_copy(update={"workers": 1})})
    if voxel_mm:  # map resolution (a 6 m corridor at 1 mm is ~12 M voxels)
        v = voxel_mm * 1e-3
        cfg = cfg.model_copy(update={"fusion": cfg.fusion.model_copy(update={"voxel_size_m": v, "tsdf_voxel_m": 2 * v})})
    source = open_source(seq, cfg)
    out = results_root / f"{name}_{resolution}"
    wall, cpu = time.perf_counter(), time.process_time()
    with RssSampler() as rss:
        report = Pipeline(source, cfg, out, overwrite=True, progress=rss.progress, analyses=run_analyses()).run()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    slam = report.slam
    res: dict = {
        "sequence": str(seq), "results": str(out), "frames": report.frames_used, "keyframes": len(slam.keyframe_ids),
        "wall_s": wall, "cpu_s": cpu,
        "chain_breaks": [b.frame_id for b in slam.chain_breaks],
        "components": [[c[0], c[-1], len(c)] for c in slam.components],
        "loops": {k: report.metrics[k] for k in ("loop_candidates", "loops_verified", "loops_accepted", "loops_rejected_by_backend")},
        "loop_evaluation": report.metrics.get("loop_evaluation"),
        "rss_peak_mb_by_stage": {k: round(v) for k, v in rss.peak_mb.items()},
        "rss_mb_at_frames": {k: round(v) for k, v in sorted(rss.at_frames_mb.items())},
    }
    views = source.describe().get("views_per_turn")
    if views:
        res["same_angle_pairs"] = same_angle_pairs(slam, int(views))
    res["map"] = map_figures(out, source, slam, cfg.fusion.voxel_size_m)
    return res


def bad_input(results_root: Path, resolution: str, gap: tuple[int, int]) -> dict:
    """Re-run the turntable24 keyframes with views ``gap[0] .. gap[1]-1`` left out."""
    from fpp_graph.config import load_config
    from fpp_graph.slam.frame_store import FrameStore
    from fpp_graph.slam.keyframes import KeyframeManager
    from fpp_graph.slam.sources import open_source

    out = results_root / f"turntable24_{resolution}"
    if not (out / "frames").exists():
        raise SystemExit(f"badinput needs the turntable24 run in {out}; run --only turntable24 first")
    cfg = load_config(None)
    source = open_source(sequence_dir("turntable24", resolution), cfg)
    cache = FrameStore.open(out / "frames", max_in_memory=2)
    ids = [i for i in source.frame_ids() if not gap[0] <= i < gap[1]]
    manager = KeyframeManager(source.make_registrar(), cfg)
    for i in ids:
        manager.process(cache.get(i))
    result = manager.finish()
    return {
        "left_out": list(gap),
        "chain_breaks": [{"frame": b.frame_id, "after_keyframe": b.last_keyframe_id, "reason": b.reason} for b in result.chain_breaks],
        "components": [[c[0], c[-1], len(c)] for c in result.components],
        "poses": len(result.poses_world_sensor),
    }


def print_run(name: str, r: dict) -> None:
    print(f"\n== {name}: {r['frames']} frames, {r['keyframes']} keyframes, {r['wall_s']:.0f} s wall / {r['cpu_s']:.0f} s CPU ({r['results']})")
    print(f"chain breaks at frames {r['chain_breaks'][:30]}{' ...' if len(r['chain_breaks']) > 30 else ''} ({len(r['chain_breaks'])}); "
          f"{len(r['components'])} connected part(s), largest {max(c[2] for c in r['components'])} keyframes")
    print(f"loops: {r['loops']}")
    ev = r.get("loop_evaluation")
    if ev:
        print(f"loop candidates vs ground truth (overlap >= {ev['min_overlap']}; {ev['true_loops']} true loops among {ev['universe_pairs']} keyframe pairs):")
        for stage, s in ev["stages"].items():
            p = "  -  " if s["precision"] is None else f"{s['precision']:.3f}"
            print(f"  {stage:<11} pairs {s['pairs']:>5}  true {s['true']:>5}  precision {p}  recall {s['recall']:.3f}")
        print(f"  false loops verified: {len(ev['false_verified'])}, accepted after GNC: {len(ev['false_accepted'])} {ev['false_accepted'][:5]}")
    if "same_angle_pairs" in r:
        print(f"same-angle revisit pairs: {r['same_angle_pairs']}")
    m = r["map"]
    print(f"ATE {m['ate_rmse_mm']:.3f} mm; map vs GT mesh: before loop closure RMS {m['before']['rms_mm']:.3f} mm (p95 {m['before']['p95_mm']:.3f}), "
          f"after RMS {m['after']['rms_mm']:.3f} mm (mean {m['after']['mean_mm']:.3f}, p95 {m['after']['p95_mm']:.3f}, max {m['after']['max_mm']:.2f}, {m['after']['points']} points)")
    g = m["gt_poses"]
    print(f"map fused under ground-truth poses (registration taken out): RMS {g['rms_mm']:.3f} mm (mean {g['mean_mm']:.3f}, p95 {g['p95_mm']:.3f}, max {g['max_mm']:.2f})")
    print(f"RSS MB at frames {r['rss_mb_at_frames']}; peak by stage {r['rss_peak_mb_by_stage']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preview", action="store_true", help="640x400 (same as --resolution preview)")
    parser.add_argument("--resolution", choices=("preview", "mid", "full"), default="mid")
    parser.add_argument("--only", default="turntable13,turntable24,corridor,badinput", help="comma-separated parts")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "keyframes_acceptance")
    parser.add_argument("--voxel-mm", type=float, default=None, help="map voxel (TSDF voxel twice that); default: the config's")
    args = parser.parse_args(argv)
    resolution = "preview" if args.preview else args.resolution
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"resolution": resolution, "voxel_mm": args.voxel_mm}
    for part in [p.strip() for p in args.only.split(",") if p.strip()]:
        if part == "badinput":
            r = bad_input(args.out, resolution, (30, 42))
            print(f"\n== bad input: turntable24 with views {r['left_out'][0]}..{r['left_out'][1] - 1} left out (a 195 deg jump, no overlap)")
            for b in r["chain_breaks"]:
                print(f"  chain broke at frame {b['frame']} (after keyframe {b['after_keyframe']}): {b['reason']}")
            print(f"  {len(r['components'])} connected part(s) [first, last, keyframes]: {r['components']}; poses for {r['poses']} frames")
        else:
            r = run_sequence(part, resolution, args.out, args.voxel_mm)
            r["map_voxel_mm"] = args.voxel_mm or 1.0
            print_run(f"{part} ({resolution})", r)
        summary[part] = r
        (args.out / f"summary_{resolution}_{'_'.join(sorted(k for k in summary if k not in ('resolution', 'voxel_mm')))}.json").write_text(json.dumps(summary, indent=1, default=float))
    print(f"\nsummaries in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
