"""FPP sequences a hostile user hands over: a calibration of another camera, frames of the wrong
size, truncated, missing or unreadable images, and a sequence.yaml that cannot be read. What
breaks the whole sequence is refused when it is opened, in one line; what breaks one frame skips
that frame, saying why in the log and in metrics.json."""

from __future__ import annotations

import hashlib
import json
import logging
import pathlib
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from fpp_graph.cli import main
from fpp_graph.config import config_from_dict
from fpp_graph.errors import CalibrationError, InputDataError
from fpp_graph.slam.pipeline import run_sequence
from frontend.fpp.images import check_images_match_calibration, image_size, load_image
from frontend.fpp.rig import load_calibration
from frontend.fpp.sequence import read_sequence
from frontend.fpp.source import FppSequenceSource

WIDTH, HEIGHT = 160, 100  # small enough that a run of the whole sequence takes seconds
FRAMES = 5


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    from frontend.sim import simulate_sequence

    return simulate_sequence(
        {"scene": "turntable", "turntable": {"turns": 1, "views_per_turn": 13}},
        tmp_path_factory.mktemp("sim") / "seq", max_frames=FRAMES, resolution=(WIDTH, HEIGHT), calibration_mode="true",
    )


@pytest.fixture
def seq(simulated, tmp_path) -> Path:
    return Path(shutil.copytree(simulated, tmp_path / "seq"))


def _hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def _edit_meta(seq: Path, edit) -> None:
    path = seq / "sequence.yaml"
    meta = yaml.safe_load(path.read_text())
    edit(meta)
    path.write_text(yaml.safe_dump(meta, sort_keys=False))


def _image(seq: Path, frame: int, k: int) -> Path:
    return seq / f"frame_{frame:06d}" / f"{k:03d}.png"


def _one_line_refusal(code: int, captured, *needles: str) -> str:
    assert code == 2, captured
    assert "Traceback" not in captured.err + captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), captured.err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _cli_run(seq: Path, tmp_path: Path) -> int:
    config = tmp_path / "cfg.yaml"
    if not config.exists():
        config.write_text("run:\n  workers: 1\nfusion:\n  mesh: false\n")
    return main(["run", str(seq), "--out", str(tmp_path / "results"), "--config", str(config)])


def _run_skipping(seq: Path, tmp_path: Path, caplog) -> dict[str, str]:
    """Run the pipeline on ``seq`` (in this process: workers 1) and return metrics.json's
    skipped frames, each checked to be in the log with its reason."""
    config = config_from_dict({"run": {"workers": 1}, "fusion": {"mesh": False}})
    out = tmp_path / "results"
    with caplog.at_level(logging.WARNING):
        run_sequence(seq, config, out)
    metrics = json.loads((out / "metrics.json").read_text())
    skipped = metrics["skipped_frames"]
    assert metrics["frames_total"] == FRAMES and metrics["frames"] == FRAMES - len(skipped)
    for frame, reason in skipped.items():
        assert f"skipping frame {frame}: {reason}" in caplog.text
    return skipped


def _calibration_scaled(meta: dict, factor: int) -> None:
    camera = meta["calibration"]["camera"]
    camera["width"], camera["height"] = factor * camera["width"], factor * camera["height"]


# -- the calibration of another camera ---------------------------------------------------------------
def test_calibration_of_another_camera_is_refused_when_the_run_opens_the_sequence(seq, tmp_path, capsys):
    _edit_meta(seq, lambda meta: _calibration_scaled(meta, 2))
    before = _hashes(seq)
    code = _cli_run(seq, tmp_path)
    line = _one_line_refusal(
        code, capsys.readouterr(), str(seq), f"images are {WIDTH}x{HEIGHT} ({FRAMES} of {FRAMES} frames",
        f"calibration's camera in sequence.yaml is {2 * WIDTH}x{2 * HEIGHT} pixels", "put the calibration of the camera",
    )
    assert "0 valid" not in line
    assert not (tmp_path / "results").exists()
    assert _hashes(seq) == before


def test_calibration_check_reads_one_png_header_when_the_sizes_agree(seq, monkeypatch):
    sequence = read_sequence(seq)
    looked_at = []
    real = image_size
    monkeypatch.setattr("frontend.fpp.sequence.image_size", lambda path: looked_at.append(path) or real(path))
    sequence.check_frames_match_calibration()
    assert looked_at == [_image(seq, 0, 0)]


