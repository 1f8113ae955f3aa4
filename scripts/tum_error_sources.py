"""Where the TUM fr1_rpy subset's registration errors come from, against the motion capture.

    .venv/bin/python -m scripts.tum_error_sources RESULTS [--sequence ../shared/data/rgbd/tum_fr1_rpy_subset] [--loops 20]

``RESULTS``: the folder ``fpp-slam run`` (or ``scripts.rgbd_acceptance``) wrote for the sequence.
Prints, for the run's own edges (``graph.g2o``) and for pairs registered again here:

1. **clock**: median rotation / translation error of loop and odometry edges with the reference
   taken at each image's timestamp shifted by -40 ... +20 ms;
2. **asynchrony**: loops registered again with every keypoint moved from its colour image's time
   to its depth image's time by the true rotation between them;
3. **rolling shutter**: loops registered again with each depth row turned back by the true angular
   velocity over its exposure time (rows spread over a readout of 0, 20, 33, 40 ms);
4. **excursion**: the odometry pairs of frames 16-30 tracked densely from the *true* relative pose;
5. **another registration**: the same pairs by Open3D's RGB-D odometry (``compute_rgbd_odometry``,
   its colour term and its colour + depth term), also from the true pose, on the undistorted
   images: is the limit the data or this project's fit?
6. **reference frame**: the run's ATE with the frames of the excursion (17-29) left out, and with
   a constant offset of the camera centre from the motion capture's fitted (3 more parameters
   than the SE(3) alignment: what a hand-eye or depth-origin error of the reference would take).

Each uses the reference poses the evaluation uses; the figures are quoted in the README's NEES
paragraph.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"


def _setup(results: Path, sequence: Path):
    from fpp_graph.config import load_config
    from fpp_graph.slam.sources import open_source
    from fpp_graph.trajectory import read_tum

    source = open_source(sequence, load_config(None))
    ref = read_tum(sequence / "groundtruth.txt")
    est = read_tum(results / "trajectory.tum")
    estimate = dict(zip([round(t, 4) for t in est.timestamps_s], est.poses_world_sensor, strict=True))
    return source, ref, estimate


def _error(T_ref: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    from fpp_graph.geometry import invert, se3_log

    e = se3_log(invert(T_ref) @ T)
    return float(np.degrees(np.linalg.norm(e[:3]))), float(1e3 * np.linalg.norm(e[3:]))


def clock(results: Path, source, ref) -> None:
    from fpp_graph.backend.g2o import read_g2o
    from fpp_graph.geometry import invert
    from frontend.rgbd.source import interpolate_pose

    edges = list(read_g2o(results / "graph.g2o").edges())
    print("1. clock offset of the reference (median rotation / translation error of the run's edges)")
    for offset_ms in (-40, -30, -20, -10, 0, 10, 20):
        ref_at = {e.frame_id: interpolate_pose(ref, e.timestamp + offset_ms / 1e3, 0.05) for e in source.entries}
        row = []
        for kind in ("loop", "odometry"):
            errs = np.array([_error(invert(ref_at[e.target_id]) @ ref_at[e.source_id], e.T_target_source) for e in edges if kind in str(e.kind)])
            row.append(f"{kind} {np.median(errs[:, 0]):.2f} deg / {np.median(errs[:, 1]):.1f} mm" if len(errs) else f"{kind} -")
        print(f"   {offset_ms:+4d} ms: " + ", ".join(row))


def _loops(results: Path, count: int) -> list[tuple[int, int]]:
    verified = [(c["match"], c["query"]) for c in json.loads((results / "loops.json").read_text()) if c["verified"]]
    return verified[:: max(1, len(verified) // count)][:count]


def _angular_velocity(ref, t: float) -> np.ndarray:
    from fpp_graph.geometry import invert, se3_log
    from frontend.rgbd.source import interpolate_pose

    a, b = interpolate_pose(ref, t - 0.01, 0.05), interpolate_pose(ref, t + 0.01, 0.05)
    return se3_log(invert(a) @ b)[:3] / 0.02


def _register_loops(source, estimate, pairs, variant) -> np.ndarray:
    """Median errors of ``pairs`` registered as loops (guess: the run's estimate) with frames from ``variant``."""
    from fpp_graph.geometry import invert
    from fpp_graph.types import ConstraintKind

    registrar = source.make_registrar()
    gt = {e.frame_id: e.T_world_sensor for e in source.entries}
    stamp = {e.frame_id: round(e.timestamp, 4) for e in source.entries}
    errs = []
    for a, b in pairs:
        c = registrar.register(variant(a), variant(b), T_guess=invert(estimate[stamp[a]]) @ estimate[stamp[b]], kind=ConstraintKind.LOOP)
        errs.append(_error(invert(gt[a]) @ gt[b], c.T_target_source) if c.accepted else (np.nan, np.nan))
    return np.nanmedian(np.array(errs), axis=0)


def asynchrony(source, ref, estimate, pairs, sequence: Path) -> None:
    import cv2

    from frontend.rgbd.source import interpolate_pose

    depth_times = np.array(sorted(float(line.split()[0]) for line in (sequence / "depth.txt").read_text().splitlines() if line and not line.startswith("#")))
    frames: dict[int, object] = {}
    describer = source.make_registrar()

    def as_is(i):
        if i not in frames:  # described here: a source's frames get their keypoints as keyframes
            frames[i] = describer.describe(source.load_frame(i))
        return frames[i]

    def at_depth_time(i):
        f = as_is(i)
        t_colour = source._by_id[i].timestamp
        t_depth = depth_times[np.argmin(np.abs(depth_times - t_colour))]
        R_depth_colour = interpolate_pose(ref, t_depth, 0.05)[:3, :3].T @ interpolate_pose(ref, t_colour, 0.05)[:3, :3]
        uv = np.asarray(f.keypoints_uv, np.float64).reshape(-1, 1, 2)
        rays = cv2.undistortPoints(uv, source.K, source.distortion, None, None, None, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9)).reshape(-1, 2)
        moved, _ = cv2.projectPoints(np.c_[rays, np.ones(len(rays))] @ R_depth_colour.T, np.zeros(3), np.zeros(3), source.K, source.distortion)
        return dataclasses.replace(f, keypoints_uv=moved.reshape(-1, 2))

    base, moved = _register_loops(source, estimate, pairs, as_is), _register_loops(source, estimate, pairs, at_depth_time)
    print(f"2. keypoints at the depth image's time: loops {base[0]:.2f} deg / {base[1]:.1f} mm -> {moved[0]:.2f} deg / {moved[1]:.1f} mm (median of {len(pairs)})")


