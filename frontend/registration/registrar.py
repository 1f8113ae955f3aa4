"""The project's :class:`~fpp_graph.types.PairRegistrar` for FPP frames: :class:`FppPairRegistrar`."""

from __future__ import annotations

import logging
import time
import weakref
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import RegistrationConfig
from fpp_graph.errors import FppError
from fpp_graph.geometry import invert, se3_exp
from fpp_graph.types import Constraint, ConstraintKind, Frame
from frontend.dense_alignment import DenseAlignment, OrganisedSurface, align_dense
from frontend.features import (
    Detector,
    detect_and_describe,
    feature_signature,
    make_detector,
    match_descriptors,
)
from frontend.registration.icp import (
    IcpCloud,
    information_from_icp,
    organised_subsample,
    prepare_icp_cloud,
    refine_icp,
)
from frontend.registration.keypoints import (
    drop_sensor_fixed_matches,
    information_from_keypoints,
    keypoint_inliers,
    lift_keypoints,
    ransac_rigid,
)
from frontend.registration.texture import _MIN_AGREEMENT_BLOCKS, TextureCamera, texture_agreement
from frontend.registration.weak_directions import (
    _CHI2_3DOF_9999,
    _CHI2_6DOF_999,
    Degeneracy,
    _disagreement_along,
    _max_motion_m,
    _weak_direction_sigma_m,
    _weak_directions_from,
    check_degeneracy,
    joint_keypoint_step,
    plane_directions,
    weak_direction_pin,
    without_weak_directions,
)

log = logging.getLogger(__name__)


