"""Benchmark: triangulation of a 1920x1200 frame on one core, against a per-pixel 3x3 solve.

Prints milliseconds per frame (median of repeats) for ``Triangulator.triangulate`` and for the
peer, a straightforward batched ``np.linalg.solve`` of the 3x3 system of eq. 9 per pixel on the
same inputs (the same undistorted camera grid, the same u_p map), their ratio and the largest
difference in metres. A second rig adds projector lens distortion: the peer cannot model it, so
there the fast path is compared against the exact (refined) triangulation and ground truth.

Usage: ``.venv/bin/python scripts/bench_triangulation.py [--repeats N]``
"""

from __future__ import annotations

import os

# One core: pin the BLAS/OpenMP pools before numpy and OpenCV load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from fpp_graph.geometry import make_pose  # noqa: E402
from frontend.fpp.lens import project_to_projector  # noqa: E402
from frontend.fpp.rig import PinholeModel, RigCalibration  # noqa: E402
from frontend.fpp.triangulation import Triangulator  # noqa: E402

cv2.setNumThreads(1)


def make_rig(projector_distortion: bool) -> RigCalibration:
    camera = PinholeModel(1920, 1200, np.array([[2300.0, 0, 958.0], [0, 2300.0, 603.0], [0, 0, 1]]), np.array([-0.08, 0.12, 0.0005, -0.0003, -0.05]))
    pd = np.array([-0.04, 0.2, -0.0007, 0.001, -0.3]) if projector_distortion else np.zeros(5)
    projector = PinholeModel(1920, 1080, np.array([[2500.0, 0, 990.0], [0, 2500.0, 1000.0], [0, 0, 1]]), pd)
    R = Rotation.from_euler("xyz", [1.0, -9.0, 0.5], degrees=True).as_matrix()
    return RigCalibration(camera, projector, make_pose(R, -R @ np.array([0.15, 0.005, 0.01])))


def scene(tri: Triangulator) -> np.ndarray:
    """A wavy surface ~0.5-0.8 m away, as an xyz map seen by every camera pixel."""
    r = tri.rays
    depth = 0.6 + 0.1 * r[..., 0] + 0.03 * np.sin(20 * r[..., 1])
    return r * depth[..., None]


def peer_solve(cal: RigCalibration, uv_camera: np.ndarray, u_p: np.ndarray) -> np.ndarray:
    """Per-pixel 3x3 solve of eq. 9 (corrected third row), batched, float64."""
    Ac, Ap = cal.A_camera, cal.A_projector
    u_c, v_c = uv_camera[..., 0].ravel(), uv_camera[..., 1].ravel()
    up = u_p.ravel()
    rows = [Ac[0] - u_c[:, None] * Ac[2], Ac[1] - v_c[:, None] * Ac[2], Ap[0] - up[:, None] * Ap[2]]
    M = np.stack(rows, axis=1)  # (N, 3, 4)
    ok = np.isfinite(up)
    X = np.full((up.size, 3), np.nan)
    X[ok] = np.linalg.solve(M[ok, :, :3], -M[ok, :, 3:])[..., 0]
    return X.reshape(*u_p.shape, 3)


class Ms(float):
    """Median wall milliseconds that prints as ``median (min, CPU median)``: on a shared machine
    the wall time includes waiting for a core, the process CPU time does not."""

    minimum: float
    cpu: float

    def __format__(self, spec: str) -> str:
        return f"{float(self):{spec}} (min {self.minimum:.1f}, CPU {self.cpu:.1f})"


