"""What a run of the :class:`~fpp_graph.slam.keyframes.KeyframeManager` gives: the poses, the
keyframes, the odometry and loop constraints, each loop candidate's fate and the chain breaks."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fpp_graph.types import Constraint


@dataclass(frozen=True)
class LoopRecord:
    """What happened to one loop candidate."""

    query_id: int
    match_id: int
    stage: str  # proximity | appearance | proximity+appearance
    score: float
    verified: bool
    reason: str | None
    fitness: float
    inlier_rmse_m: float
    inlier_count: int
    rejected_by_backend: bool = False
    held_out: bool = False  # verified, but failed the innovation test: kept out of the running estimate


@dataclass(frozen=True)
class ChainBreak:
    """Registration failed between ``frame_id`` and every keyframe tried."""

    frame_id: int
    last_keyframe_id: int
    reason: str


@dataclass
class SlamResult:
    """Outcome of a run of the keyframe manager."""

    poses_world_sensor: dict[int, NDArray[np.float64]]
    keyframe_ids: list[int]
    odometry: list[Constraint]
    loops: list[Constraint]
    loop_records: list[LoopRecord]
    chain_breaks: list[ChainBreak]
    components: list[list[int]]
    rejected_loops: list[tuple[int, int]]
    optimization: dict = field(default_factory=dict)
    held_out_loops: list[tuple[int, int]] = field(default_factory=list)  # (query, match), see LoopRecord.held_out
    # keyframes.track_from_motion: {"tracked_frames": n, "fallbacks": {reason: count}, "promoted_keyframes": n}
    tracking: dict = field(default_factory=dict)
