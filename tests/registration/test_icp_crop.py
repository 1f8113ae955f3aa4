"""ICP on the source points that can correspond (``frontend.registration.icp.SourceCrop``): a
pair that shares part of its surface iterates on that part, and ends where ICP on the whole
source ends."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.geometry import se3_exp
from frontend.registration.aligner import AlignmentRequest
from frontend.registration.icp import (
    IcpBasin,
    SmallGicpAligner,
    SourceCrop,
    _align,
    prepare_icp_cloud,
)


def _bumpy_patch(rng: np.random.Generator, centre_x: float, n: int = 6000) -> np.ndarray:
    """A 20 cm square of a bumpy surface 60 cm ahead: every direction constrained."""
    u, v = rng.uniform(-0.1, 0.1, (2, n))
    z = 0.01 * np.exp(-(u**2 + v**2) / 0.002) + 0.004 * np.sin(40 * u) * np.cos(30 * v)
    return np.stack([u + centre_x, v, z + 0.6], 1)


def _pair(seed: int = 5):
    """Target: patches at x = 0 and x = -0.5; source: the x = 0 patch seen from ``T_true`` plus a
    patch at x = +0.5 the target never saw."""
    rng = np.random.default_rng(seed)
    shared, target_only, source_only = _bumpy_patch(rng, 0.0), _bumpy_patch(rng, -0.5), _bumpy_patch(rng, 0.5)
    T_true = se3_exp(np.array([0.01, -0.02, 0.015, 0.004, -0.003, 0.002]))  # maps source to target
    source = (np.concatenate([shared, source_only]) - T_true[:3, 3]) @ T_true[:3, :3]
    target = prepare_icp_cloud(np.concatenate([shared, target_only]), 0.004)
    return target, prepare_icp_cloud(source, 0.004), T_true


_INLIERS = np.array([[0.05, 0.0, 0.6], [-0.05, 0.05, 0.6], [0.0, -0.05, 0.61]])


def test_the_crop_keeps_the_shared_part_and_ends_where_the_whole_source_ends():
    target, source, T_true = _pair()
    crop = SourceCrop(target.target, source.source, np.eye(4), 0.03, 0.045)
    near_shared = source.source.points[:, 0] < 0.3  # the source's own copy of the shared patch
    assert crop.kept[near_shared].all() and not crop.kept[~near_shared].any()
    assert crop.cloud is not source.source.cloud and crop.cloud.size() == crop.size
    whole = _align(target.target, source.source, np.eye(4), "GICP", 0.03, 50, 1e-7)
    cropped = SmallGicpAligner().align(target, source, AlignmentRequest(np.eye(4), 0.03, 50, 1e-7, IcpBasin(_INLIERS, 0.045)))
    assert np.abs(cropped.T_target_source[:3, 3] - T_true[:3, 3]).max() < 2e-4
    assert np.abs(cropped.T_target_source - whole[0]).max() < 5e-5
    # the figures are of the whole source: half of it has a counterpart
    assert cropped.fitness == pytest.approx(0.5, abs=0.05)


def test_a_pose_that_reaches_points_outside_the_crop_adds_them():
    target, source, _ = _pair()
    # started 10 cm off along x, the shared patch's edge is outside a 1 cm reach
    T_off = se3_exp(np.array([0, 0, 0, 0.1, 0, 0]))
    crop = SourceCrop(target.target, source.source, T_off, 0.005, 0.005)
    kept_before = crop.size
    assert 0 < kept_before < source.source.size
    assert crop.cover(np.eye(4))  # near the true pose the rest of the shared patch corresponds
    assert crop.size > kept_before
    assert not crop.cover(np.eye(4))  # nothing left to add at the same pose


def test_a_crop_of_everything_or_of_too_few_points_is_the_whole_cloud():
    target, source, _ = _pair()
    wide = SourceCrop(target.target, source.source, np.eye(4), 0.03, 2.0)
    assert wide.size == source.source.size and wide.cloud is source.source.cloud
    far = SourceCrop(target.target, source.source, se3_exp(np.array([0, 0, 0, 0, 0, 5.0])), 0.03, 0.045)
    assert far.size == 0 and far.cloud is source.source.cloud


def test_bounded_search_matches_the_unbounded_one_within_the_radius():
    target, source, _ = _pair()
    role = target.target
    query = source.source.points
    idx, sq = role.nearest_within(query, 0.01)
    full_idx, full_sq = role.tree.batch_nearest_neighbor_search(query, num_threads=1)
    full_sq = np.asarray(full_sq, dtype=np.float64)
    inside = full_sq <= 0.01**2
    assert np.array_equal(idx >= 0, inside)
    assert np.allclose(sq[inside], full_sq[inside], rtol=1e-9, atol=1e-15)
    assert np.all(np.isinf(sq[~inside]))
    empty_idx, empty_sq = role.nearest_within(np.zeros((0, 3)), 0.01)
    assert empty_idx.shape == (0,) and empty_sq.shape == (0,)


def test_points_within_reach_keep_the_covariances_of_the_whole_cloud():
    # GICP weighs a point by the covariance of its nearest neighbours: the crop holds the
    # neighbours of every point within reach, so those covariances are the whole cloud's
    target, source, _ = _pair()
    role = source.source
    crop = SourceCrop(target.target, role, np.eye(4), 0.003, 0.002)  # a reach shorter than a neighbourhood
    assert 0 < np.count_nonzero(crop.core) < np.count_nonzero(crop.kept) < role.size
    whole = np.asarray(role.cloud.covs())
    cropped = np.asarray(crop.cloud.covs())
    position_in_crop = np.cumsum(crop.kept) - 1
    core = np.flatnonzero(crop.core)
    assert np.allclose(cropped[position_in_crop[core]], whole[core], rtol=1e-9, atol=1e-15)
    # (a point of the neighbour ring may lack some of its own neighbours: not used unless ICP moves it within reach)
