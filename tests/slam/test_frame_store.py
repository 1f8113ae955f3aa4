"""save_frame / load_frame: points and colours derivable from the map are not stored twice."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.slam.frame_store import load_frame, save_frame
from fpp_graph.types import Frame, grey_colors

H, W = 120, 160


def sensor_like_frame(rng: np.random.Generator) -> Frame:
    """A frame built the way both sensors build theirs: points/colours = the map's finite pixels."""
    # float32-representable values, so the float32 cache gives back exactly these numbers
    xyz = (rng.normal(size=(H, W, 3)) + [0.0, 0.0, 2.0]).astype(np.float32).astype(np.float64)
    xyz[rng.random((H, W)) < 0.1] = np.nan
    xyz[:5, :7] = np.nan  # a hole, as a shadow gives
    texture = rng.integers(0, 256, size=(H, W), dtype=np.uint8)
    valid = np.isfinite(xyz[..., 2])
    return Frame(
        id=7,
        timestamp=0.25,
        points=xyz[valid],
        colors=np.repeat(texture[valid][:, None] / 255.0, 3, axis=1),
        xyz_map=xyz,
        texture=texture,
        keypoints_uv=rng.uniform(0, W, size=(4, 2)),
        descriptors=rng.integers(0, 256, size=(4, 32), dtype=np.uint8),
        metadata={"K": np.eye(3).tolist(), "sensor": "rgbd"},  # as the RGB-D source does
    )


def save_old_format(path, frame: Frame) -> None:
    """The layout save_frame wrote before derivable points/colours were left out."""
    np.savez(
        path,
        id=np.array(frame.id),
        timestamp=np.array(frame.timestamp),
        points=frame.points.astype(np.float32),
        texture=frame.texture,
        keypoints_uv=frame.keypoints_uv,
        descriptors=frame.descriptors,
        colors=(np.clip(frame.colors, 0, 1) * 255).round().astype(np.uint8),
        xyz_map=frame.xyz_map.astype(np.float32),
        metadata_json=np.array(json.dumps({"K": np.eye(3).tolist(), "sensor": "rgbd"})),
    )


