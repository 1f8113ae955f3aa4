"""One optimisation's problem: the GTSAM factors of a :class:`~fpp_graph.backend.pose_graph.PoseGraph`
under one noise model (anchors, priors, edges), its costs, the loop screen and the odometry-cycle
check of :mod:`fpp_graph.backend.outliers`, and the least-squares solve. The truncated
least-squares stage lives in :mod:`fpp_graph.backend.robust_stage`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from fpp_graph.backend.gtsam_bridge import (
    ANCHOR_STIFFNESS,
    as_pose,
    poses_from,
    run_isam2_batch,
    run_lm,
    short_message,
    solver_error,
    values_from,
)
from fpp_graph.backend.noise_model import isotropic_information
from fpp_graph.backend.outliers import (
    CycleCheck,
    LoopScreen,
    describe_scale,
    family_bound,
    odometry_cycle_chi2,
)
from fpp_graph.config import PoseGraphConfig
from fpp_graph.types import ConstraintKind

if TYPE_CHECKING:
    import gtsam

    from fpp_graph.backend.pose_graph import PoseGraph

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Largest median rotation error (rad, standard deviation at the measured scale) of an odometry
#: step for which the first-order odometry-cycle test counts as evidence against a loop. Why 0.1:
#: first-order propagation drops terms of relative size ~theta per composed step, about 10 % at
#: 0.1 rad; sphere2500, parking-garage and the 7-Scenes RGB-D run (0.07 rad and below) stay
#: under it, while on a torus with 0.7 rad per step true loops score chi-square in the hundreds.
CYCLE_LINEAR_STEP_RAD = 0.1


class GraphProblem:
    """GTSAM factors of one optimisation: anchors, priors and edges under one noise model."""

    def __init__(self, graph: PoseGraph, anchors: Sequence[int], cfg: PoseGraphConfig) -> None:
        import gtsam

        self.given_poses = graph._poses
        self.anchors = list(anchors)
        self.edges = graph.edges()
        self.priors = graph.priors()
        self.num_edges = len(self.edges)
        if self.edges:
            info = np.stack([e.information_rot_trans for e in self.edges])
            if cfg.noise_model == "isotropic":
                info = isotropic_information(info)
        else:
            info = np.zeros((0, 6, 6))
        self.model_information = info
        stiffest = max([float(np.abs(np.diagonal(info, axis1=1, axis2=2)).max()) if len(info) else 1.0]
                       + [float(np.abs(np.diag(p.information_rot_trans)).max()) for p in self.priors])
        self.stiffest = stiffest
        self.anchor_poses = {k: graph._poses[k] for k in self.anchors}
        anchor_noise = gtsam.noiseModel.Isotropic.Precision(6, ANCHOR_STIFFNESS * stiffest)
        self.anchor_factors = [
            gtsam.PriorFactorPose3(k, gtsam.Pose3(graph._poses[k]), anchor_noise) for k in self.anchors
        ]
        self.prior_factors = [
            gtsam.PriorFactorPose3(p.key, gtsam.Pose3(p.T_world_sensor), gtsam.noiseModel.Gaussian.Information(p.information_rot_trans))
            for p in self.priors
        ]
        self.noise = [gtsam.noiseModel.Gaussian.Information(w) for w in info]
        self.measured = [gtsam.Pose3(e.T_target_source) for e in self.edges]
        self.gaussian = [
            gtsam.BetweenFactorPose3(e.target_id, e.source_id, m, n)
            for e, m, n in zip(self.edges, self.measured, self.noise, strict=True)
        ]
        self.is_loop = np.array([e.kind is ConstraintKind.LOOP for e in self.edges], dtype=bool)
        self._cycle_checks: dict[bytes, CycleCheck] = {}

    # -- graphs ----------------------------------------------------------------------------
    def gaussian_graph(self, active: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        """Anchors, priors and the active edges, Gaussian noise."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in self.anchor_factors:
            graph.add(f)
        for f in self.prior_factors:
            graph.add(f)
        for i in np.flatnonzero(active):
            graph.add(self.gaussian[i])
        return graph

    def robust_graph(self, active: NDArray[np.bool_], cauchy_scale: float) -> gtsam.NonlinearFactorGraph:
        """As :meth:`gaussian_graph`, with a Cauchy loss on loop edges."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for f in [*self.anchor_factors, *self.prior_factors]:
            graph.add(f)
        loss = gtsam.noiseModel.mEstimator.Cauchy.Create(float(cauchy_scale))
        for i in np.flatnonzero(active):
            if self.is_loop[i]:
                e = self.edges[i]
                graph.add(gtsam.BetweenFactorPose3(e.target_id, e.source_id, self.measured[i], gtsam.noiseModel.Robust.Create(loss, self.noise[i])))
            else:
                graph.add(self.gaussian[i])
        return graph

    def chordal_graph(self, active: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        """Anchors, priors and active edges with every information divided by the stiffest one.

        ``InitializePose3`` adds unit-precision priors of its own (its anchor orientation and
        pose); next to edges of precision ~1e8 and more (sub-mm, sub-mrad ICP constraints) its
        linear solves report an indeterminate system. Its result does not change under a common
        scaling of all information, so the graph is normalised to a largest precision of 1 and
        the anchors are given that precision.
        """
        import gtsam

        scale = 1.0 / self.stiffest
        graph = gtsam.NonlinearFactorGraph()
        anchor_noise = gtsam.noiseModel.Isotropic.Precision(6, 1.0)
        for k in self.anchors:
            graph.add(gtsam.PriorFactorPose3(k, gtsam.Pose3(self.anchor_poses[k]), anchor_noise))
        for p in self.priors:
            noise = gtsam.noiseModel.Gaussian.Information(scale * p.information_rot_trans)
            graph.add(gtsam.PriorFactorPose3(p.key, gtsam.Pose3(p.T_world_sensor), noise))
        for i in np.flatnonzero(active):
            e = self.edges[i]
            noise = gtsam.noiseModel.Gaussian.Information(scale * self.model_information[i])
            graph.add(gtsam.BetweenFactorPose3(e.target_id, e.source_id, self.measured[i], noise))
        return graph

    def chordal(self, active: NDArray[np.bool_]) -> tuple[gtsam.Values | None, str]:
        """Chordal initialisation (``gtsam.InitializePose3``) over the active edges, anchors
        held exactly; ``(None, reason)`` when it fails."""
        import gtsam

        try:
            values = gtsam.InitializePose3.initialize(self.chordal_graph(active))
            poses = poses_from(values, self.given_poses)
        except Exception as exc:  # gtsam raises RuntimeError/ValueError subclasses from C++
            return None, short_message(exc)
        if not np.all(np.isfinite(np.stack(list(poses.values())))):
            return None, "it returned non-finite poses"
        poses = self.poses_with_gauge_values(poses, self.given_poses, self.anchors, bool(self.priors))
        return values_from(poses), ""

    # -- costs -----------------------------------------------------------------------------
    def cost(self, values: gtsam.Values, active: NDArray[np.bool_]) -> float:
        """``0.5 sum ||whitened||^2`` over priors and active edges (anchors excluded)."""
        total = sum(f.error(values) for f in self.prior_factors)
        for i in np.flatnonzero(active):
            total += self.gaussian[i].error(values)
        return float(total)

    # -- loop statistics -------------------------------------------------------------------
    def loop_chi2(self, values: gtsam.Values, loops: NDArray[np.int64]) -> Array:
        """Whitened squared residuals (``2 x`` GTSAM's error) of edges ``loops`` at ``values``."""
        return np.array([2.0 * self.gaussian[i].error(values) for i in loops], dtype=np.float64)

    def cycle_check(self, active: NDArray[np.bool_]) -> CycleCheck:
        """The active loops against the odometry paths between their ends.

        It depends on the active set only (not on the values): kept per active set, so the
        screens of one optimisation measure the scale once while no edge is dropped.
        """
        key = np.asarray(active, dtype=bool).tobytes()
        if key not in self._cycle_checks:
            self._cycle_checks[key] = self._cycle_check(active)
        return self._cycle_checks[key]

    def _cycle_check(self, active: NDArray[np.bool_]) -> CycleCheck:
        idx = np.flatnonzero(active)
        check = odometry_cycle_chi2(
            list(self.given_poses),
            np.array([self.edges[i].pair for i in idx], dtype=np.int64).reshape(-1, 2),
            np.stack([self.edges[i].T_target_source for i in idx]),
            self.model_information[idx],
            self.is_loop[idx],
            [*self.anchors, *(p.key for p in self.priors)],
        )
        return CycleCheck(idx[check.loop_index], check.chi2)

    def cycle_step_rad(self, cycles: CycleCheck) -> float:
        """Median rotation error (rad, standard deviation) of an odometry step at the scale the
        cycles show: the first-order cycle test is accurate only where it is small."""
        odometry = self.model_information[~self.is_loop]
        if not len(odometry):
            return 0.0
        rotation_variance = np.linalg.eigvalsh(np.linalg.inv(odometry)[:, :3, :3])[:, -1]
        return math.sqrt(cycles.measured_scale() * float(np.median(rotation_variance)))

    def refuted_by_cycles(self, cycles: CycleCheck, num_loops: int, cfg: PoseGraphConfig) -> NDArray[np.int64]:
        """Loops refuted by their odometry cycle: evidence against them that no solution enters.

        A loop is refuted when its cycle's chi-square exceeds the family-wise bound at the scale
        the cycles show (:meth:`~fpp_graph.backend.outliers.CycleCheck.measured_scale`, below 1 when the
        information is conservative: the same scale GNC's start uses). The test propagates the
        odometry's covariance to first order; it is evidence only where that is accurate, i.e.
        where an odometry step's rotation error at that scale is small (:meth:`cycle_step_rad`
        at most ``CYCLE_LINEAR_STEP_RAD``; the neglected second-order terms are about half the
        angle relative to the first-order ones). Beyond it (a torus with 0.7 rad rotation noise
        per step) true loops show cycle chi-squares in the hundreds, and nothing is refuted.
        """
        step_rad = self.cycle_step_rad(cycles)
        if step_rad > CYCLE_LINEAR_STEP_RAD:
            log.info("odometry steps' rotation error %.2g rad (at the cycles' scale %.3g) is beyond the first-order "
                     "cycle test: no loop refuted by it", step_rad, cycles.measured_scale())
            return np.zeros(0, dtype=np.int64)
        bound = cycles.measured_scale() * family_bound(num_loops, cfg.loop_false_alarm)
        return cycles.loop_index[cycles.chi2 > bound]

    def screen(
        self,
        values: gtsam.Values,
        active: NDArray[np.bool_],
        cfg: PoseGraphConfig,
        measure_scale: bool = True,
        cycles: CycleCheck | None = None,
    ) -> LoopScreen:
        """The evidence against each active loop at ``values`` (see :mod:`fpp_graph.backend.outliers`).

        The information's scale is measured (odometry cycles) only when some loop exceeds the
        bound at unit scale: it can only widen the bound, so otherwise nothing is flagged.
        ``measure_scale=False`` skips that measurement (a first look at approximate values);
        ``cycles`` is the odometry-cycle check of ``active`` when already computed. Where the
        first-order cycle test does not hold (:meth:`refuted_by_cycles`) its scale is not a
        measurement either; the scale is then the a-posteriori variance factor of the
        least-squares residuals (``2 cost / redundancy``), never below 1.
        """
        loops = np.flatnonzero(active & self.is_loop)
        unit_bound = family_bound(len(loops), cfg.loop_false_alarm)
        r2 = self.loop_chi2(values, loops)
        if len(loops) == 0 or r2.max() <= unit_bound or not measure_scale:
            return LoopScreen(loops, r2, 1.0, unit_bound, None)
        cycles = self.cycle_check(active) if cycles is None else cycles
        if self.cycle_step_rad(cycles) > CYCLE_LINEAR_STEP_RAD:
            redundancy = 6 * (int(np.sum(active)) + len(self.priors) + len(self.anchors) - len(self.given_poses))
            s2 = max(1.0, 2.0 * self.cost(values, active) / redundancy) if redundancy > 0 else 1.0
            log.info("odometry cycles beyond first order: variance factor %.3g from the residuals (redundancy %d)", s2, redundancy)
        else:
            s2 = cycles.variance_factor()
        log.info("%s", describe_scale(s2, s2 * unit_bound, len(cycles.chi2)))
        return LoopScreen(loops, r2, s2, s2 * unit_bound, cycles)

    def necessary_loops(self, active: NDArray[np.bool_]) -> set[int]:
        """Active loop edges whose removal would leave part of the graph without an anchor.

        Such a loop has no redundancy: nothing can confirm or refute it, and the solve needs
        it. GNC treats them as known inliers and the consistency check does not remove them.
        """
        import networkx as nx

        graph = nx.MultiGraph()
        graph.add_nodes_from(self.given_poses)
        index = {}
        for i in np.flatnonzero(active):
            u, v = self.edges[i].pair
            graph.add_edge(u, v, key=int(i))
            index[frozenset((u, v))] = int(i)
        anchored = set(self.anchors) | {p.key for p in self.priors}
        needed = set()
        for u, v in nx.bridges(graph):
            i = index[frozenset((u, v))]  # a bridge is a single edge, so the pair names it
            if not self.is_loop[i]:
                continue
            graph.remove_edge(u, v, key=i)
            if any(not anchored.intersection(part) for part in nx.connected_components(graph)):
                needed.add(i)
            graph.add_edge(u, v, key=i)
        return needed

    # -- solving ---------------------------------------------------------------------------
    def solve(
        self, initial: gtsam.Values, active: NDArray[np.bool_], cfg: PoseGraphConfig, robust: str | None = None
    ) -> tuple[gtsam.Values, int]:
        """Least squares (or the Cauchy loss on loops) over the active edges from ``initial``."""
        robust = cfg.robust if robust is None else robust
        try:
            graph = self.robust_graph(active, cfg.cauchy_scale) if robust == "cauchy" else self.gaussian_graph(active)
            if cfg.solver == "isam2":
                return run_isam2_batch(graph, initial, cfg)
            return run_lm(graph, initial, cfg.max_iterations, cfg.relative_error_tol)
        except RuntimeError as exc:
            raise solver_error(exc) from None

    def solve_tls(
        self, values: gtsam.Values, active: NDArray[np.bool_], screen: LoopScreen, cfg: PoseGraphConfig
    ) -> tuple[gtsam.Values, int, list[int]]:
        """Truncated least squares on loop edges (:func:`fpp_graph.backend.robust_stage.solve_tls`)."""
        from fpp_graph.backend.robust_stage import solve_tls

        return solve_tls(self, values, active, screen, cfg)

    # -- gauge -----------------------------------------------------------------------------
    def poses_with_gauge(self, values: gtsam.Values, given: Mapping[int, Array], anchors: Sequence[int], has_priors: bool) -> dict[int, Array]:
        return self.poses_with_gauge_values(poses_from(values, given), given, anchors, has_priors)

    @staticmethod
    def poses_with_gauge_values(
        poses: dict[int, Array], given: Mapping[int, Array], anchors: Sequence[int], has_priors: bool
    ) -> dict[int, Array]:
        """Hold anchors exactly: a rigid move of the whole solution when one anchor is the only
        absolute information (an exact symmetry of the cost), else the anchors' given values."""
        if not anchors:
            return poses
        if len(anchors) == 1 and not has_priors:
            key = anchors[0]
            correction = given[key] @ np.linalg.inv(poses[key])
            correction = as_pose(correction, "gauge correction")
            keys = list(poses)
            moved = np.einsum("ij,njk->nik", correction, np.stack([poses[k] for k in keys]))
            moved[:, 3] = (0.0, 0.0, 0.0, 1.0)
            moved.setflags(write=False)
            poses = dict(zip(keys, moved, strict=True))
        for key in anchors:
            poses[key] = given[key].copy()
        return poses