def rolling_shutter(source, ref, estimate, pairs) -> None:
    from fpp_graph.geometry import se3_exp

    print("3. depth rows turned back by the true angular velocity (median loop error)")
    loaded: dict[int, object] = {}
    for readout_s in (0.0, 0.020, 0.033, 0.040):
        def unrolled(i, readout_s=readout_s):
            if i not in loaded:
                loaded[i] = source.load_frame(i)
            f = loaded[i]
            if readout_s == 0:
                return f
            w = _angular_velocity(ref, source._by_id[i].timestamp)
            xyz = np.asarray(f.xyz_map)
            rows = xyz.shape[0]
            dt = (np.arange(rows) - rows / 2) / rows * readout_s
            R = np.stack([se3_exp(np.r_[w * d, 0.0, 0.0, 0.0])[:3, :3] for d in dt])
            out = np.einsum("vij,vuj->vui", R, xyz)
            return dataclasses.replace(f, xyz_map=out, points=out[np.isfinite(out[..., 2])])
        err = _register_loops(source, estimate, pairs, unrolled)
        print(f"   readout {1e3 * readout_s:4.0f} ms: {err[0]:.2f} deg / {err[1]:.1f} mm")


def excursion(source) -> None:
    from fpp_graph.geometry import invert

    registrar = source.make_registrar()
    gt = {e.frame_id: e.T_world_sensor for e in source.entries}
    frames = {i: source.load_frame(i) for i in range(15, 31)}
    print("4. odometry pairs tracked densely from the true relative pose (error after the fit)")
    for b in range(16, 31):
        T_true = invert(gt[b - 1]) @ gt[b]
        c = registrar.track(frames[b - 1], frames[b], T_true)
        text = "{:.2f} deg / {:.1f} mm".format(*_error(T_true, c.T_target_source)) if c.accepted else c.rejection_reason
        print(f"   {b - 1:3d}-{b:3d}: {text}")


