"""Each FPP codec simulated by the virtual sensor and decoded through ``fpp-slam decode``: fringe-order
errors, depth error against the truth next to what the phase noise predicts, and both-coordinate
against one-coordinate triangulation.

    .venv/bin/python -m scripts.codec_accuracy [--resolution 640x400] [--json OUT.json] [--keep DIR]

The rig: the simulator's camera binned to ``--resolution`` and a 1280x720 projector 0.13 m to the
camera's right and 0.06 m below it (so that both projector axes encode depth). The scene: a
matte sphere of 60 mm radius in front of a tilted plate (smooth surfaces and depth edges with
mixed pixels). Every codec's images are rendered with the simulator's default noise and defocus
(``interreflection`` rows add the simulator's global-illumination term), written as PNGs with a
pattern file, and decoded by ``fpp-slam decode`` in a subprocess, exactly as a user would.

Per codec the script prints:

* ``order errors``: decoded pixels whose projector coordinate is off the true one (the truth's
  point projected into the projector) by more than half the finest pitch (a wrong fringe order);
* ``depth error``: the RMS and median absolute error of the decoded depth against the rendered
  truth over the pixels the CLI kept, away from depth edges, next to the RMS that the phase
  noise predicts there (the decoder's per-pixel coordinate noise propagated through the
  triangulation), and their ratio;
* for captures that code both axes, the same depth error triangulated from the column
  coordinate alone, the row coordinate alone and both (least squares over the two projector
  planes).
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from frontend.fpp.lens import project_to_projector
from frontend.fpp.pattern_file import load_pattern_spec
from frontend.fpp.phase import make_decoder
from frontend.fpp.rig import RigCalibration, save_calibration
from frontend.fpp.triangulation import Triangulator
from frontend.fpp.two_axis_triangulation import TwoAxisTriangulator
from frontend.sim import (
    FppSimulator,
    RenderSettings,
    RigParameters,
    build_rig,
    with_camera_resolution,
)
from frontend.sim.scenes import Scene, plane_scene, sphere_scene

REPO = Path(__file__).resolve().parents[1]
PROJECTOR_SIZE = (1280, 720)
DEPTH_RANGE_M = (0.2, 1.5)
# Pixels whose true depth varies by more than this within 2 pixels lie on a depth edge: their
# error is the edge filter's business (mixed pixels), not the codec's noise.
EDGE_DEPTH_JUMP_M = 0.005

# The carrier runs along the rows with a 24-px pitch: 12 camera pixels at the 640x400 preview,
# well above the camera's blur, and well below the indirect light's 20-pixel kernel.
MODULATED = [
    {"axis": "columns", "codec": "modulated_phase_shift", "pitch_px": p, "steps": 3, "carrier_steps": 3, "carrier_pitch_px": 24}
    for p in (1280, 160, 20)
]
CODECS: dict[str, dict[str, Any]] = {
    "both axes 4/4/4/6 hierarchical, 10 px": {"file": "datasets/patterns/both_axes_hierarchical_4446.yaml"},
    "3-step single period": {"fringe_sets": [{"axis": "columns", "periods": 1, "steps": 3}]},
    "2+1, hierarchical 1280/128/16 px": {"fringe_sets": [
        {"axis": "columns", "codec": "two_plus_one", "pitch_px": p} for p in (1280, 128, 16)]},
    "modulated 3x3, hierarchical 1280/160/20 px": {"fringe_sets": MODULATED},
    "micro phase shifting, 12 images": {"micro": True},
    "3-step single period, interreflection": {"fringe_sets": [{"axis": "columns", "periods": 1, "steps": 3}], "interreflection": True},
    "micro phase shifting, interreflection": {"micro": True, "interreflection": True},
    "modulated 3x3, interreflection": {"fringe_sets": MODULATED, "interreflection": True},
    # Spatial unwrapping needs neighbouring pixels under half a period apart: at the sphere's
    # silhouette they are up to 52 projector columns apart at 640x400 (in the rendered truth),
    # under half of this 213-px pitch (with 16 periods, 80 px, the plate was put a period off
    # the sphere: 191735 wrong orders at 640x400).
    # The camera sees columns 126-1280, more than L - pitch, so the extent alone fixes the order.
    "3-step spatially unwrapped, 6 periods": {"fringe_sets": [{"axis": "columns", "periods": 6, "steps": 3, "unwrapping": "spatial"}]},
}


def rig(resolution: tuple[int, int]) -> RigCalibration:
    """The simulator's camera binned to ``resolution``, a 1280x720 projector offset right and down."""
    params = RigParameters(
        projector_width=PROJECTOR_SIZE[0], projector_height=PROJECTOR_SIZE[1], projector_fx_px=1400.0, projector_fy_px=1400.0,
        projector_cx_px=639.5, projector_cy_px=359.5, baseline_m=0.13, baseline_height_m=0.06,
    )
    return build_rig(with_camera_resolution(params, *resolution))


