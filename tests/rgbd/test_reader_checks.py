"""What the RGB-D readers (7-Scenes and TUM layouts) check in what they read.

A folder that cannot be read as a whole is refused when the source opens: `fpp-slam run` exits
with status 2 and one line naming the file, and the user's files are left as they were. A frame
whose own files are bad (a missing, truncated, unreadable or odd-sized image) is skipped with its
reason logged and recorded; a 7-Scenes pose file that holds no rigid pose leaves that frame out
of the reference, said and counted.
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from fpp_graph.config import Config
from fpp_graph.errors import InputDataError
from fpp_graph.slam.pipeline import prepare_frames
from fpp_graph.trajectory import Trajectory, write_tum
from frontend.rgbd.source import RgbdSource

W, H = 40, 32
# a camera whose principal point is the centre of the 40x32 test images
K_40x32 = "40 0 20\n0 40 16\n0 0 1\n"


def _seven_scenes(folder: Path, frames: int = 3, size: tuple[int, int] = (W, H), colour_ext: str = "png", intrinsics: bool = True) -> Path:
    """A 7-Scenes folder of ``frames`` flat views of a wall 1 m away, each with its pose."""
    folder.mkdir(parents=True)
    if intrinsics:
        (folder / "camera-intrinsics.txt").write_text(K_40x32)
        (folder / "color-intrinsics.txt").write_text(K_40x32)
    rng = np.random.default_rng(0)
    for i in range(frames):
        stem = folder / f"frame-{i:06d}"
        cv2.imwrite(f"{stem}.color.{colour_ext}", rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
        cv2.imwrite(f"{stem}.depth.png", np.full((size[1], size[0]), 1000, np.uint16))
        T = np.eye(4)
        T[0, 3] = 0.01 * i
        np.savetxt(f"{stem}.pose.txt", T)
    return folder


def _tum(folder: Path, frames: int = 3) -> Path:
    """A TUM RGB-D folder of ``frames`` 40x32 views, intrinsics and a reference at 100 Hz."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    times = [1.0 + k / 30.0 for k in range(frames)]
    rng = np.random.default_rng(0)
    for t in times:
        cv2.imwrite(str(folder / f"rgb/{t:.6f}.png"), rng.integers(0, 255, (H, W), dtype=np.uint8))
        cv2.imwrite(str(folder / f"depth/{t:.6f}.png"), np.full((H, W), 5000, np.uint16))
    (folder / "rgb.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in times))
    (folder / "depth.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in times))
    (folder / "intrinsics.txt").write_text("40 40 19.5 15.5\n")
    reference = [0.9 + k / 100 for k in range(30)]
    write_tum(folder / "groundtruth.txt", Trajectory.from_poses(reference, [np.eye(4)] * len(reference)))
    return folder


def _hashes(folder: Path) -> dict[str, str]:
    with_open = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            with open(p, "rb") as f:
                with_open[str(p.relative_to(folder))] = hashlib.sha256(f.read()).hexdigest()
    return with_open


class _Deny:
    """``deny(path)``: make ``path`` unreadable. chmod 000 where that binds the test's user; as
    root (who reads any file) the reader's reads of it raise the PermissionError chmod would."""

    def __init__(self, monkeypatch) -> None:
        self.denied: list[Path] = []
        self.as_root = os.geteuid() == 0
        if self.as_root:
            read_bytes = Path.read_bytes

            def refusing(path: Path) -> bytes:
                if path in self.denied:
                    raise PermissionError(13, "Permission denied", str(path))
                return read_bytes(path)

            monkeypatch.setattr(Path, "read_bytes", refusing)

    def __call__(self, path: Path) -> None:
        self.denied.append(path)
        if not self.as_root:
            path.chmod(0)

    def restore(self) -> None:
        for path in self.denied:
            path.chmod(0o644)
        self.denied.clear()


@pytest.fixture
def deny(monkeypatch):
    denier = _Deny(monkeypatch)
    yield denier
    denier.restore()


@pytest.fixture
def refused(tmp_path, capsys, deny):
    """``refused(folder, unreadable=())``: run `fpp-slam run folder` in this process (the files
    ``unreadable`` made so); assert it exits with 2, one `fpp-slam: error:` line on stderr and no
    traceback, the input files unchanged and no results folder; return the line."""
    from fpp_graph.cli import main

    config = tmp_path / "quiet.yaml"
    config.write_text("run:\n  log_level: WARNING\n")  # the run's own INFO lines are not the refusal's
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level

    def run(folder: Path, unreadable: tuple[Path, ...] = ()) -> str:
        before = _hashes(folder)
        for path in unreadable:
            deny(path)
        out = tmp_path / "results"
        capsys.readouterr()
        try:
            code = main(["run", str(folder), "--out", str(out), "--config", str(config)])
        finally:  # the CLI's logging set-up is the CLI's, not the next test's
            root.handlers[:], root.level = handlers, level
            deny.restore()
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), err
        assert "Traceback" not in err
        assert _hashes(folder) == before
        assert not out.exists()
        return lines[0]

    return run


def _skipped(source: RgbdSource, tmp_path: Path, caplog) -> dict[int, str]:
    """The frames the pipeline's decoding step skips, with their reasons (each also logged)."""
    skipped: dict[int, str] = {}
    with caplog.at_level(logging.WARNING):
        decoded = [f.id for f in prepare_frames(source, tmp_path / "cache", None, skipped)]
    assert sorted(decoded + list(skipped)) == source.frame_ids()
    for fid, reason in skipped.items():
        assert f"skipping frame {fid}: {reason}" in caplog.text
    return skipped


# -- image sizes ----------------------------------------------------------------------------
def test_depth_images_of_another_size_than_the_intrinsics_refuse_the_sequence(tmp_path, refused):
    seq = _seven_scenes(tmp_path / "seq")
    (seq / "camera-intrinsics.txt").write_text("80 0 40\n0 80 32\n0 0 1\n")  # an 80x64 camera's
    line = refused(seq)
    assert str(seq / "camera-intrinsics.txt") in line
    assert "depth images are 40x32" in line and "about 80x64 images" in line
    assert "give camera-intrinsics.txt for 40x32 images, or resize" in line


def test_images_without_intrinsics_are_checked_against_the_7scenes_default(tmp_path, caplog):
    seq = _seven_scenes(tmp_path / "seq", intrinsics=False)
    with pytest.raises(InputDataError, match=r"depth images are 40x32 .*default 7-Scenes \(fx=fy=585, cx=320, cy=240\).*"
                                             r"about 640x480 images; give camera-intrinsics.txt for 40x32 images"):
        RgbdSource(seq, Config())


def test_tum_colour_images_of_another_size_than_the_depth_refuse_the_sequence(tmp_path, refused):
    seq = _tum(tmp_path / "seq")
    for p in (seq / "rgb").iterdir():
        cv2.imwrite(str(p), np.zeros((2 * H, 2 * W), np.uint8))
    line = refused(seq)
    assert str(seq) in line and "colour images are 80x64 but its depth images 40x32" in line


@pytest.mark.parametrize("image", ["depth", "color"])
def test_a_single_image_of_another_size_is_a_skipped_frame(tmp_path, caplog, image):
    seq = _seven_scenes(tmp_path / "seq", frames=4)
    odd = seq / f"frame-000002.{image}.png"
    cv2.imwrite(str(odd), np.full((H // 2, W // 2), 1000, np.uint16) if image == "depth" else np.zeros((H // 2, W // 2, 3), np.uint8))
    source = RgbdSource(seq, Config())
    assert source.describe()["intrinsics"]["image_size"] == [W, H]
    skipped = _skipped(source, tmp_path, caplog)
    assert list(skipped) == [2]
    assert str(odd) in skipped[2] and f"image is {W // 2}x{H // 2}" in skipped[2] and f"are {W}x{H}" in skipped[2]


# -- frames that lost an image --------------------------------------------------------------
def test_a_7scenes_frame_without_its_colour_image_is_counted_and_skipped(tmp_path, caplog):
    seq = _seven_scenes(tmp_path / "seq", frames=4, colour_ext="jpg")
    (seq / "frame-000001.color.jpg").unlink()
    with caplog.at_level(logging.WARNING):
        source = RgbdSource(seq, Config())
    assert source.frame_ids() == [0, 1, 2, 3]  # fpp-slam's frames_total counts it
    assert source.describe()["incomplete_frames"] == {"frame-000001": "no colour image"}
    assert "1 of 4 frames lack an image" in caplog.text
    skipped = _skipped(source, tmp_path, caplog)
    assert list(skipped) == [1]
    assert str(seq / "frame-000001.color.jpg") in skipped[1] and "No such file" in skipped[1]


@pytest.mark.parametrize("damaged", ["frame-000001.color.jpg", "frame-000001.depth.png"])
def test_a_truncated_image_is_a_skipped_frame_said_by_the_reader(tmp_path, caplog, capfd, damaged):
    seq = _seven_scenes(tmp_path / "seq", colour_ext="jpg")
    data = (seq / damaged).read_bytes()
    (seq / damaged).write_bytes(data[: len(data) * 2 // 3])  # an interrupted copy
    source = RgbdSource(seq, Config())
    capfd.readouterr()
    skipped = _skipped(source, tmp_path, caplog)
    assert list(skipped) == [1]
    assert str(seq / damaged) in skipped[1] and "truncated" in skipped[1] and "copy it again" in skipped[1]
    # the image is not handed to the decoder: no libjpeg/libpng line of its own on stderr
    assert "JPEG" not in capfd.readouterr().err


def test_a_complete_jpeg_and_png_pass_the_truncation_check(tmp_path):
    from frontend.rgbd.source import _truncation

    image = np.random.default_rng(1).integers(0, 255, (H, W, 3), dtype=np.uint8)
    for ext in (".png", ".jpg"):
        data = cv2.imencode(ext, image)[1].tobytes()
        assert _truncation(data) is None
        assert _truncation(data[:-1]) is not None and _truncation(data[: len(data) // 2]) is not None


# -- layouts --------------------------------------------------------------------------------
def test_a_folder_holding_both_layouts_is_refused_as_ambiguous(tmp_path, refused):
    seq = _tum(tmp_path / "seq")
    _seven_scenes(tmp_path / "chess")
    for p in (tmp_path / "chess").iterdir():
        p.rename(seq / p.name)
    line = refused(seq)
    assert str(seq) in line and "TUM RGB-D" in line and "7-Scenes" in line and "rgb.txt" in line
    assert "move one set of files into a folder of its own" in line


# -- intrinsics -----------------------------------------------------------------------------
def test_missing_intrinsics_fall_back_to_the_7scenes_default_said_and_recorded(tmp_path, caplog):
    seq = _seven_scenes(tmp_path / "seq", frames=2, size=(640, 480), intrinsics=False)
    with caplog.at_level(logging.WARNING):
        source = RgbdSource(seq, Config())
    assert "no camera-intrinsics.txt; using the 7-Scenes intrinsics fx=fy=585, cx=320, cy=240" in caplog.text
    described = source.describe()
    assert described["intrinsics"] == {"source": "default 7-Scenes (fx=fy=585, cx=320, cy=240)", "image_size": [640, 480]}
    assert described["color_intrinsics"]["source"].startswith("default Kinect v1 colour")


@pytest.mark.parametrize(("matrix", "said"), [
    ("0 0 20\n0 40 16\n0 0 1\n", "fx = 0 is not a focal length"),
    ("40 0 20\n0 -40 16\n0 0 1\n", "fy = -40 is not a focal length"),
    ("nan 0 20\n0 40 16\n0 0 1\n", "fx = nan is not a focal length"),
    ("40 0 inf\n0 40 16\n0 0 1\n", "cx = inf is not a finite pixel position"),
    ("40 0 90\n0 40 16\n0 0 1\n", "principal point at cx=90, cy=16, outside them"),
    ("40 0 20\n0 40 16\n", "expected a 3x3 camera matrix, got 6 numbers; correct the file"),
])
def test_impossible_7scenes_intrinsics_are_refused_naming_file_and_value(tmp_path, refused, matrix, said):
    seq = _seven_scenes(tmp_path / "seq")
    (seq / "camera-intrinsics.txt").write_text(matrix)
    line = refused(seq)
    assert str(seq / "camera-intrinsics.txt") in line and said in line


def test_impossible_tum_intrinsics_are_refused_naming_file_and_value(tmp_path, refused):
    seq = _tum(tmp_path / "seq")
    (seq / "intrinsics.txt").write_text("40 0 19.5 15.5\n")
    line = refused(seq)
    assert str(seq / "intrinsics.txt") in line and "fy = 0 is not a focal length" in line


# -- reference poses ------------------------------------------------------------------------
@pytest.mark.parametrize(("pose", "said"), [
    ("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "non-finite values"),
    ("1.01 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not orthonormal"),
    ("-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "a reflection"),
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", "last row is 0 0 1 1"),
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "12 numbers"),
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 -1.#INF\n", "not a 4x4 matrix of numbers"),
])
def test_a_7scenes_pose_file_without_a_rigid_pose_leaves_its_frame_out_of_the_reference(tmp_path, caplog, pose, said):
    """A recording's pose file that holds no rigid pose (lost tracking written as nan or inf, a
    damaged file) is part of otherwise good input: the frame stays, its reference pose goes."""
    seq = _seven_scenes(tmp_path / "seq")
    (seq / "frame-000001.pose.txt").write_text(pose)
    with caplog.at_level(logging.WARNING):
        source = RgbdSource(seq, Config())
        gt = source.ground_truth()
    assert source.frame_ids() == [0, 1, 2]
    np.testing.assert_allclose(gt.timestamps_s, [0.0, 2 / 30])
    assert "1 pose file(s) hold no rigid pose" in caplog.text and "frame-000001.pose.txt" in caplog.text and said in caplog.text
    left_out = source.describe()["reference_poses_left_out"]
    assert left_out["count"] == 1 and said in left_out["files"]["frame-000001.pose.txt"]


def test_a_rotation_as_far_from_orthonormal_as_the_real_7scenes_poses_is_kept(tmp_path):
    """The real 7-Scenes pose files deviate up to 1.6e-4 from orthonormal (KinectFusion's poses)."""
    seq = _seven_scenes(tmp_path / "seq")
    T = np.eye(4)
    T[:3, :3] *= 1 + 2e-4
    np.savetxt(seq / "frame-000001.pose.txt", T)
    source = RgbdSource(seq, Config())
    assert len(source.ground_truth()) == 3 and source.describe()["reference_poses_left_out"]["count"] == 0


@pytest.mark.parametrize(("line", "said"), [
    ("1.05 0 0 nan 0 0 0 1", "'nan' is not finite"),
    ("1.05 0 0 0 0 0 0.5 1", "quaternion norm is 1.11803"),
    ("1.05 0 0 0 0 0 1", "expected 8 values"),
])
def test_a_bad_tum_reference_line_is_refused_naming_file_and_line(tmp_path, refused, line, said):
    seq = _tum(tmp_path / "seq")
    gt = seq / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    lines[3] = line  # the 4th line of the file: the header, then samples
    gt.write_text("\n".join(lines) + "\n")
    said_line = refused(seq)
    assert f"{gt}:4:" in said_line and said in said_line and "correct or delete that line" in said_line


# -- unreadable files -----------------------------------------------------------------------
PERMISSION = "Permission denied; check the file's permissions (the user running fpp-slam must be able to read it)"


@pytest.mark.parametrize("name", ["frame-000001.pose.txt", "camera-intrinsics.txt", "rgb.txt", "groundtruth.txt"])
def test_an_unreadable_text_file_is_refused_naming_it(tmp_path, refused, name):
    """A pose file that cannot be read is refused rather than left out of the reference like one
    holding no pose: it is the user's to fix (a permission), not the recording's content."""
    seq = _tum(tmp_path / "seq") if name in ("rgb.txt", "groundtruth.txt") else _seven_scenes(tmp_path / "seq")
    assert refused(seq, unreadable=(seq / name,)) == f"fpp-slam: error: cannot read {seq / name}: {PERMISSION}"


def test_an_unreadable_image_is_a_skipped_frame(tmp_path, caplog, deny):
    seq = _seven_scenes(tmp_path / "seq")
    source = RgbdSource(seq, Config())
    deny(seq / "frame-000002.depth.png")
    skipped = _skipped(source, tmp_path, caplog)
    assert skipped == {2: f"cannot read {seq / 'frame-000002.depth.png'}: {PERMISSION}"}
