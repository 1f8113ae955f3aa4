"""Keyframes, odometry, loop closure and the pose graph they feed.

:class:`KeyframeManager` is the back-end's middle. Per incoming frame it

1. registers the frame against the last keyframe through the front-end's ``PairRegistrar``
   (falling back to the keyframe before it; when both fail the chain breaks, and the break is
   recorded and the run goes on as a new segment). With ``keyframes.track_from_motion`` and a
   registrar that is also a :class:`~fpp_graph.types.FrameTracker`, the registrar's ``track``
   comes first, from a constant-velocity prediction (:mod:`fpp_graph.slam.motion`): a frame it
   accepts costs a dense fit or two instead of a full registration (a new keyframe's odometry
   edge is then the tracked constraint); a frame ``track`` hands on is tracked once more against
   the frame before it, which becomes a keyframe when it was tracked against the same keyframe
   (it saw more of the new frame's view), and is registered in full when that fails too, its
   reason counted;
2. decides whether the frame is a keyframe (its view changed by ``keyframes.min_view_change``,
   from the keyframe's :class:`~fpp_graph.types.CameraModel`);
3. for a keyframe (once the camera has gone :data:`QUERY_VIEW_CHANGE` of the way to
   leaving the last keyframe that asked), asks the ``LoopDetector`` for revisit candidates (pose proximity with a gate
   that widens with the drift accumulated since the last closure, and appearance; never a
   keyframe of its local window), submits each to the ``PairVerifier`` (the ``PairRegistrar`` in
   this process, or on the run's workers), applies the results :data:`VERIFY_LAG_KEYFRAMES`
   keyframes later in submission order, and logs every accepted and rejected candidate with its
   reason and figures;
4. keeps its running estimate with iSAM2 (:class:`~fpp_graph.backend.pose_graph.IncrementalPoseGraph`,
   one per connected part): the keyframe and its odometry go in, each verified loop goes in as
   a Gaussian factor after a per-edge innovation test (a loop that fails it is held out of the
   running estimate only, logged and counted, and still reaches the final solve), and one
   iSAM2 update follows, so later proximity gates use corrected poses at a cost that does not
   grow with the map.

:meth:`KeyframeManager.finish` runs the final robust optimisation (GNC by default: odometry edges
are known inliers, loops may be false) per connected component and returns poses for every frame.
Only keyframes are kept (bounded by the :class:`~fpp_graph.slam.frame_store.FrameStore`).

Chain breaks: a new segment starts its own iSAM2 graph anchored at its first keyframe's pose
(the last keyframe's pose, or the frame's pose guess); a loop that joins two parts merges their
graphs (:meth:`~fpp_graph.backend.pose_graph.IncrementalPoseGraph.absorb`, the newer part moved rigidly
onto the loop). Such a joining loop is accepted without the innovation test: it is the only link
between the parts, so nothing can confirm or refute it yet (the batch solve treats it the same way).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace

import networkx as nx
import numpy as np
from numpy.typing import NDArray

from fpp_graph.backend.incremental import IncrementalPoseGraph
from fpp_graph.backend.outliers import chi2_6_quantile
from fpp_graph.config import Config
from fpp_graph.errors import InputDataError
from fpp_graph.geometry import compose, invert
from fpp_graph.slam.drift import (
    constraint_covariance,
    step_position_variance_m2,
    transport_covariance,
)
from fpp_graph.slam.frame_store import FrameStore
from fpp_graph.slam.loop_closure import ProximityAppearanceLoopDetector
from fpp_graph.slam.motion import MotionTracking, readout_motion, with_readout_motion
from fpp_graph.slam.slam_result import ChainBreak, LoopRecord, SlamResult
from fpp_graph.slam.verification import InlineVerifier
from fpp_graph.slam.views import ViewModel, median_depth_m, view_change
from fpp_graph.types import (
    Constraint,
    ConstraintKind,
    Frame,
    FrameDescriber,
    LoopCandidate,
    LoopDetector,
    PairRegistrar,
    PairVerifier,
)

log = logging.getLogger(__name__)

VERIFY_LAG_KEYFRAMES = 2
"""A keyframe's loop candidates are registered on the run's workers while this many later
keyframes are tracked, then applied in the order they were proposed, so the result does not
depend on timing or worker count. 2, not 1: a keyframe has up to
``loop_closure.max_candidates_per_frame`` candidates and tracking the next keyframe takes one or
two registrations, so one keyframe of slack would leave two workers idle."""

LOOP_CHECK_PROBABILITY = 0.999
"""A verified loop whose innovation d2 against the running (iSAM2) estimate exceeds the
chi-square (6 dof) quantile at this probability is held out of that estimate only (the batch
solve at the end decides): one true loop in a thousand is held out of it for nothing."""

QUERY_VIEW_CHANGE = 0.25
"""A keyframe asks for loop candidates once the camera has gone this fraction of the way to
leaving the last keyframe that asked (of an image side of pixel flow, or of 90 degrees of axis
turn): a revisit stays in view while the camera leaves it and is still queried about four times,
while a 30 Hz camera (a keyframe per 5 % step of its view) no longer proposes the same revisit at
every keyframe; views a third of an image apart query at every keyframe."""


class KeyframeManager:
    """Keyframe selection, odometry and loop closure over any :class:`PairRegistrar`."""

    def __init__(
        self,
        registrar: PairRegistrar,
        config: Config | None = None,
        store: FrameStore | None = None,
        loop_detector: LoopDetector | None = None,
        on_loop: Callable[[LoopRecord], None] | None = None,
        proximity_across_parts: bool = False,
        verifier: PairVerifier | None = None,
    ) -> None:
        self.registrar = registrar
        self.config = config or Config()
        self.store = store if store is not None else FrameStore()
        # loop candidates are registered by the verifier (in this process by default, or on the
        # run's workers) and applied VERIFY_LAG_KEYFRAMES keyframes later, in submission order
        self.verifier: PairVerifier = verifier if verifier is not None else InlineVerifier(registrar, self.store)
        self._pending_loops: deque[tuple[int, list[tuple[LoopCandidate, Future[Constraint]]]]] = deque()
        # each keyframe's twist over its rolling-shutter readout (motion.readout_motion; None: still)
        self._readout_motion: dict[int, NDArray[np.float64] | None] = {}
        self.loop_detector = loop_detector if loop_detector is not None else ProximityAppearanceLoopDetector(self.config.loop_closure, seed=self.config.run.seed)
        self.on_loop = on_loop
        # After a chain break the new part's poses are unrelated to the older parts' (it starts
        # at the last keyframe's pose), so by default only appearance proposes candidates across
        # parts. True restores proximity across parts (their pose guess is then arbitrary).
        self.proximity_across_parts = bool(proximity_across_parts)
        self.keyframe_ids: list[int] = []
        self.odometry: list[Constraint] = []
        self.loops: list[Constraint] = []
        self.loop_records: list[LoopRecord] = []
        self.chain_breaks: list[ChainBreak] = []
        self.segment_starts: list[int] = []
        # Current estimates: keyframes in the world; non-keyframes relative to their keyframe.
        self.T_world_keyframe: dict[int, NDArray[np.float64]] = {}
        self.T_keyframe_frame: dict[int, tuple[int, NDArray[np.float64]]] = {}
        self._drift_var_m2: dict[int, float] = {}
        # 6x6 [rot, trans] covariance (body frame) of each keyframe relative to its last closure
        self._drift_cov: dict[int, NDArray[np.float64]] = {}
        # median depth of each keyframe's points (m), for view_change: once per keyframe, not
        # once per frame registered to it (a median over ~2M points of an FPP frame)
        self._median_depth_m: dict[int, float] = {}
        self._parent: dict[int, int] = {}  # union-find over keyframes joined by odometry or loops
        # The running estimate: one iSAM2 graph per connected part, shared by its keyframes.
        self._incremental: dict[int, IncrementalPoseGraph] = {}
        self.held_out_loops: list[tuple[int, int]] = []
        # the last keyframe that asked the loop detector for candidates, and its view
        self._last_query: tuple[int, ViewModel | None] | None = None
        # tracking from motion (keyframes.track_from_motion): the prediction, track() and its counts
        self._tracking = MotionTracking(registrar, bool(self.config.keyframes.track_from_motion))
        # the last frame tracked against the current keyframe, with its odometry (kept until the next keyframe)
        self._last_tracked: tuple[Frame, Constraint] | None = None
        self._promoted_keyframes = 0  # such frames made keyframes (_promote)

    # -- per frame -------------------------------------------------------------------------
    def process(self, frame: Frame) -> bool:
        """Add one frame; returns whether it became a keyframe (InputDataError: the frame has no
        camera model while ``keyframes.min_view_change`` needs one)."""
        if frame.camera is None and self.config.keyframes.min_view_change > 0:
            raise InputDataError(
                f"frame {frame.id} has no camera model (Frame.camera), which keyframes.min_view_change measures the view "
                "change with: give the frame source's frames a fpp_graph.types.CameraModel, or set keyframes.min_view_change: 0 "
                "to make every frame a keyframe"
            )
        if not self.keyframe_ids:
            T0 = frame.T_world_sensor_guess if frame.T_world_sensor_guess is not None else np.eye(4)
            frame = self._add_keyframe(frame, np.array(T0), odometry=None, drift_var=0.0)
            self.segment_starts.append(frame.id)
            self.loop_detector.add(frame)
            self._keyframe_done(frame.id)
            self._tracking.predictor.observe(frame.id, frame.timestamp, None, np.eye(4))
            return True
        T_predicted = self._tracking.predict(self.keyframe_ids[-1], frame.timestamp)
        promotable = self._promotable()
        odometry = self._tracking.track(self.store.get(self.keyframe_ids[-1]), frame, T_predicted, last_try=promotable is None)
        if odometry is None and promotable is not None:
            self._promote(*promotable)
            T_predicted = self._tracking.predict(self.keyframe_ids[-1], frame.timestamp)
            odometry = self._tracking.track(self.store.get(self.keyframe_ids[-1]), frame, T_predicted)
        tracked = odometry is not None  # by the registrar's track(), from the prediction
        if odometry is None:
            odometry = self._register_to_recent(frame, T_predicted)
        if odometry is None:
            self._tracking.predictor.reset()
            self._tracking.predictor.observe(frame.id, frame.timestamp, None, np.eye(4))
            last = self.keyframe_ids[-1]
            T_guess = frame.T_world_sensor_guess
            T_start = np.array(T_guess) if T_guess is not None else self.T_world_keyframe[last].copy()
            log.warning("chain broken at frame %d: new segment starts there (pose unknown relative to the previous segment until a loop joins them)", frame.id)
            frame = self._add_keyframe(frame, T_start, odometry=None, drift_var=0.0)
            self.segment_starts.append(frame.id)
            self._close_loops(frame, force_query=True)  # appearance may rejoin the new segment to an older one
            self._keyframe_done(frame.id)
            return True
        kf_id = odometry.target_id
        is_keyframe = self._is_keyframe(odometry)
        self._tracking.predictor.observe(frame.id, frame.timestamp, kf_id, odometry.T_target_source)
        if is_keyframe:
            self._make_keyframe(frame, odometry)
            return True
        self.T_keyframe_frame[frame.id] = (kf_id, odometry.T_target_source.copy())
        self._last_tracked = (frame, odometry) if tracked else None
        return False

    def _make_keyframe(self, frame: Frame, odometry: Constraint) -> None:
        """``frame`` a keyframe, linked to its keyframe by ``odometry``; its loop candidates proposed."""
        kf_id = odometry.target_id
        self._last_tracked = None
        # the keyframe's motion while its rows were read out widens every constraint it takes part in
        self._readout_motion[frame.id] = readout_motion(frame, self._tracking.predictor.twist_per_s())
        odometry = with_readout_motion(odometry, self._readout_motion[frame.id], self._readout_motion.get(kf_id))
        T_world = compose(self.T_world_keyframe[kf_id], odometry.T_target_source)
        step_cov = constraint_covariance(odometry)
        step_var = step_position_variance_m2(step_cov, odometry.T_target_source)
        frame = self._add_keyframe(frame, T_world, odometry, self._drift_var_m2[kf_id] + step_var,
                                   transport_covariance(self._drift_cov[kf_id], odometry.T_target_source, step_cov))
        self._close_loops(frame)
        self._keyframe_done(frame.id)

    def _promotable(self) -> tuple[Frame, Constraint] | None:
        """The last frame tracked against the current keyframe, with its odometry, if any: a frame
        the keyframe no longer tracks can still be close to the frame before it, which saw more of it."""
        last = self._last_tracked
        return last if last is not None and last[1].target_id == self.keyframe_ids[-1] else None

    def _promote(self, frame: Frame, odometry: Constraint) -> None:
        """Make a :meth:`_promotable` frame a keyframe, ``odometry`` (its tracked constraint) its edge."""
        del self.T_keyframe_frame[frame.id]
        self._make_keyframe(frame, odometry)
        self._promoted_keyframes += 1

    def _register_to_recent(self, frame: Frame, T_predicted: NDArray[np.float64] | None = None) -> Constraint | None:
        reasons = []
        for kf_id in self.keyframe_ids[-1:-3:-1]:
            target = self.store.get(kf_id)
            T_guess = T_predicted if kf_id == self.keyframe_ids[-1] else None
            if frame.T_world_sensor_guess is not None and target.T_world_sensor_guess is not None:
                T_guess = invert(target.T_world_sensor_guess) @ frame.T_world_sensor_guess
            constraint = self.registrar.register(target, frame, T_guess, kind=ConstraintKind.ODOMETRY)
            if constraint.accepted:
                return replace(constraint, kind=ConstraintKind.ODOMETRY)
            reasons.append(f"to keyframe {kf_id}: {constraint.rejection_reason}")
            log.info("frame %d: registration %s", frame.id, reasons[-1])
        self.chain_breaks.append(ChainBreak(frame.id, self.keyframe_ids[-1], "; ".join(reasons)))
        return None

    def _is_keyframe(self, odometry: Constraint) -> bool:
        """Keyframe once the view moved by ``keyframes.min_view_change`` of the image side since
        the last keyframe (0: every frame; a keyframe without points in front of it: always)."""
        threshold = self.config.keyframes.min_view_change
        if threshold <= 0:
            return True
        keyframe = self.store.get(odometry.target_id)
        change = view_change(keyframe, odometry.T_target_source, self._keyframe_depth_m(keyframe))
        return change is None or change >= threshold

    def _keyframe_depth_m(self, keyframe: Frame) -> float:
        """The keyframe's median depth, computed once (a median over ~2M points of an FPP frame)."""
        if keyframe.id not in self._median_depth_m:
            self._median_depth_m[keyframe.id] = median_depth_m(keyframe)
        return self._median_depth_m[keyframe.id]

    def _find(self, k: int) -> int:
        root = k
        while self._parent[root] != root:
            root = self._parent[root]
        while self._parent[k] != root:  # path compression
            self._parent[k], k = root, self._parent[k]
        return root

    def _join(self, a: int, b: int) -> None:
        self._parent[self._find(a)] = self._find(b)

    def _add_keyframe(
        self, frame: Frame, T_world: NDArray, odometry: Constraint | None, drift_var: float, drift_cov: NDArray | None = None
    ) -> Frame:
        """Make ``frame`` a keyframe; returns it as stored, with its keypoints and descriptors (a
        source whose frames are tracked may decode them without: :class:`~fpp_graph.types.FrameDescriber`;
        the keyframe needs them for the loop detector's index, for loop verification on the
        workers, which read the stored copy, and for the frames tracked against it)."""
        self._parent.setdefault(frame.id, frame.id)
        if odometry is not None:
            self._join(frame.id, odometry.target_id)
        described = frame
        if frame.descriptors is None and isinstance(self.registrar, FrameDescriber):
            described = self.registrar.describe(frame)
        self.store.put(described, rewrite=described is not frame)
        frame = described
        self.keyframe_ids.append(frame.id)
        self.T_world_keyframe[frame.id] = np.asarray(T_world, dtype=np.float64)
        self._drift_var_m2[frame.id] = drift_var
        self._drift_cov[frame.id] = np.zeros((6, 6)) if drift_cov is None else drift_cov
        if odometry is None:  # first keyframe of a segment: a graph of its own, anchored there
            graph = self._new_incremental()
        else:
            self.odometry.append(odometry)
            graph = self._incremental[odometry.target_id]
        graph.add_keyframe(frame.id, self.T_world_keyframe[frame.id], odometry)
        self._incremental[frame.id] = graph
        return frame

    def _new_incremental(self) -> IncrementalPoseGraph:
        return IncrementalPoseGraph(self.config.pose_graph)

    def _keyframe_done(self, frame_id: int) -> None:
        """One iSAM2 update of the keyframe's part; the estimate feeds later proximity gates."""
        graph = self._incremental[frame_id]
        try:
            estimate = graph.update()
        except Exception as exc:  # keep tracking on the uncorrected chain rather than stop the run
            log.warning("iSAM2 update failed at keyframe %d (%s); continuing with the previous estimate", frame_id, exc)
            return
        # only the poses iSAM2's update re-read (the active part and a round robin of older
        # keyframes, see IncrementalPoseGraph): copying every pose would cost O(map) per keyframe
        for k in graph.refreshed_keys:
            self.T_world_keyframe[k] = estimate[k]

    # -- loops -----------------------------------------------------------------------------
    def _close_loops(self, frame: Frame, force_query: bool = False) -> None:
        """Propose the keyframe's loop candidates (when it is due to query, see
        :meth:`_due_to_query`) and submit their verification; apply the verifications that are
        due (those of the keyframe :data:`VERIFY_LAG_KEYFRAMES` back)."""
        if force_query or self._due_to_query(frame):
            self._last_query = (frame.id, ViewModel.of(frame, self._keyframe_depth_m(frame)))
            self._submit_loops(frame)
        else:
            self.loop_detector.add(frame)  # still a match for later queries
            self._pending_loops.append((frame.id, []))
        self._apply_due_loops(keep=VERIFY_LAG_KEYFRAMES)

    def _due_to_query(self, frame: Frame) -> bool:
        """Whether the keyframe asks for loop candidates: once the camera has gone
        :data:`QUERY_VIEW_CHANGE` (a quarter) of the way to leaving the last keyframe
        that asked, in either of the loop window's measures: that fraction of the image side of
        pixel flow, or of 90 degrees of optical-axis turn (always without a pinhole view). A
        revisit stays in view over a stretch of keyframes, so a query at every 5 % step of a
        30 Hz camera proposes the same revisit again and again; sparse captures (steps of a third
        of the view or more) query every time."""
        threshold = QUERY_VIEW_CHANGE
        last = self._last_query
        due = last is None or last[1] is None
        if not due:
            last_id, view = last
            T_last_frame = invert(self.T_world_keyframe[last_id]) @ self.T_world_keyframe[frame.id]
            # the loop window's two ways of leaving a place (a view side of pixel flow, or the
            # optical axis turned 90 degrees: an orbit keeps its centre in the image), scaled
            axis_turn_deg = math.degrees(math.acos(min(1.0, max(-1.0, float(T_last_frame[2, 2])))))
            due = axis_turn_deg >= 90.0 * threshold or view.change(T_last_frame) >= threshold
        return due

    def _submit_loops(self, frame: Frame) -> None:
        sigma = math.sqrt(self._drift_var_m2[frame.id])
        # Proximity means something only within the query's connected part: after a chain break
        # the new part's poses are unrelated to the older parts' (unless the frame brings a prior
        # pose), so across parts only appearance proposes candidates.
        if frame.T_world_sensor_guess is None and not self.proximity_across_parts:
            root = self._find(frame.id)
            poses = {k: T for k, T in self.T_world_keyframe.items() if self._find(k) == root}
        else:
            poses = self.T_world_keyframe
        candidates: list[LoopCandidate] = list(
            self.loop_detector.candidates(frame, poses, position_sigma_m=sigma)
        )
        self.loop_detector.add(frame)
        submitted = []
        for cand in candidates:
            T_guess = invert(self.T_world_keyframe[cand.match_id]) @ self.T_world_keyframe[frame.id]
            guess = T_guess if "proximity" in cand.source else None
            submitted.append((cand, self.verifier.submit(cand.match_id, frame.id, guess, ConstraintKind.LOOP)))
        self._pending_loops.append((frame.id, submitted))

    def _apply_due_loops(self, keep: int = 0) -> None:
        """Apply the verifications of the oldest keyframes until at most ``keep`` keyframes'
        remain pending: in submission order, waiting for each result, so the order and the
        running estimate never depend on which worker finished first."""
        while len(self._pending_loops) > keep:
            query_id, submitted = self._pending_loops.popleft()
            matched = [cand.match_id for cand, future in submitted if self._apply_loop(query_id, cand, future.result())]
            if matched:
                self._closed_at(query_id, matched)

    def _apply_loop(self, query_id: int, cand: LoopCandidate, constraint: Constraint) -> bool:
        """Record one verified (or refused) candidate; whether it entered the running estimate."""
        record = LoopRecord(
            query_id=query_id,
            match_id=cand.match_id,
            stage=cand.source,
            score=cand.score,
            verified=constraint.accepted,
            reason=constraint.rejection_reason,
            fitness=constraint.fitness,
            inlier_rmse_m=constraint.inlier_rmse_m,
            inlier_count=constraint.inlier_count,
        )
        entered = False
        if constraint.accepted:
            log.info(
                "loop %d->%d (%s, score %.3f) accepted: fitness %.3f, rmse %.3f mm, %d inliers",
                query_id, cand.match_id, cand.source, cand.score, constraint.fitness,
                constraint.inlier_rmse_m * 1e3, constraint.inlier_count,
            )
            loop = with_readout_motion(
                replace(constraint, kind=ConstraintKind.LOOP), self._readout_motion.get(constraint.source_id), self._readout_motion.get(constraint.target_id)
            )
            self.loops.append(loop)  # every verified loop reaches the final batch solve
            self._join(query_id, cand.match_id)
            entered = self._add_to_running_estimate(loop)
            if not entered:
                record = replace(record, held_out=True)
        else:
            log.info("loop %d->%d (%s, score %.3f) rejected: %s", query_id, cand.match_id, cand.source, cand.score, constraint.rejection_reason)
        self.loop_records.append(record)
        if self.on_loop is not None:
            self.on_loop(record)
        return entered

    def _closed_at(self, query_id: int, matched: list[int]) -> None:
        """The closure ties the query keyframe to older ones: its drift is now theirs."""
        self._drift_var_m2[query_id] = min(self._drift_var_m2[m] for m in matched)
        T_q = self.T_world_keyframe[query_id]
        moved = [transport_covariance(self._drift_cov[m], invert(self.T_world_keyframe[m]) @ T_q) for m in matched]
        self._drift_cov[query_id] = min(moved, key=lambda c: float(np.trace(c)))

    def _add_to_running_estimate(self, loop: Constraint) -> bool:
        """Put a verified loop into iSAM2 unless its innovation test fails; whether it went in.

        The test: ``d2 = r^T (Sigma_loop + Sigma_rel)^-1 r <= chi2_6(p)``, ``r`` the loop's
        residual at the current estimate (``Log(T_target_source^-1 T_world_target^-1
        T_world_source)``, 6 dof), ``p =`` :data:`LOOP_CHECK_PROBABILITY`. Why: for a true
        loop and an unbiased estimate, ``r`` is zero-mean Gaussian with the loop's covariance
        plus that of the estimated relative pose, so ``d2`` is chi-square with 6 degrees of
        freedom and the test holds out a true loop with probability ``1 - p`` only, whereas a
        false loop (a look-alike place, a wrong ICP basin) sits many sigmas off. The relative
        pose's covariance matters: after a long stretch of odometry it dwarfs an ICP loop's,
        and the loop's covariance alone would hold out every first closure. ``Sigma_rel`` is
        bounded by the drift both keyframes accumulated since their last closure (odometry
        covariances propagated along the chain, :func:`transport_covariance`), summed as if
        independent: an overestimate, so the test errs towards letting a loop in (GNC at the
        batch solve has the last word), and free, unlike iSAM2's joint marginal of the two
        keyframes (a Bayes-tree shortcut per loop, milliseconds to tens of milliseconds).

        A loop that joins two parts is not tested (nothing else relates them): it merges the
        two iSAM2 graphs.
        """
        q, m = loop.source_id, loop.target_id
        graph, other = self._incremental[q], self._incremental[m]
        if graph is not other:
            # the part that started first keeps its anchor (the run's frame for the first part)
            order = {k: i for i, k in enumerate(self.segment_starts)}
            keep, gone = (graph, other) if order[graph.anchor] < order[other.anchor] else (other, graph)
            moved = gone.keys()
            keep.absorb(gone, loop)
            for k in moved:
                self._incremental[k] = keep
            self.T_world_keyframe.update(keep.estimate())
            log.info("loop %d->%d joins two parts of the trajectory: their running estimates are merged", q, m)
            return True
        T_m_q = invert(self.T_world_keyframe[m]) @ self.T_world_keyframe[q]
        sigma_rel = self._drift_cov[q] + transport_covariance(self._drift_cov[m], T_m_q)
        d2 = graph.loop_innovation(loop, relative_covariance=sigma_rel)
        bound = chi2_6_quantile(LOOP_CHECK_PROBABILITY)
        if d2 > bound:
            self.held_out_loops.append((q, m))
            log.warning(
                "loop %d->%d held out of the running estimate: innovation d2 %.3g > chi-square bound %.3g "
                "(it stays in the final robust solve); %d loop(s) held out so far",
                q, m, d2, bound, len(self.held_out_loops),
            )
            return False
        graph.add_loop(loop)
        return True

    # -- final -----------------------------------------------------------------------------
    def components(self) -> list[list[int]]:
        graph = nx.Graph()
        graph.add_nodes_from(self.keyframe_ids)
        for c in [*self.odometry, *self.loops]:
            graph.add_edge(c.source_id, c.target_id)
        order = {k: i for i, k in enumerate(self.keyframe_ids)}
        comps = [sorted(c, key=order.__getitem__) for c in nx.connected_components(graph)]
        return sorted(comps, key=lambda c: order[c[0]])

    def _optimize_components(self):
        from fpp_graph.backend.pose_graph import PoseGraph

        poses: dict[int, NDArray[np.float64]] = {}
        rejected: list[tuple[int, int]] = []
        stats: dict = {"components": []}
        # the mirror copies only the poses each update re-read: start from iSAM2's full estimate
        for graph in {id(g): g for g in self._incremental.values()}.values():
            try:
                self.T_world_keyframe.update(graph.estimate())
            except Exception as exc:
                log.warning("reading the iSAM2 estimate failed (%s); the batch solve starts from the mirrored poses", exc)
        for comp in self.components():
            members = set(comp)
            graph = PoseGraph()
            for k in comp:
                graph.add_pose(k, self.T_world_keyframe[k])
            graph.fix_pose(comp[0])
            n_edges = 0
            for c in [*self.odometry, *self.loops]:
                if c.source_id in members and c.target_id in members:
                    graph.add_constraint(c)
                    n_edges += 1
            if n_edges == 0:
                poses[comp[0]] = self.T_world_keyframe[comp[0]]
                continue
            result = graph.optimize(self.config.pose_graph)
            poses.update(result.poses_world_sensor)
            rejected.extend(result.rejected_loops)
            rejected.extend(result.inconsistent_loops)
            stats["components"].append(
                {
                    "first": comp[0],
                    "size": len(comp),
                    "initial_cost": result.initial_cost,
                    "final_cost": result.final_cost,
                    "iterations": result.iterations,
                    "seconds": result.seconds,
                    "initialization": result.initialization,
                }
            )
        return poses, sorted(set(rejected)), stats

    def finish(self) -> SlamResult:
        """Apply the loops still being verified, then the final robust optimisation; poses for
        every processed frame."""
        self._apply_due_loops(keep=0)
        if self.keyframe_ids:
            poses, rejected, stats = self._optimize_components()
            self.T_world_keyframe.update(poses)
        else:
            rejected, stats = [], {}
        stats["held_out_loops"] = len(self.held_out_loops)
        if self.held_out_loops:
            log.info("%d loop(s) were held out of the running estimate by the innovation test: %s",
                     len(self.held_out_loops), self.held_out_loops)
        rejected_set = set(rejected)
        self.loop_records = [
            replace(r, rejected_by_backend=(r.query_id, r.match_id) in rejected_set) if r.verified else r
            for r in self.loop_records
        ]
        all_poses = dict(self.T_world_keyframe)
        for fid, (kf, T_kf_frame) in self.T_keyframe_frame.items():
            all_poses[fid] = compose(self.T_world_keyframe[kf], T_kf_frame)
        components = self.components()
        if len(components) > 1:
            log.warning(
                "the trajectory has %d disconnected parts (chain broke at frames %s): %s",
                len(components), [b.frame_id for b in self.chain_breaks],
                "; ".join(f"{c[0]}..{c[-1]} ({len(c)} keyframes)" for c in components),
            )
        return SlamResult(
            poses_world_sensor=dict(sorted(all_poses.items())),
            keyframe_ids=list(self.keyframe_ids),
            odometry=list(self.odometry),
            loops=list(self.loops),
            loop_records=list(self.loop_records),
            chain_breaks=list(self.chain_breaks),
            components=components,
            rejected_loops=rejected,
            optimization=stats,
            held_out_loops=list(self.held_out_loops),
            tracking=self._tracking.summary() | ({"promoted_keyframes": self._promoted_keyframes} if self._tracking.tracker is not None else {}),
        )