def test_images_match_calibration_check_for_the_decode_command(seq):
    rig = read_sequence(seq).calibration
    check_images_match_calibration((11, HEIGHT, WIDTH), rig, "capture")  # a stack of the camera's size
    check_images_match_calibration((HEIGHT, WIDTH), rig, "capture")  # one image
    with pytest.raises(CalibrationError) as info:
        check_images_match_calibration((11, 2 * HEIGHT, 2 * WIDTH), rig, "captures/view1 (calibration rig.yaml)")
    message = str(info.value)
    assert isinstance(info.value, InputDataError) and "\n" not in message
    assert message.startswith(
        f"captures/view1 (calibration rig.yaml): images are {2 * WIDTH}x{2 * HEIGHT} but the calibration's camera is "
        f"{WIDTH}x{HEIGHT} pixels; the calibration is of another camera"
    )


# -- one bad frame: skipped, with its reason ------------------------------------------------------
def test_frames_of_another_size_are_skipped_with_the_reason(seq, tmp_path, caplog):
    for k in range(len(read_sequence(seq).spec.layout())):  # frame 0, all of its images
        image = cv2.imread(str(_image(seq, 0, k)), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(_image(seq, 0, k)), cv2.resize(image, (WIDTH + 8, HEIGHT)))
    one = _image(seq, 3, 4)  # frame 3, one image
    cv2.imwrite(str(one), cv2.imread(str(one), cv2.IMREAD_UNCHANGED)[:, : WIDTH - 2])
    FppSequenceSource(seq, config_from_dict({}))  # the other frames fit: opened
    skipped = _run_skipping(seq, tmp_path, caplog)
    assert set(skipped) == {"0", "3"}
    assert f"images are {WIDTH + 8}x{HEIGHT} but the calibration's camera is {WIDTH}x{HEIGHT} pixels" in skipped["0"]
    assert f"004.png: size {WIDTH - 2}x{HEIGHT} differs from 000.png ({WIDTH}x{HEIGHT})" in skipped["3"]


def test_truncated_png_and_jpeg_frames_are_skipped_with_the_reason(seq, tmp_path, caplog):
    count = len(read_sequence(seq).spec.layout())
    png = _image(seq, 1, 2)
    png.write_bytes(png.read_bytes()[: png.stat().st_size // 2])
    for frame in (2, 4):  # frame 2 and 4 as JPEG (quality 100), frame 2's last image cut before its end marker
        for k in range(count):
            ok, data = cv2.imencode(".jpg", cv2.imread(str(_image(seq, frame, k)), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_JPEG_QUALITY, 100])
            assert ok
            _image(seq, frame, k).unlink()
            _image(seq, frame, k).with_suffix(".jpg").write_bytes(data.tobytes())
    cut = _image(seq, 2, count - 1).with_suffix(".jpg")
    cut.write_bytes(cut.read_bytes()[:-2])
    assert cv2.imdecode(np.fromfile(cut, np.uint8), cv2.IMREAD_UNCHANGED) is not None  # what OpenCV alone would accept

    def as_jpeg(meta):
        for frame in (2, 4):
            meta["frames"][frame]["images"] = [Path(name).with_suffix(".jpg").name for name in meta["frames"][frame]["images"]]

    _edit_meta(seq, as_jpeg)
    skipped = _run_skipping(seq, tmp_path, caplog)
    assert set(skipped) == {"1", "2"}  # frame 4, whole JPEGs, is decoded
    assert f"{png}: not a readable image (corrupt, truncated or unsupported format)" in skipped["1"]
    assert f"{cut}: truncated JPEG file (its end is missing" in skipped["2"]


@pytest.mark.parametrize("kind", ["png", "jpg"])
def test_an_image_cut_short_is_refused_even_by_a_lenient_decoder(tmp_path, monkeypatch, kind):
    """libpng refuses a PNG without its end chunk, and libjpeg pads a scan cut short with grey
    (OpenCV builds differ in whether they pass that on): the reader checks the end itself."""
    image = (np.arange(HEIGHT * WIDTH) % 251).astype(np.uint8).reshape(HEIGHT, WIDTH)
    path = tmp_path / f"a.{kind}"
    cv2.imwrite(str(path), image)
    assert load_image(path).shape == (HEIGHT, WIDTH)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 12])  # a PNG's IEND chunk, a JPEG's end marker and a little more
    monkeypatch.setattr(cv2, "imdecode", lambda buffer, flags: image.copy())  # a decoder that returns what it could
    with pytest.raises(InputDataError, match=rf"a\.{kind}: truncated {kind.replace('jpg', 'jpeg').upper()} file \(its end is missing"):
        load_image(path)


