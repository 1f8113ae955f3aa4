"""The project's :class:`~fpp_graph.types.PairRegistrar`: :class:`TexturedSurfaceRegistrar`, for
any two frames with a texture image and an organised point map (the FPP rig's, an RGB-D camera's)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.types import Constraint, ConstraintKind, Frame
from frontend.config import RegistrationConfig
from frontend.localization.reference import reference_to_arrays
from frontend.organised_surface import OrganisedSurface
from frontend.registration.aligner import PointCloudAligner
from frontend.registration.gates import Checkpoint, check
from frontend.registration.icp import make_aligner, with_shared_error_floor
from frontend.registration.keypoints import KEYPOINT_INFORMATION_SCALE
from frontend.registration.refinement import (
    DenseInput,
    DenseStage,
    PhotometricInput,
    PhotometricStage,
    WeakGeometryCheck,
    WeakGeometryStage,
)
from frontend.registration.stages import (
    IcpStage,
    JointInformationStage,
    KeypointMatching,
    KeypointRansac,
    MatchLifting,
    PoseEstimate,
    WeakDirectionOutcome,
    WeakDirectionStage,
)
from frontend.registration.state import PairFrames, PairReport, Rejected
from frontend.registration.texture import TextureCamera
from frontend.registration.tracking import DenseTracker
from frontend.registration.weak_directions import DEGENERACY_RATIO, surface_is_plane_like

log = logging.getLogger(__name__)


PREPARED_REFERENCE = "photometric_reference."
"""Name prefix of the photometric reference pixels :meth:`TexturedSurfaceRegistrar.prepare` stores
in :attr:`~fpp_graph.types.Frame.prepared`."""


class TexturedSurfaceRegistrar:
    """Keypoints + RANSAC + ICP + dense (+ photometric) registration of two frames with a texture
    and an organised point map (implements ``PairRegistrar``, ``FrameTracker``, ``FrameDescriber``).

    :meth:`register` is the list of stages (:mod:`.stages`, :mod:`.refinement`), each checked by
    its rows of the gate table (:data:`.gates.GATES`). Each stage holds its per-frame caches
    (keypoints, ICP clouds, dense surfaces, photometric references; weakly per :class:`Frame`), so
    a frame taking part in several pairs is described, voxelised and prepared once.

    Parameters
    ----------
    config : RegistrationConfig
    seed : int
        RANSAC sampling seed (results are reproducible).
    texture_camera : TextureCamera, optional
        The rig's camera and projector centre; enables the photometric refinement of plane-like
        pairs (``photometric.enabled``).
    aligner : PointCloudAligner, optional
        The ICP; default the implementation of ``icp.method``
        (:func:`~frontend.registration.icp.make_aligner`).
    """

    def __init__(self, config: RegistrationConfig | None = None, seed: int = 0, texture_camera: TextureCamera | None = None,
                 aligner: PointCloudAligner | None = None):
        cfg = self.config = config or RegistrationConfig()
        self.seed, self.texture_camera = seed, texture_camera
        # the texture sets a plane's in-plane directions: ICP then keeps its coarse pose on planes,
        # the plane rule always applies, and the dense fit holds the plane's directions
        self.texture_sets_planes = texture_camera is not None and cfg.photometric.enabled and cfg.dense.enabled
        self.matching = KeypointMatching(cfg)
        self.lifting = MatchLifting(cfg)
        self.ransac = KeypointRansac(cfg, seed)
        self.icp = IcpStage(cfg, aligner or make_aligner(cfg.icp.method), self.texture_sets_planes)
        self.weak_directions = WeakDirectionStage(cfg, self.texture_sets_planes)
        self.information = JointInformationStage(cfg)
        self.dense = DenseStage(cfg, self.texture_sets_planes)
        self.photometric = PhotometricStage(cfg, texture_camera)
        self.weak_geometry = WeakGeometryStage(cfg)
        self.tracker = DenseTracker(cfg, self.dense.surfaces, self.matching.features)
        self.last_timings_s: dict[str, float] = {}
        self.last_cpu_timings_s: dict[str, float] = {}  # process CPU time per stage (wall in last_timings_s)

    # -- per-frame work ----------------------------------------------------------------------
    def describe(self, frame: Frame) -> Frame:
        """The frame with keypoints/descriptors of the configured type (cached)."""
        return self.matching.features.describe(frame)

    def prepare(self, frame: Frame) -> Frame:
        """``frame`` with what every pair it takes part in will need, made once where the frame is
        made (a decode worker) and stored with it (:attr:`Frame.prepared`), so that the tracking
        process and each worker verifying one of its loops read it instead of making it again:

        * its dense surface (:meth:`OrganisedSurface.to_arrays`: normals and rays, ~50 ms of a
          1920x1200 map, ~8 ms of a 640x480 one, ~5 bytes a pixel on disk): a frame is the
          target and source of odometry and of loop candidates on several workers;
        * the photometric step's reference pixels (0.3-0.9 s of a 1920x1200 frame) for a frame
          whose own surface is plane-like (:func:`surface_is_plane_like`): each of its pairs
          takes the step.

        Both are made from the map as the frame store keeps it (float32), so every process
        reading the frame back gets the numbers it would have made itself. A frame without a
        map is returned as it is.
        """
        if frame.xyz_map is None:
            return frame
        stored_map = np.asarray(frame.xyz_map, dtype=np.float32)
        prepared: dict[str, NDArray] = {}
        if self.config.dense.enabled:
            try:
                prepared.update(OrganisedSurface(stored_map).to_arrays())
            except InputDataError as exc:
                # too few valid pixels for a surface: each pair that needs one says so again
                log.debug("frame %d: no dense surface stored with it (%s)", frame.id, exc)
        if (
            self.texture_sets_planes and frame.texture is not None
            and surface_is_plane_like(frame.xyz_map, self.config.lengths.icp_voxel_m, DEGENERACY_RATIO)
        ):
            pixels = self.photometric.reference_pixels(stored_map.astype(np.float64), frame.texture)
            prepared.update(reference_to_arrays(pixels, PREPARED_REFERENCE))
        return dataclasses.replace(frame, prepared={**frame.prepared, **prepared}) if prepared else frame

    def track(self, target: Frame, source: Frame, T_predicted: NDArray[np.float64]) -> Constraint:
        """``T_target_source`` from a motion prediction by the dense fit alone (implements
        :class:`~fpp_graph.types.FrameTracker`; :class:`~.tracking.DenseTracker`); rejected when
        only a full :meth:`register` can be trusted."""
        return self.tracker.track(target, source, T_predicted)

    # -- the pair ------------------------------------------------------------------------------
    def register(
        self, target: Frame, source: Frame, T_guess: NDArray[np.float64] | None = None, kind: ConstraintKind | str = ConstraintKind.ODOMETRY,
    ) -> Constraint:
        """Estimate ``T_target_source``; a failed pair returns a rejected Constraint with the reason.

        Parameters
        ----------
        target, source : Frame
            Need ``xyz_map`` and ``texture`` (same size per frame, checked by Frame).
        T_guess : (4, 4), optional
            Prior ``T_target_source``; scored as one more RANSAC hypothesis (never trusted alone).
        kind : ConstraintKind
            Recorded on the constraint.

        Returns
        -------
        Constraint
            Accepted with information ``[rot, trans]``, or rejected with ``rejection_reason``.
        """
        report = PairReport(PairFrames(target, source, kind, T_guess))
        self.last_timings_s, self.last_cpu_timings_s = report.timer.wall_s, report.timer.cpu_s
        try:
            return self._stages(report)
        except Rejected as rejected:
            return rejected.constraint

    def _stages(self, report: PairReport) -> Constraint:
        """The stages in order, each result checked by its gates (a failing gate raises :class:`Rejected`)."""
        cfg, pair, timer = self.config, report.pair, report.timer

        def gate(checkpoint: Checkpoint, result: object) -> None:
            check(checkpoint, result, report, cfg)

        gate(Checkpoint.INPUT, pair)
        matches = self.matching.run(pair, timer)
        gate(Checkpoint.FEATURES, matches)
        report.add(matches.metadata)
        gate(Checkpoint.MATCHES, matches)
        with timer.timed("ransac"):  # the lift included
            lifted = self.lifting.run(pair, matches)
            gate(Checkpoint.LIFTED, lifted)
            start = self.ransac.run(pair, lifted)
        report.add(start.metadata(cfg.features.type))
        report.quality = {"inlier_count": start.ransac.num_inliers}
        gate(Checkpoint.RANSAC, start)
        icp = self.icp.run(pair, start, timer)
        report.add(icp.metadata)
        report.quality = icp.quality(start.ransac.num_inliers)
        gate(Checkpoint.ICP, icp)
        weak = self.weak_directions.run(start, icp)
        report.add(weak.metadata)
        report.quality = weak.quality(start.ransac.num_inliers)
        gate(Checkpoint.POSE, weak)
        with timer.timed("information"):
            information = self.information.run(lifted, icp, weak)
            report.add(information.metadata)
        if pair.appearance_only and information.pose.degeneracy.degenerate:
            self._look_alike(report, information.pose, weak)
        with timer.timed("dense"):
            dense = self.dense.run(DenseInput(pair, start, icp, weak, information))
        report.add(dense.metadata)
        pose, checked, photometric_information = dense.pose, None, np.zeros((6, 6))
        if self.photometric.applies(self.texture_sets_planes, weak, dense):
            if pair.appearance_only:
                checked = self._look_alike(report, pose, weak)
            with timer.timed("photometric"):
                photometric = self.photometric.run(PhotometricInput(pair, start, weak, pose, information.keypoints), PREPARED_REFERENCE)
            report.add(photometric.metadata)
            pose, photometric_information = photometric.pose, photometric.information
        if checked is None or pose is not checked[0]:  # the photometric step moved it (or nothing checked yet)
            checked = (pose, self._weak_geometry(report, pose, weak))
        gate(Checkpoint.FINAL, checked[1])
        return self._accept(report, pose, weak, photometric_information)

    def _weak_geometry(self, report: PairReport, pose: PoseEstimate, weak: WeakDirectionOutcome) -> WeakGeometryCheck:
        """Stage 9 at ``pose``: whether the keypoints pin weak geometry and, for an appearance-only
        revisit, whether the textures agree."""
        result = self.weak_geometry.run(report.pair, pose, weak.icp.source_points)
        report.add(result.metadata)
        return result

    def _look_alike(self, report: PairReport, pose: PoseEstimate, weak: WeakDirectionOutcome) -> tuple[PoseEstimate, WeakGeometryCheck]:
        """The look-alike test of an appearance-only revisit on weak geometry at ``pose``
        (:attr:`Checkpoint.REVISIT`; raises :class:`Rejected`).

        It runs before each expensive step a look-alike would take: first at the keypoint / ICP
        pose, before the dense stage (0.3-0.6 s a pair at 1920x1200), since a look-alike's
        textures disagree by whole blocks, not by the dense stage's sub-millimetre correction;
        then at the dense pose, before the photometric step (2-3 s a pair), which rarely
        converges on a look-alike's mismatched textures. A pair that passes is tested again on
        its final pose.
        """
        result = self._weak_geometry(report, pose, weak)
        check(Checkpoint.REVISIT, result, report, self.config)
        return pose, result

    def _accept(self, report: PairReport, pose: PoseEstimate, weak: WeakDirectionOutcome, photometric_information: NDArray) -> Constraint:
        report.meta["timings_s"] = dict(report.timer.wall_s)
        pair = report.pair
        return Constraint(
            source_id=pair.source.id,
            target_id=pair.target.id,
            T_target_source=pose.T_target_source,
            # The gates use the keypoints' raw information; the constraint carries it scaled
            # (KEYPOINT_INFORMATION_SCALE: n keypoints of one detector on one texture are worth
            # fewer than n independent points), with the error both views share added
            information=with_shared_error_floor(
                pose.information_geometry + KEYPOINT_INFORMATION_SCALE * pose.information_keypoints + photometric_information,
                weak.icp.source_points, self.config.sensor_noise().shared_depth_sigma_per_m2,
            ),
            kind=pair.kind,
            metadata=report.meta,
            **report.quality,
        )

