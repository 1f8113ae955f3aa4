"""The ICP of a pair as a declared protocol, :class:`PointCloudAligner`: the ICP stage aligns two
frames' voxelised clouds through it. Implementations (:mod:`frontend.registration.icp`):
small_gicp's GICP and point-to-plane ICP, and the start pose measured (``icp.method: none``);
:func:`~frontend.registration.icp.make_aligner` chooses one, ``TexturedSurfaceRegistrar(aligner=...)``
takes another."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from frontend.registration.icp import IcpBasin, IcpCloud, IcpResult


@dataclass(frozen=True, eq=False)
class AlignmentRequest:
    """One alignment: from ``T_init`` (``T_target_source``, RANSAC's pose), points further apart
    than ``max_correspondence_m`` do not correspond; at most ``max_iterations`` (0: the start's
    correspondences measured), stopping once a step moves less than ``convergence_m`` (metres;
    radians per metre of lever) or, unconverged, once the fit has left ``basin`` without slowing
    down. The quality figures and the information are measured on about ``analysis_points``
    evenly strided points of each cloud."""

    T_init: NDArray[np.float64]
    max_correspondence_m: float
    max_iterations: int
    convergence_m: float = 1e-6
    basin: IcpBasin | None = None
    analysis_points: int = 6000


@runtime_checkable
class PointCloudAligner(Protocol):
    """An ICP: aligns ``source`` onto ``target`` (voxelised clouds of two frames, sensor frames,
    metres) and reports the pose with its correspondences (fitness, overlap, point-to-plane
    residuals for the information)."""

    def align(self, target: IcpCloud, source: IcpCloud, request: AlignmentRequest) -> IcpResult: ...


__all__ = ["AlignmentRequest", "PointCloudAligner"]