def assert_same_frame(a: Frame, b: Frame) -> None:
    assert (a.id, a.timestamp) == (b.id, b.timestamp)
    for name in ("points", "colors", "xyz_map", "texture", "keypoints_uv", "descriptors"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert dict(a.metadata) == dict(b.metadata)


def test_derivable_points_and_colors_round_trip_exactly_in_a_smaller_file(tmp_path, rng):
    frame = sensor_like_frame(rng)
    assert 0.8 * H * W < frame.num_points < 0.95 * H * W
    save_frame(tmp_path / "new.npz", frame)
    save_old_format(tmp_path / "old.npz", frame)

    with np.load(tmp_path / "new.npz") as data:
        assert "points" not in data.files and "colors" not in data.files
        assert sorted(data["derived_from_map"].tolist()) == ["colors", "points"]
    back = load_frame(tmp_path / "new.npz")
    np.testing.assert_array_equal(back.points, frame.points)
    np.testing.assert_array_equal(back.colors, frame.colors)
    assert back.points.dtype == np.float64 and back.colors.dtype == np.float64
    assert back.colors.strides[1] == 0  # one grey column seen three times, not three copies
    # a frame whose grey colours are such a view is stored the same way
    viewed = dataclasses.replace(frame, colors=grey_colors(frame.colors[:, 0].copy()))
    save_frame(tmp_path / "viewed.npz", viewed)
    assert_same_frame(load_frame(tmp_path / "viewed.npz"), back)
    with np.load(tmp_path / "viewed.npz") as data:
        assert "colors" not in data.files
    # exactly what the old layout gives back, every array
    assert_same_frame(back, load_frame(tmp_path / "old.npz"))
    # points (12 B/pt) + colours (3 B/pt) were half of the old file
    new_size, old_size = (
        (tmp_path / "new.npz").stat().st_size,
        (tmp_path / "old.npz").stat().st_size,
    )
    assert new_size <= 0.6 * old_size, (new_size, old_size)


def test_points_that_are_not_the_maps_finite_pixels_are_stored(tmp_path, rng):
    frame = sensor_like_frame(rng)
    valid = np.isfinite(frame.xyz_map[..., 2])
    cases = {  # label: points, colours, the arrays left out of the file
        "subset": (frame.points[::2], frame.colors[::2], []),
        "reordered": (frame.points[::-1], frame.colors[::-1], []),
        # the colours are still the texture at the map's finite pixels: only they are left out
        "moved 1 mm": (frame.points + [0.0, 0.0, 1e-3], frame.colors, ["colors"]),
    }
    for label, (points, colors, derived) in cases.items():
        odd = Frame(
            id=1,
            timestamp=0.0,
            points=points,
            colors=colors,
            xyz_map=frame.xyz_map,
            texture=frame.texture,
        )
        save_frame(tmp_path / "odd.npz", odd)
        with np.load(tmp_path / "odd.npz") as data:
            assert "points" in data.files and ("colors" in data.files) == (not derived), label
            assert (
                data["derived_from_map"].tolist() if "derived_from_map" in data.files else []
            ) == derived, label
        back = load_frame(tmp_path / "odd.npz")
        np.testing.assert_array_equal(
            back.points, points.astype(np.float32).astype(np.float64), err_msg=label
        )
        # colours k / 255 survive the uint8 cache exactly
        np.testing.assert_array_equal(back.colors, colors, err_msg=label)

    # points derivable but colours not the grey texture (a tint): only the points are dropped
    tinted = frame.colors * [1.0, 0.5, 0.25]
    odd = Frame(
        id=2,
        timestamp=0.0,
        points=frame.points,
        colors=tinted,
        xyz_map=frame.xyz_map,
        texture=frame.texture,
    )
    save_frame(tmp_path / "tint.npz", odd)
    with np.load(tmp_path / "tint.npz") as data:
        assert data["derived_from_map"].tolist() == ["points"] and "colors" in data.files
    back = load_frame(tmp_path / "tint.npz")
    np.testing.assert_array_equal(back.points, frame.points)
    np.testing.assert_allclose(back.colors, tinted, atol=0.5 / 255)
    assert np.count_nonzero(valid) == back.num_points

    # no map: float64 points stored as they are, bit for bit
    bare = Frame(id=3, timestamp=0.0, points=rng.normal(size=(50, 3)))
    save_frame(tmp_path / "bare.npz", bare)
    back = load_frame(tmp_path / "bare.npz")
    np.testing.assert_array_equal(back.points, bare.points)
    assert back.colors is None and back.xyz_map is None


def test_old_format_file_still_loads(tmp_path, rng):
    frame = sensor_like_frame(rng)
    save_old_format(tmp_path / "old.npz", frame)
    back = load_frame(tmp_path / "old.npz")
    assert_same_frame(back, frame)


def test_derived_marker_without_its_map_is_a_clear_error(tmp_path):
    np.savez(
        tmp_path / "bad.npz",
        id=np.array(1),
        timestamp=np.array(0.0),
        derived_from_map=np.array(["points"]),
        metadata_json=np.array("{}"),
    )
    with pytest.raises(InputDataError, match="lacks 'xyz_map'.*delete it to recompute"):
        load_frame(tmp_path / "bad.npz")


def test_put_keeps_the_first_stored_copy_unless_told_to_rewrite_it(tmp_path):
    from dataclasses import replace

    from fpp_graph.slam.frame_store import FrameStore

    store = FrameStore(tmp_path, max_in_memory=1)
    bare = Frame(id=7, timestamp=0.0, points=np.zeros((3, 3)))
    store.put(bare)
    described = replace(bare, keypoints_uv=np.ones((2, 2)), descriptors=np.ones((2, 4), np.float32))
    store.put(described)  # the worker's cache is already there: left as it is
    assert load_frame(store.path_of(7)).descriptors is None
    store.put(described, rewrite=True)
    np.testing.assert_array_equal(load_frame(store.path_of(7)).descriptors, described.descriptors)


def test_discard_unstored_deletes_only_a_cached_frame_that_was_never_put(tmp_path):
    from fpp_graph.slam.frame_store import FrameStore

    store = FrameStore(tmp_path, max_in_memory=1)
    keyframe, tracked = (Frame(id=i, timestamp=0.0, points=np.zeros((3, 3))) for i in (1, 2))
    store.put(keyframe)
    save_frame(store.path_of(2), tracked)  # a worker's decode cache
    assert store.discard_unstored(2) and not store.path_of(2).exists()
    assert not store.discard_unstored(2)  # already gone
    assert not store.discard_unstored(1) and store.path_of(1).exists()
    assert not FrameStore(None).discard_unstored(1)


def test_load_frame_points_samples_the_points_load_frame_gives(tmp_path):
    """A frame whose points are its map's finite pixels (not stored) and one whose points are
    stored: the sample is a seeded, ordered subset of exactly the points load_frame returns."""
    from fpp_graph.slam.frame_store import load_frame_points

    rng = np.random.default_rng(4)
    derived = sensor_like_frame(rng)
    stored = Frame(id=8, timestamp=0.5, points=rng.normal(size=(500, 3)).astype(np.float32).astype(np.float64))
    for frame in (derived, stored):
        path = tmp_path / f"frame_{frame.id:06d}.npz"
        save_frame(path, frame)
        everything = load_frame(path).points
        assert np.array_equal(load_frame_points(path, 10**6), everything)
        sample = load_frame_points(path, 200, seed=3)
        assert sample.shape == (200, 3) and sample.dtype == np.float64
        rows = {tuple(p) for p in everything}
        assert all(tuple(p) in rows for p in sample)
        assert np.array_equal(sample, load_frame_points(path, 200, seed=3))
        assert not np.array_equal(sample, load_frame_points(path, 200, seed=4))
        # in the frame's order (a sorted subset), so a sample is reproducible from the file alone
        index = {tuple(p): i for i, p in enumerate(everything)}
        assert np.all(np.diff([index[tuple(p)] for p in sample]) > 0)
    broken = tmp_path / "frame_000009.npz"
    broken.write_bytes(b"not a zip")
    with pytest.raises(InputDataError, match="cannot read cached frame .*frame_000009.npz.*delete it"):
        load_frame_points(broken, 10)
    empty = tmp_path / "frame_000010.npz"
    np.savez(empty, id=np.array(10))
    with pytest.raises(InputDataError, match="neither points nor an xyz map"):
        load_frame_points(empty, 10)


def test_prepared_arrays_round_trip_and_bad_ones_are_refused(tmp_path):
    frame = dataclasses.replace(
        sensor_like_frame(np.random.default_rng(5)),
        prepared={"ref.index": np.arange(5, dtype=np.int64), "ref.settings": np.array([np.nan, 1.5]), "ref.flag": np.array([True, False])},
    )
    assert not frame.prepared["ref.index"].flags.writeable
    save_frame(tmp_path / "f.npz", frame)
    loaded = load_frame(tmp_path / "f.npz")
    assert sorted(loaded.prepared) == sorted(frame.prepared)
    for name, value in frame.prepared.items():
        assert loaded.prepared[name].dtype == value.dtype and np.array_equal(loaded.prepared[name], value, equal_nan=True)
    with pytest.raises(InputDataError, match="prepared array name"):
        dataclasses.replace(frame, prepared={"a/b": np.zeros(2)})
    with pytest.raises(InputDataError, match="Python objects"):
        dataclasses.replace(frame, prepared={"a": np.array([{}, 1], dtype=object)})


def test_grey_colour_views_that_are_not_the_texture_are_stored(tmp_path, rng):
    frame = sensor_like_frame(rng)
    other = dataclasses.replace(frame, colors=grey_colors(1.0 - frame.colors[:, 0]))
    save_frame(tmp_path / "f.npz", other)
    with np.load(tmp_path / "f.npz") as data:
        assert "colors" in data.files and data["colors"].shape == (frame.num_points, 3)
    back = load_frame(tmp_path / "f.npz")
    np.testing.assert_allclose(back.colors, other.colors, atol=0.5 / 255)


def test_a_full_disk_is_an_output_error_and_leaves_the_cached_frames_whole(tmp_path, rng, monkeypatch):
    import errno

    from fpp_graph.errors import OutputError
    from fpp_graph.slam import frame_store

    frame = sensor_like_frame(rng)
    save_frame(tmp_path / "frame_000006.npz", frame)  # cached before the disk filled up

    def full_disk(handle, **arrays):
        handle.write(b"PK partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(frame_store.np, "savez", full_disk)
    with pytest.raises(OutputError, match=r"frame_000007\.npz: No space left on device; free space .* --resume"):
        save_frame(tmp_path / "frame_000007.npz", frame)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame_000006.npz"]  # no partial file
    assert_same_frame(load_frame(tmp_path / "frame_000006.npz"), frame)
