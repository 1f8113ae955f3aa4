"""The running state of one pair through :meth:`FppPairRegistrar.register`.

Each stage writes its typed result into :class:`PairState`; the gates (:mod:`.gates`) read it.
``meta`` is only the constraint's metadata being assembled (output), never read for control.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.types import ConstraintKind, Frame
from frontend.registration.keypoints import RansacResult
from frontend.registration.refinement import DenseOutcome, PhotometricOutcome, WeakGeometryCheck
from frontend.registration.stages import (
    IcpOutcome,
    KeypointMatches,
    KeypointTerm,
    LiftedMatches,
    PoseEstimate,
    WeakDirectionOutcome,
)


class StageTimer:
    """Wall and process-CPU seconds per stage of one pair (the registrar's ``last_timings_s`` and
    ``last_cpu_timings_s``). A stage that raises is not recorded."""

    def __init__(self) -> None:
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}

    @staticmethod
    def start() -> tuple[float, float]:
        return time.perf_counter(), time.process_time()

    def stop(self, stage: str, started: tuple[float, float], accumulate: bool = False) -> None:
        wall, cpu = time.perf_counter() - started[0], time.process_time() - started[1]
        if accumulate:
            self.wall_s[stage] += wall
            self.cpu_s[stage] += cpu
        else:
            self.wall_s[stage], self.cpu_s[stage] = wall, cpu

    def zero(self, *stages: str) -> None:
        """Start accumulating stages that may run more than once (ICP per voxel size)."""
        for stage in stages:
            self.wall_s[stage] = self.cpu_s[stage] = 0.0


@dataclass
class PairState:
    """Everything known about the pair so far; a stage's field is None until it has run."""

    target: Frame
    source: Frame
    kind: ConstraintKind | str
    T_guess: NDArray[np.float64] | None
    timer: StageTimer = field(default_factory=StageTimer)
    meta: dict[str, Any] = field(default_factory=dict)
    matches: KeypointMatches | None = None
    lifted: LiftedMatches | None = None
    ransac: RansacResult | None = None
    icp: IcpOutcome | None = None
    weak: WeakDirectionOutcome | None = None
    keypoints: KeypointTerm | None = None
    pose: PoseEstimate | None = None
    dense: DenseOutcome | None = None
    photometric: PhotometricOutcome | None = None
    check: WeakGeometryCheck | None = None

    @property
    def quality(self) -> dict[str, Any]:
        """The constraint's quality figures as far as they are known: RANSAC's inlier count, then
        ICP's correspondences at the current pose."""
        if self.ransac is None:
            return {}
        icp = self.weak.icp if self.weak is not None else self.icp.icp if self.icp is not None else None
        if icp is None:
            return {"inlier_count": self.ransac.num_inliers}
        return {"fitness": icp.fitness, "inlier_rmse_m": icp.inlier_rmse_m, "inlier_count": self.ransac.num_inliers, "overlap": icp.overlap}