def other_registration(source) -> None:
    import cv2
    import open3d as o3d

    from fpp_graph.geometry import invert

    K = source.K
    maps = cv2.initUndistortRectifyMap(K, source.distortion, None, K, (640, 480), cv2.CV_32FC1) if source.distortion is not None else None

    def rgbd(i: int):
        e = source._by_id[i]
        colour = cv2.cvtColor(cv2.imread(str(e.color)), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(e.depth), cv2.IMREAD_UNCHANGED)
        if maps is not None:
            colour = cv2.remap(colour, *maps, cv2.INTER_LINEAR)
            depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST)
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(colour)), o3d.geometry.Image(depth), depth_scale=source.depth_per_m,
            depth_trunc=4.0, convert_rgb_to_intensity=True)

    gt = {e.frame_id: e.T_world_sensor for e in source.entries}
    images = {i: rgbd(i) for i in range(15, 31)}
    camera = o3d.camera.PinholeCameraIntrinsic(640, 480, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    terms = {"colour": o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm(),
             "colour + depth": o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()}
    print("5. the same pairs by Open3D's RGB-D odometry from the true relative pose (error after it)")
    for b in range(16, 31):
        T_true = invert(gt[b - 1]) @ gt[b]
        errors = []
        for name, term in terms.items():
            ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(images[b], images[b - 1], camera, T_true, term, o3d.pipelines.odometry.OdometryOption())
            errors.append(f"{name} " + ("{:.2f} deg / {:.1f} mm".format(*_error(T_true, T)) if ok else "failed"))
        print(f"   {b - 1:3d}-{b:3d}: " + "; ".join(errors))


def reference_frame(source, estimate) -> None:
    from fpp_graph.geometry import kabsch

    entries = [e for e in source.entries if round(e.timestamp, 4) in estimate]
    est = np.stack([estimate[round(e.timestamp, 4)] for e in entries])
    ref = np.stack([e.T_world_sensor[:3, 3] for e in entries])

    def ate_mm(points: np.ndarray, keep: np.ndarray) -> float:
        T = kabsch(ref[keep], points[keep])  # the evaluation's rigid alignment, no scale
        return float(1e3 * np.sqrt(np.mean(np.sum((points[keep] @ T[:3, :3].T + T[:3, 3] - ref[keep]) ** 2, axis=1))))

    every = np.ones(len(entries), dtype=bool)
    outside = np.array([not 17 <= e.frame_id <= 29 for e in entries])
    offset = np.zeros(3)
    for _ in range(50):  # alternate the alignment and the camera centre's offset (a linear fit)
        centres = est[:, :3, 3] + est[:, :3, :3] @ offset
        T = kabsch(ref, centres)
        R, t = T[:3, :3], T[:3, 3]
        A = np.einsum("ij,njk->nik", R, est[:, :3, :3]).reshape(-1, 3)
        offset = np.linalg.lstsq(A, (ref - est[:, :3, 3] @ R.T - t).reshape(-1), rcond=None)[0]
    shifted = est[:, :3, 3] + est[:, :3, :3] @ offset
    print("6. the run's ATE against the reference frame")
    print(f"   as evaluated {ate_mm(est[:, :3, 3], every):.1f} mm; frames 17-29 left out {ate_mm(est[:, :3, 3], outside):.1f} mm; "
          f"camera centre offset by {np.round(1e3 * offset, 1)} mm (fitted) {ate_mm(shifted, every):.1f} mm, "
          f"and without 17-29 {ate_mm(shifted, outside):.1f} mm")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--sequence", type=Path, default=SHARED / "tum_fr1_rpy_subset")
    parser.add_argument("--loops", type=int, default=20, help="verified loops registered again for 2 and 3")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    for needed in (args.results / "graph.g2o", args.results / "loops.json", args.sequence / "groundtruth.txt"):
        if not needed.exists():
            print(f"tum_error_sources: {needed} is missing (run fpp-slam run on the TUM folder first)", file=sys.stderr)
            return 2
    source, ref, estimate = _setup(args.results, args.sequence)
    pairs = _loops(args.results, args.loops)
    clock(args.results, source, ref)
    asynchrony(source, ref, estimate, pairs, args.sequence)
    rolling_shutter(source, ref, estimate, pairs)
    excursion(source)
    other_registration(source)
    reference_frame(source, estimate)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
