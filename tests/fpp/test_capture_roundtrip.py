"""Synthetic round trips through `fpp-slam decode`: the simulator renders a plane and a sphere under
a pattern set, the images are written in the set's stated order, the command decodes them, and the
xyz map is compared with the renderer's ground truth.

Gray code alone is limited by its stripe width: the decoded projector column is the stripe centre,
off by up to half a stripe, ``W / (S sqrt 12)`` RMS (0.2 px noise-free blur aside). The expected
3D error is that column error times each pixel's ``dz/du_p`` (the triangulation's sensitivity).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_helpers import run_cli, write_pattern_file

from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import save_calibration
from frontend.fpp.triangulation import Triangulator
from frontend.sim import FppSimulator, RigParameters, plane_scene, sphere_scene
from frontend.sim.render import RenderSettings, project_points

PREVIEW_RIG = RigParameters().calibration(preview=True)  # 640x400 camera, 912x1140 projector
# rows need a baseline across them: the projector above the camera
VERTICAL_RIG = RigParameters(baseline_m=0.01, baseline_height_m=-0.13).calibration(preview=True)


def _scene(kind: str):
    return plane_scene(0.5, tilt_deg=-7.0, albedo=0.8) if kind == "plane" else sphere_scene(0.48, radius_m=0.09, resolution=120)


# The round trips check the pattern description -> image order -> decode path, so they render
# with a linear projector; the default response (x^1.1) biases 3-step phase shifting, measured
# on its own below.
LINEAR_PROJECTOR = RenderSettings(projector_gamma=1.0, projector_gamma_compensation=1.0)


def _round_trip(tmp_path: Path, spec: PatternSpec, scene_kind: str, rig=PREVIEW_RIG, settings=LINEAR_PROJECTOR) -> dict:
    """Render, write in order, decode with the CLI; returns errors against the ground truth."""
    frame = FppSimulator(rig, spec, _scene(scene_kind), settings).render(np.eye(4), frame_index=0)
    capture = tmp_path / "capture"
    capture.mkdir()
    for i, image in enumerate(frame.images):
        cv2.imwrite(str(capture / f"image_{i}.png"), image)  # natural order: image_2 before image_10
    save_calibration(tmp_path / "rig.yaml", rig)
    patterns = write_pattern_file(tmp_path / "patterns.yaml", spec)
    code, out, err = run_cli("decode", str(capture), "--calibration", str(tmp_path / "rig.yaml"), "--patterns", str(patterns), "--out", str(tmp_path / "out"))
    assert code == 0, err
    xyz = np.load(tmp_path / "out" / "xyz_map.npy").astype(np.float64)
    gt = frame.ground_truth.xyz_map_m
    ok = np.isfinite(xyz[..., 2]) & np.isfinite(gt[..., 2]) & frame.ground_truth.lit_mask
    err_m = np.linalg.norm(xyz[ok] - gt[ok], axis=1)
    report = json.loads((tmp_path / "out" / "decode.json").read_text())
    # each pixel's depth sensitivity to its projector coordinate, for the Gray-only expectation
    tri = Triangulator(rig, axis=spec.coded_axis)
    u, v, _ = project_points(rig.projector, rig.T_projector_camera, gt[ok])
    w = u if spec.coded_axis == "columns" else v
    w_map = np.full(gt.shape[:2], np.nan, np.float32)
    w_map[ok] = w
    dz = tri.triangulate(w_map + 0.5)[..., 2][ok] - tri.triangulate(w_map - 0.5)[..., 2][ok]
    lit = frame.ground_truth.lit_mask
    return {
        "rms_mm": 1e3 * float(np.sqrt(np.mean(err_m**2))),
        "median_mm": 1e3 * float(np.median(err_m)),
        "valid_of_lit": float(ok.sum() / max(lit.sum(), 1)),
        "dz_du_mm": 1e3 * float(np.nanmedian(np.abs(dz))),
        "report": report,
    }


GRAY_ONLY_BITS = 7  # 128 stripes over 912 px: 7.1 px stripes, 2.06 px RMS


def _gray_only(order: str) -> PatternSpec:
    return PatternSpec("gray_code", gray_bits=GRAY_ONLY_BITS, with_reference=True, reference_position="start", gray_order=order)


@pytest.mark.parametrize("scene_kind", ["plane", "sphere"])
@pytest.mark.parametrize("order", ["msb_first", "lsb_first"])
def test_gray_only_references_first_meets_its_stripe_width(tmp_path, scene_kind, order):
    spec = _gray_only(order)
    assert [im.role for im in spec.layout()[:3]] == ["white", "black", "gray"]
    assert spec.layout()[2].bit == (0 if order == "msb_first" else GRAY_ONLY_BITS - 1)
    r = _round_trip(tmp_path, spec, scene_kind)
    stripe_px = PREVIEW_RIG.projector.width / 2**GRAY_ONLY_BITS
    expected_mm = stripe_px / np.sqrt(12) * r["dz_du_mm"]  # uniform error over the stripe
    print("Gray only", order, scene_kind, {k: v for k, v in r.items() if k != "report"}, "expected rms mm", expected_mm)
    assert r["valid_of_lit"] > 0.85
    assert 0.7 * expected_mm < r["rms_mm"] < 1.3 * expected_mm, (r, expected_mm)


# One period across the 912-px projector has 64 times the pitch of the 64-period sets, hence
# 64 times their depth noise (about 1 px of u_p, 2 mm at this 640x400 preview's 2 mm/px). The
# edge filter's allowances scale with each pixel's predicted depth noise, so it keeps these
# pixels (97-99 % of the lit ones); the sphere's limb, lit at grazing angles with a few times
# less modulation, lifts its RMS to about 1.8x the plane's (3.7 against 2.2 mm). The 16/15
# heterodyne set has a 57-px pitch (4x the 64-period sets') and 3 steps: about 4.6x their noise.
@pytest.mark.parametrize("scene_kind", ["plane", "sphere"])
@pytest.mark.parametrize(
    ("name", "spec", "rig", "min_valid", "max_median_mm", "max_rms_mm"),
    [
        ("single frequency, 16 steps, one period", PatternSpec("single_frequency", phase_steps=16, with_reference=True), PREVIEW_RIG, 0.9, 2.0, 4.5),
        ("3-step, 2 frequencies (heterodyne 16/15)", PatternSpec("multi_frequency", phase_steps=3, periods=(16, 15)), PREVIEW_RIG, 0.8, 0.3, 0.6),
        ("4-step + complementary Gray code with inverses", PatternSpec("complementary_gray", phase_steps=4, periods=(64,), gray_bits=6, gray_inverse=True), PREVIEW_RIG, 0.8, 0.1, 0.2),
        ("rows: 4-step + complementary Gray code", PatternSpec("complementary_gray", phase_steps=4, periods=(64,), gray_bits=6, axis="rows"), VERTICAL_RIG, 0.8, 0.1, 0.2),
        ("columns, reversed shift, origin pi", PatternSpec("complementary_gray", phase_steps=6, periods=(32,), gray_bits=5, shift_direction="reverse", phase_origin_rad=np.pi), PREVIEW_RIG, 0.8, 0.15, 0.25),
    ],
)
def test_phase_sets_round_trip(tmp_path, scene_kind, name, spec, rig, min_valid, max_median_mm, max_rms_mm):
    r = _round_trip(tmp_path, spec, scene_kind, rig)
    print(name, scene_kind, {k: v for k, v in r.items() if k != "report"})
    assert r["valid_of_lit"] > min_valid, (name, r)
    assert r["median_mm"] < max_median_mm, (name, r)
    assert r["rms_mm"] < max_rms_mm, (name, r)
    assert r["report"]["valid_pixels"] > 0 and r["report"]["thresholds"]["edge_filter"]["enabled"]


def test_projector_response_biases_three_steps_not_four(tmp_path):
    """The default projector response (P^1.1) adds a second harmonic to the fringes: N-step phase
    shifting cancels harmonics up to N - 2, so 3 steps are biased by it and 4 steps are not."""
    three = PatternSpec("multi_frequency", phase_steps=3, periods=(16, 15))
    four = PatternSpec("complementary_gray", phase_steps=4, periods=(64,), gray_bits=6)
    errors = {}
    for name, spec in (("three", three), ("four", four)):
        for response, settings in (("linear", LINEAR_PROJECTOR), ("default", RenderSettings())):
            (tmp_path / f"{name}_{response}").mkdir()
            errors[name, response] = _round_trip(tmp_path / f"{name}_{response}", spec, "plane", settings=settings)["median_mm"]
    assert errors["three", "default"] > 1.3 * errors["three", "linear"], errors
    assert errors["four", "default"] < 1.2 * errors["four", "linear"] + 0.005, errors
