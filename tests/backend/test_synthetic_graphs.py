"""Synthetic benchmark graphs: the SE-Sync-like torus and false-loop injection."""

from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.backend.g2o import read_g2o
from fpp_graph.errors import GraphError
from fpp_graph.geometry import invert, rotation_angle_rad, se3_log
from fpp_graph.testing.synthetic_graphs import (
    SPHERE2500_ROTATION_SIGMA_RAD,
    SPHERE2500_TRANSLATION_SIGMA_PER_STEP,
    add_false_loops_to_graph,
    torus_graph,
    torus_graph_high_rotation_noise,
    torus_rings_graph,
    typical_loop_information,
)
from fpp_graph.types import ConstraintKind


def whitened_chi2(sim) -> tuple[np.ndarray, np.ndarray]:
    """Per edge: rotation and translation parts of e^T I e at the truth (info is diagonal)."""
    rot, trans = [], []
    for s, t, T, info, _ in sim.edges:
        e = se3_log(invert(T) @ invert(sim.poses_true[t]) @ sim.poses_true[s])
        w = np.diag(info)
        rot.append(np.sum(w[:3] * e[:3] ** 2))
        trans.append(np.sum(w[3:] * e[3:] ** 2))
    return np.array(rot), np.array(trans)


def test_torus_counts_match_torus3d_ratio():
    sim = torus_graph(600, rng=np.random.default_rng(0))
    kinds = [e[4] for e in sim.edges]
    assert len(sim.poses_true) == 600
    assert kinds.count(ConstraintKind.ODOMETRY) == 599
    assert kinds.count(ConstraintKind.LOOP) == round(4049 / 5000 * 600)  # 486
    pairs = [(s, t) for s, t, *_ in sim.edges]
    assert len(set(pairs)) == len(pairs)
    # loops join poses close in space on an earlier winding
    for s, t, _, _, kind in sim.edges:
        if kind is ConstraintKind.LOOP:
            assert s - t >= 8
            assert np.linalg.norm(sim.poses_true[s][:3, 3] - sim.poses_true[t][:3, 3]) < 2.0


def test_torus_explicit_loop_count_and_step():
    sim = torus_graph(400, rng=np.random.default_rng(1), step_m=2.0, loops_per_pose=0.5)
    assert sum(e[4] is ConstraintKind.LOOP for e in sim.edges) == 200
    steps = [np.linalg.norm(sim.poses_true[k][:3, 3] - sim.poses_true[k - 1][:3, 3]) for k in range(1, 400)]
    assert np.median(steps) == pytest.approx(2.0, rel=0.05)


def test_torus_noise_is_what_was_asked():
    sim = torus_graph(1500, rng=np.random.default_rng(2))
    rot, trans = whitened_chi2(sim)
    n = len(rot)  # 2714 edges; the mean of chi2(6) has sd sqrt(12 / n) = 0.07
    assert np.mean(rot + trans) == pytest.approx(6.0, abs=0.3)
    assert np.mean(rot) == pytest.approx(3.0, abs=0.25)
    assert np.mean(trans) == pytest.approx(3.0, abs=0.25)
    assert n == 1499 + round(4049 / 5000 * 1500)
    info = sim.edges[0][3]
    assert np.diag(info)[:3] == pytest.approx(1 / SPHERE2500_ROTATION_SIGMA_RAD**2)
    assert np.diag(info)[3:] == pytest.approx(1 / SPHERE2500_TRANSLATION_SIGMA_PER_STEP**2)


def test_high_rotation_noise_variant_has_ten_times_the_rotation_sigma():
    base = torus_graph(300, rng=np.random.default_rng(3))
    noisy = torus_graph_high_rotation_noise(300, rng=np.random.default_rng(3))
    assert np.diag(noisy.edges[0][3])[:3] == pytest.approx(np.diag(base.edges[0][3])[:3] / 100)
    assert np.diag(noisy.edges[0][3])[3:] == pytest.approx(np.diag(base.edges[0][3])[3:])
    rot, _ = whitened_chi2(noisy)
    assert np.mean(rot) == pytest.approx(3.0, abs=0.5)  # rotations up to pi wrap: a looser bound


def test_torus_graph_starts_at_odometry_and_writes_g2o(tmp_path):
    sim = torus_graph(200, rng=np.random.default_rng(4))
    graph = sim.graph()
    poses = graph.poses()
    assert np.allclose(poses[0], sim.poses_true[0])
    assert np.allclose(poses[1], sim.poses_true[0] @ sim.edges[0][2])
    path = tmp_path / "torus.g2o"
    sim.write_g2o(path)
    back = read_g2o(path)
    assert back.num_poses == 200 and back.num_edges == graph.num_edges
    assert back.fixed_poses() == []
    assert sum(e.kind is ConstraintKind.LOOP for e in back.edges()) == sum(e.kind is ConstraintKind.LOOP for e in graph.edges())


