"""Map fusion: voxel averaging, TSDF mesh, re-fusion and the PLY writers."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import open3d as o3d
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.evaluation.metrics import map_accuracy
from fpp_graph.fusion.ply import write_mesh_ply, write_point_cloud_ply
from fpp_graph.fusion.tsdf_mesh import canonical_mesh, tsdf_block_voxels
from fpp_graph.fusion.voxel_map import (
    FusedMap,
    VoxelMapFuser,
    grazing_weights,
    intrinsics_of,
    render_depth,
)
from fpp_graph.geometry import compose, finite_points, make_pose
from fpp_graph.types import CameraModel, Frame, MapFuser

CENTRE = np.array([0.0, 0.0, 1.0])
RADIUS = 0.2
W, H, F = 320, 240, 400.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, -1.0, 0.0)):
    """T_world_sensor of a camera at ``eye`` looking at ``target`` (z forward, y down)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return make_pose(np.column_stack([x, np.cross(z, x), z]), eye)


def sphere_frame(fid, T_world_sensor, noise_m, rng, with_K=True, K_cam=K, size=(W, H)):
    """Organised xyz map of the sphere seen by a pinhole camera; depth noise along the ray."""
    w, h = size
    v, u = np.mgrid[0:h, 0:w].astype(float)
    d = np.stack([(u - K_cam[0, 2]) / K_cam[0, 0], (v - K_cam[1, 2]) / K_cam[1, 1], np.ones_like(u)], -1)
    c = T_world_sensor[:3, :3].T @ (CENTRE - T_world_sensor[:3, 3])
    a = (d**2).sum(-1)
    b = -2.0 * d @ c
    disc = b**2 - 4 * a * (c @ c - RADIUS**2)
    t = (-b - np.sqrt(np.where(disc > 0, disc, np.nan))) / (2 * a)
    t = t + noise_m * rng.standard_normal(t.shape)  # z noise (d has z = 1)
    xyz = d * t[..., None]
    valid = np.isfinite(t)
    texture = (u / w * 255).astype(np.uint8)
    return Frame(
        fid, float(fid), xyz[valid], colors=np.repeat(texture[valid][:, None] / 255.0, 3, 1),
        xyz_map=xyz, texture=texture, camera=CameraModel(K_cam, w, h) if with_K else None,
    )


def ring_of_views(n=7, spread_rad=0.6, distance_m=0.6):
    return [look_at(CENTRE + distance_m * np.array([np.sin(a), 0.1, -np.cos(a)]), CENTRE) for a in np.linspace(-spread_rad, spread_rad, n)]


def sphere_mesh():
    mesh = o3d.geometry.TriangleMesh.create_sphere(RADIUS, 200)
    mesh.translate(CENTRE)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def radial_error(points):
    return np.linalg.norm(points - CENTRE, axis=1) - RADIUS


@pytest.fixture(scope="module")
def views():
    rng = np.random.default_rng(7)
    poses = ring_of_views()
    frames = [sphere_frame(i, T, 0.0003, rng) for i, T in enumerate(poses)]
    return frames, dict(enumerate(poses))


@pytest.fixture(scope="module")
def fused(views):
    frames, poses = views
    return VoxelMapFuser(0.002, 0.002, mesh=True).fuse(frames, poses)


def test_fuser_is_a_map_fuser():
    assert isinstance(VoxelMapFuser(0.001, 0.002, mesh=False), MapFuser)


def test_fused_points_lie_on_the_surface(views, fused):
    frames, poses = views
    V, Fc = sphere_mesh()
    acc = map_accuracy(fused.points_world_m, V, Fc)
    assert acc.count == fused.num_points > 10000
    assert acc.rms_m < 0.0003  # below the 0.3 mm per-point noise
    # the mesh-based figure agrees with the analytic distance to the sphere
    assert acc.rms_m == pytest.approx(np.sqrt(np.mean(radial_error(fused.points_world_m) ** 2)), abs=2e-5)
    # every point counts, with weight cos(normal, ray) in (0, 1]
    assert 0.3 * sum(f.num_points for f in frames) < fused.weights.sum() < sum(f.num_points for f in frames)
    plain = VoxelMapFuser(0.002, 0.002, mesh=False, grazing_weight=False).fuse(frames, poses)
    assert plain.weights.sum() == sum(f.num_points for f in frames)
    assert fused.colors.shape == fused.points_world_m.shape
    assert 0.0 <= fused.colors.min() and fused.colors.max() <= 1.0


def test_weighted_average_reduces_noise():
    # many views from nearly one place: each 6 mm voxel averages ~20 points of 0.2 mm noise.
    # (Noise close to the voxel size averages less: voxels the surface only grazes keep
    # one-sided samples.)
    rng = np.random.default_rng(3)
    poses = ring_of_views(n=8, spread_rad=0.05)
    frames = [sphere_frame(i, T, 0.0002, rng, size=(160, 120), K_cam=K * [[0.5], [0.5], [1]]) for i, T in enumerate(poses)]
    raw = np.vstack([f.points @ T[:3, :3].T + T[:3, 3] for f, T in zip(frames, poses, strict=True)])
    fused = VoxelMapFuser(0.006, 0.006, mesh=False).fuse(frames, dict(enumerate(poses)))
    rms_raw = np.sqrt(np.mean(radial_error(raw) ** 2))
    r = radial_error(fused.points_world_m)
    assert fused.mesh_vertices is None
    assert rms_raw == pytest.approx(0.00015, rel=0.2)  # z noise seen along the sphere's normal
    assert fused.weights.mean() > 15
    assert np.sqrt(np.mean(r**2)) < 0.45 * rms_raw
    assert np.sqrt(np.average(r**2, weights=fused.weights)) < 0.3 * rms_raw


