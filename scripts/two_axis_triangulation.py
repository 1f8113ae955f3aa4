"""Depth error of column-only, row-only and two-coordinate triangulation on one simulated rig.

A 1280x1024 camera (lens distortion) and a 1920x1080 projector (lens distortion) with a baseline
of 0.12 m across and 0.05 m down see a wavy surface 0.5-0.7 m away. Exact projector coordinates
of the surface get Gaussian noise of the given sigmas (``--u-sigma-px``, ``--v-sigma-px``); the
script prints, over the pixels all methods keep, the depth error's median, RMS and 90th
percentile of :class:`frontend.fpp.triangulation.Triangulator` on ``u_p`` alone and on ``v_p``
alone (float32, its default), of :class:`frontend.fpp.two_axis_triangulation.TwoAxisTriangulator`
with one coordinate trusted alone (the other's sigma infinite) and on both (weighted by the
sigmas, and with equal weights), the RMS that ``depth_sigma_m`` predicts, the residual's median,
and the time per frame of each (median of ``--repeats``, one thread).

With ``--real-calibration FILE`` it also triangulates the real procam-calibration captures
(``../shared/data/real_fpp/procam_calibration``: column and row Gray code of a 1024x768
projector, 5 chessboard poses) with that rig calibration (``scripts/calibrate_real.py`` writes
one to ``results/procam_calibration.yaml``) and prints, per capture, the pixels each method
keeps, the residual's median and 90th percentile (Gray code quantises each coordinate to its
stripe: uniform error of +-0.5 stripe, 1 / sqrt(12) stripe sigma, the weights used) and the
predicted depth noise.

Usage: ``.venv/bin/python scripts/two_axis_triangulation.py [--u-sigma-px 0.05] [--v-sigma-px 0.05] [--repeats 5]
[--real-calibration results/procam_calibration.yaml]``
"""

from __future__ import annotations

import os

# One core: pin the BLAS/OpenMP pools before numpy and OpenCV load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from fpp_graph.geometry import make_pose  # noqa: E402
from frontend.fpp.lens import project_to_projector  # noqa: E402
from frontend.fpp.rig import PinholeModel, RigCalibration  # noqa: E402
from frontend.fpp.triangulation import Triangulator, pixel_rays  # noqa: E402
from frontend.fpp.two_axis_triangulation import TwoAxisTriangulator  # noqa: E402

cv2.setNumThreads(1)
ROOT = Path(__file__).resolve().parents[1]


def make_rig() -> RigCalibration:
    """1280x1024 camera (f 1400 px), 1920x1080 projector (f 2200 px) aimed at a point 0.6 m ahead."""
    camera = PinholeModel(1280, 1024, np.array([[1400.0, 0, 638.0], [0, 1400.0, 515.0], [0, 0, 1]]), np.array([-0.08, 0.12, 0.0005, -0.0003, -0.05]))
    projector = PinholeModel(1920, 1080, np.array([[2200.0, 0, 955.0], [0, 2200.0, 545.0], [0, 0, 1]]), np.array([-0.04, 0.2, -0.0007, 0.001, -0.3]))
    centre = np.array([0.12, 0.05, 0.0])  # projector centre in the camera frame, metres
    axis = np.array([0.0, 0.0, 0.6]) - centre
    R, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [axis / np.linalg.norm(axis)])
    return RigCalibration(camera, projector, make_pose(R.as_matrix(), -R.as_matrix() @ centre))


def timed(fn, repeats: int) -> tuple[str, object]:
    """``"wall (CPU) ms"``: medians of ``fn()`` over ``repeats`` calls (on a shared machine the
    wall time includes waiting for a core, the process CPU time does not), and its last result."""
    wall, cpu, result = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return f"{1e3 * np.median(wall):5.0f} ({1e3 * np.median(cpu):4.0f} CPU) ms", result


def error_line(name: str, depth_m: np.ndarray, true_m: np.ndarray, where: np.ndarray, ms: str, extra: str = "") -> str:
    err_mm = 1e3 * np.abs(depth_m[where] - true_m[where])
    return (f"  {name:44s} median {np.median(err_mm):7.4f}  RMS {np.sqrt(np.mean(err_mm**2)):9.4f}  "
            f"p90 {np.percentile(err_mm, 90):7.4f} mm  {ms}/frame{extra}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--u-sigma-px", type=float, default=0.05, help="noise of the decoded column u_p, projector pixels")
    parser.add_argument("--v-sigma-px", type=float, default=0.05, help="noise of the decoded row v_p, projector pixels")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--real-calibration", type=Path, default=None, help="rig calibration YAML of the procam-calibration captures (1024x768 projector)")
    parser.add_argument("--real-data", type=Path, default=ROOT.parent / "shared" / "data" / "real_fpp" / "procam_calibration")
    args = parser.parse_args()
    simulated(args)
    if args.real_calibration is not None:
        real_captures(args.real_calibration, args.real_data)


