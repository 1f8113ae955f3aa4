"""Every codec of a fringe-set pattern file, rendered by the virtual sensor and decoded through
``fpp-slam decode``: no wrong fringe order, depth noise at the level the phase noise predicts,
both projector coordinates at least as good as the better one alone, and a 40-number text
calibration read by ``decode`` with the camera size taken from the images.

The figures come from :mod:`scripts.codec_accuracy` (the same measurement, at 640x400, prints
them); here at 320x200 so that the file runs in about half a minute.
"""

from __future__ import annotations

import numpy as np
import pytest

from scripts import codec_accuracy as ca

RESOLUTION = (320, 200)
# The prediction holds the image noise and the phase-to-depth propagation; what it leaves out
# (the projector response's harmonic on 3-step sets, defocus blur across steep slopes, the
# 8-bit quantisation of dark pixels) adds to the error: measured 1.00-1.27 times the prediction
# at 640x400 on every codec, so a ratio beyond 1.5 is a decoder that lost accuracy, and one
# below 0.8 a prediction that no longer describes the noise.
RATIO_RANGE = (0.8, 1.5)


@pytest.fixture(scope="module")
def rig_files(tmp_path_factory):
    work = tmp_path_factory.mktemp("codecs")
    calibration = ca.rig(RESOLUTION)
    yaml_file = work / "rig.yaml"
    ca.save_calibration(yaml_file, calibration, replace=False)
    return work, calibration, yaml_file


def text_calibration(calibration) -> str:
    """The 40 numbers of a text calibration: K and 5 distortion terms of camera and projector,
    R and T (mm) mapping camera points into the projector."""
    numbers = [*calibration.camera.K.ravel(), *calibration.camera.dist[:5], *calibration.projector.K.ravel(), *calibration.projector.dist[:5],
               *calibration.T_projector_camera[:3, :3].ravel(), *(1e3 * calibration.T_projector_camera[:3, 3])]
    assert len(numbers) == 40
    return "# camera K, distortion; projector K, distortion; R, T (mm)\n" + "\n".join(" ".join(f"{v:.17g}" for v in numbers[i : i + 5]) for i in range(0, 40, 5)) + "\n"


@pytest.mark.parametrize("name", [
    "both axes 4/4/4/6 hierarchical, 10 px", "3-step single period", "2+1, hierarchical 1280/128/16 px",
    "modulated 3x3, hierarchical 1280/160/20 px", "micro phase shifting, interreflection", "3-step spatially unwrapped, 6 periods",
])
def test_codec_decodes_at_its_noise_level(rig_files, name):
    work, calibration, yaml_file = rig_files
    row = ca.measure(name, ca.CODECS[name], calibration, yaml_file, work, seed=1)
    assert sum(row["order_errors"].values()) == 0, row["order_errors"]
    assert row["valid_pixels"] > 0.5 * RESOLUTION[0] * RESOLUTION[1] * 0.5, row  # the scene fills most of the view
    assert RATIO_RANGE[0] < row["measured_over_predicted_true_noise"] < RATIO_RANGE[1], row
    assert row["edge_filter"]["mixed_after"] == 0, row["edge_filter"]
    if name == "3-step single period":  # the noisiest codec: the filter follows its noise
        assert row["edge_filter"]["kept_fraction"] >= 0.9, row["edge_filter"]
    if row["axis"] == "both":
        tri = row["triangulation"]
        assert tri["both"]["rms_mm"] <= 1.02 * min(tri["columns"]["rms_mm"], tri["rows"]["rms_mm"]), tri
        assert row["cli"]["rms_mm"] == pytest.approx(tri["both"]["rms_mm"], rel=0.05)  # the CLI used both
        assert row["residual_median_px"] < 0.1, row


def test_decode_reads_a_text_calibration_with_the_images_size(rig_files):
    work, calibration, _ = rig_files
    text_file = work / "rig.txt"
    text_file.write_text(text_calibration(calibration))
    name = "2+1, hierarchical 1280/128/16 px"
    with_text = ca.measure(name, ca.CODECS[name], calibration, text_file, work / "text", seed=1)
    assert with_text["valid_pixels"] > 0.25 * RESOLUTION[0] * RESOLUTION[1]
    assert with_text["cli"]["rms_mm"] < 2 * with_text["predicted_true_noise_rms_mm"]
    assert np.isfinite(with_text["cli"]["median_mm"])
