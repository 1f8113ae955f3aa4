"""The photometric refinement of plane-like pairs (TexturedSurfaceRegistrar with a TextureCamera)."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.geometry import invert, pose_error, se3_exp, se3_log
from frontend.config import RegistrationConfig
from frontend.localization import (
    DenseReference,
    PhotometricQuery,
    PhotometricSettings,
    localize_photometric,
)
from frontend.registration import TextureCamera, TexturedSurfaceRegistrar


@pytest.fixture(scope="module")
def wall_pair():
    """Two fringe-simulator frames (640x400) of a textured flat wall, the camera moved along it."""
    from frontend.fpp.sensor import FppSensor
    from frontend.sim import FppSimulator, default_pattern_spec, default_rig, look_at_pose, scenes

    rig, spec = default_rig(preview=True), default_pattern_spec()
    scene = scenes.plane_scene(0.55, tilt_deg=12.0, albedo=0.6, contrast=0.7)
    sim, sensor = FppSimulator(rig, spec, scene), FppSensor(rig, spec)
    poses = [look_at_pose(np.array([x, 0.004 * i, 0.0]), np.array([x + 0.01, 0.0, 0.55])) for i, x in enumerate((-0.03, 0.03))]
    frames = [sensor.frame_from_images(i, float(i), sim.render(P, frame_index=i).images) for i, P in enumerate(poses)]
    return rig, poses, frames


def test_texture_sets_a_walls_in_plane_directions(wall_pair):
    rig, poses, frames = wall_pair
    T_true = invert(poses[0]) @ poses[1]
    plain = TexturedSurfaceRegistrar(RegistrationConfig()).register(frames[0], frames[1])
    photo_reg = TexturedSurfaceRegistrar(RegistrationConfig(), texture_camera=TextureCamera.from_rig(rig))
    photo = photo_reg.register(frames[0], frames[1])
    assert plain.accepted and photo.accepted
    assert "T_before_photometric" in photo.metadata, photo.metadata.get("photometric_not_used")
    assert "T_before_photometric" not in plain.metadata and "photometric" in photo_reg.last_cpu_timings_s
    _, trans_plain = pose_error(plain.T_target_source, T_true)
    rot_photo, trans_photo = pose_error(photo.T_target_source, T_true)
    # the keypoints put the in-plane shifts to some 0.1 mm at 640x400; every textured pixel does better
    assert trans_photo < 0.5 * trans_plain and trans_photo < 0.05e-3, (trans_plain, trans_photo)
    assert np.degrees(rot_photo) < 0.01
    # the wall's distance and tilts are the dense fit's, held: the photometric step moves only
    # along the plane (the source points' motion is parallel to the wall)
    T_held = photo.metadata["T_before_photometric"]
    P = frames[1].points[:: max(1, len(frames[1].points) // 2000)]
    moved = (P @ photo.T_target_source[:3, :3].T + photo.T_target_source[:3, 3]) - (P @ T_held[:3, :3].T + T_held[:3, 3])
    normal = np.linalg.svd(frames[0].points - frames[0].points.mean(0), full_matrices=False)[2][2]
    assert np.max(np.abs(moved @ normal)) < 0.2 * max(np.max(np.linalg.norm(moved, axis=1)), 1e-9) + 1e-6
    # covariance along the plane is no longer the keypoints' alone
    e = se3_log(invert(T_true) @ photo.T_target_source)
    assert float(e @ photo.information @ e) < 60.0  # NEES of one pair, 6 dof: not absurdly overconfident


def test_photometric_prior_holds_directions(wall_pair):
    rig, poses, frames = wall_pair
    cam = TextureCamera.from_rig(rig)
    ref = DenseReference(frames[0].xyz_map, frames[0].texture, poses[0])
    T_start = se3_exp([0.0005, -0.0004, 0.0003, 2e-4, -1e-4, 1e-4]) @ invert(poses[1])
    lit = np.isfinite(frames[1].xyz_map[..., 2])
    query, settings = PhotometricQuery(frames[1].texture, T_start, cam.K, cam.dist, cam.projector_centre_m, lit), PhotometricSettings(max_pixels=40_000)
    free = localize_photometric([ref], query, settings)
    held = localize_photometric([ref], query, settings, prior_information=1e16 * np.eye(6))
    assert free.success and np.all(np.isfinite(free.information)) and free.information[3, 3] > 0
    assert np.linalg.norm(se3_log(free.T_camera_world @ invert(T_start))) > 1e-4  # it moved towards the truth
    assert np.linalg.norm(se3_log(held.T_camera_world @ invert(T_start))) < 1e-7  # everything held
    # translation held, rotation free: the translation of T stays, the rotation moves
    Lam = np.diag([0.0, 0.0, 0.0, 1e16, 1e16, 1e16])
    part = localize_photometric([ref], query, settings, prior_information=Lam)
    step = se3_log(part.T_camera_world @ invert(T_start))
    assert np.linalg.norm(step[3:]) < 1e-7 and np.linalg.norm(step[:3]) > 1e-5
    with pytest.raises(Exception, match="prior_information"):
        localize_photometric([ref], PhotometricQuery(frames[1].texture, T_start, cam.K), prior_information=np.eye(5))


def test_a_wall_seen_with_relief_at_the_start_is_not_held(wall_pair, monkeypatch):
    """The fit held for the texture runs on a plane; when every pixel already shows relief at the
    keypoints' pose it is skipped (it would find the relief and be redone unheld)."""
    from frontend.registration.state import PairFrames

    rig, _, frames = wall_pair
    registrar = TexturedSurfaceRegistrar(RegistrationConfig(), texture_camera=TextureCamera.from_rig(rig))
    fits = []
    fit = registrar.dense.fit
    monkeypatch.setattr(registrar.dense, "fit", lambda *a, **k: fits.append(a[3]) or fit(*a, **k))
    held = registrar.register(frames[0], frames[1])
    assert held.accepted and "dense_relief_at_start" not in held.metadata and "dense_pinned" in held.metadata
    assert len(fits) == 1 and fits[0] is not None  # one fit, with the plane's directions pinned
    assert registrar.dense.relief_at(PairFrames(frames[0], frames[1]), held.T_target_source)[0] is False
    fits.clear()
    monkeypatch.setattr(registrar.dense, "relief_at", lambda *a: (True, None))
    unheld = registrar.register(frames[0], frames[1])
    assert unheld.metadata.get("dense_relief_at_start") and unheld.metadata.get("dense_rechecks_plane_rule")
    assert all(pinned is None for pinned in fits)  # no held fit


def test_the_photometric_step_takes_the_pyramid_levels_its_start_needs(wall_pair, monkeypatch):
    import frontend.localization as localization
    from frontend.localization.photometric import PYRAMID_ITERATIONS

    rig, poses, frames = wall_pair
    asked = []
    real = localization.localize_photometric

    def recorded(*args, **kwargs):
        asked.append(args[2].iterations)
        return real(*args, **kwargs)

    monkeypatch.setattr(localization, "localize_photometric", recorded)
    photo = TexturedSurfaceRegistrar(RegistrationConfig(), texture_camera=TextureCamera.from_rig(rig)).register(frames[0], frames[1])
    assert photo.accepted and "T_before_photometric" in photo.metadata
    # the keypoints' pose is within a pixel of the texture's at 640x400: the quarter-resolution level is not needed
    assert len(asked) == 1 and 1 <= len(asked[0]) < len(PYRAMID_ITERATIONS)
    assert tuple(asked[0]) == PYRAMID_ITERATIONS[-len(asked[0]):]