def simulated(args: argparse.Namespace) -> None:

    cal = make_rig()
    rays = pixel_rays(cal.camera)
    t0 = time.perf_counter()
    two_axis = TwoAxisTriangulator(cal, camera_rays=rays)
    setup_s = time.perf_counter() - t0
    columns = Triangulator(cal, "columns", camera_rays=rays)
    rows = Triangulator(cal, "rows", camera_rays=rays)

    depth_true = 0.6 + 0.1 * rays[..., 0] + 0.03 * np.sin(20.0 * rays[..., 1])
    u, v = project_to_projector(cal, rays * depth_true[..., None])
    lit = (u >= 0) & (u <= cal.projector.width - 1) & (v >= 0) & (v <= cal.projector.height - 1)
    rng = np.random.default_rng(args.seed)
    u_noisy = np.where(lit, u + args.u_sigma_px * rng.normal(size=u.shape), np.nan)
    v_noisy = np.where(lit, v + args.v_sigma_px * rng.normal(size=v.shape), np.nan)

    ms_col, z_col = timed(lambda: columns.depth(u_noisy.astype(np.float32)), args.repeats)
    ms_row, z_row = timed(lambda: rows.depth(v_noisy.astype(np.float32)), args.repeats)
    sigmas = {"u_sigma_px": args.u_sigma_px, "v_sigma_px": args.v_sigma_px}
    ms_both, both = timed(lambda: two_axis.triangulate(u_noisy, v_noisy, **sigmas), args.repeats)
    ms_equal, equal = timed(lambda: two_axis.triangulate(u_noisy, v_noisy), args.repeats)
    # One coordinate trusted alone (the other's sigma infinite): that coordinate's exact triangulation.
    ms_col_exact, col_exact = timed(lambda: two_axis.triangulate(u_noisy, v_noisy, u_sigma_px=args.u_sigma_px, v_sigma_px=np.inf), args.repeats)
    ms_row_exact, row_exact = timed(lambda: two_axis.triangulate(u_noisy, v_noisy, u_sigma_px=np.inf, v_sigma_px=args.v_sigma_px), args.repeats)
    depths = [z_col, z_row, col_exact.xyz_m[..., 2], row_exact.xyz_m[..., 2], both.xyz_m[..., 2], equal.xyz_m[..., 2]]
    where = np.logical_and.reduce([np.isfinite(z) for z in depths])

    print(f"rig: 1280x1024 camera, 1920x1080 projector, both distorted; baseline {cal.baseline_m:.3f} m (0.12 across, 0.05 down)")
    print(f"noise: u_p {args.u_sigma_px} px, v_p {args.v_sigma_px} px (Gaussian, seed {args.seed}); "
          f"{int(where.sum())} pixels of {lit.size} kept by all ({lit.mean():.1%} lit); two-axis set-up {setup_s:.2f} s")
    print(f"depth error over those pixels; times: wall (CPU) medians of {args.repeats}, one thread, load average {os.getloadavg()[0]:.2f}")
    names = ["column u_p only: Triangulator (float32)", "row v_p only: Triangulator (float32)",
             "column u_p only: two-axis, v_sigma inf", "row v_p only: two-axis, u_sigma inf",
             "both: two-axis, weighted by the sigmas", "both: two-axis, equal weights"]
    for name, z, ms, result in zip(names, depths, (ms_col, ms_row, ms_col_exact, ms_row_exact, ms_both, ms_equal), (None, None, col_exact, row_exact, both, None), strict=True):
        extra = ""
        if result is not None:
            extra = f"  (predicted RMS {1e3 * np.sqrt(np.mean(result.depth_sigma_m[where].astype(np.float64) ** 2)):.4f} mm)"
        print(error_line(name, z, depth_true, where, ms, extra))
    print(f"  residual median {np.median(both.residual_px[where]):.4f} px (weighted), {np.median(equal.residual_px[where]):.4f} px (equal weights)")


def real_captures(calibration_path: Path, data: Path) -> None:
    """Residuals and kept pixels on the real procam-calibration captures (two Gray-code axes)."""
    from frontend.fpp.capture import read_capture
    from frontend.fpp.pattern_file import load_pattern_spec
    from frontend.fpp.phase import make_decoder
    from frontend.fpp.rig import load_calibration

    cal = load_calibration(calibration_path)
    spec = load_pattern_spec(ROOT / "datasets" / "patterns" / "procam_graycode_1024x768.yaml")
    rays = pixel_rays(cal.camera)
    two_axis = TwoAxisTriangulator(cal, camera_rays=rays)
    columns = Triangulator(cal, "columns", camera_rays=rays)
    rows = Triangulator(cal, "rows", camera_rays=rays)
    decoder = make_decoder(spec, cal.projector.width, cal.projector.height)
    print(f"real: {data.name} captures, calibration {calibration_path} (baseline {cal.baseline_m:.3f} m)")
    for folder in sorted(data.glob("capture_*")):
        decoded = decoder.decode(read_capture(folder, spec))
        u, v, mask = decoded.u_projector_px, decoded.v_projector_px, decoded.mask
        sigma = decoded.pitch_px / np.sqrt(12.0)  # the stripe's uniform quantisation
        both = two_axis.triangulate(u, v, mask, u_sigma_px=sigma, v_sigma_px=sigma)
        kept = np.isfinite(both.xyz_m[..., 2])
        z_col, z_row = columns.depth(u, mask), rows.depth(v, mask)
        print(f"  {folder.name}: decoded {mask.mean():.1%}; kept: both {kept.mean():.1%}, column-only {np.isfinite(z_col).mean():.1%}, "
              f"row-only {np.isfinite(z_row).mean():.1%}; residual median {np.median(both.residual_px[kept]):.3f} px, "
              f"p90 {np.percentile(both.residual_px[kept], 90):.3f} px; predicted depth noise median {1e3 * np.median(both.depth_sigma_m[kept]):.2f} mm "
              f"at depth median {np.median(both.xyz_m[..., 2][kept]):.2f} m")


if __name__ == "__main__":
    main()