def scene() -> Scene:
    return Scene(plane_scene(distance_m=0.56, size_m=1.0, tilt_deg=15.0, contrast=0.3).parts + sphere_scene(distance_m=0.44, radius_m=0.06).parts)


def pattern_document(name: str, entry: dict[str, Any]) -> dict[str, Any]:
    if "file" in entry:
        return yaml.safe_load((REPO / entry["file"]).read_text())
    if entry.get("micro"):
        from frontend.fpp.micro_phase_shift import micro_pitches

        return {"format": "fpp-graph patterns v1", "description": name,
                "fringe_sets": [{"axis": "columns", "codec": "micro_phase_shift", "pitches_px": [float(p) for p in micro_pitches(PROJECTOR_SIZE[0])]}]}
    return {"format": "fpp-graph patterns v1", "description": name, "fringe_sets": entry["fringe_sets"]}


def render(calibration: RigCalibration, spec, interreflection: bool, seed: int):
    settings = RenderSettings(seed=seed, **({"interreflection_fraction": 0.3} if interreflection else {}))
    return FppSimulator(calibration, spec, scene(), settings, threads=1).render(np.eye(4), frame_index=0)


def edge_pixels(depth_m: np.ndarray) -> np.ndarray:
    filled = np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float32)
    kernel = np.ones((5, 5), np.uint8)
    span = cv2.dilate(filled, kernel) - cv2.erode(filled, kernel)
    return (span > EDGE_DEPTH_JUMP_M) | ~np.isfinite(depth_m)


def run_decode(folder: Path, calibration_file: Path, pattern_file: Path, out: Path) -> dict[str, Any]:
    # the fpp-slam beside this interpreter: the project's own environment
    cmd = [str(Path(sys.executable).parent / "fpp-slam"), "decode", str(folder), "--calibration", str(calibration_file), "--patterns", str(pattern_file),
           "--projector", f"{PROJECTOR_SIZE[0]}x{PROJECTOR_SIZE[1]}", "--depth-range", f"{DEPTH_RANGE_M[0]},{DEPTH_RANGE_M[1]}", "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr.strip()[-400:]}")
    return {"stdout": done.stdout.strip().splitlines()[-1], "report": json.loads((out / "decode.json").read_text())}


