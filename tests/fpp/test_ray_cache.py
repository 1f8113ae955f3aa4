"""Camera rays kept per camera model: the same rays as computed, made once under a lock by
concurrent processes, bounded in number, and a broken or unwritable cache only costs time."""

from __future__ import annotations

import multiprocessing
import os

import numpy as np
import pytest
from test_triangulation import make_rig

from frontend.fpp import ray_cache
from frontend.fpp.ray_cache import MAX_ENTRIES, cached_camera_rays, ray_cache_key
from frontend.fpp.rig import PinholeModel
from frontend.fpp.triangulation import Triangulator, pixel_rays


def _counting(counter: list[int]):
    def compute(camera: PinholeModel) -> np.ndarray:
        counter.append(1)
        return pixel_rays(camera)

    return compute


def test_cached_rays_equal_computed_ones_and_triangulate_the_same(tmp_path):
    rig = make_rig()
    calls: list[int] = []
    first = cached_camera_rays(rig.camera, _counting(calls), tmp_path)
    again = cached_camera_rays(rig.camera, _counting(calls), tmp_path)
    assert len(calls) == 1  # the second comes from the file
    np.testing.assert_array_equal(again, pixel_rays(rig.camera))
    assert not again.flags.writeable  # a view of the mapped file
    u = np.random.default_rng(0).uniform(50, 400, size=(rig.camera.height, rig.camera.width))
    np.testing.assert_array_equal(Triangulator(rig, camera_rays=again).triangulate(u), Triangulator(rig).triangulate(u))
    np.testing.assert_array_equal(first, again)


def test_each_camera_model_has_its_own_entry(tmp_path):
    rig = make_rig()
    other = PinholeModel(rig.camera.width, rig.camera.height, rig.camera.K, rig.camera.dist * 1.01)
    assert ray_cache_key(rig.camera) != ray_cache_key(other)
    np.testing.assert_array_equal(cached_camera_rays(other, pixel_rays, tmp_path), pixel_rays(other))
    assert len(list(tmp_path.glob("*.npy"))) == 1


def _worker(folder: str, queue) -> None:
    calls: list[int] = []
    rays = cached_camera_rays(make_rig().camera, _counting(calls), folder)
    queue.put((len(calls), float(np.nansum(rays))))


def test_concurrent_processes_compute_the_rays_once(tmp_path):
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    processes = [context.Process(target=_worker, args=(str(tmp_path), queue)) for _ in range(3)]
    for p in processes:
        p.start()
    results = [queue.get(timeout=120) for _ in processes]
    for p in processes:
        p.join(timeout=60)
    assert sum(calls for calls, _ in results) == 1
    assert len({total for _, total in results}) == 1


def test_the_cache_keeps_the_most_recently_used_entries(tmp_path):
    base = make_rig().camera
    cameras = [PinholeModel(64, 40, base.K * [[0.1], [0.1], [1]], base.dist * (1 + 0.01 * i)) for i in range(MAX_ENTRIES + 3)]
    for i, camera in enumerate(cameras):
        cached_camera_rays(camera, pixel_rays, tmp_path)
        os.utime(tmp_path / f"{ray_cache_key(camera)}.npy", (i, i))  # distinct, ordered last uses
    kept = {p.stem for p in tmp_path.glob("*.npy")}
    assert kept == {ray_cache_key(c) for c in cameras[-MAX_ENTRIES:]}


def test_a_broken_entry_is_recomputed_and_an_unwritable_cache_only_costs_time(tmp_path, caplog):
    rig = make_rig()
    path = tmp_path / f"{ray_cache_key(rig.camera)}.npy"
    path.write_bytes(b"not an array")
    np.testing.assert_array_equal(cached_camera_rays(rig.camera, pixel_rays, tmp_path), pixel_rays(rig.camera))
    assert "computing them again" in caplog.text
    np.save(path, np.zeros((3, 4, 3)))  # another camera's shape under this key
    np.testing.assert_array_equal(cached_camera_rays(rig.camera, pixel_rays, tmp_path), pixel_rays(rig.camera))
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    np.testing.assert_array_equal(cached_camera_rays(rig.camera, pixel_rays, blocked / "rays"), pixel_rays(rig.camera))
    assert "cannot cache camera rays" in caplog.text


