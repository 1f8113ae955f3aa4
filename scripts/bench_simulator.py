"""Render speed of the virtual FPP sensor: one frame's full pattern stack.

    .venv/bin/python scripts/bench_simulator.py [--repeats 3] [--threads 0]

Target: a 1920x1200 frame's full stack (11 images of the default pattern set) in <= 3 s on
this machine. Prints the time of the ray cast + shading inputs (ground truth) and of the whole
stack, for a plane, the doll turntable and a corridor frame, at full and preview resolution.
The machine is shared with other jobs: the best of ``--repeats`` runs is the honest figure,
the median is printed too.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from frontend.sim import FppSimulator, default_pattern_spec, default_rig, load_simulation, scenes  # noqa: E402

DATASETS = Path(__file__).resolve().parents[1] / "datasets"


def bench(name: str, sim: FppSimulator, T: np.ndarray, repeats: int) -> None:
    sim.render(T, 0)  # warm-up: noise tiles, thread pools
    gt_times, full_times = [], []
    for k in range(repeats):
        t0 = time.perf_counter()
        sim.ground_truth(T)
        t1 = time.perf_counter()
        sim.render(T, k)
        t2 = time.perf_counter()
        gt_times.append(t1 - t0)
        full_times.append(t2 - t1)
    cam = sim.calibration.camera
    print(f"{name:28s} {cam.width}x{cam.height}, {sim.spec.image_count()} images: full stack best {min(full_times):.2f} s "
          f"(median {statistics.median(full_times):.2f}), of which ray cast + shading inputs {min(gt_times):.2f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=0, help="shading threads (0 = one per core)")
    args = parser.parse_args()
    spec = default_pattern_spec()
    for preview in (False, True):
        rig = default_rig(preview=preview)
        bench("plane", FppSimulator(rig, spec, scenes.plane_scene(0.5, tilt_deg=-7.0), threads=args.threads), np.eye(4), args.repeats)
        for cfg, k in (("turntable.yaml", 0), ("corridor.yaml", 5)):
            setup = load_simulation(DATASETS / cfg, preview=preview, max_frames=k + 1)
            sim = FppSimulator(setup.calibration, setup.spec, setup.scene, setup.settings, threads=args.threads)
            bench(f"{cfg} frame {k}", sim, setup.poses_world_sensor[k], args.repeats)
    print("target: <= 3 s per 1920x1200 frame's full pattern stack")


if __name__ == "__main__":
    main()
