"""Loop-closure candidates: pose proximity under the current estimate, and appearance.

Two independent proposers, because each fails where the other works: proximity needs a decent
pose estimate (fails after large drift), appearance needs distinctive texture (fails on
look-alike places, e.g. repeated posters, and proposes false loops there). Every candidate is then
verified geometrically by the front-end's :class:`~fpp_graph.types.PairRegistrar` and the robust
back-end (GNC) has the last word.

Appearance is a VLAD global descriptor (an aggregated bag of visual words) over the frames'
keypoint descriptors, with a vocabulary clustered (k-means) from the first keyframes'
descriptors, so it adapts to whatever descriptor the front-end uses (SURF, SIFT, ORB bits, ...).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from fpp_graph.config import LoopClosureConfig
from fpp_graph.geometry import invert
from fpp_graph.slam.views import ViewModel
from fpp_graph.types import Frame, LoopCandidate

log = logging.getLogger(__name__)


def _as_float_descriptors(descriptors: NDArray) -> NDArray[np.float32]:
    d = np.asarray(descriptors)
    if d.dtype == np.uint8 and d.ndim == 2:
        # Binary descriptors (ORB, AKAZE): cluster their bits so Hamming ~ squared Euclidean.
        return np.unpackbits(d, axis=1).astype(np.float32)
    return d.astype(np.float32, copy=False)


class AppearanceIndex:
    """VLAD global descriptors over keyframe descriptors, scored by cosine similarity.

    VLAD (Jegou et al. 2010) sums, per visual word, the residuals of the descriptors assigned to
    it; unlike a plain bag-of-words histogram it keeps where in descriptor space each feature
    lies, so two views of the same texture correlate strongly while different places score near
    zero. Signed square-root (power) normalisation, then per-word and global L2 normalisation.
    The vocabulary is clustered (k-means) from the first keyframes' descriptors.
    """

    def __init__(self, vocabulary_size: int = 64, training_descriptors: int = 20000, seed: int = 0) -> None:
        self.vocabulary_size = vocabulary_size
        self.training_descriptors = training_descriptors
        self.seed = seed
        self._pending: list[tuple[int, NDArray[np.float32]]] = []
        self._centroids: NDArray[np.float64] | None = None
        self._tree: cKDTree | None = None
        self._vectors: dict[int, NDArray[np.float64]] = {}

    def _train(self) -> None:
        from scipy.cluster.vq import kmeans2

        sample = np.concatenate([d for _, d in self._pending])
        rng = np.random.default_rng(self.seed)
        if len(sample) > self.training_descriptors:
            sample = sample[rng.choice(len(sample), self.training_descriptors, replace=False)]
        k = min(self.vocabulary_size, max(2, len(sample) // 8))
        centroids, _ = kmeans2(sample.astype(np.float64), k, minit="++", seed=self.seed, iter=15)
        self._centroids = centroids
        self._tree = cKDTree(centroids)
        pending, self._pending = self._pending, []
        for frame_id, desc in pending:
            self._vectors[frame_id] = self._vlad(desc)
        log.debug("appearance vocabulary: %d words from %d descriptors", k, len(sample))

    def _vlad(self, desc: NDArray[np.float32]) -> NDArray[np.float64]:
        assert self._tree is not None and self._centroids is not None
        _, words = self._tree.query(desc, k=1)
        k, dim = self._centroids.shape
        residuals = desc.astype(np.float64) - self._centroids[words]
        vlad = np.zeros((k, dim))
        np.add.at(vlad, words, residuals)
        vlad = np.sign(vlad) * np.sqrt(np.abs(vlad))
        norms = np.linalg.norm(vlad, axis=1, keepdims=True)
        vlad = np.divide(vlad, norms, out=np.zeros_like(vlad), where=norms > 0)
        flat = vlad.reshape(-1)
        norm = np.linalg.norm(flat)
        return flat / norm if norm > 0 else flat

    def add(self, frame_id: int, descriptors: NDArray | None) -> None:
        """Index a keyframe's descriptors (frames without descriptors are ignored)."""
        if descriptors is None or len(descriptors) == 0:
            return
        desc = _as_float_descriptors(descriptors)
        if self._tree is None:
            self._pending.append((frame_id, desc))
            if sum(len(d) for _, d in self._pending) >= 16 * self.vocabulary_size and len(self._pending) >= 2:
                self._train()
            return
        self._vectors[frame_id] = self._vlad(desc)

    def query(self, descriptors: NDArray | None, top_k: int, exclude: set[int] | None = None) -> list[tuple[int, float]]:
        """The ``top_k`` indexed frames most similar to ``descriptors`` as ``(frame_id, cosine)``."""
        if descriptors is None or len(descriptors) == 0 or top_k <= 0:
            return []
        if self._tree is None:
            if len(self._pending) >= 1 and sum(len(d) for _, d in self._pending) >= 2 * self.vocabulary_size:
                self._train()
            else:
                return []
        q = self._vlad(_as_float_descriptors(descriptors))
        exclude = exclude or set()
        scores = [(fid, float(q @ v)) for fid, v in self._vectors.items() if fid not in exclude]
        scores.sort(key=lambda s: -s[1])
        return scores[:top_k]