def depth_sigma_one_axis(tri: Triangulator, coord: np.ndarray, sigma: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The coordinate noise propagated through one-axis triangulation (central difference)."""
    hi = tri.depth(coord + sigma, mask).astype(np.float64)
    lo = tri.depth(coord - sigma, mask).astype(np.float64)
    return 0.5 * np.abs(hi - lo)


def stats_mm(error_m: np.ndarray) -> dict[str, float]:
    e = 1e3 * np.abs(error_m[np.isfinite(error_m)])
    if e.size == 0:
        return {"count": 0}
    return {"count": int(e.size), "rms_mm": float(np.sqrt(np.mean(e**2))), "median_mm": float(np.median(e)), "p90_mm": float(np.percentile(e, 90))}


def measure(name: str, entry: dict[str, Any], calibration: RigCalibration, calibration_file: Path, work: Path, seed: int) -> dict[str, Any]:
    folder = work / name.replace(" ", "_").replace("/", "-").replace(",", "")
    images_dir = folder / "images"
    images_dir.mkdir(parents=True)
    pattern_file = folder / "patterns.yaml"
    pattern_file.write_text(yaml.safe_dump(pattern_document(name, entry), sort_keys=False))
    spec = load_pattern_spec(pattern_file)
    frame = render(calibration, spec, bool(entry.get("interreflection")), seed)
    for i, image in enumerate(frame.images):
        cv2.imwrite(str(images_dir / f"{i:03d}.png"), image)
    cli = run_decode(images_dir, calibration_file, pattern_file, folder / "decoded")
    xyz_cli = np.load(folder / "decoded" / "xyz_map.npy").astype(np.float64)
    truth = frame.ground_truth
    interior = ~edge_pixels(truth.depth_m)

    decoded = make_decoder(spec, *PROJECTOR_SIZE).decode(frame.images)
    u_true, v_true = project_to_projector(calibration, truth.xyz_map_m)
    axis = decoded.axis
    coords = {"columns": (decoded.u_projector_px, u_true, decoded.u_noise_px)} if axis in ("columns", "both") else {}
    if axis == "rows":
        coords["rows"] = (decoded.u_projector_px, v_true, decoded.u_noise_px)
    if axis == "both":
        coords["rows"] = (decoded.v_projector_px, v_true, decoded.v_noise_px)
    pitch = float(decoded.pitch_px)
    wrong = {a: decoded.mask & (np.abs(c.astype(np.float64) - t) > 0.5 * pitch) for a, (c, t, _) in coords.items()}
    # a pixel on a depth edge integrates both sides: its coordinate lies between them (a mixed
    # pixel, the edge filter's business); elsewhere a coordinate half a pitch off is a wrong order
    order_errors = {a: int(np.count_nonzero(w & interior)) for a, w in wrong.items()}
    order_errors_at_edges = {a: int(np.count_nonzero(w & ~interior)) for a, w in wrong.items()}

    kept = np.isfinite(xyz_cli[..., 2]) & interior
    error_cli = np.where(kept, xyz_cli[..., 2] - truth.depth_m, np.nan)
    result: dict[str, Any] = {
        "codec": name, "images": spec.image_count(), "axis": axis, "pitch_px": pitch,
        "decoded_pixels": int(cli["report"]["decoded_pixels"]), "valid_pixels": int(cli["report"]["valid_pixels"]),
        "image_noise_grey": decoded.image_noise_grey, "order_errors": order_errors, "order_errors_at_edges": order_errors_at_edges, "cli": stats_mm(error_cli),
    }
    predicted = {}
    per_axis = {}
    for a, (coord, _, sigma) in coords.items():
        tri = Triangulator(calibration, axis=a, depth_range_m=DEPTH_RANGE_M)
        if sigma is not None:
            predicted[a] = depth_sigma_one_axis(tri, coord.astype(np.float64), sigma.astype(np.float64), decoded.mask)
        z = tri.depth(coord, decoded.mask).astype(np.float64)
        per_axis[a] = stats_mm(np.where(kept, z - truth.depth_m, np.nan))
    if axis == "both":
        xyz_both, residual_px, sigma_both = _two_axis(calibration, decoded)
        per_axis["both"] = stats_mm(np.where(kept, xyz_both[..., 2] - truth.depth_m, np.nan))
        predicted["both"] = sigma_both
        result["residual_median_px"] = float(np.nanmedian(np.where(kept, residual_px, np.nan)))
    result["triangulation"] = per_axis
    result["edge_filter"] = edge_filter_account(calibration, spec, frame, xyz_cli)
    used = "both" if axis == "both" else next(iter(coords))
    if used in predicted and predicted[used] is not None:
        # the decoder's prediction rests on the image noise it measures on the capture (the
        # sinusoid fit's residual, which also holds the projector response's harmonics); the
        # simulator's own noise model gives each pixel's true image noise
        sig = np.where(kept, predicted[used], np.nan)
        true_noise = simulated_image_noise_grey(frame.images, RenderSettings())
        sig_true = sig * true_noise / decoded.image_noise_grey
        rms = result["cli"]["rms_mm"]
        for key, values in (("predicted_rms_mm", sig), ("predicted_true_noise_rms_mm", sig_true)):
            result[key] = float(np.sqrt(np.nanmean(values**2))) * 1e3
        result["measured_over_predicted"] = rms / result["predicted_rms_mm"]
        result["measured_over_predicted_true_noise"] = rms / result["predicted_true_noise_rms_mm"]
        result["true_image_noise_grey_median"] = float(np.median(true_noise[kept]))
    return result


# A pixel at a depth edge is mixed when its depth is off the true depth of every pixel of its 5x5
# neighbourhood by more than this many of its predicted sigma_z: a noisy surface point, even
# blurred across a steep slope, is within a few sigma of one of them (4 sigma: a 6e-5
# two-sided normal tail); a point between the two sides of a silhouette is not.
MIXED_SIGMAS = 4.0


# The scene's smooth parts change depth by a few millimetres per pixel at most (the sphere's limb
# included); its silhouette jumps 60 mm or more onto the plate behind.
SILHOUETTE_JUMP_M = 0.02


def silhouette_pixels(depth_m: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood holds a true depth jump: both sides of the silhouette."""
    filled = np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    return (cv2.dilate(filled, kernel) - cv2.erode(filled, kernel)) > SILHOUETTE_JUMP_M


def edge_filter_account(calibration: RigCalibration, spec, frame, xyz_cli: np.ndarray) -> dict[str, Any]:
    """What the CLI's edge filter kept of the decoded pixels, and the mixed pixels at the
    silhouette before it (the same images through the sensor with the filter off) and after it."""
    from frontend.fpp.sensor import FppSensor

    sensor = FppSensor(calibration, spec, depth_range_m=DEPTH_RANGE_M, edge_max_angle_deg=None)
    result = sensor.decode(frame.images)
    raw, sigma_z, _ = sensor._triangulate(result)
    z_raw, z_cli = raw[..., 2], xyz_cli[..., 2]
    limit = MIXED_SIGMAS * (sigma_z if sigma_z is not None else np.full(z_raw.shape, 5e-4))
    closest = np.full(z_raw.shape, np.inf)
    truth = np.pad(frame.ground_truth.depth_m, 2, constant_values=np.nan)
    h, w = z_raw.shape
    with np.errstate(invalid="ignore"):
        for dy in range(5):
            for dx in range(5):
                closest = np.fmin(closest, np.abs(z_raw - truth[dy : dy + h, dx : dx + w]))
        mixed = silhouette_pixels(frame.ground_truth.depth_m) & np.isfinite(z_raw) & (closest > limit)
    triangulated = int(np.count_nonzero(np.isfinite(z_raw)))
    kept = int(np.count_nonzero(np.isfinite(z_cli)))
    return {"triangulated": triangulated, "kept": kept, "kept_fraction": kept / max(triangulated, 1),
            "mixed_before": int(np.count_nonzero(mixed)), "mixed_after": int(np.count_nonzero(mixed & np.isfinite(z_cli)))}


def simulated_image_noise_grey(images: np.ndarray, settings: RenderSettings) -> np.ndarray:
    """Each pixel's image noise in the simulator's camera model: read noise, shot noise at the
    pixel's mean signal over the capture's images, and the 8-bit quantisation."""
    signal = np.asarray(images, np.float64).mean(axis=0)
    return np.sqrt(settings.read_noise_grey**2 + settings.shot_noise_gain * signal + 1.0 / 12.0)


def _two_axis(calibration: RigCalibration, decoded) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    tri = TwoAxisTriangulator(calibration, depth_range_m=DEPTH_RANGE_M)
    out = tri.triangulate(decoded.u_projector_px, decoded.v_projector_px, decoded.mask, u_sigma_px=decoded.u_noise_px, v_sigma_px=decoded.v_noise_px)
    xyz, residual = out[0], out[1]
    sigma = out[2] if len(out) > 2 else getattr(tri, "depth_sigma_m", None)
    return xyz, residual, sigma


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--resolution", default="640x400", help="camera WxH (the simulator's camera binned; 16:10)")
    parser.add_argument("--only", nargs="*", help="codec names (substrings) to run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--keep", type=Path, help="keep the rendered captures and decodes in this new folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    calibration = rig((width, height))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep if args.keep is not None else Path(tmp)
        work.mkdir(parents=True, exist_ok=args.keep is None)
        calibration_file = work / "rig.yaml"
        save_calibration(calibration_file, calibration, replace=False)
        for name, entry in CODECS.items():
            if args.only and not any(s in name for s in args.only):
                continue
            row = measure(name, entry, calibration, calibration_file, work, args.seed)
            rows.append(row)
            print_row(row)
    if args.json is not None:
        args.json.write_text(json.dumps({"resolution": [width, height], "projector": list(PROJECTOR_SIZE), "rows": rows}, indent=2))
    return 0


def print_row(row: dict[str, Any]) -> None:
    tri = row["triangulation"]
    parts = [f"{row['codec']:<42s} {row['images']:3d} images  valid {row['valid_pixels']:7d}/{row['decoded_pixels']:7d}",
             f"order errors {sum(row['order_errors'].values())} (at depth edges {sum(row['order_errors_at_edges'].values())})",
             f"depth rms {row['cli'].get('rms_mm', float('nan')):.3f} mm, predicted {row.get('predicted_rms_mm', float('nan')):.3f} "
             f"(ratio {row.get('measured_over_predicted', float('nan')):.2f}; with the true image noise "
             f"{row.get('predicted_true_noise_rms_mm', float('nan')):.3f}, ratio {row.get('measured_over_predicted_true_noise', float('nan')):.2f})"]
    parts.append("triangulation rms " + ", ".join(f"{k} {v.get('rms_mm', float('nan')):.3f}" for k, v in tri.items()) + " mm")
    ef = row["edge_filter"]
    parts.append(f"edge filter kept {100 * ef['kept_fraction']:.1f} %, mixed pixels {ef['mixed_before']} -> {ef['mixed_after']}")
    if "residual_median_px" in row:
        parts.append(f"residual median {row['residual_median_px']:.3f} px")
    print("  ".join(parts), flush=True)


if __name__ == "__main__":
    sys.exit(main())
