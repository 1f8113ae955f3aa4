"""Accuracy of the virtual FPP sensor decoded by the front-end, against ground truth.

    .venv/bin/python scripts/sim_accuracy.py                  # plane + sphere at 1920x1200, overlaps
    .venv/bin/python scripts/sim_accuracy.py --preview        # the same at 640x400
    .venv/bin/python scripts/sim_accuracy.py --sequence datasets/generated/corridor [--every 5]

1. Plane and sphere: render the default rig's pattern stack, decode it with
   :class:`frontend.fpp.sensor.FppSensor` (the real-recording path) and compare every valid
   pixel's point with the ray-cast ground truth of the same pixel (3D distance; both lie on the
   pixel's ray). Printed with the noise settings; the paper's single-view figure is 0.067 mm.
2. Overlap of adjacent frames (corridor, turntable), from ground truth: the fraction of frame
   k's surface points that frame k+1 sees too (mean of both directions).
3. ``--sequence``: read a written sequence back, decode frames and measure the distance of
   the decoded points (put in the world by the ground-truth pose) to the ground-truth mesh.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from frontend.fpp.sensor import FppSensor  # noqa: E402
from frontend.sim import (  # noqa: E402
    FppSimulator,
    RenderSettings,
    default_pattern_spec,
    default_rig,
    load_simulation,
    scenes,
)

DATASETS = Path(__file__).resolve().parents[1] / "datasets"


def error_stats(decoded_xyz: np.ndarray, gt_xyz: np.ndarray, region: np.ndarray | None = None) -> dict[str, float]:
    ok = np.isfinite(decoded_xyz[..., 2]) & np.isfinite(gt_xyz[..., 2])
    if region is not None:
        ok &= region
    err = np.linalg.norm(decoded_xyz[ok] - gt_xyz[ok], axis=1)
    return {
        "pixels": int(ok.sum()),
        "rms_mm": 1e3 * float(np.sqrt(np.mean(err**2))),
        "median_mm": 1e3 * float(np.median(err)),
        "p99_mm": 1e3 * float(np.percentile(err, 99)),
        "gross_errors_over_1mm": int(np.count_nonzero(err > 1e-3)),
    }


def single_view(preview: bool) -> None:
    cal = default_rig(preview=preview)
    spec = default_pattern_spec()
    settings = RenderSettings()
    sensor = FppSensor(cal, spec)
    print(f"rig: camera {cal.camera.width}x{cal.camera.height} f={cal.camera.K[0, 0]:.1f}px, projector {cal.projector.width}x{cal.projector.height} "
          f"fx={cal.projector.K[0, 0]:.0f} fy={cal.projector.K[1, 1]:.0f}, baseline {1e3 * cal.baseline_m:.1f} mm; patterns {spec.to_dict()}")
    print(f"noise: read {settings.read_noise_grey} grey + shot variance {settings.shot_noise_gain} x signal; projector white on albedo 1 at 0.5 m = "
          f"{settings.projector_irradiance_grey} grey, ambient {settings.ambient_grey}; blur sigma {settings.blur_sigma_px} px (+defocus, aperture "
          f"{1e3 * settings.aperture_diameter_m} mm, focus {settings.focus_distance_m} m); 8-bit")
    cases = [
        ("plane 0.5 m, albedo 0.8, tilted 7 deg to face the rig's bisector", scenes.plane_scene(0.5, tilt_deg=-7.0, albedo=0.8), None),
        ("sphere r=50 mm, front at 0.45 m, albedo 0.8", scenes.sphere_scene(0.45, 0.05, albedo=0.8), 0.05),
    ]
    for name, scene, radius in cases:
        sim = FppSimulator(cal, spec, scene, settings)
        t0 = time.perf_counter()
        rendered = sim.render(np.eye(4), frame_index=0)
        t1 = time.perf_counter()
        frame = sensor.frame_from_images(0, 0.0, rendered.images)
        t2 = time.perf_counter()
        gt = rendered.ground_truth.xyz_map_m
        stats = error_stats(frame.xyz_map, gt)
        noise = rendered.images[0].astype(float)[rendered.ground_truth.lit_mask]
        print(f"{name}: render {t1 - t0:.2f} s, decode+triangulate {t2 - t1:.2f} s, valid {frame.metadata['valid_fraction']:.3f}, "
              f"lit {rendered.ground_truth.lit_mask.mean():.3f}, mean grey {noise.mean():.0f}")
        print(f"   all valid pixels: RMS {stats['rms_mm']:.4f} mm, median {stats['median_mm']:.4f} mm, p99 {stats['p99_mm']:.3f} mm, "
              f"{stats['gross_errors_over_1mm']} of {stats['pixels']} pixels > 1 mm")
        if radius is not None:
            # Away from the silhouette: surface normal within 60 deg of the viewing ray.
            centre = np.array([0.0, 0.0, 0.45 + radius])
            p = gt
            n = (p - centre) / radius
            cos_view = -np.sum(n * p, axis=-1) / np.linalg.norm(p, axis=-1)
            inner = error_stats(frame.xyz_map, gt, np.nan_to_num(cos_view) > 0.5)
            print(f"   normal within 60 deg of the view ray: RMS {inner['rms_mm']:.4f} mm, median {inner['median_mm']:.4f} mm over {inner['pixels']} pixels")
        print(f"   paper single-view accuracy 0.067 mm; ratio RMS/paper = {stats['rms_mm'] / 0.067:.2f}")


def overlaps(config: Path, step: int = 1) -> None:
    setup = load_simulation(config, preview=True)
    sim = FppSimulator(setup.calibration, setup.spec, setup.scene, setup.settings)
    K = setup.calibration.camera.K
    gts = [sim.ground_truth(T)[0] for T in setup.poses_world_sensor]
    values = []
    for a, b in zip(gts[:-1], gts[1:], strict=True):
        o_ab = scenes.frame_overlap(a.xyz_map_m, a.T_world_sensor, b.depth_m, b.T_world_sensor, K)
        o_ba = scenes.frame_overlap(b.xyz_map_m, b.T_world_sensor, a.depth_m, a.T_world_sensor, K)
        values.append(0.5 * (o_ab + o_ba))
    v = np.array(values)
    print(f"{config.name}: {len(gts)} frames; adjacent-frame overlap from ground truth: mean {v.mean():.3f}, median {np.median(v):.3f}, "
          f"min {v.min():.3f}, max {v.max():.3f} (paper's corridor: about 1/3)")
    # Revisits: frames far apart in time that see the same place (loops).
    T = setup.poses_world_sensor
    loops = 0
    for i in range(len(gts)):
        for j in range(i + 10, len(gts)):
            if np.linalg.norm(T[i][:3, 3] - T[j][:3, 3]) < 0.2 and np.dot(T[i][:3, 2], T[j][:3, 2]) > 0.9:
                loops += 1
    print(f"   revisit pairs (>= 10 frames apart, < 0.2 m and < 25 deg apart): {loops}")


def check_sequence(path: Path, every: int) -> None:
    import open3d as o3d

    from frontend.fpp.sequence import read_sequence

    seq = read_sequence(path)
    if seq.ground_truth is None or seq.ground_truth_mesh_path is None:
        raise SystemExit(f"{path} has no ground truth")
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.io.read_triangle_mesh(str(seq.ground_truth_mesh_path)))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(mesh)
    sensor = FppSensor(seq.calibration, seq.spec)
    poses = seq.ground_truth.poses_world_sensor
    rows = []
    t0 = time.perf_counter()
    for i in range(0, len(seq), every):
        frame = sensor.frame_from_images(seq.frames[i].id, seq.frames[i].timestamp, seq.load_frame_images(i))
        pts = frame.points @ poses[i][:3, :3].T + poses[i][:3, 3]
        d = rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
        rows.append((i, frame.num_points, frame.metadata["valid_fraction"], 1e3 * np.sqrt(np.mean(d**2)), 1e3 * np.median(d)))
    dt = time.perf_counter() - t0
    arr = np.array(rows)
    print(f"{path}: {len(seq)} frames {seq.calibration.camera.width}x{seq.calibration.camera.height}, {seq.spec.image_count()} images each; "
          f"read back + decoded {len(rows)} frames in {dt:.1f} s")
    print(f"   valid fraction mean {arr[:, 2].mean():.3f} (min {arr[:, 2].min():.3f}); decoded point to GT mesh: RMS per frame median "
          f"{np.median(arr[:, 3]):.4f} mm (max {arr[:, 3].max():.4f}), median distance {np.median(arr[:, 4]):.4f} mm")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preview", action="store_true")
    parser.add_argument("--sequence", type=Path, action="append", default=[])
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--skip-overlap", action="store_true")
    args = parser.parse_args()
    if args.sequence:
        for p in args.sequence:
            check_sequence(p, args.every)
        return
    single_view(args.preview)
    if not args.skip_overlap:
        overlaps(DATASETS / "corridor.yaml")
        overlaps(DATASETS / "turntable.yaml")


if __name__ == "__main__":
    main()