PROXIMITY_SIGMAS = 3.0
"""The proximity radius grows by this many standard deviations of the new keyframe's position
(largest axis of its drift covariance), so the gate widens as drift grows: 3 holds a revisit
inside the pose uncertainty with 99.7 % probability per axis."""

APPEARANCE_MIN_SCORE = 0.1
"""Least VLAD cosine similarity of an appearance candidate: low on purpose, verification by
registration rejects the false ones (``loop_closure.appearance_top_k`` bounds their cost)."""

MIN_KEYFRAME_SEPARATION = 5
"""Keyframes fewer than this many keyframes apart are never loop candidates of each other: the
odometry chain already links them."""

REVISIT_VIEW_CHANGE = 1.0
"""A keyframe is a loop candidate once the camera's view has moved away from it by this fraction
of the image side at some keyframe since, or its optical axis turned by 90 degrees (1: the whole
view, at its median depth, left the image); until then the odometry chain runs through frames
that keep seeing it (ORB-SLAM's covisibility exclusion)."""


class ProximityAppearanceLoopDetector:
    """Implements :class:`~fpp_graph.types.LoopDetector` with pose proximity and appearance.

    Proximity: earlier keyframes whose position, under the current estimate, lies within
    ``proximity_radius_m + PROXIMITY_SIGMAS * sigma`` of the query, where ``sigma`` is the position
    standard deviation of the query's marginal covariance (so the gate widens as drift grows) and
    whose optical axes point within 90 degrees (a sensor facing away sees nothing in common),
    best first by the share of the query's image their view covers under the estimate
    (:meth:`~fpp_graph.slam.views.ViewModel.overlap`; the distance breaks ties and ranks
    keyframes without a pinhole view). Nearest first instead spent a camera turning on the
    spot's slots on keyframes looking elsewhere: all of them lie within the radius.
    Appearance: the best ``appearance_top_k`` bag-of-words matches.

    Neither proposes a keyframe of the query's local window: one closer than
    :data:`MIN_KEYFRAME_SEPARATION` in the sequence, or one the camera has not left yet, i.e. whose
    view has not moved by :data:`REVISIT_VIEW_CHANGE` (a fraction of the image side, see
    :func:`~fpp_graph.slam.views.view_change`), nor turned its optical axis by 90 degrees, at any
    keyframe since, under the current estimate.
    Those are linked by the odometry chain through frames that keep seeing them; a revisit is
    coming back to a place after leaving it. Keyframes without a pinhole view (no ``K``), or
    outside the query's part of the trajectory, are outside every window.
    """

    def __init__(self, config: LoopClosureConfig | None = None, seed: int = 0) -> None:
        self.config = config or LoopClosureConfig()
        self.appearance = AppearanceIndex(seed=seed)
        self._order: list[int] = []
        self._index: dict[int, int] = {}  # frame id -> its (last) position in self._order
        # keyframes the camera has not left yet, with their views (oldest first)
        self._in_view: dict[int, ViewModel] = {}
        self._views: dict[int, ViewModel] = {}  # every keyframe's (a few numbers each)

    def add(self, frame: Frame) -> None:
        self._index[frame.id] = len(self._order)
        self._order.append(frame.id)
        self.appearance.add(frame.id, frame.descriptors)
        view = ViewModel.of(frame)
        if view is not None:
            self._views[frame.id] = view
            self._in_view[frame.id] = view

    def local_window(self, frame_id: int, poses_world_sensor: Mapping[int, NDArray[np.float64]]) -> set[int]:
        """Keyframes the camera has not left by ``frame_id``'s pose (updated with it: once left, never back)."""
        T_world_query = poses_world_sensor.get(frame_id)
        if T_world_query is None:
            return set(self._in_view)
        threshold = REVISIT_VIEW_CHANGE
        for fid in list(self._in_view):
            T_world_kf = poses_world_sensor.get(fid)
            # another part of the trajectory is not linked to the query by odometry: not local;
            # optical axes 90 degrees apart or more: the keyframe's surfaces are seen edge-on or
            # from behind (an orbit around an object keeps its centre in the image, so the
            # pixel flow alone would call the far side of a turntable still in view)
            if (
                T_world_kf is None
                or float(T_world_kf[:3, 2] @ T_world_query[:3, 2]) <= 0.0
                or self._in_view[fid].change(invert(T_world_kf) @ T_world_query) >= threshold
            ):
                del self._in_view[fid]
        return set(self._in_view)

    def _overlap_score(self, fid: int, T_world_kf: NDArray[np.float64], T_world_query: NDArray[np.float64], distance_m: float, radius_m: float) -> float:
        """How much of keyframe ``fid``'s view the query sees under the estimate, in [0, 1]: the
        share of the query's image the view covers (:meth:`ViewModel.overlap`; a turn on the spot
        loses overlap as a step sideways does), or 1 minus the distance over the gate's radius
        for a keyframe without a pinhole view."""
        view = self._views.get(fid)
        if view is None:
            return 1.0 - distance_m / max(radius_m, 1e-12)
        return view.overlap(invert(T_world_kf) @ T_world_query)

    def candidates(
        self,
        frame: Frame,
        poses_world_sensor: Mapping[int, NDArray[np.float64]],
        position_sigma_m: float = 0.0,
    ) -> Sequence[LoopCandidate]:
        cfg = self.config
        if not cfg.enabled:
            return []
        index_of = self._index
        position_in_sequence = index_of.get(frame.id, len(self._order))
        sep = MIN_KEYFRAME_SEPARATION
        near = self._order[max(0, position_in_sequence - sep + 1): max(0, position_in_sequence + sep)]
        too_close = {fid for fid in near if abs(position_in_sequence - index_of[fid]) < sep}
        too_close.add(frame.id)
        too_close |= self.local_window(frame.id, poses_world_sensor)
        found: dict[int, LoopCandidate] = {}
        distance_of: dict[int, float] = {}
        T_world_query = poses_world_sensor.get(frame.id)
        if T_world_query is not None:
            radius = cfg.proximity_radius_m + PROXIMITY_SIGMAS * max(0.0, position_sigma_m)
            # One vectorised pass over the keyframes (a 4x4 inverse per keyframe in Python cost
            # ~7 ms per query at 1000 keyframes): with T_other_query = T_world_other^-1
            # T_world_query, its translation's norm is the distance between the two positions
            # and its [2, 2] entry the cosine between the two optical (+z) axes.
            fids = [fid for fid in self._order if fid not in too_close and fid in poses_world_sensor]
            if fids:
                T = np.stack([np.asarray(poses_world_sensor[fid], dtype=np.float64) for fid in fids])
                Tq = np.asarray(T_world_query, dtype=np.float64)
                distance = np.linalg.norm(T[:, :3, 3] - Tq[:3, 3], axis=1)
                facing = T[:, :3, 2] @ Tq[:3, 2]
                distance_of.update(zip(fids, distance.tolist(), strict=True))
                for i in np.flatnonzero((distance <= radius) & (facing > 0.0)):
                    score = self._overlap_score(fids[i], T[i], Tq, float(distance[i]), radius)
                    found[fids[i]] = LoopCandidate(frame.id, fids[i], score, "proximity")
        proximity = sorted(found.values(), key=lambda c: (-c.score, distance_of[c.match_id]))
        appearance: list[LoopCandidate] = []
        for fid, score in self.appearance.query(frame.descriptors, cfg.appearance_top_k, exclude=too_close):
            if score < APPEARANCE_MIN_SCORE:
                continue
            if fid in found:
                found[fid] = LoopCandidate(frame.id, fid, found[fid].score, "proximity+appearance")
            else:
                appearance.append(LoopCandidate(frame.id, fid, score, "appearance"))
        # proximity candidates first (most overlap first): they are the likely revisits under a
        # decent estimate; appearance fills the remaining slots (it finds loops after drift)
        proximity = [found[c.match_id] for c in proximity]
        n_prox = max(0, cfg.max_candidates_per_frame - len(appearance))
        return [*proximity[:n_prox], *appearance][: cfg.max_candidates_per_frame]