def test_voxel_mean_is_exact():
    # two frames, hand-made points: the voxel holds the weighted mean of what fell in it
    a = Frame(0, 0.0, np.array([[0.0101, 0.0101, 0.0101], [0.0109, 0.0109, 0.0109]]), colors=np.array([[1.0, 0, 0], [0, 0, 1.0]]))
    b = Frame(1, 1.0, np.array([[0.0, 0.0, 0.0]]), colors=np.array([[0.0, 1.0, 0.0]]))
    fuser = VoxelMapFuser(0.001, 0.001, mesh=False)
    fuser.integrate(a, np.eye(4))
    fuser.integrate(b, make_pose(translation=[0.0105, 0.0105, 0.0105]), point_weights=np.array([2.0]))
    out = fuser.result()
    assert out.num_points == 1
    np.testing.assert_allclose(out.points_world_m[0], [(0.0101 + 0.0109 + 2 * 0.0105) / 4] * 3, atol=1e-15)
    np.testing.assert_allclose(out.colors[0], [0.25, 0.5, 0.25], atol=1e-15)
    assert out.weights[0] == 4.0


def test_streaming_matches_batch_and_merges(views):
    frames, poses = views
    batch = VoxelMapFuser(0.002, 0.002, mesh=False).fuse(frames, poses)
    stream = VoxelMapFuser(0.002, 0.002, mesh=False)
    for f in frames:
        stream.integrate(f, poses[f.id])
        stream.result()  # intermediate results force merges along the way
    out = stream.result()
    np.testing.assert_allclose(out.points_world_m, batch.points_world_m, atol=1e-15)
    np.testing.assert_array_equal(out.weights, batch.weights)


def test_tsdf_mesh_is_close_to_the_surface(fused):
    assert fused.mesh_vertices is not None and len(fused.mesh_triangles) > 10000
    r = radial_error(fused.mesh_vertices)
    assert np.sqrt(np.mean(r**2)) < 0.0008  # 2 mm TSDF voxels
    assert abs(r.mean()) < 0.0002  # no systematic offset (would mean a wrong extrinsic)
    assert fused.mesh_vertex_colors.shape == fused.mesh_vertices.shape
    # texture runs left to right in each image; colours carry through, not constant grey
    assert fused.mesh_vertex_colors.std() > 0.05


@pytest.mark.parametrize(("truncation_m", "voxel_m", "block"), [
    (0.008, 0.002, 8),  # FPP defaults: a band of 8 voxels
    (0.04, 0.01, 8),  # RGB-D defaults
    (0.005, 0.002, 8),  # a band of 5 voxels: not below 8
    (0.012, 0.002, 12),
    (0.016, 0.001, 16),  # a band of 32 voxels: not above Open3D's 16
])
def test_tsdf_blocks_are_as_thick_as_the_band(truncation_m, voxel_m, block):
    assert tsdf_block_voxels(truncation_m, voxel_m) == block
    if truncation_m == 4 * voxel_m:  # the band the fuser makes of its voxel
        fuser = VoxelMapFuser(voxel_m, voxel_m, mesh=True)
        assert fuser.tsdf_block_voxels == block and fuser.tsdf_block_count * block**3 >= 1000 * 16**3


@pytest.mark.parametrize(("truncation_m", "voxel_m"), [(0.0, 0.002), (0.008, 0.0), (float("nan"), 0.002), (0.008, -1.0)])
def test_tsdf_blocks_of_a_bad_band_are_refused(truncation_m, voxel_m):
    with pytest.raises(InputDataError, match="truncation and voxel"):
        tsdf_block_voxels(truncation_m, voxel_m)


def test_band_thick_blocks_mesh_the_same_surface(views, fused):
    """Blocks of 16^3 voxels (Open3D's default) leave the surface where the band-thick 8^3 put it:
    only the free space each view sets in front of it differs."""
    frames, poses = views
    wide = VoxelMapFuser(0.002, 0.002, mesh=True)
    wide.tsdf_block_voxels, wide.tsdf_block_count = 16, 1000
    coarse = wide.fuse(frames, poses)
    assert fused.mesh_vertices is not None and coarse.mesh_vertices is not None
    from scipy.spatial import cKDTree

    distance_m, _ = cKDTree(coarse.mesh_vertices).query(fused.mesh_vertices)
    assert np.mean(distance_m < 1e-9) > 0.9  # most vertices exactly the same
    assert np.percentile(distance_m, 99) < 0.001  # half a voxel (0.47 mm here)
    assert abs(len(fused.mesh_vertices) - len(coarse.mesh_vertices)) < 0.01 * len(coarse.mesh_vertices)  # 0.5 % here
    r_fine, r_coarse = radial_error(fused.mesh_vertices), radial_error(coarse.mesh_vertices)
    assert abs(np.sqrt(np.mean(r_fine**2)) - np.sqrt(np.mean(r_coarse**2))) < 2e-5  # 0.453 against 0.458 mm here


def test_tsdf_hash_map_grown_by_copy_meshes_what_an_ample_one_does(views, fused, caplog):
    # one block to start with: the map grows (by a new grid and a copy of its blocks) several
    # times while the views are integrated; the mesh is the one of a map that never grew
    frames, poses = views
    with caplog.at_level("DEBUG", logger="fpp_graph.fusion.tsdf_mesh"):
        fuser = VoxelMapFuser(0.002, 0.002, mesh=True, tsdf_block_count=1)
        grown = fuser.fuse(frames, poses)
    assert sum("TSDF hash map grown" in r.getMessage() for r in caplog.records) >= 3
    ample = VoxelMapFuser(0.002, 0.002, mesh=True, tsdf_block_count=100_000).fuse(frames, poses)
    assert len(fused.mesh_triangles) > 1000
    for got, expected in ((grown, fused), (ample, fused)):
        np.testing.assert_array_equal(got.mesh_vertices, expected.mesh_vertices)
        np.testing.assert_array_equal(got.mesh_triangles, expected.mesh_triangles)
        np.testing.assert_array_equal(got.mesh_vertex_colors, expected.mesh_vertex_colors)


