"""iSAM2: the pose graph grown one keyframe at a time, for live use (the keyframe manager's
running estimate); the batch optimiser is :class:`fpp_graph.backend.pose_graph.PoseGraph`."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from fpp_graph.backend.gtsam_bridge import (
    ANCHOR_STIFFNESS,
    CAUCHY_SCALE_SIGMA,
    Array,
    as_information,
    as_pose,
    poses_from,
    short_message,
    solver_error,
)
from fpp_graph.backend.noise_model import isotropic_information
from fpp_graph.backend.pose_graph import PoseGraph, PoseGraphEdge, PoseGraphResult
from fpp_graph.config import PoseGraphConfig
from fpp_graph.errors import GraphError
from fpp_graph.types import Constraint, ConstraintKind

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)


class IncrementalPoseGraph:
    """A pose graph grown one keyframe at a time and solved incrementally with iSAM2.

    The first keyframe is the anchor. Each later keyframe comes with its odometry constraint
    (to any keyframe already in the graph); loops join between updates. :meth:`update` runs
    one iSAM2 step (a few when a loop arrived). :meth:`loop_innovation` tests a loop against
    the current estimate before it goes in; :meth:`absorb` joins another graph through a loop
    (a chain break rejoined); :meth:`polish` runs the batch optimiser (GNC by default) on the
    whole graph and restarts iSAM2 from its solution without the loops GNC rejected.

    Constant cost per update. iSAM2 re-eliminates the cliques between the variables a new
    factor touches and the root of the Bayes tree. Its default ordering puts every key a new
    factor observes last, so each loop pulls an old keyframe up to the root and the update time
    grows with the map (about tenfold over 1000 keyframes of a 50-keyframe circuit). Here the
    most recent keyframes form the last ordering group instead, in every iSAM2 step of an
    update: the loop frontier, one keyframe more than the longest span (in keyframes) of the
    loops added within the last ``ordering_window`` keyframes, so a loop's target is in it and
    the group is no larger (a fixed 100-keyframe group re-eliminated ~45 variables per update
    where the frontier needs ~17). Old keyframes a loop touches are eliminated below it, and
    the re-eliminated part stays bounded by the problem's own frontier, flat after the first
    laps (:attr:`reeliminated_variables` reports it per update).

    Parameters
    ----------
    config : PoseGraphConfig, optional
        Used by :meth:`polish` and for the noise model (``noise_model``); ``robust ==
        "cauchy"`` also puts a Cauchy loss on loop edges inside iSAM2 (GNC is batch-only:
        iSAM2 keeps loops Gaussian until the batch solve).
    relinearize_threshold : float
        iSAM2 re-linearises a variable whose linear update exceeds this (tangent units, rad/m).
    loop_extra_updates : int
        Additional iSAM2 steps after an update that brought loops (re-linearisation settles).
    ordering_window : int
        The longest loop frontier kept last in the elimination order, and how far back (in
        keyframes) loops count towards it (see above); 0 leaves iSAM2's default ordering.
    refresh_per_update : int
        Older keyframes whose cached pose each :meth:`update` re-reads from iSAM2, round robin
        (see "Reading the estimate").

    Reading the estimate. ``calculateEstimate()`` back-substitutes and copies every variable,
    O(map) per update; :meth:`update` instead re-reads from iSAM2 (one
    ``calculateEstimatePose3`` each) only the keys it re-solved: the new keyframes, the keys
    the new factors observe and those iSAM2 re-linearised (its marked keys), the loop
    frontier (the top of the Bayes tree, where a new keyframe and its loops land), and
    ``refresh_per_update`` older keyframes in turn. The rest of the cache can lag iSAM2 by the
    small corrections its back-substitution carries below the top of the tree (refreshed
    within ``n / refresh_per_update`` updates). The whole estimate is read at once after a
    reorder, and whenever what the update should re-read (those keys, or every variable it
    re-eliminated if that is more: a loop reaching deep) is more than a fifth of the map: one
    read of all is then the cheaper. Above that the read-out no longer grows with the map.
    :meth:`estimate` reads every pose, so it is exact; :meth:`loop_innovation` re-reads the
    loop's two keyframes.
    """

    def __init__(
        self,
        config: PoseGraphConfig | None = None,
        *,
        relinearize_threshold: float = 0.01,
        loop_extra_updates: int = 2,
        ordering_window: int = 100,
        refresh_per_update: int = 64,
    ) -> None:
        self.config = config or PoseGraphConfig()
        self.relinearize_threshold = float(relinearize_threshold)
        self.loop_extra_updates = int(loop_extra_updates)
        self.ordering_window = int(ordering_window)
        self.refresh_per_update = int(refresh_per_update)
        self._graph = PoseGraph()  # bookkeeping of what iSAM2 holds: poses (guesses), edges
        self._rejected: list[tuple[int, int]] = []
        self._order: list[int] = []  # keys in the order they were added
        self._position: dict[int, int] = {}  # key -> its index in self._order
        # (position of the newest keyframe when the loop came, loop span in keyframes) of the
        # loops added within the last ordering_window keyframes: they set the frontier
        self._recent_loops: deque[tuple[int, int]] = deque()
        self._reset_isam()
        self._estimate: dict[int, Array] = {}
        self._stale = False  # some cached poses may lag iSAM2 (see "Reading the estimate")
        self._sweep = 0  # round-robin position over self._order for the refresh of older keys
        self._refreshed: list[int] = []
        self._pending_loops = False
        self._reeliminated = 0

    def _reset_isam(self) -> None:
        import gtsam

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.relinearize_threshold)
        params.relinearizeSkip = 1
        # The relinearisation check descends from the root and stops at cliques whose
        # variables stay under the threshold, instead of testing every variable: an old
        # keyframe deep in the tree no longer drags its whole path to the root into the
        # update (on 40 laps x 50 keyframes the last 100 updates cost 5.2 ms instead of 7.7,
        # and the end estimate is as close to the batch optimum).
        params.enablePartialRelinearizationCheck = True
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._anchor_key: int | None = None
        self._in_isam: set[int] = set()
        self._stale_all = True  # the next update reads the whole estimate (a fresh iSAM2)

    # -- building --------------------------------------------------------------------------
    @property
    def num_poses(self) -> int:
        return self._graph.num_poses

    @property
    def num_edges(self) -> int:
        return self._graph.num_edges

    @property
    def anchor(self) -> int | None:
        """The anchored (first) keyframe."""
        return self._anchor_key

    @property
    def rejected_loops(self) -> list[tuple[int, int]]:
        """Loops dropped by earlier :meth:`polish` calls."""
        return list(self._rejected)

    def __contains__(self, key: object) -> bool:
        return key in self._graph

    def keys(self) -> list[int]:
        """Keyframe keys in the order they were added."""
        return list(self._order)

    def constraints(self) -> list[Constraint]:
        """The edges iSAM2 holds, as constraints (odometry and loops)."""
        return [
            Constraint(e.source_id, e.target_id, e.T_target_source, e.information_rot_trans, kind=e.kind)
            for e in self._graph._edges
        ]

    def add_keyframe(self, key: int, T_world_sensor_guess: ArrayLike | None = None, odometry: Constraint | None = None) -> None:
        """Add a keyframe with its initial guess and its odometry constraint.

        Parameters
        ----------
        key : int
            New pose key.
        T_world_sensor_guess : (4, 4), optional
            Initial guess; when omitted, the odometry composed onto the current estimate of the
            other keyframe (identity for the first keyframe).
        odometry : Constraint, optional
            Accepted constraint between ``key`` and a keyframe already added. Required for every
            keyframe but the first (iSAM2 cannot hold a disconnected pose).
        """
        import gtsam

        first = self._graph.num_poses == 0
        if odometry is not None and not odometry.accepted:
            raise GraphError(f"keyframe {key}: its odometry was rejected ({odometry.rejection_reason}); it cannot enter the graph")
        if odometry is None and not first:
            raise GraphError(
                f"keyframe {key}: an odometry constraint to an earlier keyframe is required; a chain "
                "break needs a new IncrementalPoseGraph (or a prior) for the new segment"
            )
        if odometry is not None:
            if key not in (odometry.source_id, odometry.target_id):
                raise GraphError(f"keyframe {key}: its odometry links {odometry.source_id}->{odometry.target_id}, not {key}")
            other = odometry.target_id if odometry.source_id == key else odometry.source_id
            if other not in self._graph:
                raise GraphError(f"keyframe {key}: its odometry refers to keyframe {other}, which is not in the graph")
        if T_world_sensor_guess is None:
            if odometry is None:
                guess = np.eye(4)
            elif odometry.source_id == key:
                guess = self._current(odometry.target_id) @ odometry.T_target_source
            else:
                guess = self._current(odometry.source_id) @ np.linalg.inv(odometry.T_target_source)
        else:
            guess = T_world_sensor_guess
        self._graph.add_pose(key, guess)
        T = self._graph._poses[key]
        self._new_values.insert(int(key), gtsam.Pose3(T))
        self._position[int(key)] = len(self._order)
        self._order.append(int(key))
        if first:
            self._graph.fix_pose(key)
            self._anchor_key = int(key)
        if odometry is not None:
            self._add_edge(odometry, ConstraintKind(odometry.kind))
        self._estimate[int(key)] = T.copy()

    def add_loop(self, constraint: Constraint) -> None:
        """Add an accepted loop constraint between two keyframes already added."""
        for k in (constraint.source_id, constraint.target_id):
            if k not in self._graph:
                raise GraphError(f"loop {constraint.source_id}->{constraint.target_id}: keyframe {k} is not in the graph")
        self._add_edge(constraint, ConstraintKind.LOOP)
        self._pending_loops = True
        span = abs(self._position[int(constraint.source_id)] - self._position[int(constraint.target_id)])
        self._recent_loops.append((len(self._order) - 1, span))

    def _frontier_size(self) -> int:
        """How many of the most recent keyframes form the last ordering group: one more than
        the longest span (in keyframes) of the loops added within the last ``ordering_window``
        keyframes, at most ``ordering_window``; 0 (iSAM2's default) without recent loops."""
        recent = self._recent_loops
        while recent and recent[0][0] < len(self._order) - self.ordering_window:
            recent.popleft()
        if not recent:
            return 0
        return min(self.ordering_window, 1 + max(span for _, span in recent))

    def _information(self, info: Array) -> Array:
        return isotropic_information(info) if self.config.noise_model == "isotropic" else info

    def _add_edge(self, constraint: Constraint, kind: ConstraintKind) -> None:
        import gtsam

        first_edge = self._graph.num_edges == 0
        self._graph.add_constraint(constraint)
        edge = self._graph._edges[-1]
        if kind is not edge.kind:
            self._graph._edges[-1] = PoseGraphEdge(edge.source_id, edge.target_id, edge.T_target_source, edge.information_rot_trans, kind)
        info = self._information(edge.information_rot_trans)
        noise = gtsam.noiseModel.Gaussian.Information(info)
        if kind is ConstraintKind.LOOP and self.config.robust == "cauchy":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(CAUCHY_SCALE_SIGMA), noise)
        if first_edge:
            # The anchor's stiffness follows the first edge's information; until an edge
            # exists the first keyframe waits in _new_values (iSAM2 cannot hold a lone pose).
            self._new_factors.add(self._anchor_factor(info))
        self._new_factors.add(gtsam.BetweenFactorPose3(edge.target_id, edge.source_id, gtsam.Pose3(edge.T_target_source), noise))

    def _anchor_factor(self, info: Array):
        import gtsam

        precision = ANCHOR_STIFFNESS * float(np.abs(np.diag(info)).max())
        T = self._graph._poses[self._anchor_key]
        return gtsam.PriorFactorPose3(self._anchor_key, gtsam.Pose3(T), gtsam.noiseModel.Isotropic.Precision(6, precision))

    def _current(self, key: int) -> Array:
        return self._estimate.get(int(key), self._graph._poses[int(key)])

    # -- solving ---------------------------------------------------------------------------
    def _update_params(self):
        """iSAM2 update parameters: the most recent keyframes last in the elimination order."""
        import gtsam

        params = gtsam.ISAM2UpdateParams()
        frontier = self._frontier_size()
        recent = [k for k in self._order[-frontier:] if k in self._in_isam or self._new_values.exists(k)] if frontier else []
        # Constraint groups must be consecutive from 0 and fewer than the variables iSAM2
        # re-orders (CCOLAMD's rule); with two or more present, group 1 always qualifies.
        if len(recent) >= 2:
            groups = gtsam.KeyGroupMap()
            for k in recent:
                groups.insert2(k, 1)
            params.constrainedKeys = groups
        return params

    def update(self) -> dict[int, Array]:
        """One iSAM2 step with everything added since the last call.

        Returns
        -------
        dict[int, (4, 4) float64]
            The current estimate ``T_world_sensor`` of every keyframe (read-only arrays).
        """
        import gtsam

        self._refreshed, self._reeliminated = [], 0
        if self._graph.num_edges and (self._new_factors.size() or self._new_values.size()):
            new_keys = [int(k) for k in self._new_values.keys()]
            try:
                params = self._update_params()
                results = [self._isam.update(self._new_factors, self._new_values, params)]
                if self._pending_loops:
                    for _ in range(self.loop_extra_updates):
                        results.append(self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), params))
            except RuntimeError as exc:
                raise solver_error(exc) from None
            self._in_isam.update(new_keys)
            self._new_factors.resize(0)
            self._new_values.clear()
            self._pending_loops = False
            self._refresh(new_keys, results)
        return MappingProxyType(self._estimate)

    # A pose read one at a time costs about as much as five read together by calculateEstimate():
    # below that map size the whole estimate is read (measured with scripts/bench_incremental.py).
    _FULL_READ_RATIO = 5

    def _refresh(self, new_keys: list[int], results: list) -> None:
        """Re-read from iSAM2 the poses the last update re-solved (see the class notes)."""
        n = len(self._order)
        self._reeliminated = sum(r.getVariablesReeliminated() for r in results)
        keys = dict.fromkeys(new_keys)
        for r in results:
            keys.update(dict.fromkeys(int(k) for k in r.getMarkedKeys()))
        top = max(self._frontier_size(), 1)
        keys.update(dict.fromkeys(self._order[-top:]))
        reeliminated = max(r.getVariablesReeliminated() for r in results)
        # what this update should re-read: the keys above, or all it re-eliminated if more; one
        # read of everything is cheaper once that is more than 1/_FULL_READ_RATIO of the map
        wanted = max(len(keys) + self.refresh_per_update, reeliminated)
        if self._stale_all or any(r.getBatchReorderTriggered() for r in results) or n <= self._FULL_READ_RATIO * wanted:
            self._read_all()
            return
        older = n - top
        if older > 0 and self.refresh_per_update > 0:
            start = self._sweep % older
            stop = start + min(self.refresh_per_update, older)
            sweep = self._order[start:stop] + self._order[: max(stop - older, 0)]
            self._sweep = stop % older
            keys.update(dict.fromkeys(sweep))
        self._read(keys)
        self._stale = True

    def _read(self, keys: Iterable[int]) -> None:
        isam, estimate, anchor = self._isam, self._estimate, self._anchor_key
        refreshed = self._refreshed
        for k in keys:
            if k == anchor or k not in self._in_isam:
                continue
            T = isam.calculateEstimatePose3(k).matrix()
            T.setflags(write=False)
            estimate[k] = T
            refreshed.append(k)
        # The anchor is a prior 1e8 times stiffer than any edge: it moves by ~1e-8 of an
        # edge's sigma, so its given value stands and the rest is left as solved (a rigid
        # move of all poses, as the batch solver does, costs O(n) per update).
        if anchor is not None:
            estimate[anchor] = self._graph._poses[anchor]

    def _read_all(self) -> None:
        """Every pose from iSAM2 at once (one back-substitution, vectorised extraction)."""
        anchor = self._anchor_key
        poses = poses_from(self._isam.calculateEstimate())
        if anchor is not None and anchor in poses:
            poses[anchor] = self._graph._poses[anchor]
        self._estimate.update(poses)
        self._refreshed = list(poses)
        self._stale = self._stale_all = False

    @property
    def reeliminated_variables(self) -> int:
        """Variables iSAM2 re-eliminated in the last :meth:`update` (all its steps): the part
        of the Bayes tree the update re-solved, which sets its cost."""
        return self._reeliminated

    @property
    def refreshed_keys(self) -> list[int]:
        """Keys whose pose the last :meth:`update` re-read from iSAM2 (all of them after a
        full read); a caller mirroring the estimate copies these instead of every pose."""
        return list(self._refreshed)

    def estimate(self) -> dict[int, Array]:
        """The estimate after the last :meth:`update` (guesses for keyframes added since),
        every pose read from iSAM2 (O(map) when some cached poses lag)."""
        if self._stale and self._in_isam:
            self._read_all()
        return dict(self._estimate)

    def pose(self, key: int) -> Array:
        """The current estimate of one keyframe (fresh from iSAM2; the guess before its first update)."""
        key = int(key)
        if key not in self._graph:
            raise GraphError(f"pose: keyframe {key} is not in the graph")
        if self._stale and key in self._in_isam:
            self._read([key])
        return self._current(key)

    def loop_innovation(self, constraint: Constraint, relative_covariance: ArrayLike | None = None) -> float:
        """Squared Mahalanobis norm of a loop's innovation at the current estimate.

        ``d2 = r^T (Sigma_z + Sigma_rel)^-1 r`` with ``r = Log(T_target_source^-1 *
        T_world_target^-1 * T_world_source)`` (GTSAM's between-factor error, ``[rot, trans]``
        in the source frame), ``Sigma_z`` the loop's covariance (the graph's noise model) and
        ``Sigma_rel`` the covariance of the estimated relative pose, from the joint marginal
        of the two keyframes in iSAM2's Bayes tree (right perturbations: ``delta_rel = xi_s -
        Ad(T_target_source_est^-1) xi_t``). For a true loop and a consistent estimate, ``d2``
        follows a chi-square law with 6 degrees of freedom. Brings pending keyframes in first
        (one :meth:`update`), so both ends are in the tree.

        Parameters
        ----------
        constraint : Constraint
            The loop (both keyframes in the graph).
        relative_covariance : (6, 6), optional
            ``Sigma_rel`` (``[rot, trans]``, source frame) when the caller has a bound of its
            own; the joint marginal is exact but costs a Bayes-tree shortcut from the older
            keyframe to the root (milliseconds to tens of milliseconds on 1000 keyframes).
        """
        import gtsam

        from fpp_graph.geometry import adjoint, se3_log

        s, t = int(constraint.source_id), int(constraint.target_id)
        for k in (s, t):
            if k not in self._graph:
                raise GraphError(f"loop {s}->{t}: keyframe {k} is not in the graph")
        if relative_covariance is None and self._new_values.size() and self._graph.num_edges:
            self.update()
        T_ts_est = np.linalg.inv(self.pose(t)) @ self.pose(s)
        r = se3_log(np.linalg.inv(np.asarray(constraint.T_target_source, dtype=np.float64)) @ T_ts_est)
        cov = np.linalg.inv(self._information(as_information(constraint.information, f"loop {s}->{t}")))
        if relative_covariance is not None:
            cov = cov + np.asarray(relative_covariance, dtype=np.float64).reshape(6, 6)
        elif s in self._in_isam and t in self._in_isam:
            try:
                joint = self._isam.jointMarginalCovariance(gtsam.KeyVector([t, s]))
                J = np.hstack([-adjoint(np.linalg.inv(T_ts_est)), np.eye(6)])
                blocks = np.block([[joint.at(t, t), joint.at(t, s)], [joint.at(s, t), joint.at(s, s)]])
                cov = cov + J @ blocks @ J.T
            except RuntimeError as exc:
                log.warning("loop %d->%d: no joint marginal from iSAM2 (%s); testing against the loop's covariance alone", s, t, short_message(exc))
        cov = 0.5 * (cov + cov.T)
        return float(r @ np.linalg.solve(cov, r))

    def absorb(self, other: IncrementalPoseGraph, loop: Constraint) -> None:
        """Join ``other`` (a separate part, e.g. after a chain break) to this graph through ``loop``.

        ``other``'s estimate is moved rigidly so that ``loop`` holds exactly, its poses and
        edges join this graph with ``loop``, and iSAM2 restarts from the joint estimate (one
        batch elimination: a rare event). This graph's anchor stays; ``other`` is left empty.
        """
        s, t = int(loop.source_id), int(loop.target_id)
        if (s in self) == (t in self) or (s in other) == (t in other):
            raise GraphError(f"absorb: loop {s}->{t} must join a keyframe of this graph to one of the other graph")
        self.update()
        other.update()
        mine, theirs = self.estimate(), other.estimate()
        T_ts = np.asarray(loop.T_target_source, dtype=np.float64)
        if t in self:  # T_world_source in this graph's frame, from the loop
            correction = mine[t] @ T_ts @ np.linalg.inv(theirs[s])
        else:
            correction = mine[s] @ np.linalg.inv(T_ts) @ np.linalg.inv(theirs[t])
        correction = as_pose(correction, "absorb: rigid correction")
        poses = dict(mine)
        for k in other.keys():
            poses[k] = correction @ theirs[k]
        loop = replace(loop, kind=ConstraintKind.LOOP)
        edges = [*self.constraints(), *other.constraints(), loop]
        order = [*self._order, *other._order]
        self._restart(poses, order, edges)
        other._graph, other._order, other._estimate = PoseGraph(), [], {}
        other._position, other._recent_loops = {}, deque()
        other._reset_isam()

    def _restart(self, poses: Mapping[int, Array], order: Sequence[int], edges: Sequence[Constraint]) -> None:
        """Start iSAM2 afresh on ``poses`` and ``edges`` (anchor kept): one batch step."""
        import gtsam

        anchor = self._anchor_key
        self._graph = PoseGraph()
        self._order = [int(k) for k in order]
        self._position = {k: i for i, k in enumerate(self._order)}
        self._recent_loops.clear()  # a batch step: the frontier forms anew from the next loops
        self._reset_isam()
        for key in self._order:
            self._graph.add_pose(key, poses[key])
            self._new_values.insert(int(key), gtsam.Pose3(self._graph._poses[key]))
        self._anchor_key = anchor
        self._graph.fix_pose(anchor)
        for c in edges:
            self._add_edge(c, ConstraintKind(c.kind))
        self._pending_loops = any(ConstraintKind(c.kind) is ConstraintKind.LOOP for c in edges)
        self._estimate = {k: self._graph._poses[k].copy() for k in self._order}
        self.update()

    def to_pose_graph(self) -> PoseGraph:
        """A batch :class:`PoseGraph` at the current estimate (first keyframe fixed)."""
        graph = PoseGraph()
        if self._stale and self._in_isam:
            self._read_all()
        for key in self._graph._poses:
            graph.add_pose(key, self._current(key))
        if self._anchor_key is not None:
            graph.fix_pose(self._anchor_key)
        for e in self._graph._edges:
            graph.add_edge(e.source_id, e.target_id, e.T_target_source, e.information_rot_trans, e.kind)
        return graph

    def polish(self, config: PoseGraphConfig | None = None) -> PoseGraphResult:
        """Batch-optimise the whole graph (GNC by default) and restart iSAM2 from the result.

        Loops rejected by the batch pass leave the incremental graph for good.
        """
        self.update()
        result = self.to_pose_graph().optimize(config or self.config)
        rejected = set(result.rejected_loops)
        self._rejected.extend(sorted(rejected))
        kept = [c for c in self.constraints() if not (c.kind is ConstraintKind.LOOP and (c.source_id, c.target_id) in rejected)]
        self._restart(result.poses_world_sensor, self._order, kept)
        return result