def test_missing_folder_and_unreadable_images_are_skipped_with_the_reason(seq, tmp_path, caplog, monkeypatch):
    missing, folder, denied = _image(seq, 1, 5), _image(seq, 2, 0), _image(seq, 4, 1)
    missing.unlink()
    folder.unlink()
    folder.mkdir()
    real = pathlib.Path.read_bytes

    def read_bytes(self):  # chmod 000 does not stop root, which the tests may run as
        if self == denied:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(pathlib.Path, "read_bytes", read_bytes)
    skipped = _run_skipping(seq, tmp_path, caplog)
    assert set(skipped) == {"1", "2", "4"}
    assert skipped["1"] == f"{missing}: image file not found; restore it, or correct the list or folder that names it"
    assert skipped["2"] == f"{folder}: a folder, not an image file; correct the list or folder that names it"
    assert skipped["4"] == f"{denied}: cannot read image file (Permission denied); check its permissions"


def test_image_size_of_a_missing_file_names_it(tmp_path):
    with pytest.raises(InputDataError, match="image file not found"):
        image_size(tmp_path / "none.png")


# -- sequence.yaml and other files that cannot be read ------------------------------------------------
def test_sequence_file_that_is_a_folder_is_one_line(seq, tmp_path, capsys):
    meta = seq / "sequence.yaml"
    meta.unlink()
    meta.mkdir()
    code = _cli_run(seq, tmp_path)
    _one_line_refusal(code, capsys.readouterr(), f"cannot read sequence file {meta}: it is a folder; give the path of the file itself")
    assert not (tmp_path / "results").exists()


def test_unreadable_sequence_file_is_one_line(seq, tmp_path, capsys, monkeypatch):
    meta = seq / "sequence.yaml"
    before = _hashes(seq)
    real = pathlib.Path.read_text

    def read_text(self, *args, **kwargs):
        if self == meta:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "read_text", read_text)
    code = _cli_run(seq, tmp_path)
    _one_line_refusal(code, capsys.readouterr(), f"cannot read sequence file {meta}: Permission denied; check the file's permissions")
    assert _hashes(seq) == before and not (tmp_path / "results").exists()


def test_folder_that_cannot_be_looked_into_is_one_line(seq, monkeypatch):
    real = pathlib.Path.exists

    def exists(self, *args, **kwargs):
        if self == seq / "sequence.yaml":
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "exists", exists)
    assert FppSequenceSource.detect(seq)  # the layout is claimed, so that reading it says what is wrong
    with pytest.raises(InputDataError, match=rf"cannot look for {seq / 'sequence.yaml'}: Permission denied; check the permissions of {seq}"):
        read_sequence(seq)


def test_duplicated_key_in_sequence_file_is_one_line(seq, tmp_path, capsys):
    meta = seq / "sequence.yaml"
    text = meta.read_text()
    meta.write_text(text.replace("image_count:", "format: fpp-graph sequence v1\nimage_count:", 1))
    first = 1 + text.splitlines().index("format: fpp-graph sequence v1")
    second = 1 + meta.read_text().splitlines().index("format: fpp-graph sequence v1", first)
    before = _hashes(seq)
    code = _cli_run(seq, tmp_path)
    _one_line_refusal(code, capsys.readouterr(), f"{meta}:{second}: format is given twice (lines {first} and {second})", "remove one")
    assert _hashes(seq) == before and not (tmp_path / "results").exists()


def test_duplicated_key_inside_the_calibration_names_its_path(seq):
    meta = seq / "sequence.yaml"
    lines = meta.read_text().splitlines()
    at = next(k for k, line in enumerate(lines) if line.strip().startswith("width:"))
    lines.insert(at + 1, lines[at])
    meta.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputDataError, match=rf"calibration\.camera\.width is given twice \(lines {at + 1} and {at + 2}\)"):
        read_sequence(seq)


def test_unreadable_ground_truth_calibration_is_an_input_error(seq, monkeypatch):
    path = seq / "groundtruth_calibration.yaml"
    assert load_calibration(path).camera.width == WIDTH
    real = pathlib.Path.read_text

    def read_text(self, *args, **kwargs):
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "read_text", read_text)
    with pytest.raises(CalibrationError, match=rf"cannot read calibration {path}: Permission denied; check the file's permissions"):
        load_calibration(path)


def test_pattern_file_messages_say_file_once(tmp_path):
    from frontend.fpp.pattern_file import load_pattern_spec

    folder = tmp_path / "patterns.yaml"
    folder.mkdir()
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"kind: \xff\n")
    for path in (folder, binary):
        with pytest.raises(Exception) as info:  # noqa: PT011 - the pattern file's reader chooses the type
            load_pattern_spec(path)
        assert "file file" not in str(info.value) and str(path) in str(info.value)


def test_non_finite_timestamp_in_sequence_file(seq):
    _edit_meta(seq, lambda meta: meta["frames"][2].update(timestamp=float("nan")))
    with pytest.raises(InputDataError, match=r"frames\[2\]: timestamp nan is not a finite number of seconds"):
        read_sequence(seq)
