"""Front-end config sections, the noise model the registration thresholds derive from, old keys."""

from __future__ import annotations

import pytest

from fpp_graph import config as config_module
from fpp_graph.config import (
    Config,
    StrictModel,
    config_from_dict,
    default_config_text,
    register_sections,
)
from fpp_graph.errors import ConfigError
from frontend.config import (
    FPP_NOISE,
    DecodeConfig,
    RegistrationConfig,
    SensorNoise,
    chi2_quantile,
)
from frontend.dense_alignment import DenseSchedule
from frontend.registration.weak_directions import (
    JOINT_OPTIMUM_PROBABILITY,
    PLANE_DISAGREEMENT_PROBABILITY,
)
from frontend.rgbd.source import KINECT_V1_NOISE, RgbdSource

# the FPP thresholds before they were expressed from the noise model: the defaults must give them exactly
OLD_FPP_LENGTHS = {
    "ransac_inlier_m": 0.002,
    "icp_voxel_m": 0.002,
    "icp_coarse_voxel_m": 0.004,
    "icp_max_correspondence_m": 0.004,
    "max_inlier_rmse_m": 0.002,
    "max_icp_shift_m": 0.003,
    "max_weak_sigma_m": 0.002,
    "icp_information_scale": 1.0,
    "keypoint_edge_step_m": 0.005,  # lift_keypoints' depth-edge step
    "texture_distance_m": 0.003,  # texture_agreement's surface distance
}


def test_front_end_sections_are_registered_and_typed():
    cfg = Config()
    assert isinstance(cfg.registration, RegistrationConfig)
    assert isinstance(cfg.decode, DecodeConfig)
    assert cfg.section_names()[:2] == ["decode", "registration"]
    assert "registration:" in default_config_text() and "pose_graph:" in default_config_text()


def test_default_thresholds_are_the_fpp_rigs():
    lengths = RegistrationConfig().lengths
    assert {k: getattr(lengths, k) for k in OLD_FPP_LENGTHS} == OLD_FPP_LENGTHS
    assert RegistrationConfig().with_noise(FPP_NOISE).lengths == lengths


def test_rgbd_differs_from_fpp_by_its_noise_model_only():
    fpp, rgbd = Config().registration, RgbdSource.resolve_config(Config()).registration
    assert rgbd.model_copy(update={"noise": fpp.noise}) == fpp
    # the Kinect's 9x9 correlation window: every 4th pixel (coarse steps every 8th), not FPP's 2nd
    schedule = DenseSchedule.of(rgbd)
    assert (schedule.fine_stride_px, schedule.coarse_stride_px) == (4, 8)
    assert (DenseSchedule.of(fpp).fine_stride_px, DenseSchedule.of(fpp).coarse_stride_px) == (2, 4)
    assert rgbd.sensor_noise() == KINECT_V1_NOISE
    sigma = KINECT_V1_NOISE.point_sigma_m
    lengths = rgbd.lengths
    assert lengths.ransac_inlier_m == pytest.approx(4 * sigma)
    assert lengths.max_inlier_rmse_m == pytest.approx(4 * sigma)
    assert lengths.icp_voxel_m == KINECT_V1_NOISE.voxel_m
    assert lengths.icp_max_correspondence_m == pytest.approx(4 * sigma + KINECT_V1_NOISE.voxel_m)
    assert lengths.icp_information_scale == pytest.approx(KINECT_V1_NOISE.information_correlation)
    # ICP stops two orders under the noise: 1 um on FPP, 15 um on Kinect depth
    assert lengths.icp_convergence_m == pytest.approx(0.002 * sigma)
    assert fpp.lengths.icp_convergence_m == pytest.approx(1e-6)
    # idempotent, and a user's own noise value wins over the source's
    assert RgbdSource.resolve_config(RgbdSource.resolve_config(Config())) == RgbdSource.resolve_config(Config())
    mine = config_from_dict({"registration": {"noise": {"point_sigma_m": 0.004}}})
    resolved = RgbdSource.resolve_config(mine).registration
    assert resolved.noise.point_sigma_m == 0.004 and resolved.noise.voxel_m == KINECT_V1_NOISE.voxel_m
    # a user's stride wins over the source's, finer or coarser
    for stride in (2, 6):
        mine = RgbdSource.resolve_config(config_from_dict({"registration": {"noise": {"dense_stride_px": stride}}})).registration
        assert (DenseSchedule.of(mine).fine_stride_px, DenseSchedule.of(mine).coarse_stride_px) == (stride, 2 * stride)


def test_chi_square_probabilities_give_the_former_constants():
    assert chi2_quantile(PLANE_DISAGREEMENT_PROBABILITY, 3) == pytest.approx(21.108, abs=1e-3)
    assert chi2_quantile(JOINT_OPTIMUM_PROBABILITY, 6) == pytest.approx(22.458, abs=1e-3)


def test_every_old_metre_key_is_retired_at_its_length():
    fixed = {"icp_max_correspondence_m": 0.004, "dense_icp_voxel_m": 0.004, "max_inlier_rmse_m": 0.002, "max_icp_shift_m": 0.003,
             "max_weak_sigma_m": 0.002}
    lengths = config_from_dict({"registration": fixed}).registration.lengths
    assert (lengths.icp_max_correspondence_m, lengths.icp_coarse_voxel_m, lengths.max_inlier_rmse_m) == pytest.approx((0.004, 0.004, 0.002))
    assert (lengths.max_icp_shift_m, lengths.max_weak_sigma_m) == pytest.approx((0.003, 0.002))
    with pytest.raises(ConfigError, match=r"registration\.max_icp_shift_m is no longer a setting .*set registration\.ransac\.inlier_sigmas instead"):
        config_from_dict({"registration": {"max_icp_shift_m": 0.0041}})


def test_retired_registration_keys_load_at_their_value_and_name_what_to_set():
    loaded = config_from_dict({"registration": {"icp": {"max_iterations": 50}, "dense": {"stride_px": 2}, "degeneracy_ratio": 0.02}})
    assert loaded.registration == RegistrationConfig()
    with pytest.raises(ConfigError, match=r"registration\.dense\.stride_px is no longer a setting .*set registration\.noise\.dense_stride_px instead"):
        config_from_dict({"registration": {"dense": {"stride_px": 4}}})


def test_a_third_party_section_is_validated_like_the_others():
    class LidarConfig(StrictModel):
        max_range_m: float = 30.0

    register_sections({"lidar_test": LidarConfig})
    try:
        assert Config().lidar_test == LidarConfig()
        assert config_from_dict({"lidar_test": {"max_range_m": 5.0}}).lidar_test.max_range_m == 5.0
        with pytest.raises(ConfigError, match=r"lidar_test\.max_rang: unknown key; did you mean 'max_range_m'"):
            config_from_dict({"lidar_test": {"max_rang": 5.0}})
        with pytest.raises(ConfigError, match="registered twice"):
            register_sections({"lidar_test": DecodeConfig})
        with pytest.raises(ConfigError, match="belongs to fpp_graph"):
            register_sections({"pose_graph": LidarConfig})
    finally:
        config_module._SECTIONS.pop("lidar_test")


def test_sensor_noise_fills_only_unset_values():
    reg = RegistrationConfig(noise={"voxel_m": 0.005}).with_noise(SensorNoise(0.001, 0.01, 0.5))
    assert (reg.noise.point_sigma_m, reg.noise.voxel_m, reg.noise.information_correlation) == (0.001, 0.005, 0.5)