def test_rays_of_the_wrong_shape_are_refused():
    rig = make_rig()
    with pytest.raises(ValueError, match="camera_rays must have shape"):
        Triangulator(rig, camera_rays=np.zeros((3, 4, 3)))


def test_default_folder_follows_the_cache_variable(monkeypatch, tmp_path):
    monkeypatch.setenv("FPP_GRAPH_CACHE", str(tmp_path))
    assert ray_cache.default_ray_cache_dir() == tmp_path / "rays"


# --- the projector's inverse distortion, kept per rig ---------------------------------------


def _triangulator_counting_fits(monkeypatch, calls: list[int]):
    from frontend.fpp import triangulation

    real = triangulation.fit_inverse_distortion

    def counting(*args):
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(triangulation, "fit_inverse_distortion", counting)


def test_a_kept_projector_fit_triangulates_as_a_fresh_one_and_is_made_once(monkeypatch, tmp_path):
    from test_triangulation import plane_scene

    from frontend.fpp.lens import project_to_projector

    monkeypatch.setenv("FPP_GRAPH_CACHE", str(tmp_path))
    rig = make_rig()
    calls: list[int] = []
    _triangulator_counting_fits(monkeypatch, calls)
    fresh = Triangulator(rig)
    first, second = Triangulator(rig, cache_projector_fit=True), Triangulator(rig, cache_projector_fit=True)
    assert len(calls) == 2  # the fresh one and the first cached one; the second read it
    assert len(list((tmp_path / "projector_fits").glob("*.npz"))) == 1
    u_p, _ = project_to_projector(rig, plane_scene(rig))
    for kept in (first, second):
        assert kept.projector_fit_degree == fresh.projector_fit_degree
        assert kept.projector_fit_max_error_px == fresh.projector_fit_max_error_px
        np.testing.assert_array_equal(kept.triangulate(u_p), fresh.triangulate(u_p))
    # another tolerance or number type is another entry
    Triangulator(rig, cache_projector_fit=True, projector_fit_tolerance_px=1e-2)
    Triangulator(rig, cache_projector_fit=True, dtype=np.float64)
    assert len(calls) == 4 and len(list((tmp_path / "projector_fits").glob("*.npz"))) == 3


def test_a_broken_projector_fit_is_made_again_and_an_unwritable_cache_only_costs_time(monkeypatch, tmp_path, caplog):
    from test_triangulation import plane_scene

    from frontend.fpp.lens import project_to_projector
    from frontend.fpp.ray_cache import cached_projector_fit, projector_fit_cache_key

    rig = make_rig()
    u_p, _ = project_to_projector(rig, plane_scene(rig))
    expected = Triangulator(rig).triangulate(u_p)
    monkeypatch.setenv("FPP_GRAPH_CACHE", str(tmp_path))
    path = tmp_path / "projector_fits" / f"{projector_fit_cache_key(rig, 0, 1e-3, np.dtype(np.float32))}.npz"
    path.parent.mkdir()
    path.write_bytes(b"not an archive")
    np.testing.assert_array_equal(Triangulator(rig, cache_projector_fit=True).triangulate(u_p), expected)
    assert "unreadable projector fit" in caplog.text
    fit = cached_projector_fit(rig, 0, 1e-3, np.dtype(np.float32), lambda: None)  # read back: compute is not called
    arrays = {"center": fit.center, "degree": fit.degree + 1, "table_error_px": 0.0, "coverage": 1.0, "nodes": fit.nodes, "coeffs": np.stack(fit.coeffs)}
    np.savez(path, **arrays)  # a degree that does not match its coefficients
    np.testing.assert_array_equal(Triangulator(rig, cache_projector_fit=True).triangulate(u_p), expected)
    assert "computing it again" in caplog.text
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    monkeypatch.setenv("FPP_GRAPH_CACHE", str(blocked))
    np.testing.assert_array_equal(Triangulator(rig, cache_projector_fit=True).triangulate(u_p), expected)
    assert "cannot cache the projector's inverse distortion" in caplog.text