def timed(fn, repeats: int) -> tuple[Ms, object]:
    times, cpu, result = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    ms = Ms(1e3 * float(np.median(times)))
    ms.minimum = 1e3 * float(np.min(times))
    ms.cpu = 1e3 * float(np.median(cpu))
    return ms, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()

    print(f"times: wall median (min, CPU median) over repeats, one thread; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print("rig 1: camera distortion, no projector distortion (1920x1200 camera, 1920x1080 projector)")
    cal = make_rig(projector_distortion=False)
    t0 = time.perf_counter()
    tri32 = Triangulator(cal)
    print(f"  precompute (once per calibration): {time.perf_counter() - t0:.2f} s")
    tri64 = Triangulator(cal, dtype=np.float64)
    X = scene(tri32)
    u_p, v_p = project_to_projector(cal, X)
    inside = (u_p >= 0) & (u_p <= 1919) & (v_p >= 0) & (v_p <= 1079)
    u_p = np.where(inside, u_p, np.nan)
    u_p32 = u_p.astype(np.float32)
    print(f"  pixels lit by the projector: {inside.mean():.1%}")
    uv_camera = (tri32.rays @ cal.camera.K.T)[..., :2]  # undistorted camera pixels, shared input
    out = np.empty((1200, 1920, 3))
    ms32, xyz32 = timed(lambda: tri32.triangulate(u_p32), args.repeats)
    ms32_out, _ = timed(lambda: tri32.triangulate(u_p32, out=out), args.repeats)
    msd, _ = timed(lambda: tri32.depth(u_p32), args.repeats)
    ms64, xyz64 = timed(lambda: tri64.triangulate(u_p), args.repeats)
    ms_peer, xyz_peer = timed(lambda: peer_solve(cal, uv_camera, u_p), max(2, args.repeats // 5))
    err = lambda a, b: float(np.nanmax(np.linalg.norm(a - b, axis=-1)))  # noqa: E731
    print(f"  Triangulator float32 triangulate:        {ms32:7.1f} ms/frame  (max |error| vs truth {err(xyz32, X) * 1e6:.3f} um)")
    print(f"  Triangulator float32 with out= buffer:   {ms32_out:7.1f} ms/frame")
    print(f"  Triangulator float32 depth map only:     {msd:7.1f} ms/frame")
    print(f"  Triangulator float64 triangulate:        {ms64:7.1f} ms/frame  (max |error| vs truth {err(xyz64, X) * 1e6:.3g} um)")
    print(f"  peer: batched per-pixel 3x3 solve:       {ms_peer:7.1f} ms/frame  (max |error| vs truth {err(xyz_peer, X) * 1e6:.3g} um)")
    print(f"  speed-up vs peer (medians): float32 {float(ms_peer) / float(ms32):.0f}x, float64 {float(ms_peer) / float(ms64):.0f}x")
    print(f"  max |Triangulator float32 - peer| = {err(xyz32, xyz_peer) * 1e6:.3f} um, float64 - peer = {err(xyz64, xyz_peer) * 1e6:.3g} um")
    same = np.isfinite(xyz32[..., 2]) == np.isfinite(xyz_peer[..., 2])
    print(f"  validity agreement with the peer: {same.mean():.4%}")

    print("rig 2: distortion on camera and projector")
    cal = make_rig(projector_distortion=True)
    t0 = time.perf_counter()
    tri = Triangulator(cal)
    print(f"  precompute: {time.perf_counter() - t0:.2f} s, inverse-distortion polynomial degree {tri.projector_fit_degree}, "
          f"max fit error {tri.projector_fit_max_error_px:.2g} px")
    exact = Triangulator(cal, dtype=np.float64, projector_refine_iterations=2)
    X = scene(tri)
    u_p, v_p = project_to_projector(cal, X)
    inside = (u_p >= 0) & (u_p <= 1919) & (v_p >= 0) & (v_p <= 1079)
    u_p32 = np.where(inside, u_p, np.nan).astype(np.float32)
    ms, xyz = timed(lambda: tri.triangulate(u_p32), args.repeats)
    ms_exact, xyz_exact = timed(lambda: exact.triangulate(u_p32.astype(np.float64)), max(2, args.repeats // 5))
    print(f"  Triangulator float32 (polynomial):       {ms:7.1f} ms/frame  (max |error| vs truth {err(xyz, X) * 1e6:.3f} um)")
    print(f"  Triangulator float64 + 2 exact refinements: {ms_exact:7.1f} ms/frame  (max |error| vs truth {err(xyz_exact, X) * 1e6:.3g} um)")


if __name__ == "__main__":
    main()
