"""Tracking, loop closure and the final robust optimisation over a results folder's decoded frames.

Re-runs the back-end (KeyframeManager over the FPP registrar, default or given config) on the
``frames/`` an earlier ``fpp-slam run`` left, without decoding or fusing, and prints chain breaks,
loop figures (verified loops more than 5 mm off ground truth counted as wrong) and the ATE
(SE(3)-aligned) of the largest part. For iterating on registration/loop settings on the corridor.

    .venv/bin/python scripts/corridor_tracking.py RESULTS_DIR --gt datasets/generated/corridor/groundtruth.tum
"""

from __future__ import annotations

import argparse
import collections
import logging
import time
from pathlib import Path

import numpy as np

from fpp_graph.config import Config, load_config
from fpp_graph.evaluation.metrics import ate_rpe
from fpp_graph.slam.frame_store import FrameStore, load_frame
from fpp_graph.slam.keyframes import KeyframeManager
from fpp_graph.trajectory import Trajectory, read_tum
from frontend.registration import TexturedSurfaceRegistrar


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--gt", type=Path, required=True, help="ground-truth TUM file of the sequence")
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cfg = load_config(args.config) if args.config else Config()
    G = read_tum(args.gt).poses_world_sensor
    store = FrameStore.open(args.results / "frames", max_in_memory=cfg.run.frames_in_memory)
    ids = sorted(store.ids)[: args.frames]
    manager = KeyframeManager(TexturedSurfaceRegistrar(cfg.registration), cfg, store=store)
    t0 = time.time()
    for i in ids:
        manager.process(load_frame(store.path_of(i)))
    res = manager.finish()
    print(f"chain breaks {[b.frame_id for b in res.chain_breaks]}; parts {[(c[0], c[-1], len(c)) for c in res.components]}")
    wrong = 0
    for c in res.loops:
        T_true = np.linalg.inv(G[c.target_id]) @ G[c.source_id]
        if np.linalg.norm((np.linalg.inv(T_true) @ c.T_target_source)[:3, 3]) > 0.005:
            wrong += 1
    verified = sum(r.verified for r in res.loop_records)
    print(f"loop candidates {len(res.loop_records)}, verified {verified}, wrong (> 5 mm) {wrong}, removed by the back-end {len(res.rejected_loops)}")
    for (stage, reason), n in collections.Counter((r.stage, (r.reason or "accepted").split(" (")[0]) for r in res.loop_records).most_common(8):
        print(f"   {n:4d}  {stage}: {reason}")
    big = max(res.components, key=len)
    est = Trajectory.from_poses([float(i) for i in big], [res.poses_world_sensor[i] for i in big])
    ref = Trajectory.from_poses([float(i) for i in big], [G[i] for i in big])
    r = ate_rpe(est, ref)
    print(f"ATE of the largest part ({len(big)} frames): {r.ate_rmse_m * 1e3:.3f} mm RMS, max {r.ate_max_m * 1e3:.3f} mm; {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
