"""Loop-closure candidates: pose proximity under the current estimate, and appearance.

Two independent proposers, because each fails where the other works: proximity needs a decent
pose estimate (fails after large drift), appearance needs distinctive texture (fails on
look-alike places, e.g. repeated posters, and proposes false loops there). Every candidate is then
verified geometrically by the front-end's :class:`~fpp_graph.types.PairRegistrar` and the robust
back-end (GNC) has the last word.

Appearance is a TF-IDF bag of visual words over the frames' keypoint descriptors, with a
vocabulary clustered (k-means) from the first keyframes' descriptors, so it adapts to whatever
descriptor the front-end uses (SURF, SIFT, ORB bits, ...).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from fpp_graph.config import LoopClosureConfig
from fpp_graph.geometry import invert
from fpp_graph.types import Frame, LoopCandidate

log = logging.getLogger(__name__)


def _as_float_descriptors(descriptors: NDArray) -> NDArray[np.float32]:
    d = np.asarray(descriptors)
    if d.dtype == np.uint8 and d.ndim == 2:
        # Binary descriptors (ORB, AKAZE): cluster their bits so Hamming ~ squared Euclidean.
        return np.unpackbits(d, axis=1).astype(np.float32)
    return d.astype(np.float32, copy=False)


class AppearanceIndex:
    """TF-IDF bag-of-words index over keyframe descriptors, scored by cosine similarity."""

    def __init__(self, vocabulary_size: int = 256, training_descriptors: int = 20000, seed: int = 0) -> None:
        self.vocabulary_size = vocabulary_size
        self.training_descriptors = training_descriptors
        self.seed = seed
        self._pending: list[tuple[int, NDArray[np.float32]]] = []
        self._tree: cKDTree | None = None
        self._histograms: dict[int, NDArray[np.float64]] = {}
        self._document_frequency: NDArray[np.float64] | None = None

    @property
    def trained(self) -> bool:
        return self._tree is not None

    def _train(self) -> None:
        from scipy.cluster.vq import kmeans2

        sample = np.concatenate([d for _, d in self._pending])
        rng = np.random.default_rng(self.seed)
        if len(sample) > self.training_descriptors:
            sample = sample[rng.choice(len(sample), self.training_descriptors, replace=False)]
        k = min(self.vocabulary_size, max(2, len(sample) // 4))
        centroids, _ = kmeans2(sample.astype(np.float64), k, minit="++", seed=self.seed, iter=15)
        self._tree = cKDTree(centroids)
        self._document_frequency = np.zeros(k)
        pending, self._pending = self._pending, []
        for frame_id, desc in pending:
            self._insert(frame_id, desc)
        log.debug("appearance vocabulary: %d words from %d descriptors", k, len(sample))

    def _words(self, desc: NDArray[np.float32]) -> NDArray[np.float64]:
        assert self._tree is not None
        _, words = self._tree.query(desc, k=1)
        return np.bincount(words, minlength=self._tree.n).astype(np.float64)

    def _insert(self, frame_id: int, desc: NDArray[np.float32]) -> None:
        counts = self._words(desc)
        self._histograms[frame_id] = counts
        assert self._document_frequency is not None
        self._document_frequency += counts > 0

    def add(self, frame_id: int, descriptors: NDArray | None) -> None:
        """Index a keyframe's descriptors (frames without descriptors are ignored)."""
        if descriptors is None or len(descriptors) == 0:
            return
        desc = _as_float_descriptors(descriptors)
        if self._tree is None:
            self._pending.append((frame_id, desc))
            if sum(len(d) for _, d in self._pending) >= 4 * self.vocabulary_size and len(self._pending) >= 2:
                self._train()
            return
        self._insert(frame_id, desc)

    def _tfidf(self, counts: NDArray[np.float64]) -> NDArray[np.float64]:
        assert self._document_frequency is not None
        n_docs = max(1, len(self._histograms))
        idf = np.log((n_docs + 1.0) / (self._document_frequency + 1.0)) + 1.0
        v = counts / max(counts.sum(), 1.0) * idf
        norm = np.linalg.norm(v)
        return v / norm if norm > 0 else v

    def query(self, descriptors: NDArray | None, top_k: int, exclude: set[int] | None = None) -> list[tuple[int, float]]:
        """The ``top_k`` indexed frames most similar to ``descriptors`` as ``(frame_id, cosine)``."""
        if descriptors is None or len(descriptors) == 0 or top_k <= 0:
            return []
        if self._tree is None:
            if len(self._pending) >= 2:
                self._train()
            else:
                return []
        q = self._tfidf(self._words(_as_float_descriptors(descriptors)))
        exclude = exclude or set()
        scores = [
            (fid, float(q @ self._tfidf(h))) for fid, h in self._histograms.items() if fid not in exclude
        ]
        scores.sort(key=lambda s: -s[1])
        return scores[:top_k]