def test_canonical_mesh_does_not_depend_on_the_order_it_was_listed_in(rng):
    """Open3D lists the same mesh in another order each run; the canonical order is the mesh's own:
    any listing of its vertices and triangles gives the same arrays, each triangle keeps its
    winding, exact duplicate vertices merge and triangles that collapse or repeat go."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.1, 20)
    V, T = np.asarray(sphere.vertices), np.asarray(sphere.triangles).astype(np.int64)
    C = rng.uniform(0, 1, V.shape)
    reference = canonical_mesh(V, T, C)
    assert np.all(np.diff(np.lexsort(reference[0].T[::-1])) > 0)  # sorted by x, then y, then z
    for _ in range(3):
        p = rng.permutation(len(V))
        rank = np.argsort(p)
        T_listed = np.roll(rank[T], rng.integers(0, 3), axis=1)[rng.permutation(len(T))]  # a rotation keeps the winding
        shuffled = canonical_mesh(V[p], T_listed, C[p])
        assert all(np.array_equal(a, b) for a, b in zip(reference, shuffled, strict=True))
    # the winding: the normal of each triangle points the same way (outwards) before and after
    Vc, Tc, _ = reference
    normals = np.cross(Vc[Tc[:, 1]] - Vc[Tc[:, 0]], Vc[Tc[:, 2]] - Vc[Tc[:, 0]])
    assert np.all(np.einsum("ij,ij->i", normals, Vc[Tc].mean(axis=1)) > 0)
    # a duplicate vertex (same place and colour) merges; a triangle on both copies collapses; a repeated one goes
    V2, C2 = np.vstack([V, V[:1]]), np.vstack([C, C[:1]])
    T2 = np.vstack([T, [[0, len(V), 1]], T[:1]])
    merged = canonical_mesh(V2, T2, C2)
    assert len(merged[0]) == len(V) and len(merged[1]) == len(T)
    empty = canonical_mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3)))
    assert all(len(a) == 0 for a in empty)


def test_two_fusions_of_the_same_frames_give_the_same_mesh(views, fused):
    frames, poses = views
    again = VoxelMapFuser(0.002, 0.002, mesh=True).fuse(frames, poses)
    for a, b in ((fused.mesh_vertices, again.mesh_vertices), (fused.mesh_triangles, again.mesh_triangles), (fused.mesh_vertex_colors, again.mesh_vertex_colors)):
        assert np.array_equal(a, b)


def test_intrinsics_are_estimated_without_metadata(views):
    frames, _ = views
    f = frames[0]
    bare = Frame(f.id, f.timestamp, f.points, f.colors, f.xyz_map, f.texture)
    np.testing.assert_allclose(intrinsics_of(bare), K, atol=1e-3)
    depth, rgb = render_depth(bare, intrinsics_of(bare))
    valid = np.isfinite(f.xyz_map[..., 2])
    np.testing.assert_allclose(depth[valid], f.xyz_map[..., 2][valid], atol=1e-12)
    assert np.all(depth[~valid] == 0)
    np.testing.assert_array_equal(rgb[..., 1][valid], f.texture[valid])


def test_refuse_after_pose_update_moves_the_map(views):
    frames, poses = views
    fuser = VoxelMapFuser(0.002, 0.003, mesh=True)
    first = fuser.fuse(frames, poses)
    shift = make_pose(translation=[0.05, 0.0, 0.0])
    moved = fuser.fuse(frames, {k: compose(shift, T) for k, T in poses.items()})
    assert moved.num_points == pytest.approx(first.num_points, rel=0.05)
    centre_moved = CENTRE + [0.05, 0.0, 0.0]
    r = np.linalg.norm(moved.points_world_m - centre_moved, axis=1) - RADIUS
    assert np.sqrt(np.mean(r**2)) < 0.0004
    rm = np.linalg.norm(moved.mesh_vertices - centre_moved, axis=1) - RADIUS
    assert np.sqrt(np.mean(rm**2)) < 0.0012


def test_fused_map_pickles(fused):
    back = pickle.loads(pickle.dumps(fused))
    assert isinstance(back, FusedMap)
    np.testing.assert_array_equal(back.points_world_m, fused.points_world_m)
    np.testing.assert_array_equal(back.mesh_triangles, fused.mesh_triangles)


def test_point_cloud_ply_round_trip_is_exact(tmp_path, rng):
    points = rng.normal(size=(1000, 3)) * 3.0 + 1e3 * rng.random()
    colors = rng.random((1000, 3))
    path = tmp_path / "sub" / "map.ply"
    write_point_cloud_ply(path, points, colors)
    cloud = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(cloud.points), points)  # doubles, bit for bit
    np.testing.assert_allclose(np.asarray(cloud.colors), np.round(colors * 255) / 255, atol=1e-12)
    assert [p.name for p in path.parent.iterdir()] == ["map.ply"]  # no temp file left


def test_mesh_ply_round_trip_is_exact(tmp_path, fused):
    path = tmp_path / "mesh.ply"
    write_mesh_ply(path, fused.mesh_vertices, fused.mesh_triangles, fused.mesh_vertex_colors)
    mesh = o3d.io.read_triangle_mesh(str(path))
    np.testing.assert_array_equal(np.asarray(mesh.vertices), fused.mesh_vertices)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), fused.mesh_triangles)
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors), np.round(fused.mesh_vertex_colors * 255) / 255, atol=1e-12)


def test_empty_map_writes_a_valid_ply(tmp_path):
    out = VoxelMapFuser(0.001, 0.002, mesh=True).result()
    assert out.num_points == 0 and len(out.mesh_vertices) == 0
    write_point_cloud_ply(tmp_path / "m.ply", out.points_world_m, out.colors)
    assert (tmp_path / "m.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")


def test_bad_input_is_reported(views, tmp_path):
    frames, poses = views
    with pytest.raises(InputDataError, match=r"no pose for frames \[6\]"):
        VoxelMapFuser(0.002, 0.002, mesh=False).fuse(frames, {k: v for k, v in poses.items() if k != 6})
    with pytest.raises(InputDataError, match="voxel_size_m must be a positive"):
        VoxelMapFuser(0.0, 0.002, mesh=False)
    far = Frame(0, 0.0, np.array([[5000.0, 0.0, 0.0]]))
    with pytest.raises(InputDataError, match="beyond the .* voxel grid"):
        VoxelMapFuser(0.001, 0.002, mesh=False).integrate(far, np.eye(4))
    with pytest.raises(InputDataError, match="2 points but 3 weights"):
        VoxelMapFuser(0.001, 0.002, mesh=False).integrate(
            Frame(0, 0.0, np.zeros((2, 3))), np.eye(4), point_weights=np.ones(3)
        )
    with pytest.raises(InputDataError, match="colors shape"):
        write_point_cloud_ply(tmp_path / "x.ply", np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(InputDataError, match="triangle indices out of range"):
        write_mesh_ply(tmp_path / "x.ply", np.zeros((3, 3)), np.array([[0, 1, 3]]))
    assert not (tmp_path / "x.ply").exists()
    with pytest.raises(InputDataError, match="3x3 pinhole matrix"):
        CameraModel(np.array([[1, 0], [0, 1]]), 4, 4)


def test_frame_without_xyz_map_is_left_out_of_the_mesh(caplog):
    fuser = VoxelMapFuser(0.001, 0.002, mesh=True)
    fuser.integrate(Frame(0, 0.0, np.zeros((1, 3))), np.eye(4))
    assert fuser.frames_meshed == 0 and "no xyz_map" in caplog.text
    assert fuser.result().num_points == 1


# -- the depth-discontinuity / mixed-pixel filter of the FPP front-end --------------------------
def _step_scene_xyz(rng, noise_m=5e-5):
    """A wall at 0.6 m, a box face at 0.45 m in front of it, mixed pixels on the box's edge.

    Returns the xyz map, the mask of mixed pixels and the mask of the tilted (80 deg) patch.
    """
    h, w, f = 120, 160, 400.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / f, (v - h / 2) / f
    z = np.full((h, w), 0.6)
    box = (u >= 40) & (u < 90) & (v >= 30) & (v < 80)
    z[box] = 0.45
    # a patch seen at about 85 degrees from the ray: depth grows by z tan(85)/f per column
    tilt = (u >= 110) & (u < 150) & (v >= 30) & (v < 80)
    z[tilt] = 0.6 * (1 + np.tan(np.radians(85)) / f) ** (u[tilt] - 110)
    mixed = np.zeros((h, w), bool)
    mixed[30:80, 90] = True  # the column right of the box: half box, half wall
    z[mixed] = 0.525
    z += rng.normal(0, noise_m, z.shape)
    xyz = np.dstack([x * z, y * z, z])
    xyz[:5, :] = np.nan  # a shadow band at the top
    return xyz, f, mixed, tilt, box


def test_edge_filter_removes_mixed_pixels_and_grazing_surfaces(rng):
    from frontend.fpp.sensor import edge_filter_mask

    xyz, f, mixed, tilt, box = _step_scene_xyz(rng)
    keep = edge_filter_mask(xyz, f, max_angle_deg=75.0)
    assert not keep[mixed].any()  # every mixed pixel goes
    assert not keep[tilt].any()
    assert not keep[:6, :].any()  # the shadow band and the ring of pixels next to it
    interior_box = np.zeros_like(box)
    interior_box[32:78, 42:88] = True
    assert keep[interior_box].all()  # the box face away from its edges stays
    wall = np.zeros_like(box)
    wall[90:115, 5:150] = True
    assert keep[wall].all()  # so does the wall (seen head on)
    # the discontinuity costs at most a 1-pixel ring on each side
    lost_on_box = box & ~keep
    assert lost_on_box.sum() <= 2 * (50 + 50) + 4


def test_edge_filter_keeps_a_moderately_tilted_plane(rng):
    from frontend.fpp.sensor import edge_filter_mask

    h, w, f = 60, 80, 300.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / f, (v - h / 2) / f
    # plane through (0, 0, 0.5) with normal at 60 degrees to the optical axis
    n = np.array([np.sin(np.radians(60)), 0.0, -np.cos(np.radians(60))])
    z = 0.5 * n[2] / (n[0] * x + n[1] * y + n[2])  # ray (x, y, 1) z meets n . p = n . (0, 0, 0.5)
    xyz = np.dstack([x * z, y * z, z]) + rng.normal(0, 3e-5, (h, w, 3))
    keep = edge_filter_mask(xyz, f, max_angle_deg=75.0)
    assert keep[1:-1, 1:-1].all()


def test_grazing_weights_follow_the_angle_to_the_ray():
    from fpp_graph.fusion.voxel_map import grazing_weights

    # a plane z = 0.5 + x tan(60 deg): its normal makes 60 deg with the optical axis
    h, w, f = 40, 60, 200.0
    v, u = np.mgrid[0:h, 0:w].astype(float)
    x, y = (u - w / 2) / f, (v - h / 2) / f
    z = 0.5 / (1 - x * np.tan(np.radians(60)))
    xyz = np.dstack([x * z, y * z, z])
    xyz[0, 0] = np.nan
    g = grazing_weights(xyz)
    rays = xyz / np.linalg.norm(xyz, axis=2, keepdims=True)
    n = np.array([-np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))])
    expected = np.abs(rays @ n)
    ok = np.isfinite(expected)
    ok[:2, :2] = False  # next to the NaN pixel the normal is unknown (weight 1)
    np.testing.assert_allclose(g[ok], expected[ok], atol=1e-6)
    assert g[0, 1] == 1.0 and g.min() >= 0.05


def test_surface_smoothing_removes_the_voxel_sorting_of_noise():
    # 0.2 mm noise on 6 mm voxels seen from nearly one place: plain voxel means keep part of the
    # noise (points are sorted into voxels by their error); the local quadric fit averages
    # across voxels without flattening the 0.2 m sphere (noise-free: no bias added)
    out = {}
    for noise in (0.0, 0.0002):
        rng = np.random.default_rng(3)
        poses = ring_of_views(n=8, spread_rad=0.05)
        frames = [sphere_frame(i, T, noise, rng, size=(160, 120), K_cam=K * [[0.5], [0.5], [1]]) for i, T in enumerate(poses)]
        for smooth in (False, True):
            fused = VoxelMapFuser(0.006, 0.006, mesh=False, surface_smoothing=smooth).fuse(frames, dict(enumerate(poses)))
            out[noise, smooth] = np.sqrt(np.mean(radial_error(fused.points_world_m) ** 2))
    assert out[0.0, True] < out[0.0, False] + 5e-6  # no curvature bias (both ~12 um of voxel sampling)
    assert out[0.0002, True] < 0.5 * out[0.0002, False]


def test_surface_smoothing_leaves_isolated_points_and_edges():
    from fpp_graph.fusion.voxel_grid import project_to_local_planes, voxel_keys

    pts = np.array([[0.0105, 0.0105, 0.0105], [0.0505, 0.0505, 0.0505]])
    keys = voxel_keys(pts, 0.001)
    order = np.argsort(keys)
    moved = project_to_local_planes(keys[order], pts[order], np.ones(2), 0.001)
    np.testing.assert_array_equal(moved, pts[order])


@pytest.mark.parametrize("rows_per_pass", [1, 97, 1000])
def test_surface_smoothing_in_passes_of_rows_is_one_pass_bit_for_bit(rng, rows_per_pass, monkeypatch):
    # a chunk's voxels are fitted a cache-sized pass at a time: each voxel's sums are its own, so
    # any pass size moves every voxel exactly as one pass does (a curved, noisy sheet with holes,
    # and edge voxels that keep their mean)
    from fpp_graph.fusion import voxel_grid

    u, v = np.meshgrid(np.arange(60), np.arange(50))
    pts = np.column_stack([u.ravel() * 1e-3, v.ravel() * 1e-3, 0.02 * np.sin(u.ravel() / 15.0) + rng.normal(0, 1e-4, u.size)])
    pts = pts[rng.random(len(pts)) > 0.05]
    keys = voxel_grid.voxel_keys(pts, 0.001)
    order = np.argsort(keys, kind="stable")
    keys, pts = keys[order], pts[order] + rng.uniform(-3e-4, 3e-4, pts.shape)
    weights = rng.uniform(0.5, 2.0, len(pts))
    one_pass = voxel_grid.project_to_local_planes(keys, pts, weights, 0.001)
    monkeypatch.setattr(voxel_grid, "ROWS_PER_PASS", rows_per_pass)
    np.testing.assert_array_equal(voxel_grid.project_to_local_planes(keys, pts, weights, 0.001), one_pass)
    assert np.count_nonzero(np.any(one_pass != pts, axis=1)) > 0.3 * len(pts)  # the fits moved many voxels (1319 of 2837)


def test_neighbour_search_finds_what_a_search_per_offset_finds(rng):
    # 9 searches (one per z column) against 27: the same pairs in the same order, for a dense
    # block, scattered voxels with gaps in their columns, and queries at both ends of the keys
    from fpp_graph.fusion.voxel_grid import _KEY_BITS, _neighbour_indices, voxel_keys

    def per_offset(keys, query):
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    target = query + ((dx << (2 * _KEY_BITS)) + (dy << _KEY_BITS) + dz)
                    pos = np.minimum(np.searchsorted(keys, target), len(keys) - 1)
                    i = np.flatnonzero(keys[pos] == target)
                    yield i, pos[i]

    block = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    scattered = rng.integers(-6, 6, (400, 3))
    for voxels in (block, scattered, np.array([[0, 0, 0]])):
        keys = np.unique(voxel_keys(voxels + 0.5, 1.0))
        for query in (keys, keys[[0, -1]], keys[::3]):
            ours, theirs = list(_neighbour_indices(keys, query)), list(per_offset(keys, query))
            assert len(ours) == 27
            for (i, j), (k, m) in zip(ours, theirs, strict=True):
                np.testing.assert_array_equal(i, k)
                np.testing.assert_array_equal(j, m)


def test_surface_screen_keeps_what_eigh_alone_calls_a_surface(rng):
    # planes, lines, blobs, neighbourhoods at the flatness bound, repeated eigenvalues and a zero
    # matrix: the screened selection and eigenvectors are those of eigh on all of them
    from fpp_graph.fusion.voxel_grid import _surface_neighbourhoods

    rotations = np.linalg.qr(rng.normal(size=(3000, 3, 3)))[0]
    spectra = np.concatenate([
        rng.uniform(0.01, 1.0, (500, 3)),  # blobs
        np.column_stack([rng.uniform(0, 1e-3, 500), rng.uniform(0.1, 1, 500), rng.uniform(0.1, 1, 500)]),  # planes
        np.column_stack([rng.uniform(0, 1e-9, 500), rng.uniform(0, 1e-8, 500), rng.uniform(0.1, 1, 500)]),  # lines
        np.column_stack([np.full(500, 0.05), np.ones(500), np.ones(500)]) * rng.uniform(0.98, 1.02, (500, 1)) ** [[1, 0, 0]],  # at the bound
        np.column_stack([np.full(500, 0.3), np.full(500, 0.3), rng.uniform(0.3, 1, 500)]),  # repeated
        np.column_stack([rng.uniform(0, 0.1, 500), np.full(500, 1.0), np.full(500, 1.0)]),  # repeated largest
    ])
    cov = np.einsum("nab,nb,ncb->nac", rotations, spectra, rotations)
    cov = np.concatenate([cov, np.zeros((1, 3, 3))])
    idx, vectors = _surface_neighbourhoods(cov, 0.05)
    values, expected_vectors = np.linalg.eigh(cov)
    expected = np.flatnonzero(values[:, 0] <= 0.05 * np.maximum(values[:, 1], 1e-30))
    np.testing.assert_array_equal(idx, expected)
    np.testing.assert_array_equal(vectors, expected_vectors[expected])
    assert 900 < len(expected) < 2200  # the cases straddle the bound


def test_render_depth_keeps_the_nearest_point_where_two_land_on_one_pixel():
    # a map that is not its camera's own pinhole grid (a distorted lens): pixel (0, 1)'s point
    # projects onto pixel (0, 0) as well, nearer; the z-buffer keeps the nearer one there
    K2 = np.array([[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 1.0]])
    xyz = np.full((2, 2, 3), np.nan)
    xyz[0, 0] = [0.0, 0.0, 2.0]
    xyz[0, 1] = [0.0, 0.0, 1.0]  # same ray as (0, 0), nearer
    xyz[1, 1] = [0.01, 0.01, 1.0]  # on its own pixel
    texture = np.array([[10, 20], [30, 40]], dtype=np.uint8)
    frame = Frame(0, 0.0, xyz[np.isfinite(xyz[..., 2])], None, xyz, texture)
    depth, rgb = render_depth(frame, K2)
    np.testing.assert_allclose(depth, [[1.0, 0.0], [0.0, 1.0]])
    assert rgb[0, 0, 0] == 20 and rgb[1, 1, 0] == 40 and rgb[0, 1, 0] == 0
    assert rgb.flags.c_contiguous and np.all(rgb == rgb[..., :1])  # grey in all three channels
    # RGB colours per point (no texture) travel with their point through the z-buffer as well
    colors = np.array([[0.2, 0.4, 0.6], [1.0, 0.0, 0.5], [0.0, 1.0, 0.0]])
    coloured = Frame(0, 0.0, xyz[np.isfinite(xyz[..., 2])], colors, xyz, None)
    depth_c, rgb_c = render_depth(coloured, K2)
    np.testing.assert_array_equal(depth_c, depth)
    np.testing.assert_array_equal(rgb_c[0, 0], [255, 0, 128])
    np.testing.assert_array_equal(rgb_c[1, 1], [0, 255, 0])
    assert not rgb_c[0, 1].any() and not rgb_c[1, 0].any()


def test_points_beyond_max_depth_stay_out_of_map_and_mesh_and_are_counted(rng):
    # the sphere's near cap is at z = 0.8 m: a 0.9 m limit keeps only the cap (each map sees the
    # frame twice: the mesh needs a TSDF weight above 1)
    frame = sphere_frame(0, np.eye(4), 0.0, rng)
    z = frame.points[:, 2]
    full = VoxelMapFuser(0.004, 0.004, mesh=True)
    near = VoxelMapFuser(0.004, 0.004, mesh=True, max_depth_m=0.9)
    for fuser in (full, near, full, near):
        fuser.integrate(frame, np.eye(4))
    assert near.points_beyond_max_depth == 2 * int(np.count_nonzero(z > 0.9)) > 0
    assert full.points_beyond_max_depth == 0
    kept, every = near.result(), full.result()
    assert kept.points_world_m[:, 2].max() <= 0.9 + 0.004
    assert 0 < len(kept.points_world_m) < len(every.points_world_m)
    assert every.mesh_vertices[:, 2].max() > 0.92
    assert kept.mesh_vertices[:, 2].max() <= 0.9 + 0.016 + 0.004  # TSDF: its truncation band past the limit at most
    with pytest.raises(InputDataError, match="max_depth_m"):
        VoxelMapFuser(0.004, 0.004, mesh=False, max_depth_m=0.0)


def test_rgbd_fusion_range_is_where_kinect_noise_reaches_the_truncation():
    from fpp_graph.config import Config, config_from_dict
    from frontend.rgbd.source import KINECT_DEPTH_SIGMA_PER_M2, RgbdSource

    resolved = RgbdSource.resolve_config(Config())
    depth_m = resolved.fusion.max_depth_m
    assert KINECT_DEPTH_SIGMA_PER_M2 * depth_m**2 == pytest.approx(4 * resolved.fusion.tsdf_voxel_m)
    assert 5.0 < depth_m < 5.5
    assert RgbdSource.resolve_config(config_from_dict({"fusion": {"max_depth_m": 3.0}})).fusion.max_depth_m == 3.0
    assert Config().fusion.max_depth_m is None  # FPP: no limit


def test_fusion_on_worker_processes_gives_the_same_map(views, tmp_path):
    # fuse_map with an executor: each keyframe's share (voxel sums) is prepared in a worker
    # process and folded in in keyframe order, the smoothing runs there by chunks, and a worker
    # makes the mesh; the map, the mesh and the "before" plot samples equal the one-process fusion's
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from types import SimpleNamespace

    from fpp_graph.config import load_config
    from fpp_graph.slam.frame_store import FrameStore
    from fpp_graph.slam.map_fusion import fuse_map
    from fpp_graph.types import ParallelMapFuser

    frames, poses = views
    store = FrameStore(tmp_path / "frames")
    for f in frames:
        store.put(f)
    store = FrameStore.open(tmp_path / "frames")  # both fusions read the stored frames
    result = SimpleNamespace(keyframe_ids=[f.id for f in frames], poses_world_sensor=poses)
    config = load_config(None)
    serial_samples, parallel_samples = {}, {}
    serial_fuser = VoxelMapFuser(0.002, 0.002, mesh=True)
    assert isinstance(serial_fuser, ParallelMapFuser)
    (tmp_path / "serial").mkdir()
    (tmp_path / "parallel").mkdir()
    serial = fuse_map(tmp_path / "serial", result, store, config, fuser=serial_fuser, plot_samples=serial_samples)
    class CountingExecutor:
        def __init__(self, pool):
            self.pool, self.tasks = pool, []

        def submit(self, fn, *args):
            self.tasks.append(fn.__name__)
            return self.pool.submit(fn, *args)

    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        executor = CountingExecutor(pool)
        parallel = fuse_map(tmp_path / "parallel", result, store, config, fuser=VoxelMapFuser(0.002, 0.002, mesh=True),
                            plot_samples=parallel_samples, executor=executor)
    # the mesh made by one task on a worker, each keyframe prepared there, then the surface
    # smoothing's chunks of 50 000 voxels
    chunks = -(-serial.num_points // 50_000)
    assert chunks >= 2 and executor.tasks == ["mesh_keyframes"] + ["prepare_for_fusion_task"] * len(frames) + ["project_chunk_task"] * chunks
    np.testing.assert_array_equal(parallel.points_world_m, serial.points_world_m)
    np.testing.assert_array_equal(parallel.weights, serial.weights)
    # the worker wrote the mesh (its arrays stay there): the same file, byte for byte
    assert parallel.mesh_vertices is None and len(serial.mesh_triangles) > 10000
    assert (tmp_path / "parallel" / "mesh.ply").read_bytes() == (tmp_path / "serial" / "mesh.ply").read_bytes()
    assert not (tmp_path / "parallel" / ".mesh-stop.tmp").exists()
    assert parallel_samples.keys() == serial_samples.keys()
    for kf in serial_samples:
        np.testing.assert_array_equal(parallel_samples[kf], serial_samples[kf])
    assert (tmp_path / "parallel" / "map.ply").read_bytes() == (tmp_path / "serial" / "map.ply").read_bytes()


def test_preparer_refuses_a_bad_pose_before_any_work(views):
    frames, _ = views
    prepare = VoxelMapFuser(0.002, 0.002, mesh=True).preparer()
    with pytest.raises(InputDataError, match="pose of frame 0 must be a finite 4x4"):
        prepare(frames[0], np.full((4, 4), np.nan))


def test_voxel_sums_match_a_plain_unique_and_bincount(rng):
    """``_reduce`` gives np.unique's keys and the same per-key sums, bit for bit, whatever the
    keys' order (runs as a frame's pixels give them, or shuffled) and however its sort orders
    equal keys (ties in many keys of few values)."""
    from fpp_graph.fusion.voxel_grid import _reduce

    runs = np.repeat(rng.integers(-50, 50, 3000), rng.integers(1, 6, 3000))
    merged = np.concatenate([np.sort(runs[:5000]), np.sort(runs[5000:])])  # sorted runs end to end, as a merge gives
    cases = [(runs, False), (rng.permutation(runs), False), (merged, True), (merged, False), (np.zeros(0, dtype=np.int64), False), (np.array([7]), True)]
    for keys, sorted_runs in cases:
        planes = rng.normal(size=(7, len(keys)))
        unique, sums = _reduce(keys, planes, sorted_runs=sorted_runs)
        expected_keys, inverse = np.unique(keys, return_inverse=True)
        assert np.array_equal(unique, expected_keys) and sums.shape == (7, len(expected_keys))
        for c in range(7):
            assert np.array_equal(sums[c], np.bincount(inverse, weights=planes[c], minlength=len(expected_keys)))
        # summed in the keys' input order: a plain loop over the values gives the same doubles
        if 0 < len(keys) < 50_000:
            looped = {}
            for key, value in zip(keys.tolist(), planes[0].tolist(), strict=True):
                looped[key] = looped.get(key, 0.0) + value
            assert sums[0].tolist() == [looped[key] for key in unique.tolist()]


def test_grazing_weights_leave_a_map_stored_as_coordinate_planes_as_it_was(rng):
    # channels that are contiguous (an (H, W, 3) view of (3, H, W) planes): the weights are those
    # of the same map in the usual layout, and the caller's map is not written to
    planes = rng.normal(0.0, 0.01, (3, 40, 60)) + np.array([0.0, 0.0, 1.0])[:, None, None]
    planes[:, 5:9, 10:20] = np.nan
    view = np.moveaxis(planes, 0, -1)
    kept = view.copy()
    weights = grazing_weights(view)
    np.testing.assert_array_equal(view, kept)
    np.testing.assert_array_equal(weights, grazing_weights(np.ascontiguousarray(kept)))


def test_doubled_gradient_is_numpys_times_two_bit_for_bit(rng):
    from fpp_graph.fusion.voxel_map import _twice_gradient

    for shape in ((2, 2), (2, 5), (5, 3), (40, 60)):
        f = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 3)
        f[rng.random(shape) < 0.1] = np.nan
        for ours, numpys in zip(_twice_gradient(f), np.gradient(f), strict=True):
            np.testing.assert_array_equal(ours, 2.0 * numpys)


@pytest.mark.parametrize("box", [(slice(10, 30), slice(20, 45)), (slice(0, 25), slice(40, 60)), (slice(0, 40), slice(0, 60)), (slice(5, 6), slice(5, 50)), (slice(0, 0), slice(0, 0))])
@pytest.mark.parametrize("band_rows", [1, 3, 16])
def test_grazing_weights_of_a_partial_map_are_the_whole_maps_bit_for_bit(rng, box, band_rows, monkeypatch):
    # the weights are computed over the finite pixels' box only, in bands of rows: an object in
    # the middle, one at the border, the whole image, a single row (too thin: all weight 1) and
    # no points at all, with the bands' boundaries anywhere
    from fpp_graph.fusion import voxel_map
    from fpp_graph.fusion.voxel_map import _grazing_cos, grazing_weights

    monkeypatch.setattr(voxel_map, "GRAZING_BAND_ROWS", band_rows)

    h, w = 40, 60
    v, u = np.mgrid[0:h, 0:w].astype(float)
    z = 0.5 + 0.05 * np.sin(u / 7.0) * np.cos(v / 5.0) + rng.normal(0, 1e-4, (h, w))
    xyz = np.dstack([(u - w / 2) / 200 * z, (v - h / 2) / 200 * z, z])
    partial = np.full_like(xyz, np.nan)
    partial[box] = xyz[box]
    if box[0].stop - box[0].start > 4:
        partial[box[0].start + 2, box[1].start + 3] = np.nan  # a hole in the object
    expected = _grazing_cos(partial, 0.05)
    got = grazing_weights(partial)
    assert got.shape == (h, w)
    np.testing.assert_array_equal(got, expected)
    # the finite pixels handed in (as the fusion preparer does) give the same weights
    np.testing.assert_array_equal(grazing_weights(partial, finite=finite_points(partial)), got)


def test_render_depth_with_the_finite_pixels_handed_in_is_the_same(rng):
    from fpp_graph.fusion.voxel_map import intrinsics_of, render_depth

    h, w = 30, 40
    v, u = np.mgrid[0:h, 0:w].astype(float)
    z = 0.8 + 0.1 * np.sin(u / 6.0) + rng.normal(0, 1e-4, (h, w))
    xyz = np.dstack([(u - w / 2) / 150 * z, (v - h / 2) / 150 * z, z])
    xyz[3:6, 4:9] = np.nan
    xyz[10, 10, 2] = -0.5  # behind the camera: never rendered, with or without the mask
    finite = finite_points(xyz)
    frame = Frame(id=0, timestamp=0.0, points=xyz[finite], xyz_map=xyz)
    K = intrinsics_of(dataclasses.replace(frame, xyz_map=np.where(xyz[..., 2:] > 0, xyz, np.nan)))
    depth, rgb = render_depth(frame, K)
    depth_f, rgb_f = render_depth(frame, K, finite=finite)
    np.testing.assert_array_equal(depth_f, depth)
    np.testing.assert_array_equal(rgb_f, rgb)
    assert np.count_nonzero(depth) == np.count_nonzero(finite) - 1


@pytest.mark.parametrize("box", [(20, 50, 30, 70), (0, 40, 0, 30), (10, 64, 50, 96), (0, 64, 0, 96)])
def test_edge_filter_on_the_decoded_box_equals_the_whole_map(box):
    """The filter computes only the box around the decoded pixels: the same mask as the whole
    map, for an object inside the frame and for one touching its borders."""
    from frontend.fpp.sensor import _edge_filter_box, edge_filter_mask

    rng = np.random.default_rng(sum(box))
    h, w = 64, 96
    v, u = np.mgrid[0:h, 0:w].astype(float)
    z = 0.5 + 0.02 * np.sin(u / 7.0) + 0.01 * (v > 35) + 1e-4 * rng.normal(size=(h, w))  # a step: a depth edge
    xyz = np.dstack([(u - w / 2) * z / 500.0, (v - h / 2) * z / 500.0, z])
    r0, r1, c0, c1 = box
    outside = np.ones((h, w), bool)
    outside[r0:r1, c0:c1] = False
    xyz[outside] = np.nan
    xyz[rng.random((h, w)) < 0.02] = np.nan  # holes
    keep = edge_filter_mask(xyz, 500.0)
    np.testing.assert_array_equal(keep, _edge_filter_box(xyz, 500.0, 75.0, 0.0005))
    assert keep.any() and not keep[outside].any()
    assert not edge_filter_mask(np.full((8, 8, 3), np.nan), 500.0).any()


@pytest.mark.parametrize("band_rows", [0, 1, 2, 5, 31])
def test_edge_filter_in_bands_of_rows_equals_one_pass(band_rows, monkeypatch):
    """The filter runs in bands of rows (cache-sized): any band height gives the one-pass mask (0: rows one by one),
    with depth edges, holes and the box's border falling on band boundaries."""
    from frontend.fpp import sensor

    rng = np.random.default_rng(band_rows)
    h, w = 70, 90
    v, u = np.mgrid[0:h, 0:w].astype(float)
    z = 0.5 + 0.02 * np.sin(u / 7.0) + 0.01 * (v > 35) + 0.3 * (u > 60) * (v % 11 < 2) + 1e-4 * rng.normal(size=(h, w))
    xyz = np.dstack([(u - w / 2) * z / 500.0, (v - h / 2) * z / 500.0, z])
    xyz[:3] = np.nan
    xyz[rng.random((h, w)) < 0.03] = np.nan
    whole = sensor._edge_filter_box(xyz[2:], 500.0, 75.0, 0.0005)  # the decoded box: rows 2.. (one undecoded row above)
    monkeypatch.setattr(sensor, "EDGE_FILTER_BAND_ROWS", band_rows)
    keep = sensor.edge_filter_mask(xyz, 500.0)
    np.testing.assert_array_equal(keep[2:], whole)
    assert not keep[:2].any() and 0.5 < keep.mean() < 0.95
