"""Frames read from the cache as views of the mapped file: the same arrays as ``np.load``, read-only,
and every broken file refused with the cache's own error."""

from __future__ import annotations

import os

import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.mapped_npz import mapped_npz
from fpp_graph.slam.frame_store import load_frame, load_frame_points, save_frame
from fpp_graph.types import Frame


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {
        "map": rng.normal(size=(30, 40, 3)).astype(np.float32),
        "fortran": np.asfortranarray(rng.normal(size=(5, 7))),
        "empty": np.zeros((0, 3)),
        "scalar": np.array(7),
        "text": np.array('{"a": 1}'),
        "record": np.zeros(4, dtype=[("x", "<f8"), ("n", "<i4")]),
        "bytes": rng.integers(0, 255, size=(11, 13), dtype=np.uint8),
    }


def test_the_same_arrays_as_np_load_as_read_only_views(tmp_path):
    path = tmp_path / "a.npz"
    arrays = _arrays()
    np.savez(path, **arrays)
    mapped = mapped_npz(path)
    assert set(mapped) == set(arrays)
    with np.load(path) as loaded:
        for name in arrays:
            assert mapped[name].dtype == loaded[name].dtype and mapped[name].shape == loaded[name].shape, name
            assert mapped[name].flags.f_contiguous == loaded[name].flags.f_contiguous, name
            np.testing.assert_array_equal(mapped[name], loaded[name])
            assert not mapped[name].flags.writeable, name
    with pytest.raises(ValueError, match="read-only"):
        mapped["map"][0, 0, 0] = 1.0


def test_a_file_replaced_while_mapped_keeps_its_views(tmp_path):
    path = tmp_path / "a.npz"
    np.savez(path, x=np.arange(1000.0))
    view = mapped_npz(path)["x"]
    np.savez(tmp_path / "b.npz", x=np.zeros(1000))
    os.replace(tmp_path / "b.npz", path)  # as the store's atomic writes do
    np.testing.assert_array_equal(view, np.arange(1000.0))
    np.testing.assert_array_equal(mapped_npz(path)["x"], np.zeros(1000))


@pytest.mark.parametrize("damage", ["compressed", "truncated", "not a zip", "empty", "cut member", "foreign member"])
def test_broken_cache_files_are_refused_with_the_cache_error(tmp_path, damage):
    frame_path = tmp_path / "frame_000001.npz"
    xyz = np.random.default_rng(0).normal(size=(20, 30, 3))
    save_frame(frame_path, Frame(id=1, timestamp=0.0, points=xyz.reshape(-1, 3), xyz_map=xyz))
    data = frame_path.read_bytes()
    if damage == "compressed":
        with np.load(frame_path) as stored:
            arrays = dict(stored)
        np.savez_compressed(tmp_path / "compressed.npz", **arrays)
        os.replace(tmp_path / "compressed.npz", frame_path)
    elif damage == "truncated":
        frame_path.write_bytes(data[: len(data) // 2])
    elif damage == "not a zip":
        frame_path.write_text("hello")
    elif damage == "empty":
        frame_path.write_bytes(b"")
    elif damage == "cut member":  # a member's npy record longer than the member (a header edited by hand)
        offset = data.find(b"'shape': (20, 30, 3)")
        frame_path.write_bytes(data[:offset] + b"'shape': (90, 30, 3)" + data[offset + 20 :])
    else:  # a zip member that is not an npy record
        import zipfile

        with zipfile.ZipFile(frame_path, "w") as archive:
            archive.writestr("xyz_map.npy", b"not an array")
    with pytest.raises(InputDataError, match="delete it to recompute"):
        load_frame(frame_path)
    with pytest.raises(InputDataError, match="delete it to recompute"):
        load_frame_points(frame_path, 10)


def test_frames_read_from_the_mapped_cache_equal_the_saved_ones(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(24, 32, 3))
    xyz[3, 4] = np.nan
    texture = rng.integers(0, 255, size=(24, 32), dtype=np.uint8)
    frame = Frame(id=4, timestamp=1.5, points=xyz[np.isfinite(xyz[..., 2])], xyz_map=xyz, texture=texture,
                  keypoints_uv=rng.uniform(0, 20, size=(6, 2)).astype(np.float32), descriptors=rng.normal(size=(6, 64)).astype(np.float32),
                  metadata={"k": 2})
    save_frame(tmp_path / "f.npz", frame)
    back = load_frame(tmp_path / "f.npz")
    np.testing.assert_array_equal(back.xyz_map, xyz.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(back.texture, texture)
    np.testing.assert_array_equal(back.keypoints_uv, frame.keypoints_uv)
    np.testing.assert_array_equal(back.descriptors, frame.descriptors)
    assert back.metadata == {"k": 2} and back.id == 4 and back.timestamp == 1.5
    assert len(load_frame_points(tmp_path / "f.npz", 100)) == 100