@dataclass(frozen=True)
class PoseUncertainty:
    """Position standard deviation (m) of a keyframe relative to another, from the covariance."""

    position_sigma_m: float


class ProximityAppearanceLoopDetector:
    """Implements :class:`~fpp_graph.types.LoopDetector` with pose proximity and appearance.

    Proximity: earlier keyframes whose position, under the current estimate, lies within
    ``proximity_radius_m + proximity_sigma * sigma`` of the query, where ``sigma`` is the position
    standard deviation of the query's marginal covariance (so the gate widens as drift grows) and
    whose optical axes point within 90 degrees (a sensor facing away sees nothing in common).
    Appearance: the best ``appearance_top_k`` bag-of-words matches. Keyframes closer than
    ``min_frame_separation`` in the sequence are never proposed (that is odometry's job).
    """

    def __init__(self, config: LoopClosureConfig | None = None) -> None:
        self.config = config or LoopClosureConfig()
        self.appearance = AppearanceIndex()
        self._order: list[int] = []

    def add(self, frame: Frame) -> None:
        self._order.append(frame.id)
        self.appearance.add(frame.id, frame.descriptors)

    def candidates(
        self,
        frame: Frame,
        poses_world_sensor: Mapping[int, NDArray[np.float64]],
        position_sigma_m: float = 0.0,
    ) -> Sequence[LoopCandidate]:
        cfg = self.config
        if not cfg.enabled:
            return []
        index_of = {fid: i for i, fid in enumerate(self._order)}
        position_in_sequence = index_of.get(frame.id, len(self._order))
        too_close = {
            fid for fid, i in index_of.items() if abs(position_in_sequence - i) < cfg.min_frame_separation
        }
        too_close.add(frame.id)
        found: dict[int, LoopCandidate] = {}
        T_world_query = poses_world_sensor.get(frame.id)
        if T_world_query is not None:
            radius = cfg.proximity_radius_m + cfg.proximity_sigma * max(0.0, position_sigma_m)
            for fid in self._order:
                T_world_other = poses_world_sensor.get(fid)
                if fid in too_close or T_world_other is None:
                    continue
                T_other_query = invert(T_world_other) @ T_world_query
                distance = float(np.linalg.norm(T_other_query[:3, 3]))
                facing = float(T_other_query[2, 2])  # cosine between the two optical (+z) axes
                if distance <= radius and facing > 0.0:
                    score = 1.0 - distance / max(radius, 1e-12)
                    found[fid] = LoopCandidate(frame.id, fid, score, "proximity")
        for fid, score in self.appearance.query(frame.descriptors, cfg.appearance_top_k, exclude=too_close):
            if fid in found:
                found[fid] = LoopCandidate(frame.id, fid, max(found[fid].score, score), "proximity+appearance")
            elif score > 0:
                found[fid] = LoopCandidate(frame.id, fid, score, "appearance")
        ranked = sorted(found.values(), key=lambda c: -c.score)
        return ranked[: cfg.max_candidates_per_frame]


def position_sigma_from_covariance(covariance_rot_trans: NDArray[np.float64] | None) -> float:
    """Largest position standard deviation (m) of a 6x6 [rot, trans] covariance; 0 if unknown."""
    if covariance_rot_trans is None:
        return 0.0
    cov = np.asarray(covariance_rot_trans)[3:, 3:]
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    return math.sqrt(max(float(eig.max()), 0.0))
