"""The ICP of a pair as a declared protocol: :class:`PointCloudAligner`.

The ICP stage (:class:`~frontend.registration.stages.IcpStage`) aligns the voxelised clouds of
two frames from RANSAC's pose through this protocol, and the weak-direction stage measures the
correspondences at a pose through it (``max_iterations=0``). The implementations in
:mod:`frontend.registration.icp` are small_gicp's GICP and point-to-plane ICP
(:class:`~frontend.registration.icp.SmallGicpAligner`) and, for ``icp.method: none``,
:class:`~frontend.registration.icp.CorrespondencesAligner` (the start pose, measured);
:func:`~frontend.registration.icp.make_aligner` chooses one from ``registration.icp.method``.
Another ICP plugs in as an object with this ``align`` method passed to the registrar
(``TexturedSurfaceRegistrar(aligner=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from frontend.registration.icp import IcpBasin, IcpCloud, IcpResult


@dataclass(frozen=True, eq=False)
class AlignmentRequest:
    """What one alignment is asked to do.

    Attributes
    ----------
    T_init : (4, 4)
        Initial ``T_target_source`` (RANSAC's pose).
    max_correspondence_m : float
        Pairs of points further apart do not correspond.
    max_iterations : int
        0: no iteration, the correspondences measured at ``T_init``.
    convergence_m : float
        Stop once a step moves less than this (metres; radians per metre of lever).
    basin : IcpBasin, optional
        Stop, unconverged, once the fit has left it and is not slowing down.
    analysis_points : int
        The quality figures and the information are measured on about this many evenly strided
        source (and target) points.
    """

    T_init: NDArray[np.float64]
    max_correspondence_m: float
    max_iterations: int
    convergence_m: float = 1e-6
    basin: IcpBasin | None = None
    analysis_points: int = 6000


@runtime_checkable
class PointCloudAligner(Protocol):
    """An ICP: aligns ``source`` onto ``target`` (voxelised clouds of two frames, sensor frames,
    metres) and reports the pose with its correspondences (:class:`~frontend.registration.icp.IcpResult`:
    fitness, overlap, point-to-plane residuals for the information)."""

    def align(self, target: IcpCloud, source: IcpCloud, request: AlignmentRequest) -> IcpResult: ...


__all__ = ["AlignmentRequest", "PointCloudAligner"]
