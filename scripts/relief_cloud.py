"""Decode + triangulate the real SLMaster monocular capture into a point cloud of the relief.

Prints point count, depth range and the RMS of a plane fit on the flat border (mm), and saves a
rendered PNG of the cloud (results/frontend/slmaster_relief_cloud.png).

Run: .venv/bin/python scripts/relief_cloud.py   (needs ../shared/data/real_fpp/slmaster_monocular)
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real_fpp" / "slmaster_monocular"


def robust_plane(points: np.ndarray, iterations: int = 5, keep_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane refit on inliers; returns (normal, signed distances of all points)."""
    inliers = np.ones(len(points), bool)
    for _ in range(iterations):
        c = points[inliers].mean(axis=0)
        _, _, Vt = np.linalg.svd(points[inliers] - c, full_matrices=False)
        normal = Vt[2]
        dist = (points - c) @ normal
        inliers = np.abs(dist) < max(keep_mm * 1e-3, 3 * np.std(dist[inliers]))
    return normal, (points - points[inliers].mean(axis=0)) @ normal


def main() -> None:
    if not DATA.exists():
        sys.exit(f"real data {DATA} is absent")
    from frontend.fpp.calibration_io import read_slmaster_calibration
    from frontend.fpp.triangulation import Triangulator

    decode = runpy.run_path(str(ROOT / "scripts" / "decode_real.py"))["decode_slmaster_monocular"]
    result = decode(DATA)
    calibration = read_slmaster_calibration(DATA / "caliInfo.yml")
    xyz = Triangulator(calibration, projector_refine_iterations=1).triangulate(result.u_projector_px, result.mask)
    valid = np.isfinite(xyz[..., 2])
    # keep the plaque: the largest connected region of valid pixels (stray background patches
    # of the dark capture decode too, metres away)
    import cv2

    n_labels, labels, stats, _ = cv2.connectedComponentsWithStats(valid.astype(np.uint8), connectivity=8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) if n_labels > 1 else 0
    print(f"valid pixels: {valid.sum()}, in the largest region (the plaque): {(labels == largest).sum()}")
    valid &= labels == largest
    points = xyz[valid]
    z_mm = points[:, 2] * 1e3
    print(f"points: {len(points)} ({100 * valid.mean():.1f}% of pixels)")
    print(f"depth range: {np.percentile(z_mm, 0.5):.1f} .. {np.percentile(z_mm, 99.5):.1f} mm (0.5-99.5 percentile), full {z_mm.min():.1f} .. {z_mm.max():.1f} mm")
    # the flat border: the outer ring of the valid region (relief in the middle)
    rows, cols = np.nonzero(valid)
    r0, r1 = np.percentile(rows, [2, 98])
    c0, c1 = np.percentile(cols, [2, 98])
    ring = ((rows - r0) < 0.12 * (r1 - r0)) | ((r1 - rows) < 0.12 * (r1 - r0)) | ((cols - c0) < 0.12 * (c1 - c0)) | ((c1 - cols) < 0.12 * (c1 - c0))
    border = points[ring]
    _, dist = robust_plane(border)
    inl = np.abs(dist) < 1e-3
    print(f"flat border: {ring.sum()} points, plane-fit RMS {1e3 * np.sqrt(np.mean(dist[inl] ** 2)):.4f} mm on {100 * inl.mean():.1f}% inliers (|d| < 1 mm); all-point RMS {1e3 * np.sqrt(np.mean(dist**2)):.4f} mm")
    # The plaque is not flat over its whole border (it curves by centimetres, see the side view),
    # so the sensor noise shows in local plane fits: 4 mm x 4 mm patches of the border.
    cell = np.floor(border[:, :2] / 0.004).astype(np.int64)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    residuals = []
    for k in range(len(keys)):
        patch = border[inverse.ravel() == k]
        if len(patch) >= 30:
            c = patch.mean(axis=0)
            _, _, Vt = np.linalg.svd(patch - c, full_matrices=False)
            residuals.append((patch - c) @ Vt[2])
    local = np.concatenate(residuals)
    print(f"flat border, local 4x4 mm plane fits: RMS {1e3 * np.sqrt(np.mean(local**2)):.4f} mm over {len(residuals)} patches ({len(local)} points)")
    _, dist_all = robust_plane(points)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = ROOT / "results" / "frontend" / "slmaster_relief_cloud.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    sub = np.random.default_rng(0).choice(len(points), min(len(points), 150_000), replace=False)
    fig, axes = plt.subplots(1, 2, figsize=(14, 6))
    sc = axes[0].scatter(points[sub, 0] * 1e3, -points[sub, 1] * 1e3, c=dist_all[sub] * 1e3, s=0.3, cmap="viridis", vmin=np.percentile(dist_all * 1e3, 1), vmax=np.percentile(dist_all * 1e3, 99))
    axes[0].set_aspect("equal")
    axes[0].set_title("relief: height above the best plane (mm)")
    axes[0].set_xlabel("x (mm)")
    axes[0].set_ylabel("-y (mm)")
    fig.colorbar(sc, ax=axes[0])
    axes[1].scatter(points[sub, 0] * 1e3, points[sub, 2] * 1e3, s=0.2, c="k")
    axes[1].set_title("side view (x vs depth)")
    axes[1].set_xlabel("x (mm)")
    axes[1].set_ylabel("z (mm)")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print(f"saved {out}")


if __name__ == "__main__":
    main()
