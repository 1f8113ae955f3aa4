"""Accuracy, covariance consistency, rejection and DLT figures of the pairwise registration.

Data: ray-cast synthetic frames (:mod:`frontend.testing.synthetic_frames`: a textured bumpy wall with
boxes, 0.05 mm depth noise along the ray, 640x400 camera with the paper rig's field of view),
not the fringe simulator. Groups of pairs:

* ``shift``: lateral moves of 0.15-0.30 m at 0.5 m (down to about one-third overlap) with
  +-5 deg rotations;
* ``orbit``: the sensor orbits a wall point by 360/13 deg (adjacent turntable views);
* rejection tries: frames at distinct places of walls with different textures (no true
  overlap), plus look-alikes (a texture repeating every 0.6 m, frames one period apart, on a
  flat and on a bumpy wall).

Printed: per feature type (surf = the project's, sift, orb) the rotation/translation error
distribution, inliers and time; NEES with the raw information and the calibrated scale; the
rejection rate with reasons; DLT camera-centre errors.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python scripts/registration_accuracy.py --pairs 36
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from fpp_graph.geometry import invert, pose_error, se3_log  # noqa: E402
from frontend.config import RegistrationConfig  # noqa: E402
from frontend.localization import localize_dlt  # noqa: E402
from frontend.registration import TexturedSurfaceRegistrar, lift_keypoints  # noqa: E402
from frontend.testing.synthetic_frames import bumpy_wall_scene, render_frame, wall_pose  # noqa: E402

W, H = 640, 400


def orbit_pose(angle_deg: float, centre=(0.0, 0.0, 0.5), distance_m: float = 0.5) -> np.ndarray:
    a = np.radians(angle_deg)
    T = wall_pose(0.0, yaw_deg=angle_deg)
    T[:3, 3] = np.array(centre) - distance_m * np.array([np.sin(a), 0.0, np.cos(a)])
    return T


def make_pairs(n: int, seed: int) -> list[tuple[str, object, object, np.ndarray]]:
    rng = np.random.default_rng(seed)
    scenes = [bumpy_wall_scene(seed=s) for s in range(3)]
    pairs = []
    for k in range(n):
        scene = scenes[k % 3]
        if k % 3 == 2:
            base = rng.uniform(-25, 0)
            centre = (rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.2), 0.5)
            Ta, Tb = orbit_pose(base, centre), orbit_pose(base + 360 / 13, centre)
            kind = "orbit"
        else:
            x0, y0 = rng.uniform(-0.6, 0.4), rng.uniform(-0.3, 0.3)
            dx = rng.uniform(0.15, 0.30)
            Ta = wall_pose(x0, y0, *rng.uniform(-5, 5, 3))
            Tb = wall_pose(x0 + dx, y0 + rng.uniform(-0.03, 0.03), *rng.uniform(-5, 5, 3))
            kind = "shift"
        a = render_frame(scene, Ta, W, H, frame_id=2 * k, seed=seed)
        b = render_frame(scene, Tb, W, H, frame_id=2 * k + 1, seed=seed)
        pairs.append((kind, a, b, invert(Ta) @ Tb))
    return pairs


def pct(x, qs=(50, 90, 100)) -> str:
    x = np.asarray(x)
    return " / ".join(f"{v:.4g}" for v in np.percentile(x, qs))


def accuracy(pairs, features) -> dict:
    out = {}
    for feat in features:
        reg = TexturedSurfaceRegistrar(RegistrationConfig(features={"type": feat}))
        rows = []
        for kind, a, b, T_true in pairs:
            t0 = time.perf_counter()
            c = reg.register(a, b)
            dt = time.perf_counter() - t0
            row = {"kind": kind, "accepted": c.accepted, "reason": c.rejection_reason, "time_s": dt, "inliers": c.inlier_count}
            if c.accepted:
                rot, trans = pose_error(c.T_target_source, T_true)
                e = se3_log(invert(T_true) @ c.T_target_source)
                row.update(rot_deg=float(np.degrees(rot)), trans_mm=1e3 * trans, nees_raw=float(e @ c.information @ e))
                if feat == "surf":
                    m = c.metadata["matches_used"]
                    A, B = reg.describe(a), reg.describe(b)
                    X, ok = lift_keypoints(a.xyz_map, A.keypoints_uv[m[:, 0]])
                    loc = localize_dlt(X[ok], B.keypoints_uv[m[:, 1]][ok], a.metadata["K"])
                    if loc.success:
                        row["dlt_inliers"] = loc.num_inliers
                        row["dlt_centre_err_mm"] = 1e3 * float(np.linalg.norm(loc.camera_centre_world_m - T_true[:3, 3]))
                        row["dlt_vs_registration_mm"] = 1e3 * float(np.linalg.norm(loc.camera_centre_world_m - c.T_target_source[:3, 3]))
            rows.append(row)
        out[feat] = rows
        acc = [r for r in rows if r["accepted"]]
        print(f"\n== {feat}: {len(acc)}/{len(rows)} accepted")
        for r in rows:
            if not r["accepted"]:
                print(f"   rejected ({r['kind']}): {r['reason']}")
        if acc:
            for kind in ("shift", "orbit", None):
                sel = [r for r in acc if kind is None or r["kind"] == kind]
                if not sel:
                    continue
                print(
                    f"   {kind or 'all':5s} n={len(sel):2d}  rot err deg p50/p90/max {pct([r['rot_deg'] for r in sel])}"
                    f"  trans err mm {pct([r['trans_mm'] for r in sel])}"
                    f"  inliers p50 {np.median([r['inliers'] for r in sel]):.0f}  time s p50 {np.median([r['time_s'] for r in sel]):.3f}"
                )
            nees = np.array([r["nees_raw"] for r in acc])
            print(f"   NEES raw (information_scale=1): mean {nees.mean():.3g}, median {np.median(nees):.3g}; scale for mean 6: {6 / nees.mean():.3g}")
    return out


def rejection(seed: int) -> dict:
    reg = TexturedSurfaceRegistrar(RegistrationConfig())
    frames = []
    positions = [(x, y) for x in (-0.85, -0.3, 0.25, 0.8) for y in (-0.36, 0.36)]
    for s in range(3):
        scene = bumpy_wall_scene(seed=10 + s)
        for i, (x, y) in enumerate(positions):
            frames.append((s, i, render_frame(scene, wall_pose(x, y, *np.random.default_rng(i).uniform(-4, 4, 3)), W, H, frame_id=100 * s + i, seed=seed, supersampling=1)))
    tries = []
    for i in range(len(frames)):
        for j in range(i + 1, len(frames)):
            si, pi, fi = frames[i]
            sj, pj, fj = frames[j]
            if si == sj and pi == pj:
                continue
            tries.append(("no overlap", fi, fj))
    # look-alikes: the texture repeats every 0.6 m; frames exactly one period apart
    for flat in (True, False):
        scene = bumpy_wall_scene(seed=20 + int(flat), flat=flat, texture_period_m=0.6)
        for k, x in enumerate((-0.75, -0.45, -0.15)):
            for y in (-0.3, 0.0, 0.3):
                fa = render_frame(scene, wall_pose(x, y), W, H, frame_id=1000 + 10 * k, seed=seed, supersampling=1)
                fb = render_frame(scene, wall_pose(x + 0.6, y), W, H, frame_id=1001 + 10 * k, seed=seed, supersampling=1)
                tries.append(("look-alike " + ("flat" if flat else "bumpy"), fa, fb))
    reasons = collections.Counter()
    wrong = 0
    for kind, fa, fb in tries:
        c = reg.register(fa, fb)
        if c.accepted:
            wrong += 1
            print(f"   ACCEPTED a {kind} pair {fa.id}->{fb.id}: fitness {c.fitness:.3f} rmse {1e3 * c.inlier_rmse_m:.3f} mm")
        else:
            reasons[f"{kind}: " + c.rejection_reason.split(" (")[0].split(":")[0]] += 1
    n = len(tries)
    print(f"\n== rejection: {n - wrong}/{n} rejected ({100 * (n - wrong) / n:.1f} %)")
    for r, k in reasons.most_common():
        print(f"   {k:4d}  {r}")
    return {"tries": n, "rejected": n - wrong, "reasons": dict(reasons)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=36)
    ap.add_argument("--features", default="surf,sift,orb")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-rejection", action="store_true")
    ap.add_argument("--out", default="results/registration_accuracy.json")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t0 = time.time()
    pairs = make_pairs(args.pairs, args.seed)
    print(f"rendered {len(pairs)} pairs in {time.time() - t0:.0f} s (synthetic ray-cast frames {W}x{H}, not the fringe simulator)")
    res = {"accuracy": accuracy(pairs, args.features.split(","))}
    surf = [r for r in res["accuracy"].get("surf", []) if "dlt_centre_err_mm" in r and r["dlt_inliers"] >= 50]
    if surf:
        print(
            f"\n== DLT (surf matches, >= 50 inliers, n={len(surf)}): camera centre error mm p50/p90/max {pct([r['dlt_centre_err_mm'] for r in surf])}; "
            f"vs registration mm {pct([r['dlt_vs_registration_mm'] for r in surf])}"
        )
    if not args.skip_rejection:
        res["rejection"] = rejection(args.seed)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1, default=str)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
