"""`fpp-slam patterns | decode | calibrate | import`: the real captures, the end-to-end import, and
bad input (one-line errors naming the file and what to do)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from cli_helpers import run_cli, write_pattern_file
from conftest import shared_data_path

from fpp_graph.outputs import LOCK_NAME
from frontend.fpp.capture import decode_capture, read_capture
from frontend.fpp.pattern_file import load_pattern_spec
from frontend.fpp.patterns import PatternSpec, generate_patterns
from frontend.fpp.rig import save_calibration

ROOT = Path(__file__).resolve().parents[2]
PATTERNS = ROOT / "datasets" / "patterns"


def _one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# ---------------------------------------------------------------------------- patterns


def test_patterns_prints_the_schema_and_checks_files(tmp_path):
    code, out, _ = run_cli("patterns")
    assert code == 0 and "phase.F.N" in out and "gray_order" in out and "stripe" in out
    for path in sorted(PATTERNS.glob("*.yaml")):
        code, out, err = run_cli("patterns", str(path))
        assert code == 0, err
        assert f"{load_pattern_spec(path).image_count()} images per capture" in out
    code, out, _ = run_cli("patterns", str(PATTERNS / "gray_only_refs_first_10bit.yaml"), "--projector", "64x16", "--render-to", str(tmp_path / "r"))
    assert code == 0 and len(list((tmp_path / "r").glob("*.png"))) == 12
    white = cv2.imread(str(tmp_path / "r" / "000.png"), cv2.IMREAD_UNCHANGED)
    assert white.shape == (16, 64) and white.min() == 255


def test_a_sequence_yaml_is_read_as_is(tmp_path):
    spec = PatternSpec("complementary_gray", phase_steps=4, periods=(64,), gray_bits=6)
    (tmp_path / "sequence.yaml").write_text(yaml.safe_dump({"format": "fpp-graph sequence v1", "patterns": spec.to_dict(), "frames": []}))
    assert load_pattern_spec(tmp_path / "sequence.yaml") == spec
    assert load_pattern_spec(tmp_path) == spec


def test_unknown_role_is_a_one_line_error_naming_the_file(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("kind: gray_code\ngray_bits: 2\norder: [white, black, gray.0, gray.1, grey.2]\n")
    code, _, err = run_cli("patterns", str(path))
    _one_line_error(code, err, str(path), "unknown image role 'grey.2'", "known roles")
    path.write_text("kind: gray_code\ngray_bits: 3\norder: [white, black, gray.0, gray.1]\n")
    code, _, err = run_cli("patterns", str(path))
    _one_line_error(code, err, str(path), "misses gray.2")


# ---------------------------------------------------------------------------- bad input to decode


@pytest.fixture()
def tiny_capture(tmp_path):
    """A 4-step complementary Gray capture of a plane by the preview rig, with its files."""
    from frontend.sim import FppSimulator, default_rig, plane_scene

    rig = default_rig(preview=True)
    spec = PatternSpec("complementary_gray", phase_steps=4, periods=(64,), gray_bits=6)
    frame = FppSimulator(rig, spec, plane_scene(0.5, tilt_deg=-7.0)).render(np.eye(4), 0)
    capture = tmp_path / "capture"
    capture.mkdir()
    for i, image in enumerate(frame.images):
        cv2.imwrite(str(capture / f"{i:02d}.png"), image)
    save_calibration(tmp_path / "rig.yaml", rig)
    return capture, tmp_path / "rig.yaml", write_pattern_file(tmp_path / "patterns.yaml", spec), spec


def test_decode_image_count_mismatch(tiny_capture, tmp_path):
    capture, rig, patterns, spec = tiny_capture
    (capture / "10.png").unlink()
    code, _, err = run_cli("decode", str(capture), "--calibration", str(rig), "--patterns", str(patterns), "--out", str(tmp_path / "o"))
    _one_line_error(code, err, str(capture), "10 images", f"describes {spec.image_count()}", "--images")
    assert not (tmp_path / "o").exists()


def test_decode_calibration_size_mismatch(tiny_capture, tmp_path):
    capture, _, patterns, _ = tiny_capture
    from frontend.sim import default_rig

    save_calibration(tmp_path / "full.yaml", default_rig(preview=False))  # 1920x1200 camera
    code, _, err = run_cli("decode", str(capture), "--calibration", str(tmp_path / "full.yaml"), "--patterns", str(patterns), "--out", str(tmp_path / "o"))
    _one_line_error(code, err, str(capture), str(tmp_path / "full.yaml"), "640x400", "1920x1200")


def test_decode_unknown_calibration_format(tiny_capture, tmp_path):
    capture, _, patterns, _ = tiny_capture
    junk = tmp_path / "cal.xml"
    junk.write_text("<?xml version=\"1.0\"?>\n<opencv_storage>\n<foo>1</foo>\n</opencv_storage>\n")
    code, _, err = run_cli("decode", str(capture), "--calibration", str(junk), "--patterns", str(patterns), "--out", str(tmp_path / "o"))
    _one_line_error(code, err, str(junk), "unknown calibration format", "SLStudio", "SLMaster", "procam-calibration")


def test_decode_outputs(tiny_capture, tmp_path):
    capture, rig, patterns, _ = tiny_capture
    out = tmp_path / "o"
    code, stdout, err = run_cli("decode", str(capture), "--calibration", str(rig), "--patterns", str(patterns), "--out", str(out), "--images", "*.png")
    assert code == 0, err
    xyz = np.load(out / "xyz_map.npy")
    assert xyz.shape == (400, 640, 3) and xyz.dtype == np.float32
    valid = np.isfinite(xyz[..., 2])
    depth = cv2.imread(str(out / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and np.array_equal(depth > 0, valid)
    assert np.abs(depth[valid] * 1e-4 - xyz[..., 2][valid]).max() <= 0.5e-4 + 1e-7  # 0.1 mm units
    report = json.loads((out / "decode.json").read_text())
    assert report["valid_pixels"] == int(valid.sum()) and f"{report['valid_pixels']} valid points" in stdout
    assert report["thresholds"]["min_modulation_grey"] == 4.0 and report["modulation_grey"]["valid_pixels"]["median"] > 20
    header = (out / "points.ply").read_bytes()[:400].decode("ascii", "replace")
    assert f"element vertex {valid.sum()}" in header and "property uchar red" in header
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != LOCK_NAME]  # no temporary files left (the lock file stays)


# ---------------------------------------------------------------------------- real captures


@pytest.fixture(scope="module")
def slmaster_calibration():
    return shared_data_path("real_fpp", "slmaster_monocular", "caliInfo.yml")


def test_decode_slmaster_monocular_gives_todays_cloud(slmaster_calibration, tmp_path):
    """Same decode as scripts/decode_real.py (u_p identical), same cloud as its Triangulator
    (217154 points without the edge filter); the pipeline's edge filter, its allowances scaled by
    each pixel's predicted depth noise, keeps 212920 (a fixed 0.5 mm allowance kept 206645), the plaque
    at 694-777 mm (0.5-99.5 percentiles)."""
    folder = slmaster_calibration.parent
    spec = load_pattern_spec(PATTERNS / "slmaster_monocular.yaml")
    from frontend.fpp.calibration_io import read_slmaster_calibration
    from frontend.fpp.triangulation import Triangulator

    capture = decode_capture(read_capture(folder, spec, "*.png"), read_slmaster_calibration(slmaster_calibration), spec, edge_filter=False)
    import runpy

    today = runpy.run_path(str(ROOT / "scripts" / "decode_real.py"))["decode_slmaster_monocular"](folder)
    assert np.array_equal(today.u_projector_px, capture.decoding.u_projector_px, equal_nan=True)
    xyz_today = Triangulator(read_slmaster_calibration(slmaster_calibration), depth_range_m=(0.05, 10.0)).triangulate(today.u_projector_px, today.mask)
    assert int(np.isfinite(xyz_today[..., 2]).sum()) == capture.report["valid_pixels"] == 217154
    code, _, err = run_cli("decode", str(folder), "--calibration", str(slmaster_calibration), "--patterns", str(PATTERNS / "slmaster_monocular.yaml"), "--out", str(tmp_path), "--images", "*.png")
    assert code == 0, err
    report = json.loads((tmp_path / "decode.json").read_text())
    assert report["valid_pixels"] == 212920
    z_mm = 1e3 * np.load(tmp_path / "xyz_map.npy")[..., 2]
    lo, hi = np.nanpercentile(z_mm, [0.5, 99.5])
    assert lo == pytest.approx(693.8, abs=0.5) and hi == pytest.approx(776.8, abs=0.5)


def test_decode_slmaster_heterodyne_matches_slmaster(slmaster_calibration, tmp_path):
    """SLMaster's own regression values: fringe order 30 at (row 480, col 590), unwrapped phase
    191.95 rad at (row 470, col 590); the cloud (through the monocular capture's calibration,
    the only one shipped): 261303 points without the edge filter, 242269 with it (a fixed 0.5 mm
    allowance kept 163906: it dropped stripes of good surface whose depth ripples by about 1.5 mm
    at the fringe period, within this capture's predicted depth noise)."""
    folder = shared_data_path("real_fpp", "slmaster_heterodyne")
    spec = load_pattern_spec(PATTERNS / "slmaster_heterodyne.yaml")
    from frontend.fpp.calibration_io import read_slmaster_calibration

    capture = decode_capture(read_capture(folder, spec), read_slmaster_calibration(slmaster_calibration), spec, edge_filter=False)
    assert int(capture.decoding.fringe_order[480, 590]) == 30
    assert float(capture.decoding.absolute_phase[470, 590]) == pytest.approx(191.948, abs=0.002)
    assert capture.report["valid_pixels"] == 261303
    code, _, err = run_cli("decode", str(folder), "--calibration", str(slmaster_calibration), "--patterns", str(PATTERNS / "slmaster_heterodyne.yaml"), "--out", str(tmp_path))
    assert code == 0, err
    assert json.loads((tmp_path / "decode.json").read_text())["valid_pixels"] == 242269


def test_calibrate_procam_sample_reproduces_the_stereo_rms(tmp_path):
    """With cornerSubPix's corners (``--corners subpix``, procam-calibration's detector) the
    sample's stereo RMS is 0.295 px; the default X-junction fit brings it to 0.257 px (camera
    0.309 -> 0.299, projector 0.191 -> 0.160: the projector corners are read at the camera's)."""
    root = shared_data_path("real_fpp", "procam_calibration")
    from frontend.fpp.rig import load_calibration

    stereo = {}
    for corners in ("subpix", "model"):
        out = tmp_path / f"calibration_{corners}.yaml"
        code, stdout, err = run_cli(
            "calibrate", str(root), "--patterns", str(PATTERNS / "procam_graycode_1024x768.yaml"), "--board", "9x7", "--square-mm", "75",
            "--projector", "1024x768", "--out", str(out), "--poses", "capture_*", "--corners", corners,
        )
        assert code == 0, err
        assert len(re.findall(r"^capture_\d\s+\d\.\d{3}\s+\d\.\d{3}$", stdout, flags=re.M)) == 5  # per view
        cal = load_calibration(out)
        assert (cal.projector.width, cal.projector.height) == (1024, 768)
        stereo[corners] = cal.reprojection_rms_px["stereo"]
        assert f"stereo {stereo[corners]:.3f} px" in stdout
    assert stereo["subpix"] == pytest.approx(0.29547, abs=1e-4)
    assert stereo["model"] == pytest.approx(0.257, abs=2e-3)
    code, _, err = run_cli(
        "calibrate", str(root), "--patterns", str(PATTERNS / "procam_graycode_1024x768.yaml"), "--board", "9x7", "--square-mm", "75",
        "--projector", "1024x768", "--out", str(tmp_path / "c.yaml"), "--corners", "harris",
    )
    _one_line_error(code, err, "--corners must be 'model' or 'subpix'")



def test_calibrate_with_a_released_board_reports_the_estimated_board(tmp_path):
    root = shared_data_path("real_fpp", "procam_calibration")
    code, stdout, err = run_cli(
        "calibrate", str(root), "--patterns", str(PATTERNS / "procam_graycode_1024x768.yaml"), "--board", "9x7", "--square-mm", "75",
        "--projector", "1024x768", "--out", str(tmp_path / "calibration.yaml"), "--poses", "capture_*", "--release-board",
    )
    assert code == 0, err
    # five poses leave the board's shape loose: corners move by millimetres and the fit drops below the rigid 0.295 px
    deviation_mm = float(re.search(r"board estimated: corners up to (\d+\.\d+) mm", stdout).group(1))
    assert 0.5 < deviation_mm < 10
    stereo = float(re.search(r"stereo (\d\.\d{3}) px", stdout).group(1))
    assert stereo < 0.295


# ---------------------------------------------------------------------------- calibrate: bad input


def test_calibrate_board_not_found(tmp_path):
    spec = PatternSpec("gray_code", axis="both", gray_bits=6, gray_bits_rows=5, periods=(64, 32), gray_inverse=True, with_reference=True)
    images = generate_patterns(spec, 64, 32)  # the camera sees the bare patterns: no board anywhere
    for pose in ("pose_0", "pose_1", "pose_2"):
        (tmp_path / "captures" / pose).mkdir(parents=True)
        for i, image in enumerate(images):
            cv2.imwrite(str(tmp_path / "captures" / pose / f"{i:02d}.png"), image)
    patterns = write_pattern_file(tmp_path / "p.yaml", spec)
    white = tmp_path / "captures" / "pose_0" / f"{spec.image_count() - 2:02d}.png"
    code, _, err = run_cli("calibrate", str(tmp_path / "captures"), "--patterns", str(patterns), "--board", "9x7", "--square-mm", "20", "--projector", "64x32", "--out", str(tmp_path / "c.yaml"))
    _one_line_error(code, err, str(white), "no chessboard with 9x7 inner corners", "--board", "--skip-missing-board")
    code, _, err = run_cli("calibrate", str(tmp_path / "captures"), "--patterns", str(patterns), "--board", "9x7", "--square-mm", "20", "--projector", "64x32", "--out", str(tmp_path / "c.yaml"), "--skip-missing-board")
    assert code == 2 and "pose skipped" in err  # each skipped pose is a warning, then one error line
    assert err.strip().splitlines()[-1].startswith("fpp-slam: error: only 0 of 3 poses show the board")
    columns_only = write_pattern_file(tmp_path / "cols.yaml", PatternSpec("complementary_gray"))
    code, _, err = run_cli("calibrate", str(tmp_path / "captures"), "--patterns", str(columns_only), "--board", "9x7", "--square-mm", "20", "--projector", "64x32", "--out", str(tmp_path / "c.yaml"))
    _one_line_error(code, err, "axis: both")


# ---------------------------------------------------------------------------- import, then run


def test_import_simulated_captures_then_run(tmp_path):
    """Per-frame capture folders without a sequence.yaml -> import (copied and referenced) -> run."""
    from frontend.fpp.sequence import read_sequence
    from frontend.sim import simulate_sequence

    simulated = read_sequence(simulate_sequence({"scene": "turntable", "turntable": {"turns": 1, "views_per_turn": 24}}, tmp_path / "sim", preview=True, max_frames=3))
    root = tmp_path / "captures"
    for k, rec in enumerate(simulated.frames):
        (root / f"view{k + 1}").mkdir(parents=True)
        for j, name in enumerate(rec.images):
            shutil.copy(simulated.path / rec.folder / name, root / f"view{k + 1}" / f"img_{j}.png")  # img_2 before img_10
    save_calibration(tmp_path / "rig.yaml", simulated.calibration)
    patterns = write_pattern_file(tmp_path / "patterns.yaml", simulated.spec)
    for mode in ("--copy", "--reference"):
        out = tmp_path / f"seq{mode}"
        code, stdout, err = run_cli("import", str(root), "--patterns", str(patterns), "--calibration", str(tmp_path / "rig.yaml"), "--out", str(out), mode)
        assert code == 0, err
        assert "3 frames" in stdout
        seq = read_sequence(out)
        assert np.array_equal(seq.load_frame_images(2), simulated.load_frame_images(2))
    assert not list((tmp_path / "seq--reference").glob("frame_*"))  # referenced, not copied
    code, stdout, err = run_cli("run", str(tmp_path / "seq--reference"), "--out", str(tmp_path / "results"))
    assert code == 0, err
    assert "3/3 frames" in stdout
    assert (tmp_path / "results" / "trajectory.tum").is_file()
    code, _, err = run_cli("import", str(root), "--patterns", str(PATTERNS / "slmaster_monocular.yaml"), "--calibration", str(tmp_path / "rig.yaml"), "--out", str(tmp_path / "bad"))
    _one_line_error(code, err, str(root / "view1"), "11 images", "describes 18")
