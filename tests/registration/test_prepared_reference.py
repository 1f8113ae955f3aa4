"""TexturedSurfaceRegistrar.prepare: a frame's dense surface and, for a plane-like frame, its photometric
reference pixels, made once and stored with the frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.slam.frame_store import load_frame, save_frame
from fpp_graph.types import Frame
from frontend.config import RegistrationConfig
from frontend.localization.reference import reference_from_arrays, reference_settings
from frontend.organised_surface import SURFACE_ARRAYS, OrganisedSurface
from frontend.registration import TextureCamera, TexturedSurfaceRegistrar
from frontend.registration.registrar import PREPARED_REFERENCE
from frontend.registration.weak_directions import DEGENERACY_RATIO, surface_is_plane_like
from frontend.testing.synthetic_frames import (
    bumpy_wall_scene,
    camera_matrix,
    render_frame,
    wall_pose,
)

W, H = 640, 400
FIELDS = ("index", "X_world", "n_world", "E_ref", "has_normal")


def registrar(**photometric) -> TexturedSurfaceRegistrar:
    config = RegistrationConfig()
    if photometric:
        config = config.model_copy(update={"photometric": config.photometric.model_copy(update=photometric)})
    return TexturedSurfaceRegistrar(config, texture_camera=TextureCamera(camera_matrix(W, H), np.zeros(5), np.array([0.1, 0.0, 0.0])))


@pytest.fixture(scope="module")
def flat_frame():
    return render_frame(bumpy_wall_scene(seed=5, flat=True), wall_pose(0.02), W, H, frame_id=3)


@pytest.fixture(scope="module")
def relief_frame(flat_frame):
    """A four-sided hollow pyramid 0.5 m away at its apex (faces tilted 31 and 22 degrees): its
    relief holds every direction."""
    K = camera_matrix(W, H)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x_n, y_n = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    depth = 0.5 / (1.0 - 0.6 * np.abs(x_n) - 0.4 * np.abs(y_n))  # z = 0.5 + 0.6 |x| + 0.4 |y|
    xyz = np.stack([x_n * depth, y_n * depth, depth], axis=-1)
    return Frame(id=4, timestamp=0.0, points=xyz.reshape(-1, 3), xyz_map=xyz, texture=flat_frame.texture)


def test_plane_like_test_tells_a_wall_from_relief(flat_frame, relief_frame):
    ratio = DEGENERACY_RATIO
    assert surface_is_plane_like(flat_frame.xyz_map, 0.002, ratio)
    assert not surface_is_plane_like(relief_frame.xyz_map, 0.002, ratio)
    assert not surface_is_plane_like(np.full((20, 20, 3), np.nan), 0.002, ratio)  # no surface: nothing to prepare


def test_prepared_reference_is_what_a_reader_of_the_stored_frame_would_compute(flat_frame, tmp_path):
    prepared = registrar().prepare(flat_frame)
    assert {PREPARED_REFERENCE + name for name in (*FIELDS, "settings")} <= set(prepared.prepared)
    save_frame(tmp_path / "f.npz", prepared)
    read = load_frame(tmp_path / "f.npz")
    used = registrar().photometric.reference(read, PREPARED_REFERENCE)
    computed = registrar().photometric.reference(dataclasses.replace(read, prepared={}), PREPARED_REFERENCE)
    assert used.settings == computed.settings
    for name in FIELDS:
        assert np.array_equal(getattr(used, name), getattr(computed, name), equal_nan=True), name
    # it is the stored arrays that were used, not a second computation
    assert np.shares_memory(used.X_world, read.prepared[PREPARED_REFERENCE + "X_world"])


def test_other_settings_compute_their_own_reference(flat_frame, monkeypatch):
    import frontend.registration.refinement as refinement

    prepared = registrar().prepare(flat_frame)
    monkeypatch.setattr(refinement, "PHOTOMETRIC_MAX_PIXELS", 5000)
    fewer = registrar()
    settings = reference_settings(W, np.array([0.1, 0.0, 0.0]), 5000)
    assert reference_from_arrays(prepared.prepared, PREPARED_REFERENCE, settings) is None
    reference = fewer.photometric.reference(prepared, PREPARED_REFERENCE)
    assert reference.settings == settings and reference.index.size == 5000


def test_frames_that_need_no_reference_get_their_surface_only(flat_frame, relief_frame):
    def reference_names(frame):
        return {name for name in frame.prepared if name.startswith(PREPARED_REFERENCE)}

    for frame in (
        registrar().prepare(relief_frame),  # relief: its pairs are not weak
        TexturedSurfaceRegistrar(RegistrationConfig()).prepare(flat_frame),  # no rig: no photometric step
        registrar(enabled=False).prepare(flat_frame),
    ):
        assert not reference_names(frame)
        assert set(SURFACE_ARRAYS) <= set(frame.prepared)
    no_dense = RegistrationConfig()
    no_dense = no_dense.model_copy(update={"dense": no_dense.dense.model_copy(update={"enabled": False})})
    assert TexturedSurfaceRegistrar(no_dense).prepare(flat_frame) is flat_frame  # nothing a pair of it needs
    no_map = dataclasses.replace(flat_frame, xyz_map=None)
    assert registrar().prepare(no_map) is no_map


def test_prepared_surface_is_the_one_a_reader_of_the_stored_frame_would_make(relief_frame, tmp_path):
    save_frame(tmp_path / "f.npz", registrar().prepare(relief_frame))
    read = load_frame(tmp_path / "f.npz")
    used = registrar().dense.surfaces.surface(read)
    made = OrganisedSurface(read.xyz_map)
    # it is the stored arrays that were used, not a second computation
    assert np.shares_memory(used.normals_binned, read.prepared["surface.normals"])
    rng = np.random.default_rng(0)
    points = made.samples(4)[0] + rng.normal(0.0, 0.002, (len(made.samples(4)[0]), 3))
    for a, b in zip(used.lookup(points), made.lookup(points), strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    for a, b in zip(used.samples(2), made.samples(2), strict=True):
        assert np.array_equal(a, b)
    assert (used.fx, used.fy, used.cx, used.cy) == (made.fx, made.fy, made.cx, made.cy)
    # the surface's map is the stored float32 one, not the frame's float64 map narrowed again
    assert np.shares_memory(used.xyz, read.xyz_map_stored)
    np.testing.assert_array_equal(used.xyz, made.xyz)


def test_the_stored_float32_map_is_known_for_frames_read_from_the_store_only(relief_frame, tmp_path):
    save_frame(tmp_path / "f.npz", relief_frame)
    read = load_frame(tmp_path / "f.npz")
    stored = read.xyz_map_stored
    assert stored.dtype == np.float32
    np.testing.assert_array_equal(stored, read.xyz_map.astype(np.float32))
    np.testing.assert_array_equal(stored.astype(np.float64), read.xyz_map)
    # a frame made otherwise, or made from it with another map, has none; one made from it with
    # the same map keeps it, and its surface reads it
    assert relief_frame.xyz_map_stored is None
    assert dataclasses.replace(read, xyz_map=read.xyz_map + 1.0).xyz_map_stored is None
    surface = registrar().dense.surfaces.surface(dataclasses.replace(read, id=9))
    assert np.shares_memory(surface.xyz, stored)


def test_stored_surface_of_another_map_or_setting_is_not_used(relief_frame):
    arrays = OrganisedSurface(relief_frame.xyz_map).to_arrays()
    assert OrganisedSurface.from_arrays(relief_frame.xyz_map, arrays) is not None
    assert OrganisedSurface.from_arrays(relief_frame.xyz_map[:-2], arrays) is None  # another size
    assert OrganisedSurface.from_arrays(relief_frame.xyz_map, arrays, normal_window_px=9) is None  # other normals
    assert OrganisedSurface.from_arrays(relief_frame.xyz_map, {k: v for k, v in arrays.items() if k != "surface.rays"}) is None
    old = {**arrays, "surface.pinhole": arrays["surface.pinhole"][:5]}  # another layout
    assert OrganisedSurface.from_arrays(relief_frame.xyz_map, old) is None


def test_a_map_too_sparse_for_a_surface_is_returned_as_it_is(flat_frame):
    sparse = np.full_like(flat_frame.xyz_map, np.nan)
    sparse[5, 5:10] = flat_frame.xyz_map[5, 5:10]  # 5 pixels: no pinhole to fit, no surface
    frame = dataclasses.replace(flat_frame, xyz_map=sparse, points=sparse[5, 5:10])
    assert registrar().prepare(frame) is frame
    with pytest.raises(InputDataError, match="valid pixels"):
        registrar().dense.surfaces.surface(frame)  # the pair that needs it says so
