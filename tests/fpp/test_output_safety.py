"""What the writing commands (decode, patterns --render-to, calibrate, import, simulate, demo) do
with their output paths: nothing of the user's is replaced without --overwrite, nothing is written
into an input, a folder being written by another process is refused naming its PID, and an
operating-system error is one line naming the path, with no partial file left.

Every refusal is checked the same way: exit 2, exactly one stderr line ``fpp-slam: error: ...``
naming the path, no traceback, and the SHA-256 of every file in the folders involved unchanged.
The tests run as root, which ignores file permissions, so permission and full-disk errors are
simulated by making the system call fail.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from cli_helpers import run_cli, write_pattern_file

from fpp_graph.outputs import LOCK_NAME
from frontend.fpp.capture import OUTPUT_FILES
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.rig import RigCalibration, save_calibration
from frontend.fpp.sequence import SequenceWriter

SPEC = PatternSpec("complementary_gray", phase_steps=4, periods=(64,), gray_bits=6)


def snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` by relative path; an output folder's lock file is
    left out (it stays in a folder once written, empty, by design)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*")) if p.is_file() and p.name != LOCK_NAME
    }


def one_error(result: tuple[int, str, str], *needles: str) -> str:
    """The command's single stderr line, checked: exit 2, ``fpp-slam: error:``, no traceback."""
    code, _, err = result
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, err
    assert "Traceback" not in err
    assert len(lines) == 1 and lines[0].startswith("fpp-slam: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """One capture of a plane by a 320x200 rig, rendered once for the module."""
    from frontend.sim import FppSimulator, default_rig, plane_scene
    from frontend.sim.rig import binned_calibration

    rig = binned_calibration(default_rig(preview=True), 320, 200)
    frame = FppSimulator(rig, SPEC, plane_scene(0.5, tilt_deg=-7.0)).render(np.eye(4), 0)
    return rig, frame.images


@pytest.fixture()
def capture(rendered, tmp_path):
    """(capture folder, calibration file, pattern file) of the rendered capture."""
    rig, images = rendered
    folder = tmp_path / "capture"
    folder.mkdir()
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"{i:02d}.png"), image)
    save_calibration(tmp_path / "rig.yaml", rig)
    return folder, tmp_path / "rig.yaml", write_pattern_file(tmp_path / "patterns.yaml", SPEC)


def decode(capture, out: Path, *extra: str) -> tuple[int, str, str]:
    folder, rig, patterns = capture
    return run_cli("decode", str(folder), "--calibration", str(rig), "--patterns", str(patterns), "--out", str(out), *extra)


# ---------------------------------------------------------------------------- decode


def test_decode_keeps_a_users_depth_png(capture, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "depth.png").write_bytes(b"the user's own depth image")
    before = snapshot(tmp_path)
    one_error(decode(capture, out), str(out / "depth.png"), "exists", "--overwrite")
    assert snapshot(tmp_path) == before
    assert sorted(p.name for p in out.iterdir()) == ["depth.png"]  # nothing else was written either


def test_decode_into_its_own_capture_is_refused(capture, tmp_path):
    folder = capture[0]
    before = snapshot(tmp_path)
    one_error(decode(capture, folder), f"--out {folder}", "is the input", "choose another --out")
    one_error(decode(capture, folder, "--overwrite"), "is the input")
    one_error(decode(capture, folder / "decoded"), str(folder / "decoded"), "inside the input folder")
    one_error(decode(capture, tmp_path), f"--out {tmp_path}", "holds the input")
    assert snapshot(tmp_path) == before
    code, _, err = decode(capture, tmp_path / "out")  # the capture is as it was: it still decodes
    assert code == 0, err


def test_decode_into_a_sequence_given_as_calibration_is_refused(capture, rendered, tmp_path):
    sequence = tmp_path / "seq"
    writer = SequenceWriter(sequence, rendered[0], SPEC, source={"capture_tool": "test"})
    writer.add_frame(0, 0.0, rendered[1])
    writer.close()
    before = snapshot(tmp_path)
    result = run_cli("decode", str(sequence / "frame_000000"), "--calibration", str(sequence / "sequence.yaml"),
                     "--patterns", str(sequence / "sequence.yaml"), "--out", str(sequence / "decoded"))
    one_error(result, str(sequence / "decoded"), "inside the input folder", str(sequence))
    assert snapshot(tmp_path) == before


def test_decode_reads_the_calibration_of_a_sequence(capture, rendered, tmp_path):
    sequence = tmp_path / "seq"
    writer = SequenceWriter(sequence, rendered[0], SPEC, source={"capture_tool": "test"})
    writer.add_frame(0, 0.0, rendered[1])
    writer.close()
    for calibration in (sequence / "sequence.yaml", sequence):
        out = tmp_path / f"out_{calibration.name}"
        code, stdout, err = run_cli("decode", str(capture[0]), "--calibration", str(calibration), "--patterns", str(capture[2]), "--out", str(out))
        assert code == 0, err
        assert "valid points" in stdout and "0 valid points" not in stdout.split(",")[0]
    result = run_cli("decode", str(capture[0]), "--calibration", str(sequence / "sequence.yaml"), "--patterns", str(capture[2]),
                     "--projector", "1920x1080", "--out", str(tmp_path / "o"))
    one_error(result, str(sequence / "sequence.yaml"), "1920x1080", "--projector")


def test_decode_out_an_existing_file_is_refused(capture, tmp_path):
    plain = tmp_path / "notes.txt"
    plain.write_text("the user's notes\n")
    before = snapshot(tmp_path)
    one_error(decode(capture, plain), f"--out {plain}", "is a file, not a folder")
    one_error(decode(capture, plain, "--overwrite"), f"--out {plain}", "is a file, not a folder")
    one_error(decode(capture, plain / "decoded"), str(plain), "not a folder")
    assert snapshot(tmp_path) == before


def test_decode_out_holding_a_folder_named_as_an_output_is_refused(capture, tmp_path):
    out = tmp_path / "o"
    (out / "depth.png").mkdir(parents=True)
    (out / "depth.png" / "keep.txt").write_text("x")
    before = snapshot(tmp_path)
    one_error(decode(capture, out, "--overwrite"), str(out / "depth.png"), "is a folder")
    assert snapshot(tmp_path) == before


def test_decode_under_a_read_only_parent_is_one_line(capture, tmp_path, monkeypatch):
    parent = tmp_path / "read_only"
    parent.mkdir()
    real_mkdir = Path.mkdir

    def mkdir(self, *args, **kwargs):
        if self.parent == parent:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)  # root ignores chmod: the refusal is simulated
    before = snapshot(tmp_path)
    one_error(decode(capture, parent / "decoded"), str(parent / "decoded"), "Permission denied", "permissions")
    assert snapshot(tmp_path) == before and not list(parent.iterdir())


@pytest.mark.parametrize("failing", ["fsync", "replace"])
def test_decode_on_a_full_disk_leaves_no_output(capture, tmp_path, monkeypatch, failing):
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("the user's notes\n")

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, failing, full)
    before = snapshot(tmp_path)
    line = one_error(decode(capture, out, "--overwrite"), str(out), "No space left on device", "free some space")
    assert any(name in line for name in OUTPUT_FILES)
    assert snapshot(tmp_path) == before
    assert sorted(p.name for p in out.iterdir()) == sorted(["notes.txt", LOCK_NAME])  # no output, no temporary file


def test_decode_overwrite_replaces_its_outputs_and_keeps_the_users_files(capture, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("the user's notes\n")
    code, _, err = decode(capture, out)
    assert code == 0, err
    (out / "decode.json").write_text("{}\n")  # stands for an earlier, different result
    first = snapshot(out)
    one_error(decode(capture, out), str(out / "points.ply"), "--overwrite")
    assert snapshot(out) == first
    code, _, err = decode(capture, out, "--overwrite")
    assert code == 0, err
    second = snapshot(out)
    assert second["notes.txt"] == first["notes.txt"] and second["decode.json"] != first["decode.json"]
    assert sorted(second) == sorted(["notes.txt", *OUTPUT_FILES])
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_decode_refused_while_another_process_writes_the_folder(capture, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom fpp_graph.outputs import FolderLock\n"
         "FolderLock(sys.argv[1]).acquire()\nprint('held', flush=True)\ntime.sleep(120)\n", str(out)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(tmp_path)
        one_error(decode(capture, out), f"--out {out}", f"PID {holder.pid}", "another fpp-slam process")
        assert snapshot(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()
    code, _, err = decode(capture, out)  # the lock ends with its holder
    assert code == 0, err


def test_decode_with_another_rigs_calibration_is_refused(capture, rendered, tmp_path):
    rig = rendered[0]
    T = rig.T_projector_camera.copy()
    T[:3, 3] *= -1  # the projector on the other side: the same image sizes, another rig
    save_calibration(tmp_path / "other.yaml", RigCalibration(rig.camera, rig.projector, T))
    before = snapshot(tmp_path)
    folder, _, patterns = capture
    result = run_cli("decode", str(folder), "--calibration", str(tmp_path / "other.yaml"), "--patterns", str(patterns), "--out", str(tmp_path / "o"))
    one_error(result, str(folder), str(tmp_path / "other.yaml"), "another rig", "calibration")
    assert snapshot(tmp_path) == before and not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------- patterns --render-to


def test_render_to_keeps_existing_images_and_never_writes_into_the_input(tmp_path):
    spec = write_pattern_file(tmp_path / "patterns.yaml", SPEC)
    out = tmp_path / "render"
    args = ("patterns", str(spec), "--projector", "64x16", "--render-to")
    code, _, err = run_cli(*args, str(out))
    assert code == 0, err
    (out / "000.png").write_bytes(b"the user's edited image")
    (out / "notes.txt").write_text("x")
    before = snapshot(tmp_path)
    one_error(run_cli(*args, str(out)), f"--render-to {out}", "000.png", "--overwrite")
    one_error(run_cli(*args, str(tmp_path), "--overwrite"), f"--render-to {tmp_path}", "holds the input")
    one_error(run_cli(*args, str(spec)), str(spec), "is the input")
    assert snapshot(tmp_path) == before
    code, _, err = run_cli(*args, str(out), "--overwrite")
    assert code == 0, err
    after = snapshot(tmp_path)
    assert after["render/000.png"] != before["render/000.png"] and after["render/notes.txt"] == before["render/notes.txt"]


# ---------------------------------------------------------------------------- calibrate --out


def test_calibrate_out_is_refused_before_calibrating(tmp_path):
    (tmp_path / "captures" / "pose_0").mkdir(parents=True)
    spec = write_pattern_file(tmp_path / "p.yaml", PatternSpec("gray_code", axis="both", gray_bits=6, gray_bits_rows=5, periods=(64, 32), gray_inverse=True, with_reference=True))
    mine = tmp_path / "rig.yaml"
    mine.write_text("the user's calibration\n")
    base = ("calibrate", str(tmp_path / "captures"), "--patterns", str(spec), "--board", "9x7", "--square-mm", "20", "--projector", "64x32", "--out")
    before = snapshot(tmp_path)
    one_error(run_cli(*base, str(mine)), f"--out {mine} exists", "--overwrite")
    one_error(run_cli(*base, str(spec), "--overwrite"), str(spec), "is the input")
    one_error(run_cli(*base, str(tmp_path / "captures" / "rig.yaml"), "--overwrite"), "inside the input folder")
    one_error(run_cli(*base, str(tmp_path / "captures"), "--overwrite"), f"--out {tmp_path / 'captures'} is the input")
    (tmp_path / "results").mkdir()
    one_error(run_cli(*base, str(tmp_path / "results"), "--overwrite"), f"--out {tmp_path / 'results'} is a folder")
    assert snapshot(tmp_path) == before


def test_save_calibration_without_replace_keeps_the_file(rendered, tmp_path):
    from fpp_graph.errors import OutputError

    mine = tmp_path / "rig.yaml"
    mine.write_text("the user's calibration\n")
    with pytest.raises(OutputError, match="exists"):
        save_calibration(mine, rendered[0], replace=False)
    assert mine.read_text() == "the user's calibration\n" and sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]


# ---------------------------------------------------------------------------- import --out


@pytest.fixture()
def captures_root(rendered, tmp_path):
    """Two per-frame capture folders, a pattern file and a calibration, outside the root."""
    root = tmp_path / "captures"
    for view in ("view1", "view2"):
        (root / view).mkdir(parents=True)
        for i, image in enumerate(rendered[1]):
            cv2.imwrite(str(root / view / f"{i:02d}.png"), image)
    save_calibration(tmp_path / "rig.yaml", rendered[0])
    return root, write_pattern_file(tmp_path / "patterns.yaml", SPEC), tmp_path / "rig.yaml"


def import_into(captures_root, out: Path, *extra: str) -> tuple[int, str, str]:
    root, patterns, rig = captures_root
    return run_cli("import", str(root), "--patterns", str(patterns), "--calibration", str(rig), "--out", str(out), *extra)


def test_import_never_writes_into_its_captures(captures_root, tmp_path):
    root = captures_root[0]
    before = snapshot(tmp_path)
    one_error(import_into(captures_root, root, "--overwrite"), f"--out {root}", "is the input")
    one_error(import_into(captures_root, root / "sequence", "--overwrite"), "inside the input folder")
    one_error(import_into(captures_root, tmp_path, "--overwrite"), "holds the input")
    assert snapshot(tmp_path) == before


def test_import_replaces_only_an_imported_sequence(captures_root, rendered, tmp_path):
    users = tmp_path / "users"
    users.mkdir()
    (users / "notes.txt").write_text("x")
    recorded = tmp_path / "recorded"
    writer = SequenceWriter(recorded, rendered[0], SPEC, source={"capture_tool": "the rig's own software"})
    writer.add_frame(0, 0.0, rendered[1])
    writer.close()
    before = snapshot(tmp_path)
    one_error(import_into(captures_root, users, "--overwrite"), f"--out {users}", "notes.txt", "never deleted")
    one_error(import_into(captures_root, recorded, "--overwrite"), f"--out {recorded}", "not imported", "never replaced")
    assert snapshot(tmp_path) == before
    out = tmp_path / "seq"
    code, _, err = import_into(captures_root, out)
    assert code == 0, err
    first = snapshot(out)
    one_error(import_into(captures_root, out), f"--out {out}", "exists", "--overwrite")
    assert snapshot(out) == first
    code, _, err = import_into(captures_root, out, "--overwrite", "--frame-period", "0.5")
    assert code == 0, err
    assert snapshot(out)["sequence.yaml"] != first["sequence.yaml"]


def test_import_failing_midway_leaves_no_sequence(captures_root, tmp_path):
    root = captures_root[0]
    (root / "view2" / "05.png").write_bytes(b"not an image")
    before = snapshot(tmp_path)
    one_error(import_into(captures_root, tmp_path / "seq"), str(root / "view2" / "05.png"))
    assert snapshot(tmp_path) == before and not (tmp_path / "seq").exists()


# ---------------------------------------------------------------------------- simulate --out


def simulate(out: Path, *extra: str) -> tuple[int, str, str]:
    return run_cli("simulate", "turntable", "--out", str(out), "--resolution", "160x100", "--frames", "1", "--true-calibration", *extra)


def test_simulate_never_replaces_what_it_did_not_simulate(rendered, tmp_path):
    users = tmp_path / "users"
    users.mkdir()
    (users / "thesis.tex").write_text("x")
    recorded = tmp_path / "recorded"
    writer = SequenceWriter(recorded, rendered[0], SPEC, source={"imported_from": "/somewhere"})
    writer.add_frame(0, 0.0, rendered[1])
    writer.close()
    frames_only = tmp_path / "frames_only"
    (frames_only / "frame_000000").mkdir(parents=True)
    (frames_only / "frame_000000" / "000.png").write_bytes(b"a real capture")
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    before = snapshot(tmp_path)
    one_error(simulate(users, "--overwrite"), f"--out {users}", "thesis.tex", "never deleted")
    one_error(simulate(recorded, "--overwrite"), f"--out {recorded}", "not simulated", "never replaced")
    one_error(simulate(frames_only, "--overwrite"), f"--out {frames_only}", "no sequence.yaml")
    one_error(simulate(plain, "--overwrite"), f"--out {plain}", "is a file")
    assert snapshot(tmp_path) == before


def test_simulate_replaces_its_own_sequence_with_overwrite(tmp_path):
    out = tmp_path / "sim"
    code, _, err = simulate(out)
    assert code == 0, err
    first = snapshot(out)
    one_error(simulate(out), f"--out {out}", "exists", "--overwrite")
    assert snapshot(out) == first
    code, _, err = simulate(out, "--overwrite", "--seed", "5")
    assert code == 0, err
    assert snapshot(out)["frame_000000/000.png"] != first["frame_000000/000.png"]


def test_simulate_into_its_scene_file_folder_is_refused(tmp_path):
    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump({"scene": "turntable"}))
    before = snapshot(tmp_path)
    one_error(simulate(tmp_path, "--config", str(scene), "--overwrite"), f"--out {tmp_path}", "holds the input")
    assert snapshot(tmp_path) == before


# ---------------------------------------------------------------------------- demo --out


def test_demo_refuses_a_folder_it_did_not_make(rendered, tmp_path):
    users = tmp_path / "users"
    (users / "sequence").mkdir(parents=True)
    (users / "paper.pdf").write_bytes(b"x")
    recording = tmp_path / "recording"
    writer = SequenceWriter(recording / "sequence", rendered[0], SPEC, source={"capture_tool": "x"})
    writer.add_frame(0, 0.0, rendered[1])
    writer.close()
    before = snapshot(tmp_path)
    one_error(run_cli("demo", "--out", str(users)), f"--out {users}", "paper.pdf", "choose another --out")
    one_error(run_cli("demo", "--out", str(recording)), f"--out {recording}", "sequence")
    one_error(run_cli("demo", "--out", str(users / "paper.pdf")), "is a file")
    assert snapshot(tmp_path) == before


def test_demo_folder_accepts_new_empty_marked_and_earlier_demo_folders(tmp_path):
    from frontend.demo import DEMO_MARKER, demo_folder
    from frontend.sim import simulate_sequence

    for folder in (tmp_path / "new", tmp_path / "empty"):
        if folder.name == "empty":
            folder.mkdir()
        with demo_folder(folder):
            pass
        assert (folder / DEMO_MARKER).is_file()
    with demo_folder(tmp_path / "new"):  # marked: the user's files next to the demo's are kept
        (tmp_path / "new" / "notes.txt").write_text("x")
    with demo_folder(tmp_path / "new"):
        pass
    assert (tmp_path / "new" / "notes.txt").read_text() == "x"
    earlier = tmp_path / "earlier"  # a demo folder of a version that did not mark it
    simulate_sequence({"scene": "turntable", "turntable": {"turns": 1, "views_per_turn": 4}}, earlier / "sequence",
                      max_frames=1, resolution=(160, 100), calibration_mode="true")
    (earlier / "results").mkdir()
    with demo_folder(earlier):
        pass
    assert (earlier / DEMO_MARKER).is_file()


def test_simulate_once_replaces_only_its_own_simulation(rendered, tmp_path):
    from fpp_graph.errors import OutputError
    from frontend.demo import simulate_once

    recorded = tmp_path / "recorded"
    writer = SequenceWriter(recorded, rendered[0], SPEC, source={"capture_tool": "x"})
    writer.add_frame(0, 0.0, rendered[1])
    writer.close()
    before = snapshot(tmp_path)
    with pytest.raises(OutputError, match="not simulated"):
        simulate_once("turntable", recorded, frames=1, calibration="true")
    assert snapshot(tmp_path) == before
    shutil.rmtree(recorded)