def test_ring_torus_loops_every_pose_to_the_previous_ring():
    sim = torus_rings_graph(rings=6, per_ring=5, rot_sigma_rad=0.1, trans_sigma_m=0.05, rng=np.random.default_rng(0))
    assert len(sim.poses_true) == 30
    assert sum(e[4] is ConstraintKind.LOOP for e in sim.edges) == 30


@pytest.fixture(scope="module")
def torus_sim():
    return torus_graph(500, rng=np.random.default_rng(5))


def test_random_false_loops_count_and_input_untouched(torus_sim):
    graph = torus_sim.graph()
    loops = sum(e.kind is ConstraintKind.LOOP for e in graph.edges())
    corrupted, false = add_false_loops_to_graph(graph, 0.3, np.random.default_rng(6))
    assert len(false) == round(0.3 * loops)
    assert corrupted.num_edges == graph.num_edges + len(false)
    assert graph.num_edges == len(torus_sim.edges)  # the input is not changed
    added = [e for e in corrupted.edges() if e.pair in false]
    assert len(added) == len(false)
    info = typical_loop_information(graph)
    for e in added:
        assert e.kind is ConstraintKind.LOOP
        assert np.array_equal(e.information_rot_trans, info)
        assert e.source_id not in (e.target_id - 1, e.target_id + 1)
    original = {frozenset(e.pair) for e in graph.edges()}
    assert not original & {frozenset(p) for p in false}


def _wrongness(e, truth) -> tuple[float, float]:
    """Rotation (rad) and translation (m) error of an edge's measurement against the truth."""
    E = invert(e.T_target_source) @ invert(truth[e.target_id]) @ truth[e.source_id]
    return rotation_angle_rad(E[:3, :3]), float(np.linalg.norm(E[:3, 3]))


def test_group_false_loops_are_consistent_and_wrong(torus_sim):
    truth = torus_sim.poses_true
    graph = torus_sim.graph()
    corrupted, false = add_false_loops_to_graph(graph, 0.0, np.random.default_rng(7), "group", groups=3,
                                                reference_poses=truth)
    assert len(false) == 15
    added = sorted((e for e in corrupted.edges() if e.pair in false), key=lambda e: e.target_id)
    groups = [added[i:i + 5] for i in range(0, 15, 5)]
    sigma_rot = np.sqrt(1 / np.diag(added[0].information_rot_trans)[:3]).max()
    sigma_trans = np.sqrt(1 / np.diag(added[0].information_rot_trans)[3:]).max()
    worst_rot = 0.0
    for group in groups:
        targets = [e.target_id for e in group]
        assert targets == list(range(targets[0], targets[0] + 5))  # a_i consecutive
        for e1 in group:
            # wrong: far from the truth
            rot_err, trans_err = _wrongness(e1, truth)
            assert rot_err > 20 * sigma_rot or trans_err > 20 * sigma_trans
            for e2 in group:
                if e1 is e2:
                    continue
                # cycle a1 -> b1 -> b2 -> a2 -> a1 through the two group edges and true offsets
                a1, b1, a2, b2 = e1.target_id, e1.source_id, e2.target_id, e2.source_id
                cycle = (e1.T_target_source @ invert(truth[b1]) @ truth[b2] @ invert(e2.T_target_source)
                         @ invert(truth[a2]) @ truth[a1])
                xi = se3_log(cycle)
                # two noisy edges (sqrt(2) sigma per axis, 6 sigma over 3 axes); the rotation
                # noise of e1 moves the cycle's translation through the lever arm b1 -> b2
                lever = np.linalg.norm(truth[b1][:3, 3] - truth[b2][:3, 3]) + np.linalg.norm(truth[a1][:3, 3] - truth[a2][:3, 3])
                bound = 6 * np.sqrt(2) * np.sqrt(3)
                assert np.linalg.norm(xi[:3]) < bound * sigma_rot
                assert np.linalg.norm(xi[3:]) < bound * (sigma_trans + sigma_rot * lever)
                worst_rot = max(worst_rot, np.linalg.norm(xi[:3]) / sigma_rot)
    assert worst_rot > 0.5  # the noise is there: the cycles do not close exactly


def test_false_loop_errors():
    sim = torus_graph(60, rng=np.random.default_rng(8))
    with pytest.raises(GraphError, match="mode"):
        add_false_loops_to_graph(sim.graph(), 0.1, np.random.default_rng(0), "clustered")
    with pytest.raises(GraphError, match="num_poses"):
        torus_graph(3)
    tiny = torus_graph(10, rng=np.random.default_rng(0), loops_per_pose=0.5).graph()
    with pytest.raises(GraphError):
        add_false_loops_to_graph(tiny, 0.0, np.random.default_rng(0), "group", groups=1)
