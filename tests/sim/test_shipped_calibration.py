"""The demo's estimated calibration ships with the package: used for exactly its inputs, and the
procedure reproduces it (``python -m scripts.regenerate_demo_calibration`` writes it)."""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest

from fpp_graph.errors import CalibrationError
from frontend.demo import demo_calibration_inputs
from frontend.fpp.rig import load_calibration
from frontend.sim import calibration as sim_calibration
from frontend.sim.calibration import (
    cache_key,
    calibrate_from_rendered_board,
    estimate_rig_calibration,
    shipped_calibration_dir,
    shipped_estimate,
)


@pytest.fixture(scope="module")
def demo_inputs():
    return demo_calibration_inputs()


@pytest.fixture
def no_computation(monkeypatch):
    """Records the inputs the calibration procedure is asked to run on, instead of running it."""
    calls = []

    def computed(truth, settings, seed, progress=None):
        calls.append((settings, seed))
        raise CalibrationError("computed")

    monkeypatch.setattr(sim_calibration, "calibrate_from_rendered_board", computed)
    return calls


def test_the_demo_uses_the_shipped_estimate(demo_inputs, no_computation, tmp_path):
    truth, settings, seed = demo_inputs
    key = cache_key(truth, settings, seed)
    shipped = shipped_calibration_dir() / f"{key}.yaml"
    assert shipped.is_file(), f"no shipped estimate for the demo's inputs ({key}): run python -m scripts.regenerate_demo_calibration"
    start = time.perf_counter()
    estimate = estimate_rig_calibration(truth, settings, seed, cache_dir=tmp_path / "cache")
    assert time.perf_counter() - start < 2.0 and not no_computation
    assert not (tmp_path / "cache").exists()  # nothing to cache: the package has it
    np.testing.assert_array_equal(estimate.calibration.camera.K, load_calibration(shipped).camera.K)
    np.testing.assert_array_equal(estimate.calibration.T_projector_camera, load_calibration(shipped).T_projector_camera)
    assert estimate.report["seed"] == seed and estimate.report["poses"] == settings.poses
    # an estimate, not the truth, and a sensible one (sub-0.1 px, fractions of a percent)
    assert not np.allclose(estimate.calibration.camera.K, truth.camera.K, atol=1e-3)
    assert 0.005 < estimate.report["reprojection_rms_px"]["stereo"] < 0.1
    errors = estimate.report["errors_vs_truth"]
    assert abs(errors["camera_fx_err_percent"]) < 0.1 and abs(errors["baseline_err_mm"]) < 0.5 and errors["rotation_err_deg"] < 0.1


def test_changed_inputs_do_not_use_the_shipped_estimate(demo_inputs, no_computation, tmp_path):
    truth, settings, seed = demo_inputs
    assert shipped_estimate(truth, settings, seed) is not None
    changed = [
        (truth, settings, seed + 1),
        (truth, settings.model_copy(update={"poses": settings.poses - 1}), seed),
        (truth, settings.model_copy(update={"noise_grey": settings.noise_grey * 2}), seed),
        (truth, settings.model_copy(update={"printing_scale_error": 0.0}), seed),
    ]
    from frontend.sim import RigParameters, build_rig

    changed.append((build_rig(RigParameters(camera_focal_px=2001.0)), settings, seed))
    for rig, s, k in changed:
        assert shipped_estimate(rig, s, k) is None
        with pytest.raises(CalibrationError, match="computed"):
            estimate_rig_calibration(rig, s, k, cache_dir=tmp_path)
    assert [(s.poses, k) for s, k in no_computation] == [(settings.poses, seed + 1), (settings.poses - 1, seed), (settings.poses, seed), (settings.poses, seed), (settings.poses, seed)]
    # asked not to, it does not use the shipped one either
    with pytest.raises(CalibrationError, match="computed"):
        estimate_rig_calibration(truth, settings, seed, cache_dir=tmp_path, shipped=False)


def test_a_misnamed_estimate_is_refused(demo_inputs, no_computation, tmp_path):
    """A cached file whose report names other inputs than its key: a clear error, not another
    rig's calibration decoding the sequence."""
    truth, settings, seed = demo_inputs
    key = cache_key(truth, settings, seed)
    other = cache_key(truth, settings, seed + 1)
    shutil.copy(shipped_calibration_dir() / f"{key}.yaml", tmp_path / f"{other}.yaml")
    shutil.copy(shipped_calibration_dir() / f"{key}.json", tmp_path / f"{other}.json")
    with pytest.raises(CalibrationError, match=f"{other}.*delete"):
        estimate_rig_calibration(truth, settings, seed + 1, cache_dir=tmp_path)
    (tmp_path / f"{other}.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="unreadable"):
        estimate_rig_calibration(truth, settings, seed + 1, cache_dir=tmp_path)
    assert not no_computation


def test_regeneration_refuses_to_overwrite(capsys):
    from scripts.regenerate_demo_calibration import main

    assert main([]) == 1
    assert "--force" in capsys.readouterr().out


@pytest.mark.slow
def test_the_procedure_reproduces_the_shipped_estimate(demo_inputs):
    """The demo's inputs through the whole procedure (15 board poses rendered at 1920x1200, about
    3 minutes): the same parameters as the shipped file, to far below what the demo could see.
    OpenCV's threaded reductions change the last bits (about 1e-8 px), not more."""
    truth, settings, seed = demo_inputs
    shipped = shipped_estimate(truth, settings, seed)
    assert shipped is not None
    computed = calibrate_from_rendered_board(truth, settings, seed)
    for device in ("camera", "projector"):
        old, new = getattr(shipped.calibration, device), getattr(computed.calibration, device)
        np.testing.assert_allclose(new.K, old.K, rtol=0, atol=1e-5, err_msg=device)
        np.testing.assert_allclose(new.dist, old.dist, rtol=0, atol=1e-8, err_msg=device)
    np.testing.assert_allclose(computed.calibration.T_projector_camera[:3, :3], shipped.calibration.T_projector_camera[:3, :3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(computed.calibration.T_projector_camera[:3, 3], shipped.calibration.T_projector_camera[:3, 3], rtol=0, atol=1e-9)  # 1 nm
    rms = computed.report["reprojection_rms_px"]
    for name, value in shipped.report["reprojection_rms_px"].items():
        assert rms[name] == pytest.approx(value, abs=1e-6), name
    assert computed.report["poses"] == shipped.report["poses"]
    assert json.loads(json.dumps(computed.report["settings"])) == shipped.report["settings"]