class FppPairRegistrar:
    """Keypoints + RANSAC + ICP registration of two FPP frames (implements ``PairRegistrar``).

    Keypoints and ICP clouds are cached per :class:`Frame` object (weakly), so a frame taking
    part in several pairs is described and voxelised once.

    Parameters
    ----------
    config : RegistrationConfig
    seed : int
        RANSAC sampling seed (results are reproducible).
    texture_camera : TextureCamera, optional
        The rig's camera and projector centre; enables the photometric refinement of plane-like
        pairs (``photometric_plane_refinement``).
    """

    def __init__(self, config: RegistrationConfig | None = None, seed: int = 0, texture_camera: TextureCamera | None = None):
        self.config = config or RegistrationConfig()
        self.seed = seed
        self.texture_camera = texture_camera
        self._detector: Detector | None = None
        self._feature_signature = feature_signature(self.config)
        self._features: weakref.WeakKeyDictionary[Frame, Frame] = weakref.WeakKeyDictionary()
        self._clouds: weakref.WeakKeyDictionary[Frame, dict[float, IcpCloud]] = weakref.WeakKeyDictionary()
        self._surfaces: weakref.WeakKeyDictionary[Frame, OrganisedSurface] = weakref.WeakKeyDictionary()
        self.last_timings_s: dict[str, float] = {}
        self.last_cpu_timings_s: dict[str, float] = {}  # process CPU time per stage (wall in last_timings_s)

    # -- per-frame work ----------------------------------------------------------------------
    def describe(self, frame: Frame) -> Frame:
        """The frame with keypoints/descriptors of the configured type (cached)."""
        cached = self._features.get(frame)
        if cached is not None:
            return cached
        if frame.keypoints_uv is not None and frame.metadata.get("feature_signature") == self._feature_signature:
            # already described: nothing to cache (a WeakKeyDictionary holding the frame as its
            # own value would keep every frame alive for the registrar's lifetime)
            return frame
        else:
            if self._detector is None:
                self._detector = make_detector(self.config)
            described = detect_and_describe(frame, self.config, self._detector)
        self._features[frame] = described
        return described

    def icp_cloud(self, frame: Frame, voxel_m: float | None = None) -> IcpCloud:
        """The frame's voxel-downsampled ICP cloud (cached per voxel size; default ``icp_voxel_m``)."""
        voxel = float(self.config.icp_voxel_m if voxel_m is None else voxel_m)
        per_frame = self._clouds.setdefault(frame, {})
        cached = per_frame.get(voxel)
        if cached is None:
            pts = organised_subsample(frame.xyz_map, voxel) if frame.xyz_map is not None else frame.points
            cached = prepare_icp_cloud(pts, voxel)
            per_frame[voxel] = cached
        return cached

    def dense_surface(self, frame: Frame) -> OrganisedSurface:
        """The frame's organised map prepared for :func:`frontend.dense_alignment.align_dense` (cached)."""
        cached = self._surfaces.get(frame)
        if cached is None:
            cached = OrganisedSurface(frame.xyz_map)
            self._surfaces[frame] = cached
        return cached

    def refine_dense(
        self, target: Frame, source: Frame, T_target_source: NDArray, information_keypoints: NDArray, weak: Degeneracy | None, source_points: NDArray
    ) -> tuple[DenseAlignment | None, str]:
        """Dense point-to-plane refinement of an accepted pose (:mod:`frontend.dense_alignment`).

        Directions the geometry leaves free (``weak``: a wall's in-plane shifts and spin) are
        pinned where ICP and the keypoints put them; the keypoints' information is the prior
        elsewhere (the dense term outweighs it by orders of magnitude on relief).

        Returns
        -------
        (DenseAlignment or None, why it was not used)
        """
        cfg = self.config
        if not cfg.dense_refinement or target.xyz_map is None or source.xyz_map is None:
            return None, "off"
        prior = cfg.keypoint_information_scale * np.asarray(information_keypoints, dtype=np.float64)
        if weak is not None and len(weak.directions):
            prior = prior + weak_direction_pin(weak, source_points, strength=1e6 * max(float(np.trace(prior)), 1.0))
        try:
            dense = align_dense(
                self.dense_surface(target), self.dense_surface(source), T_target_source, prior_information=prior,
                coarse_stride_px=cfg.dense_coarse_stride_px, fine_stride_px=cfg.dense_stride_px,
                max_iterations=cfg.dense_coarse_iterations, fine_iterations=cfg.dense_fine_iterations, max_points=cfg.dense_max_points,
                max_distance_m=cfg.icp_max_correspondence_m,
            )
        except FppError as exc:
            return None, str(exc)
        if not np.all(np.isfinite(dense.T_target_source)):
            return None, "non-finite pose"
        return dense, ""

    def refine_plane_photometric(
        self, target: Frame, source: Frame, T_target_source: NDArray, weak: Degeneracy, information_geometry: NDArray, source_points: NDArray
    ) -> tuple[NDArray | None, NDArray | None, str]:
        """The ``weak`` directions (a wall's in-plane shifts and spin) by photometric alignment.

        The source's texture is predicted from the target's FPP map and texture with the
        projector's shading (:func:`frontend.localization.localize_photometric`) while the
        directions the geometry fixes are held where ICP / the dense fit put them. On a wall the
        keypoints set the in-plane shifts to ~0.05 mm (blob centres on blurred texture); every
        textured pixel does it to a few micrometres once the tilts are not free: 12 simulated corridor pairs
        with the tilts held at the truth, 0.058 -> 0.004 mm median (unheld, the tilts and the in-plane shifts trade off).

        Returns
        -------
        (T_target_source or None, its photometric information (6 x 6, ``[rot, trans]``, scaled) or None, why not)
        """
        cfg = self.config
        cam = self.texture_camera
        if not cfg.photometric_plane_refinement or cam is None:
            return None, None, "off" if not cfg.photometric_plane_refinement else "no texture camera"
        if target.texture is None or source.texture is None or target.xyz_map is None or source.xyz_map is None:
            return None, None, "no texture or xyz map"
        from frontend.localization import DenseReference, localize_photometric

        # holds: the complement of the weak directions, far above the texture's information
        strength = 1e6 * max(float(np.trace(information_geometry)), 1.0)
        prior = weak_direction_pin(weak, source_points, strength, complement=True)
        try:
            result = localize_photometric(
                [DenseReference(target.xyz_map, target.texture, np.eye(4))], source.texture, invert(np.asarray(T_target_source, dtype=np.float64)),
                cam.K, cam.dist, projector_centre_m=cam.projector_centre_m, valid_query=np.isfinite(source.xyz_map[..., 2]),
                max_pixels=cfg.photometric_max_pixels, prior_information=prior,
            )
        except FppError as exc:
            return None, None, str(exc)
        if not result.success:
            return None, None, f"did not converge ({result.pixels_used} pixels)"
        # Exp(xi) T_source_target = (T_target_source Exp(-xi))^-1: the same quadratic form
        # All six directions: the texture's in-plane estimate is tied to the tilts it was held at
        # (a wall's shift trades against its tilt), and only the joint matrix with the geometry's
        # tilt information carries that into the in-plane covariance (the weak directions' part
        # alone put the corridor NEES mean at 55 for 9.6 with the whole matrix, scale 0.01).
        return invert(result.T_camera_world), cfg.photometric_information_scale * result.information, ""

    # -- the pair ------------------------------------------------------------------------------
    def register(
        self,
        target: Frame,
        source: Frame,
        T_guess: NDArray[np.float64] | None = None,
        kind: ConstraintKind | str = ConstraintKind.ODOMETRY,
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
        cfg = self.config
        timings: dict[str, float] = {}
        cpu_timings: dict[str, float] = {}
        self.last_timings_s, self.last_cpu_timings_s = timings, cpu_timings
        ids = (source.id, target.id)

        def reject(reason: str, **quality: Any) -> Constraint:
            log.info("pair %d->%d rejected: %s", source.id, target.id, reason)
            meta = dict(quality.pop("metadata", {}))
            meta["timings_s"] = dict(timings)
            return Constraint.rejected(*ids, reason, kind=kind, metadata=meta, **quality)

        for role, frame in (("target", target), ("source", source)):
            if frame.xyz_map is None:
                return reject(f"{role} frame {frame.id} has no xyz_map: keypoints cannot be lifted to 3D")
            if frame.texture is None:
                return reject(f"{role} frame {frame.id} has no texture image: no keypoints")
            # the frame's point list is the map's valid pixels: checking it is O(1), a scan of
            # the full map costs ~5 ms per 1920x1200 frame (the map is scanned only without points)
            if frame.points.shape[0] == 0 and not np.any(np.isfinite(frame.xyz_map[..., 2])):
                return reject(f"{role} frame {frame.id} has no valid 3D points")
            if min(frame.texture.shape) < 32:
                return reject(f"{role} frame {frame.id}: texture {frame.texture.shape} too small for keypoints")
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            tgt = self.describe(target)
            src = self.describe(source)
            timings["features"], cpu_timings["features"] = time.perf_counter() - t0, time.process_time() - c0
            t0, c0 = time.perf_counter(), time.process_time()
            matches = match_descriptors(tgt.descriptors, src.descriptors, cfg.ratio_test, cfg.mutual_check)
            timings["match"], cpu_timings["match"] = time.perf_counter() - t0, time.process_time() - c0
        except FppError as exc:
            return reject(f"features failed: {exc}")
        matches, static_dropped = drop_sensor_fixed_matches(matches, tgt.keypoints_uv, src.keypoints_uv, target.texture.shape[1])
        if matches.shape[0] < cfg.min_inliers:
            return reject(f"too few matches ({matches.shape[0]} < {cfg.min_inliers})", metadata={"matches": int(matches.shape[0]), "sensor_fixed_matches_dropped": static_dropped})
        t0, c0 = time.perf_counter(), time.process_time()
        Pt, vt = lift_keypoints(target.xyz_map, tgt.keypoints_uv[matches[:, 0]])
        Ps, vs = lift_keypoints(source.xyz_map, src.keypoints_uv[matches[:, 1]])
        ok = vt & vs
        Pt, Ps = Pt[ok], Ps[ok]
        matches3d = matches[ok]
        if Pt.shape[0] < cfg.min_inliers:
            return reject(f"too few matches with valid 3D ({Pt.shape[0]} < {cfg.min_inliers})", metadata={"matches": int(matches.shape[0])})
        rng = np.random.default_rng([self.seed, source.id & 0xFFFFFFFF, target.id & 0xFFFFFFFF])
        extra = [np.asarray(T_guess, dtype=np.float64)] if T_guess is not None else None
        ransac = ransac_rigid(Pt, Ps, cfg.ransac_threshold_m, cfg.ransac_iterations, cfg.ransac_confidence, rng, extra)
        timings["ransac"], cpu_timings["ransac"] = time.perf_counter() - t0, time.process_time() - c0
        meta: dict[str, Any] = {
            "matches": int(matches.shape[0]),
            "sensor_fixed_matches_dropped": static_dropped,
            "matches_3d": int(Pt.shape[0]),
            "ransac_inliers": ransac.num_inliers,
            "ransac_iterations": ransac.iterations,
            "ransac_rmse_m": ransac.inlier_rmse_m,
            "T_ransac": ransac.T_target_source,
            "feature": cfg.feature,
        }
        if ransac.num_inliers < cfg.min_inliers:
            return reject(f"too few inliers ({ransac.num_inliers} < {cfg.min_inliers} RANSAC inliers of {Pt.shape[0]})", inlier_count=ransac.num_inliers, metadata=meta)
        # With the dense refinement on, ICP only has to reach its basin and tell relief from a
        # plane: coarser voxels do that (turntable pairs: same final error, ICP stages 2.4x
        # faster). A plane to ICP (three weak directions) skips the dense stage and keeps ICP's pose, so
        # it is redone on the fine voxels.
        dense_follows = cfg.dense_refinement and cfg.dense_icp_voxel_m > cfg.icp_voxel_m
        photometric_possible = self.texture_camera is not None and cfg.photometric_plane_refinement and cfg.dense_refinement
        voxels = [cfg.dense_icp_voxel_m, cfg.icp_voxel_m] if dense_follows else [cfg.icp_voxel_m]
        timings["icp_prepare"] = cpu_timings["icp_prepare"] = timings["icp"] = cpu_timings["icp"] = 0.0
        for voxel in voxels:
            t0, c0 = time.perf_counter(), time.process_time()
            tcloud = self.icp_cloud(target, voxel)
            scloud = self.icp_cloud(source, voxel)
            # KD-trees, normals, covariances of the ICP subsets (lazy, kept for the frame's next pairs)
            _ = (tcloud.target, scloud.source)
            timings["icp_prepare"] += time.perf_counter() - t0
            cpu_timings["icp_prepare"] += time.process_time() - c0
            if min(tcloud.size, scloud.size) < 30:
                return reject(f"too few points for ICP ({tcloud.size} target, {scloud.size} source voxels of {1e3 * voxel:g} mm)", inlier_count=ransac.num_inliers, metadata=meta)
            t0, c0 = time.perf_counter(), time.process_time()
            icp = refine_icp(tcloud, scloud, ransac.T_target_source, cfg.icp_method, cfg.icp_max_correspondence_m, cfg.icp_max_iterations)
            timings["icp"] += time.perf_counter() - t0
            cpu_timings["icp"] += time.process_time() - c0
            meta["icp_voxel_m"] = voxel
            if not np.all(np.isfinite(icp.T_target_source)):
                break  # rejected below
            info_icp_raw = information_from_icp(icp, scale=cfg.information_scale)
            deg_icp = check_degeneracy(info_icp_raw, icp.source_points, cfg.degeneracy_ratio)
            if voxel == cfg.icp_voxel_m or len(deg_icp.unconstrained) < 3 or photometric_possible:
                # (coarse and not a plane: the dense refinement takes it from here, below; a plane
                # with the texture camera: the dense fit gives the tilts and the texture the rest)
                break
            meta["coarse_icp_plane_like"] = True
        T = icp.T_target_source
        meta["T_icp"] = T
        quality = {"fitness": icp.fitness, "inlier_rmse_m": icp.inlier_rmse_m, "inlier_count": ransac.num_inliers, "overlap": icp.overlap}
        meta.update({"icp_iterations": icp.iterations, "icp_converged": icp.converged, "icp_correspondences": icp.num_correspondences})
        if not np.all(np.isfinite(T)):
            return reject("ICP diverged (non-finite pose)", metadata=meta, **quality)
        drop_weak: Degeneracy | None = None
        # where ICP moved the keypoint inliers: a large move means it left RANSAC's basin
        Ps_in = Ps[ransac.inliers]
        shift = np.linalg.norm((Ps_in @ T[:3, :3].T + T[:3, 3]) - (Ps_in @ ransac.T_target_source[:3, :3].T + ransac.T_target_source[:3, 3]), axis=1)
        meta["icp_shift_m"] = float(shift.max()) if shift.size else 0.0
        res_kp = np.linalg.norm(Pt - (Ps @ T[:3, :3].T + T[:3, 3]), axis=1)
        kp_inliers = int(np.sum(res_kp < cfg.ransac_threshold_m))
        meta["keypoint_inliers_after_icp"] = kp_inliers
        meta["matches_used"] = matches3d[res_kp < cfg.ransac_threshold_m]
        # Directions ICP cannot be trusted along come from the keypoints, with ICP's information
        # there dropped (normal scatter makes it claim ~0.05 mm in-plane on a wall, which is not
        # information about the pose):
        # - plane-like pairs (two or more weak ICP directions: a wall, an object on a big table)
        #   whose ICP pose disagrees with the keypoints in the plane (chi-square, 3 dof, 0.9999,
        #   under the keypoints' covariance given ICP's other directions): the in-plane shifts and
        #   the spin about the normal go to the keypoints' optimum given ICP's normal shift and
        #   tilts. On simulated corridor walls GICP slid 1.5-4 mm in-plane on most pairs (faint
        #   relief, the decoder's texture-correlated ripple) while the keypoints were within
        #   0.1-0.5 mm; over 104 adjacent corridor pairs the median error fell from 0.146 to 0.075 mm
        #   and the maximum from 2.09 to 0.73 mm. Where the two agree ICP's pose is kept: on relief
        #   it is the more precise (a turntable pair: ICP 0.045 mm, keypoints 1.5 mm, m2 16.9).
        # - otherwise, when ICP lost the keypoints on weak geometry (drifted along its flat
        #   directions rather than a wrong pair): those flat directions from RANSAC's pose.
        meta["icp_eigenvalue_ratios"] = deg_icp.eigenvalue_ratios
        lost_keypoints = meta["icp_shift_m"] > cfg.max_icp_shift_m or kp_inliers < cfg.min_inliers
        weak: Degeneracy | None = None
        if cfg.plane_from_keypoints and len(deg_icp.unconstrained) >= 2:
            plane = plane_directions(info_icp_raw, icp.source_points)
            meta["plane_spin_ratio"] = float(plane.eigenvalue_ratios[2])
            m2 = _disagreement_along(T, ransac.T_target_source, cfg.keypoint_information_scale * information_from_keypoints(ransac.T_target_source, Ps_in, np.full(Ps_in.shape[0], ransac.inlier_rmse_m)), plane, icp.source_points)
            meta["plane_keypoint_mahalanobis2"] = m2
            # (with the rig's texture camera the texture sets the plane's directions, below: always)
            if m2 > _CHI2_3DOF_9999 or lost_keypoints or photometric_possible:
                weak = plane
        if weak is None and lost_keypoints and deg_icp.degenerate:
            weak = deg_icp
        if weak is not None:
            if weak is deg_icp:
                T_fb = _weak_directions_from(T, ransac.T_target_source, weak, icp.source_points)
            else:
                # the keypoints' optimum given ICP's normal shift and tilts (RANSAC's own in-plane
                # estimate carries its tilt error through the lever arm of a narrow overlap strip)
                T_fb = T @ se3_exp(joint_keypoint_step(T, without_weak_directions(info_icp_raw, weak, icp.source_points), Ps_in, Pt[ransac.inliers], iterations=5))
            Ps_in_fb = Ps_in @ T_fb[:3, :3].T + T_fb[:3, 3]
            shift_fb = np.linalg.norm(Ps_in_fb - (Ps_in @ ransac.T_target_source[:3, :3].T + ransac.T_target_source[:3, 3]), axis=1)
            res_fb = np.linalg.norm(Pt - (Ps @ T_fb[:3, :3].T + T_fb[:3, 3]), axis=1)
            if float(shift_fb.max()) <= cfg.max_icp_shift_m and int(np.sum(res_fb < cfg.ransac_threshold_m)) >= cfg.min_inliers:
                icp = refine_icp(tcloud, scloud, T_fb, "none", cfg.icp_max_correspondence_m, 0)
                T = T_fb
                meta.update({"icp_shift_m": float(shift_fb.max()), "weak_directions_from_keypoints": weak.unconstrained, "icp_drift_m": meta["icp_shift_m"]})
                res_kp = res_fb
                kp_inliers = int(np.sum(res_kp < cfg.ransac_threshold_m))
                meta["keypoint_inliers_after_icp"] = kp_inliers
                meta["matches_used"] = matches3d[res_kp < cfg.ransac_threshold_m]
                quality = {"fitness": icp.fitness, "inlier_rmse_m": icp.inlier_rmse_m, "inlier_count": ransac.num_inliers, "overlap": icp.overlap}
                drop_weak = weak
        if meta["icp_shift_m"] > cfg.max_icp_shift_m:
            return reject(f"ICP left the RANSAC basin (moved keypoint inliers by {1e3 * meta['icp_shift_m']:.2f} mm > {1e3 * cfg.max_icp_shift_m:.2f} mm)", metadata=meta, **quality)
        if kp_inliers < cfg.min_inliers:
            return reject(f"too few inliers after ICP ({kp_inliers} < {cfg.min_inliers} keypoints agree)", metadata=meta, **quality)
        if icp.fitness < cfg.min_fitness:
            return reject(f"low fitness ({icp.fitness:.3f} < {cfg.min_fitness})", metadata=meta, **quality)
        if icp.overlap < cfg.min_overlap:
            return reject(f"low overlap ({icp.overlap:.3f} < {cfg.min_overlap})", metadata=meta, **quality)
        if not icp.inlier_rmse_m <= cfg.max_inlier_rmse_m:
            return reject(f"high inlier RMSE ({1e3 * icp.inlier_rmse_m:.3f} mm > {1e3 * cfg.max_inlier_rmse_m:.3f} mm)", metadata=meta, **quality)
        t0, c0 = time.perf_counter(), time.process_time()
        # ICP's information at the final pose: the one computed above unless the pose moved
        info_icp = info_icp_raw
        if drop_weak is not None:
            info_icp = without_weak_directions(information_from_icp(icp, scale=cfg.information_scale), drop_weak, icp.source_points)
        # Where the dense geometry is weak (an object on a big table plane, a wall), ICP's cost
        # is flat: the keypoints' point-to-point information constrains exactly those directions.
        kp_mask = keypoint_inliers(res_kp, cfg.ransac_threshold_m)

        def at_pose(T: NDArray, info_geometry: NDArray) -> tuple[NDArray, NDArray, Degeneracy]:
            """The keypoints' information at ``T`` (the inlier set stays), the joint information and its degeneracy."""
            res = np.linalg.norm(Pt - (Ps @ T[:3, :3].T + T[:3, 3]), axis=1)
            info_k = information_from_keypoints(T, Ps[kp_mask], res[kp_mask])
            joint = info_geometry + info_k
            return info_k, joint, check_degeneracy(joint, icp.source_points, cfg.degeneracy_ratio)

        info_kp = information_from_keypoints(T, Ps[kp_mask], res_kp[kp_mask])
        info = info_icp + info_kp
        deg = check_degeneracy(info, icp.source_points, cfg.degeneracy_ratio)
        if deg.degenerate and drop_weak is None:
            # ICP can drift along its flat directions (0.45 mm on a flat-wall test pair whose
            # RANSAC pose was within 0.01 mm, more on thinned clouds) while the information claims
            # the keypoints pin them. When ICP's pose is inconsistent with the joint optimum of
            # ICP's and the keypoints' costs (chi-square, 6 dof, 0.999), move there and take the
            # information there; otherwise keep ICP's pose, which on relief is the more precise
            # (over 36 synthetic pairs moving always doubled the median translation error).
            step = joint_keypoint_step(T, info_icp, Ps[kp_mask], Pt[kp_mask])
            m2 = float(step @ info @ step)
            meta["joint_keypoint_step"] = step
            meta["joint_keypoint_step_mahalanobis2"] = m2
            if m2 > _CHI2_6DOF_999:
                T = T @ se3_exp(step)
                meta["moved_to_joint_optimum"] = True
                info_kp, info, deg = at_pose(T, info_icp)
        timings["information"], cpu_timings["information"] = time.perf_counter() - t0, time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        # Every pixel instead of 2 mm voxels: on simulated turntable pairs the median error fell
        # from 0.0051 deg / 0.043 mm to ~0.001 deg / 0.01 mm (module doc of dense_alignment).
        # Pinned: the directions already taken from the keypoints. One weak direction of curved
        # relief (the doll's spin about the turntable axis, where GICP's error was) is left to
        # the dense fit; a plane is not refined (below).
        weak_dense = drop_weak
        T_start = T
        plane_dense: DenseAlignment | None = None
        if photometric_possible and drop_weak is not None and drop_weak is not deg_icp:
            # A wall whose plane directions the texture sets (below): the dense fit gives its
            # tilts and distance, with the plane's directions held at the keypoints' values
            # (unheld they slide 0.06 -> 0.3 mm and take the tilts along). 12 simulated corridor
            # pairs: 0.029 mm median with ICP's tilts, 0.017 mm with these. If every pixel sees
            # relief after all (a doll on a table) the unheld re-check below decides instead.
            held, _ = self.refine_dense(target, source, T, info_kp, drop_weak, icp.source_points)
            if held is not None and len(check_degeneracy(held.information, held.source_points, cfg.degeneracy_ratio).unconstrained) >= 3:
                if _max_motion_m(held.T_target_source, ransac.T_target_source, Ps_in) <= cfg.max_icp_shift_m:
                    plane_dense = held
        if plane_dense is not None:
            meta.update({"T_before_dense": T, "dense_pinned": list(drop_weak.unconstrained), "dense_iterations": plane_dense.iterations,
                         "dense_residuals": plane_dense.num_residuals, "dense_sigma_m": plane_dense.sigma_m})
            T = plane_dense.T_target_source
            info_icp = without_weak_directions(cfg.dense_information_scale * plane_dense.information, drop_weak, icp.source_points)
            info_kp, info, deg = at_pose(T, info_icp)
            dense, why_not = None, ""
        elif drop_weak is not None and drop_weak is not deg_icp:
            # The plane rule (step 4) read the pair as a plane from ICP's voxels and took the
            # in-plane directions from the keypoints. A doll on a turntable looks like that to
            # ICP (the table dominates), and ORB keypoints 1.4 mm off then replaced ICP's
            # 0.04 mm pose. Every pixel decides: from ICP's own pose, unpinned; if the dense
            # information is not plane-like the relief constrains the plane's directions.
            weak_dense, T_start = None, meta["T_icp"]
            meta["dense_rechecks_plane_rule"] = True
        if plane_dense is None:
            if len(deg_icp.unconstrained) >= 3:
                dense, why_not = None, "plane-like geometry (ICP: " + "; ".join(deg_icp.unconstrained) + ")"
            else:
                dense, why_not = self.refine_dense(target, source, T_start, info_kp, weak_dense, icp.source_points)
        if weak_dense is not None:
            meta["dense_pinned"] = list(weak_dense.unconstrained)
        if dense is not None:
            dense_deg = check_degeneracy(dense.information, dense.source_points, cfg.degeneracy_ratio)
            meta["dense_eigenvalue_ratios"] = dense_deg.eigenvalue_ratios
            # (against RANSAC's pose, as ICP's shift is: the keypoints' basin)
            shift_dense = _max_motion_m(dense.T_target_source, ransac.T_target_source, Ps_in)
            meta.update({"dense_shift_m": shift_dense, "dense_iterations": dense.iterations, "dense_residuals": dense.num_residuals, "dense_sigma_m": dense.sigma_m})
            if len(dense_deg.unconstrained) >= 3:
                # a plane even to every pixel (a wall: ratios <= 0.016 where the doll's are >= 0.2):
                # its tilts and normal shift came out no better than ICP's (9 simulated corridor
                # pairs: 0.064 -> 0.098 mm median) and the in-plane directions are the keypoints'
                why_not = "plane-like geometry (" + "; ".join(dense_deg.unconstrained) + ")"
            elif shift_dense > cfg.max_icp_shift_m:
                why_not = f"moved the keypoint inliers by {1e3 * shift_dense:.2f} mm"
            else:
                meta["T_before_dense"] = T
                T = dense.T_target_source
                info_dense = cfg.dense_information_scale * dense.information
                if weak_dense is not None:
                    info_dense = without_weak_directions(info_dense, weak_dense, icp.source_points)
                # the dense term replaces ICP's (the same surfaces, measured densely)
                info_icp = info_dense
                info_kp, info, deg = at_pose(T, info_icp)
        if why_not and why_not != "off":
            meta["dense_not_used"] = why_not
            log.debug("pair %d->%d: dense refinement not used: %s", source.id, target.id, why_not)
        timings["dense"], cpu_timings["dense"] = time.perf_counter() - t0, time.process_time() - c0
        info_photometric = np.zeros((6, 6))
        if photometric_possible and drop_weak is not None and (plane_dense is not None or "T_before_dense" not in meta):
            # the weak directions came from the keypoints and no relief took over: the texture sets them
            t0, c0 = time.perf_counter(), time.process_time()
            T_photo, info_photo, why_not_photo = self.refine_plane_photometric(target, source, T, drop_weak, info_icp, icp.source_points)
            if T_photo is not None:
                shift_photo = _max_motion_m(T_photo, T, Ps_in)
                meta["photometric_shift_m"] = shift_photo
                if shift_photo > cfg.ransac_threshold_m:
                    why_not_photo = f"moved the keypoint inliers by {1e3 * shift_photo:.2f} mm"
                else:
                    meta["T_before_photometric"] = T
                    T = T_photo
                    info_kp, info, deg = at_pose(T, info_icp)
                    # carried by the constraint only: the gates below (a plane is admitted when the
                    # keypoints pin it; look-alike places) stay on the geometry and the keypoints
                    info_photometric = info_photo
            if why_not_photo:
                meta["photometric_not_used"] = why_not_photo
                log.debug("pair %d->%d: photometric refinement not used: %s", source.id, target.id, why_not_photo)
            timings["photometric"], cpu_timings["photometric"] = time.perf_counter() - t0, time.process_time() - c0
        meta["eigenvalue_ratios"] = deg.eigenvalue_ratios
        if deg.degenerate:
            # Weak in the dense geometry (one plane, an object on a table): acceptable only if the
            # keypoints pin those directions down to within max_weak_sigma_m.
            weak_sigma_m = _weak_direction_sigma_m(info, deg, icp.source_points)
            # the same directions from the dense geometry alone (no keypoints), for diagnosis: on
            # a plane, noisy normals make point-to-plane information claim ~0.1 mm in-plane, so it
            # cannot tell relief from a plane and is not used to admit loops
            meta["weak_direction_geometry_sigma_m"] = _weak_direction_sigma_m(info_icp, deg, icp.source_points)
            meta["geometrically_weak"] = deg.unconstrained
            meta["weak_direction_sigma_m"] = weak_sigma_m
            if ConstraintKind(kind) is ConstraintKind.LOOP and T_guess is None:
                # A revisit proposed by appearance alone, on weak geometry (a plane), rests on the
                # keypoints, and look-alike places (repeated posters) fool keypoints: their
                # inliers all sit on the repeated object while the surroundings differ. Only a
                # pair whose textures agree over the whole overlap is taken (simulated corridor:
                # true revisits 0.989-1.000 of the blocks, look-alike posters 0.37-0.81).
                agreement = texture_agreement(target, source, T)
                meta["texture_agreement"] = agreement.fraction
                meta["texture_agreement_blocks"] = agreement.blocks
                meta["texture_agreement_overlap"] = agreement.overlap
                if not (agreement.fraction >= cfg.min_texture_agreement and agreement.blocks >= _MIN_AGREEMENT_BLOCKS):
                    return reject(
                        "look-alike place: degenerate geometry (unconstrained " + "; ".join(deg.unconstrained)
                        + f") and the textures agree on only {100 * agreement.fraction:.1f} % of {agreement.blocks} overlap blocks"
                        + f" (< {100 * cfg.min_texture_agreement:.0f} % of >= {_MIN_AGREEMENT_BLOCKS}) for an appearance-only candidate",
                        metadata={**meta, "unconstrained_directions": deg.directions}, **quality,
                    )
                if not agreement.overlap >= cfg.min_texture_overlap:
                    # the overlap may be the repeated object alone (poster twins on opposite walls
                    # registered 0.2 m apart agreed on 100 % of their 0.37-0.63 overlap)
                    return reject(
                        "possible look-alike place: degenerate geometry (unconstrained " + "; ".join(deg.unconstrained)
                        + f") and the agreeing overlap covers only {100 * agreement.overlap:.0f} % of the view"
                        + f" (< {100 * cfg.min_texture_overlap:.0f} %) for an appearance-only candidate",
                        metadata={**meta, "unconstrained_directions": deg.directions}, **quality,
                    )
            if ConstraintKind(kind) is ConstraintKind.LOOP and T_guess is not None:
                meta["weak_loop_guess_deviation_m"] = float(np.linalg.norm(T[:3, 3] - np.asarray(T_guess, dtype=np.float64)[:3, 3]))
            if not weak_sigma_m <= cfg.max_weak_sigma_m:
                return reject(
                    "degenerate geometry: unconstrained " + "; ".join(deg.unconstrained)
                    + f" (sigma {1e3 * weak_sigma_m:.3f} mm > {1e3 * cfg.max_weak_sigma_m:.3f} mm even with keypoints)",
                    metadata={**meta, "unconstrained_directions": deg.directions}, **quality,
                )
        meta["timings_s"] = dict(timings)
        return Constraint(
            source_id=source.id,
            target_id=target.id,
            T_target_source=T,
            # The gates above use the keypoints' raw information; the constraint carries it
            # scaled: keypoint errors are correlated (one detector, the same texture), so n
            # keypoints are worth fewer than n independent points. Calibrated by NEES on
            # simulated pairs: the corridor median fell from 64 to 10 at 0.1 with the turntable
            # unchanged (4.6: there ICP's information dominates every direction).
            information=info_icp + cfg.keypoint_information_scale * info_kp + info_photometric,
            kind=kind,
            metadata=meta,
            **quality,
        )


def with_features(frame: Frame, config: RegistrationConfig) -> Frame:
    """Alias of :func:`frontend.features.detect_and_describe` for pipeline code that only imports this module."""
    return detect_and_describe(frame, config)


