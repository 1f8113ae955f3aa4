"""The virtual FPP sensor: rig, renderer, scenes, trajectories, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data_path

from fpp_graph.errors import ConfigError, FppError, InputDataError
from frontend.fpp.sensor import FppSensor
from frontend.sim import (
    FppSimulator,
    RenderSettings,
    Scene,
    build_corridor,
    default_pattern_spec,
    default_rig,
    load_simulation,
    plane_scene,
    sphere_scene,
)
from frontend.sim.materials import ProceduralMaterial
from frontend.sim.parts import SurfacePart, box, load_mesh, make_doll
from frontend.sim.render import project_points
from frontend.sim.scenes import (
    CorridorConfig,
    TurntableConfig,
    build_turntable,
    frame_overlap,
    make_poster,
)


@pytest.fixture(scope="module")
def rig():
    return default_rig(preview=True)


@pytest.fixture(scope="module")
def spec():
    return default_pattern_spec()


@pytest.fixture(scope="module")
def plane_capture(rig, spec):
    sim = FppSimulator(rig, spec, plane_scene(0.5, tilt_deg=-7.0, albedo=0.8))
    return sim, sim.render(np.eye(4), frame_index=0)


def test_default_rig_matches_the_paper_sensor():
    full = default_rig()
    assert (full.camera.width, full.camera.height) == (1920, 1200)
    assert (full.projector.width, full.projector.height) == (912, 1140)
    assert 0.1 <= full.baseline_m <= 0.15
    # The projector's image centre meets the camera axis at the working distance (0.5 m).
    u, v, z = project_points(full.projector, full.T_projector_camera, np.array([[0.0, 0.0, 0.5]]))
    assert u[0] == pytest.approx((912 - 1) / 2, abs=15.0)
    assert v[0] == pytest.approx((1140 - 1) / 2, abs=25.0)
    preview = default_rig(preview=True)
    assert (preview.camera.width, preview.camera.height) == (640, 400)
    assert preview.camera.K[0, 0] == pytest.approx(full.camera.K[0, 0] / 3)


def test_rendered_plane_decodes_to_ground_truth(plane_capture, rig, spec):
    sim, frame = plane_capture
    assert frame.images.shape == (spec.image_count(), 400, 640)
    assert frame.images.dtype == np.uint8
    gt = frame.ground_truth
    assert gt.lit_mask.mean() > 0.8
    assert np.nanmin(gt.depth_m) > 0.4 and np.nanmax(gt.depth_m) < 0.6
    decoded = FppSensor(rig, spec).frame_from_images(0, 0.0, frame.images)
    ok = np.isfinite(decoded.xyz_map[..., 2]) & np.isfinite(gt.xyz_map_m[..., 2])
    assert ok.mean() > 0.8
    err = np.linalg.norm(decoded.xyz_map[ok] - gt.xyz_map_m[ok], axis=1)
    rms_mm = 1e3 * np.sqrt(np.mean(err**2))
    assert 0.02 < rms_mm < 0.2  # noise is there, and near the paper's 0.067 mm
    assert abs(np.mean(decoded.xyz_map[ok][:, 2] - gt.xyz_map_m[ok][:, 2])) < 2e-5  # no bias


def test_noise_is_reproducible_per_frame_index(plane_capture):
    sim, frame = plane_capture
    again = sim.render(np.eye(4), frame_index=0)
    other = sim.render(np.eye(4), frame_index=1)
    assert np.array_equal(again.images, frame.images)
    assert not np.array_equal(other.images, frame.images)


def test_noise_free_settings_give_noise_free_images(rig, spec):
    quiet = RenderSettings(read_noise_grey=0.0, shot_noise_gain=0.0)
    sim = FppSimulator(rig, spec, plane_scene(0.5, tilt_deg=-7.0), quiet)
    a, b = sim.render(np.eye(4), 0).images, sim.render(np.eye(4), 5).images
    assert np.array_equal(a, b)


def test_smooth_shading_removes_facets_from_the_texture(rig, spec):
    import cv2

    # a coarse white ball: flat triangle normals make the projector's irradiance step at every
    # edge; interpolated normals give a smooth shading over the same geometry
    ball = sphere_scene(0.45, radius_m=0.05, resolution=12)
    images = {}
    sensor = FppSensor(rig, spec)
    for smooth in (False, True):
        quiet = RenderSettings(read_noise_grey=0.0, shot_noise_gain=0.0, blur_sigma_px=0.0, smooth_shading=smooth)
        frame = FppSimulator(rig, spec, ball, quiet).render(np.eye(4), 0)
        images[smooth] = sensor.frame_from_images(0, 0.0, frame.images).texture.astype(np.float32)
        lit = frame.ground_truth.lit_mask
    inner = cv2.erode(lit.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    roughness = {k: float(np.abs(cv2.Laplacian(v, cv2.CV_32F))[inner].mean()) for k, v in images.items()}
    assert roughness[True] < 0.5 * roughness[False]
    # the same mean brightness: only the facets go
    assert abs(images[True][inner].mean() - images[False][inner].mean()) < 0.03 * images[False][inner].mean()


def test_occluder_casts_a_projector_shadow(rig, spec):
    plane = plane_scene(0.5, tilt_deg=0.0)
    blocker = box("blocker", [-0.03, -0.03, 0.38], [0.03, 0.03, 0.42], ProceduralMaterial())
    sim = FppSimulator(rig, spec, Scene(plane.parts + [blocker]))
    gt, _ = sim.ground_truth(np.eye(4))
    free, _ = FppSimulator(rig, spec, plane).ground_truth(np.eye(4))
    on_plane = np.abs(gt.depth_m - 0.5) < 1e-3
    shadowed = on_plane & ~gt.lit_mask & free.lit_mask
    # The projector sits to the camera's right, so the shadow falls on the plane left of the box.
    assert shadowed.sum() > 500
    cols = np.nonzero(shadowed)[1]
    assert np.median(cols) < 320
    # Camera frame points are exactly on the plane z = 0.5.
    assert np.nanmax(np.abs(gt.depth_m[on_plane] - 0.5)) < 1e-6


def test_sensor_inside_geometry_is_an_error(rig, spec):
    cube = box("cube", [-1, -1, -1], [1, 1, 1], ProceduralMaterial())
    sim = FppSimulator(rig, spec, Scene([cube]))
    with pytest.raises(InputDataError, match="inside or touching scene geometry"):
        sim.render(np.eye(4))


def test_textures_have_contrast_for_keypoints():
    pts = np.random.default_rng(0).uniform(-0.2, 0.2, (20000, 3))
    a = ProceduralMaterial(base=0.6, contrast=0.6, scale_m=0.02).albedo(pts)
    assert 0.0 <= a.min() and a.max() <= 1.0
    assert a.std() > 0.08
    poster = make_poster(1000)
    assert poster.std() > 0.1
    assert np.array_equal(poster, make_poster(1000))  # the look-alike poster repeats exactly
    doll = make_doll(0.22)
    assert len(doll) >= 10
    top = max(p.vertices[:, 2].max() for p in doll)
    assert top == pytest.approx(0.22, abs=0.01)


def test_turntable_protocol_trajectory():
    cfg = TurntableConfig()
    scene, poses, stamps = build_turntable(cfg)
    assert poses.shape == (39, 4, 4) and len(stamps) == 39
    np.testing.assert_allclose(poses[13], poses[0], atol=1e-12)  # each turn returns to its start
    np.testing.assert_allclose(poses[26 + 5], poses[5], atol=1e-12)
    target = np.array([0, 0, 0.5 * max(p.vertices[:, 2].max() for p in scene.parts)])
    for T in poses[:13]:
        to_target = target - T[:3, 3]
        assert np.linalg.norm(to_target) == pytest.approx(0.5)
        assert np.dot(T[:3, 2], to_target / np.linalg.norm(to_target)) == pytest.approx(1.0)
    # Consecutive views are 360/13 deg apart around the vertical axis.
    c = poses[:13, :2, 3]
    ang = np.degrees(np.diff(np.unwrap(np.arctan2(c[:, 1], c[:, 0]))))
    np.testing.assert_allclose(ang, 360 / 13, atol=1e-9)


def test_corridor_has_100_frames_overlap_and_revisits(rig, spec):
    cfg = CorridorConfig()
    scene, poses, _ = build_corridor(cfg)
    assert len(poses) >= 100
    names = [p.name for p in scene.parts]
    assert sum(n.startswith("poster") for n in names) >= 6 and any("door" in n for n in names)
    sim = FppSimulator(rig, spec, scene)
    K = rig.camera.K
    overlaps = []
    for k in (2, 8, 30):
        a, _ = sim.ground_truth(poses[k])
        b, _ = sim.ground_truth(poses[k + 1])
        overlaps.append(frame_overlap(a.xyz_map_m, poses[k], b.depth_m, poses[k + 1], K))
    assert 0.2 < np.mean(overlaps) < 0.5
    # A later pass sees the first frame's place again (a loop).
    later = [j for j in range(20, len(poses)) if np.linalg.norm(poses[j][:3, 3] - poses[0][:3, 3]) < 0.05 and poses[j][:3, 2] @ poses[0][:3, 2] > 0.99]
    assert later


def test_mesh_loading_errors(tmp_path):
    with pytest.raises(InputDataError, match="does not exist"):
        load_mesh(tmp_path / "missing.ply")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01 not a mesh at all")
    with pytest.raises(InputDataError, match="empty or not a"):
        load_mesh(garbage)
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    with pytest.raises(InputDataError, match="0 vertices"):
        load_mesh(empty)
    with pytest.raises(InputDataError, match="empty"):
        SurfacePart("nothing", np.zeros((0, 3)), np.zeros((0, 3), int))


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="zero frames"):
        load_simulation({"scene": "turntable", "turntable": {"turns": 0}}, preview=True)
    with pytest.raises(ConfigError, match="zero frames"):
        load_simulation({"scene": "corridor", "corridor": {"passes": 0}}, preview=True)
    with pytest.raises(ConfigError, match="unknown key"):
        load_simulation({"scene": "turntable", "turntabel": {}}, preview=True)
    with pytest.raises(ConfigError, match="views_per_turns"):
        load_simulation({"scene": "turntable", "turntable": {"views_per_turns": 3}}, preview=True)
    with pytest.raises(ConfigError, match="scene must be"):
        load_simulation({"scene": "garden"}, preview=True)
    with pytest.raises(InputDataError, match="does not exist"):
        load_simulation({"scene": "turntable", "turntable": {"object": str(tmp_path / "nope.obj")}}, preview=True)
    assert issubclass(ConfigError, FppError)


def test_bunny_turntable_renders_and_decodes(rig, spec):
    bunny = shared_data_path("meshes", "stanford-bunny.obj")
    setup = load_simulation({"scene": "turntable", "turntable": {"object": str(bunny), "up_axis": "y", "object_size_m": 0.2, "turns": 1, "views_per_turn": 2}}, preview=True)
    assert len(setup.poses_world_sensor) == 2
    lo, hi = setup.scene.bounds()
    sim = FppSimulator(setup.calibration, setup.spec, setup.scene, setup.settings)
    frame = sim.render(setup.poses_world_sensor[1], 1)
    decoded = FppSensor(setup.calibration, setup.spec).frame_from_images(1, 1.0, frame.images)
    assert decoded.metadata["valid_fraction"] > 0.1
    gt = frame.ground_truth.xyz_map_m
    ok = np.isfinite(decoded.xyz_map[..., 2]) & np.isfinite(gt[..., 2])
    err = np.linalg.norm(decoded.xyz_map[ok] - gt[ok], axis=1)
    assert np.median(err) < 1e-4


def test_vertex_colour_albedo_from_a_mesh_file(tmp_path):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.tile([[0.2, 0.2, 0.2]], (len(mesh.vertices), 1)))
    path = tmp_path / "grey_box.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)
    setup = load_simulation(
        {"scene": "turntable", "turntable": {"object": str(path), "object_size_m": 0.1, "texture": {"kind": "vertex_colors"}, "turns": 1, "views_per_turn": 1, "table_radius_m": 0}},
        preview=True,
    )
    sim = FppSimulator(setup.calibration, setup.spec, setup.scene, setup.settings)
    gt, _ = sim.ground_truth(setup.poses_world_sensor[0])
    hit = np.isfinite(gt.depth_m)
    assert hit.sum() > 1000
    np.testing.assert_allclose(gt.albedo[hit], 0.2, atol=1e-3)
    assert np.all(gt.albedo[~hit] == 0)


def test_scene_definition_keeps_mesh_paths_relative_to_their_file(tmp_path):
    from frontend.demo import scene_definition

    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "mine.yaml").write_text("scene: turntable\nturntable:\n  object: meshes/thing.obj\n")
    scene = scene_definition(str(folder / "mine.yaml"), seed=4)
    assert scene["turntable"]["object"] == str((folder / "meshes" / "thing.obj").resolve())
    assert scene["render"]["seed"] == 4
    assert scene_definition("turntable")["turntable"].get("object", "doll") == "doll"  # the built-in doll is left alone
