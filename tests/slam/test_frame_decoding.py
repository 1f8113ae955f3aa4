"""Frames decoded ahead of tracking (:func:`fpp_graph.slam.pipeline.prepare_frames`): through the
cache or handed over, the first one in the calling process, a full disk stopping the run."""

from __future__ import annotations

import numpy as np
import pytest
from wall_sequences import XS, write_tum_rgbd_sequence

from fpp_graph.config import config_from_dict


@pytest.fixture(scope="module")
def tum_sequence(tmp_path_factory):
    return write_tum_rgbd_sequence(tmp_path_factory.mktemp("tum") / "seq")


def test_a_frame_cache_that_cannot_be_written_stops_the_run_instead_of_skipping_frames(tmp_path, tum_sequence, monkeypatch):
    """A full disk is not a bad frame: the frames stage ends with the OutputError (one line in the
    CLI) instead of skipping every frame after it as undecodable."""
    import errno
    from concurrent.futures import ThreadPoolExecutor

    from fpp_graph.errors import OutputError
    from fpp_graph.slam import frame_store
    from fpp_graph.slam.pipeline import prepare_frames
    from fpp_graph.slam.sources import open_source

    source = open_source(tum_sequence, config_from_dict({}))
    cache = tmp_path / "frames"
    cache.mkdir()

    def full_disk(handle, **arrays):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(frame_store.np, "savez", full_disk)
    skipped: dict[int, str] = {}
    with ThreadPoolExecutor(2) as executor, pytest.raises(OutputError, match="No space left on device"):
        # a token of its own: thread workers share the module's adopted source between tests
        list(prepare_frames(source, cache, executor, skipped, worker_source=(source, "full-disk-run"), cache_every_frame=True))
    assert skipped == {} and list(cache.iterdir()) == []


@pytest.mark.parametrize("cache_every_frame", [False, True])
def test_frames_decoded_ahead_come_back_through_the_cache_or_directly(tmp_path, tum_sequence, cache_every_frame):
    """With only keyframes kept on disk, the workers hand decoded frames back directly: nothing is
    written to frames/ just to be deleted once tracked. Cached frames (a resumed run) are still
    read, and a broken frame is still skipped with its reason, either way."""
    import shutil
    from concurrent.futures import ThreadPoolExecutor

    from fpp_graph.slam.frame_store import frame_from_stored, save_frame, stored_arrays
    from fpp_graph.slam.pipeline import prepare_frames
    from fpp_graph.slam.sources import open_source

    seq = tmp_path / "seq"
    shutil.copytree(tum_sequence, seq)
    sorted((seq / "depth").iterdir())[4].write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    source = open_source(seq, config_from_dict({}))
    cache = tmp_path / "frames"
    cache.mkdir()
    resumed = source.load_frame(1)
    save_frame(cache / "frame_000001.npz", resumed)  # from an interrupted run
    skipped: dict[int, str] = {}
    with ThreadPoolExecutor(2) as executor:
        frames = list(prepare_frames(source, cache, executor, skipped, worker_source=(source, "test-run"), cache_every_frame=cache_every_frame))
    ids = [f.id for f in frames]
    assert ids == [i for i in range(len(XS)) if i != 4] and set(skipped) == {4} and "depth" in skipped[4]
    for frame in frames[:3]:  # the numbers the cache gives (float32 maps), whichever way the frame came
        expected = frame_from_stored(stored_arrays(source.load_frame(frame.id)), "expected")
        assert np.array_equal(frame.xyz_map, expected.xyz_map, equal_nan=True) and np.array_equal(frame.texture, expected.texture)
        assert np.array_equal(frame.points, expected.points) and np.array_equal(frame.colors, expected.colors)
    written = sorted(p.name for p in cache.glob("frame_*.npz"))
    if cache_every_frame:
        assert written == [f"frame_{i:06d}.npz" for i in ids]
    else:
        assert written == ["frame_000001.npz"]
    # without an executor the frames are decoded here, with the same choice
    shutil.rmtree(cache)
    local = list(prepare_frames(source, cache, None, {}, cache_every_frame=cache_every_frame))
    assert [f.id for f in local] == ids
    assert len(list(cache.glob("frame_*.npz"))) == (len(ids) if cache_every_frame else 0)


def test_the_first_frame_is_decoded_while_the_workers_start(tmp_path, tum_sequence):
    """The first frame is decoded in the calling process after the next ones are queued (a new
    pool's workers import their libraries first); the others go to the executor, and the frames
    are the same either way. A first frame that cannot be decoded is skipped with its reason, a
    cached one is read, not decoded."""
    import shutil
    from concurrent.futures import ThreadPoolExecutor

    from fpp_graph.slam.frame_store import save_frame
    from fpp_graph.slam.pipeline import prepare_frames
    from fpp_graph.slam.sources import open_source

    class Recording(ThreadPoolExecutor):
        def __init__(self) -> None:
            super().__init__(2)
            self.frame_ids: list[int] = []

        def submit(self, fn, /, *args, **kwargs):
            self.frame_ids.append(args[0])
            return super().submit(fn, *args, **kwargs)

    source = open_source(tum_sequence, config_from_dict({}))
    with Recording() as executor:
        frames = list(prepare_frames(source, tmp_path / "a", executor, {}, worker_source=(source, "first-frame-run"), cache_every_frame=False))
    assert executor.frame_ids == list(range(1, len(XS)))
    local = list(prepare_frames(source, tmp_path / "b", None, {}, cache_every_frame=False))
    assert [f.id for f in frames] == [f.id for f in local] == list(range(len(XS)))
    for a, b in zip(frames, local, strict=True):
        assert np.array_equal(a.xyz_map, b.xyz_map, equal_nan=True) and np.array_equal(a.texture, b.texture)

    seq = tmp_path / "seq"
    shutil.copytree(tum_sequence, seq)
    sorted((seq / "depth").iterdir())[0].write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    broken = open_source(seq, config_from_dict({}))
    skipped: dict[int, str] = {}
    with Recording() as executor:
        ids = [f.id for f in prepare_frames(broken, tmp_path / "c", executor, skipped, worker_source=(broken, "broken-first-run"), cache_every_frame=False)]
    assert ids == list(range(1, len(XS))) and set(skipped) == {0} and "depth" in skipped[0]

    cache = tmp_path / "d"
    cache.mkdir()
    save_frame(cache / "frame_000000.npz", source.load_frame(0))  # an interrupted run's
    with Recording() as executor:
        ids = [f.id for f in prepare_frames(broken, cache, executor, {}, worker_source=(broken, "resumed-first-run"), cache_every_frame=False)]
    assert ids == list(range(len(XS))) and executor.frame_ids == list(range(1, len(XS)))
