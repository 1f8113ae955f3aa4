"""The virtual FPP sensor's renderer: the fringe images a camera + projector rig would capture.

No FPP hardware is attached to this project, so every accuracy figure is measured against this
simulator. It renders the *raw 8-bit pattern images* (not point clouds): the front-end then
decodes them through exactly the code path a real recording takes.

Rendering one frame (:meth:`FppSimulator.render`)
-------------------------------------------------
1. Cast one ray per camera pixel (through the *distorted* pixel centre, i.e. the lens model of
   the calibration) into an Open3D ``RaycastingScene``. The hit is recomputed in float64 against
   the hit triangle's plane, because Embree works in float32.
2. Project the hit into the projector (OpenCV model with the projector's distortion and
   ``T_projector_camera``); test projector visibility with a shadow ray towards the projector
   centre.
3. Radiance of pattern image ``m``: ``albedo * (E_p * cos(theta_p) * (d0 / d_p)^2 * P_m + ambient)``
   with ``P_m`` the continuous pattern value (:func:`frontend.fpp.patterns.pattern_intensity`,
   the projector's residual response ``P^(gamma / compensation)`` and finite DMD contrast applied). Surfaces are two-sided Lambertian.
4. Interreflection (``interreflection_fraction`` > 0; off by default): diffuse indirect light.
   A point receives a fraction of the projector light that the surfaces around it reflect and
   re-reflects it with its own albedo: ``L_g,m(x) = rho * albedo(x) * (G_sigma * D_m)(x)``, with
   ``D_m`` the direct projector radiance image of pattern ``m`` (step 3 without the ambient term,
   which is global light already), ``G_sigma`` a Gaussian of ``interreflection_sigma_px`` camera
   pixels and ``rho = interreflection_fraction``. The indirect light is an average of the
   projector light over the surfaces a point sees, so a pattern much finer than ``sigma``
   arrives as its mean and a coarse one keeps its shape (Nayar et al., "Fast separation of
   direct and global components of a scene using high frequency illumination", 2006): the
   error that global light causes in low-frequency phase shifting and that micro and modulated
   phase shifting avoid. A screen-space model: it knows neither occlusion between the surfaces
   nor light from outside the view (the image border reflects).
5. Camera: depth-dependent defocus (thin-lens blur circle, blended between two Gaussian blurs),
   shot noise (variance ``gain * signal``) plus read noise, the camera response (gamma),
   8-bit quantisation and saturation.

The ray cast is done once per frame and every pattern image is shaded from the same hits.
Ground truth (xyz map in the sensor frame, depth, projector-lit mask, sensor pose) is returned
apart from the images, which are all the sensor "sees".

Units: metres, radians, pixels (pixel-centre convention: pixel ``(u, v)`` is centred at
``(u, v)``). The sensor frame is the camera frame (x right, y down, z forward).
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from pydantic import Field

from fpp_graph.errors import InputDataError
from frontend.fpp.patterns import PatternSpec, pattern_intensity
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.sim.config import StrictModel, validate_section


class RenderSettings(StrictModel):
    """Photometric model of the simulated sensor (grey levels refer to the 8-bit output).

    The default noise is that of a machine-vision CMOS camera at moderate gain: read noise
    ``0.8`` grey levels plus shot noise with variance ``0.012 * signal`` (about 1.3 grey levels
    at mid-grey).
    """

    projector_irradiance_grey: float = Field(220.0, ge=0, description="grey level of a white Lambertian surface facing the projector at the working distance, full-white pattern")
    pattern_black_level: float = Field(0.01, ge=0, lt=1, description="DMD contrast: a black pattern pixel still emits this fraction")
    projector_gamma: float = Field(2.2, gt=0, description="projector's native response exponent (a DLP projector's video gamma)")
    projector_gamma_compensation: float = Field(2.0, gt=0, description="exponent the projector firmware pre-corrects with: the emitted level is P^(gamma / compensation); partial, as on LightCrafter-class firmware, so 2.2 / 2.0 leaves x^1.1")
    ambient_grey: float = Field(8.0, ge=0, description="ambient light on a white surface, grey levels")
    inverse_square: bool = Field(True, description="projector irradiance falls off as (reference distance / distance)^2")
    irradiance_reference_m: float = Field(0.5, gt=0, description="projector distance at which projector_irradiance_grey holds")
    camera_gamma: float = Field(1.0, gt=0, description="camera response: out = 255 (in / 255)^(1 / gamma); 1 = linear, as machine-vision cameras ship (gamma off), which FPP needs")
    read_noise_grey: float = Field(0.8, ge=0, description="signal-independent Gaussian noise sigma, grey levels")
    shot_noise_gain: float = Field(0.012, ge=0, description="signal-dependent noise variance per grey level of signal")
    blur_sigma_px: float = Field(0.6, ge=0, description="in-focus blur sigma (lens + pixel integration), camera pixels at full resolution")
    aperture_diameter_m: float = Field(0.0015, ge=0, description="lens aperture (12 mm at f/8); sets the defocus blur")
    focus_distance_m: float = Field(0.5, gt=0)
    max_blur_sigma_px: float = Field(4.0, gt=0, description="cap of the defocus blur sigma")
    shadow_offset_m: float = Field(1e-4, gt=0, description="shadow-ray start offset along the normal (avoids self-hits)")
    min_lit_cosine: float = Field(0.02, ge=0, lt=1, description="grazing projector light below this cosine is treated as unlit")
    smooth_shading: bool = Field(False, description="projector irradiance from normals interpolated across each triangle (smooth surfaces) instead of the flat triangle normal (faceted shading)")
    interreflection_fraction: float = Field(0.0, ge=0, lt=1, json_schema_extra={"unit": "-"}, description="diffuse indirect light: the fraction of the surrounding surfaces' direct projector radiance a point receives and re-reflects with its albedo; 0 = off (direct light only)")
    interreflection_sigma_px: float = Field(60.0, gt=0, description="Gaussian sigma of the surroundings whose light a point receives, camera pixels at full resolution (60: a tenth of a 1920-pixel view, the scale of a nearby wall or a concave part)")
    seed: int = Field(0, description="noise seed; frame k uses (seed, k)")


def camera_ray_directions(camera: PinholeModel) -> NDArray[np.float64]:
    """Unit ray directions (H, W, 3) in the camera frame through every (distorted) pixel centre.

    Undistortion iterates to 1e-14 so the rays are exact to far below the decoder's noise.
    """
    return _camera_rays_cached(camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes()).copy()


@functools.lru_cache(maxsize=4)
def _camera_rays_cached(width: int, height: int, K_bytes: bytes, dist_bytes: bytes) -> NDArray[np.float64]:
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    dist = np.frombuffer(dist_bytes, dtype=np.float64)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    if dist.size and np.any(dist != 0):
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        xy = cv2.undistortPoints(pix, K, dist, None, None, None, criteria).reshape(-1, 2)
    else:
        xy = np.stack([(pix[:, 0, 0] - K[0, 2] - K[0, 1] * (pix[:, 0, 1] - K[1, 2]) / K[1, 1]) / K[0, 0], (pix[:, 0, 1] - K[1, 2]) / K[1, 1]], axis=1)
    d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out = d.reshape(height, width, 3)
    out.setflags(write=False)
    return out


def project_points(model: PinholeModel, T_device_sensor: NDArray, points_sensor: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Project sensor-frame points into a device with OpenCV's lens model (numpy, float64).

    Supports OpenCV's radial-tangential model with up to 8 coefficients (k1 k2 p1 p2 k3 k4 k5
    k6, rational); thin-prism/tilt models (12/14 coefficients) go through ``cv2.projectPoints``.

    Returns
    -------
    u_px, v_px : (N,) float64
        Pixel coordinates (pixel-centre convention).
    z_m : (N,) float64
        Depth in the device frame (points with ``z <= 0`` are behind it).
    """
    dtype = np.float32 if points_sensor.dtype == np.float32 else np.float64
    R = T_device_sensor[:3, :3].astype(dtype)
    t = T_device_sensor[:3, 3].astype(dtype)
    p = points_sensor @ np.ascontiguousarray(R.T) + t  # contiguous R^T: numpy's BLAS path
    z = p[:, 2]
    K = model.K
    if model.dist.size > 8 and model.has_distortion:
        rvec, _ = cv2.Rodrigues(R)
        uv, _ = cv2.projectPoints(points_sensor.reshape(-1, 1, 3), rvec, t.astype(np.float64), K, model.dist)
        uv = uv.reshape(-1, 2)
        return uv[:, 0], uv[:, 1], z
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / z
    x = p[:, 0] * inv_z
    y = p[:, 1] * inv_z
    if model.has_distortion:
        d = np.zeros(8)
        d[: model.dist.size] = model.dist
        k1, k2, p1, p2, k3, k4, k5, k6 = (float(c) for c in d)  # python floats keep the array dtype
        x2, y2, xy = x * x, y * y, x * y
        r2 = x2 + y2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if k4 or k5 or k6:
            radial = radial / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
        yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
        x, y = xd, yd
    fx, skew, cx, fy, cy = float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2])
    return fx * x + skew * y + cx, fy * y + cy, z


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What the simulator knows and the sensor does not.

    Attributes
    ----------
    T_world_sensor : (4, 4) float64
    xyz_map_m : (H, W, 3) float64
        First surface hit per camera pixel, sensor frame, NaN where the ray hits nothing.
    depth_m : (H, W) float64
        z of ``xyz_map_m`` (NaN where nothing is hit).
    lit_mask : (H, W) bool
        The hit is inside the projector image, faces it and is not in its shadow: only these
        pixels can be decoded.
    albedo : (H, W) float32
        Surface reflectance at the hit (0 where nothing is hit).
    """

    T_world_sensor: NDArray[np.float64]
    xyz_map_m: NDArray[np.float64]
    depth_m: NDArray[np.float64]
    lit_mask: NDArray[np.bool_]
    albedo: NDArray[np.float32]


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One simulated capture: the 8-bit images (all the sensor sees) and the ground truth."""

    images: NDArray[np.uint8]
    ground_truth: GroundTruth


@dataclass(frozen=True, eq=False)
class _RayHits:
    """One pose's camera rays and what they hit (Open3D's answers are per ray, hits or not)."""

    origin: NDArray[np.float64]  # (3,) sensor centre, world frame
    rays: NDArray[np.float32]  # (H*W, 6) origin and unit direction per camera pixel, world frame
    index: NDArray[np.intp]  # (n,) flat pixel index of the rays that hit
    t_hit: NDArray[np.float32]  # (n,) hit distance along those rays, metres
    normals: NDArray[np.float32]  # (H*W, 3) normal of the hit triangle
    geometry_ids: NDArray[np.uint32]  # (H*W,)
    triangle_ids: NDArray[np.uint32]  # (H*W,)
    bary_uv: NDArray[np.float32]  # (H*W, 2) barycentric (u, v) in the hit triangle
    projector_centre_world: NDArray[np.float32]  # (3,)


class FppSimulator:
    """Renders the pattern images a camera + projector rig captures of a static scene.

    Parameters
    ----------
    calibration : RigCalibration
        The rig (its camera size is the rendered image size).
    spec : PatternSpec
        The projected pattern set; ``spec.image_count()`` images per frame, in capture order.
    scene : frontend.sim.scenes.Scene
        Triangle meshes with materials, world frame, metres.
    settings : RenderSettings, optional
    full_resolution_width : int, optional
        Camera width the pixel-valued blur settings refer to (default 1920); blur sigmas scale
        with ``camera.width / full_resolution_width`` so a preview is a binned full frame.
    threads : int, optional
        Worker threads for shading (numpy and OpenCV release the GIL); 0 = one per core.

    Notes
    -----
    Embree intersects in float32: the hit distance is exact to ~1e-7 relative (0.05 um at
    0.5 m); ground-truth points are formed in float64 as ``t * ray`` in the camera frame.
    Shading quantities (projector coordinates, cosines) are float32, whose rounding (~1e-4
    projector pixels) is two orders of magnitude below the phase noise.
    """

    def __init__(self, calibration: RigCalibration, spec: PatternSpec, scene: Any, settings: RenderSettings | None = None, full_resolution_width: int = 1920, threads: int = 0):
        self.calibration = calibration
        self.spec = spec
        self.scene = scene
        self.settings = settings or RenderSettings()
        self._threads = threads if threads > 0 else max(1, min(4, os.cpu_count() or 1))
        self._pixel_scale = calibration.camera.width / float(full_resolution_width)
        self._rays_camera = camera_ray_directions(calibration.camera).reshape(-1, 3)
        self._rays_camera32 = self._rays_camera.astype(np.float32)
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._parts = list(scene.parts)
        if not self._parts:
            raise InputDataError("scene has no surfaces; add at least one non-empty mesh")
        self._gid_to_part: dict[int, int] = {}
        for i, part in enumerate(self._parts):
            gid = self._raycaster.add_triangles(
                o3d.core.Tensor(part.vertices.astype(np.float32)), o3d.core.Tensor(part.triangles.astype(np.uint32))
            )
            self._gid_to_part[int(gid)] = i
        T_cp = np.linalg.inv(calibration.T_projector_camera)
        self._projector_centre_sensor = T_cp[:3, 3].copy()
        # vertex normals (Open3D's, area-weighted), for smooth shading
        self._vertex_normals: list[NDArray[np.float32]] = []
        if self.settings.smooth_shading:
            for part in self._parts:
                mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(part.vertices), o3d.utility.Vector3iVector(part.triangles.astype(np.int32)))
                mesh.compute_vertex_normals()
                self._vertex_normals.append(np.asarray(mesh.vertex_normals, dtype=np.float32))

    def _map(self, fn, n: int) -> list:
        """Run ``fn(slice)`` over ``n`` items split into one chunk per thread."""
        k = self._threads if n >= 20000 else 1
        bounds = np.linspace(0, n, k + 1).astype(int)
        slices = [slice(bounds[i], bounds[i + 1]) for i in range(k)]
        if k == 1:
            return [fn(slices[0])]
        with ThreadPoolExecutor(k) as pool:
            return list(pool.map(fn, slices))

    # -- geometry -------------------------------------------------------------------------------
    def ground_truth(self, T_world_sensor: NDArray, where: str = "frame") -> tuple[GroundTruth, dict[str, NDArray]]:
        """Ray-cast one pose: ground truth, and the per-hit inputs of shading.

        Raises
        ------
        InputDataError
            The sensor is inside (or touching) scene geometry.
        """
        T_world_sensor = np.asarray(T_world_sensor, dtype=np.float64)
        hits = self._cast_camera_rays(T_world_sensor)
        n = hits.index.size
        out = {
            "pts_cam": np.empty((n, 3)),
            "u_p": np.empty(n, np.float32),
            "v_p": np.empty(n, np.float32),
            "lit": np.empty(n, bool),
            "irradiance": np.empty(n, np.float32),
            "albedo": np.empty(n, np.float32),
            "backfacing": np.empty(n, bool),
        }
        self._map(lambda sl: self._shade_hits(hits, sl, out), n)
        self._check_sensor_outside(out["backfacing"], n, T_world_sensor, where)
        gt = self._ground_truth_maps(T_world_sensor, hits.index, out)
        out["index"] = hits.index
        out["depth"] = out["pts_cam"][:, 2]
        return gt, out

    def _cast_camera_rays(self, T_world_sensor: NDArray) -> _RayHits:
        """Cast one ray per camera pixel from the sensor pose into the scene."""
        cam = self.calibration.camera
        H, W = cam.height, cam.width
        R32 = T_world_sensor[:3, :3].astype(np.float32)
        origin = T_world_sensor[:3, 3]
        rays = np.empty((H * W, 6), dtype=np.float32)
        rays[:, :3] = origin
        np.matmul(self._rays_camera32, np.ascontiguousarray(R32.T), out=rays[:, 3:])  # contiguous: BLAS path, 25x faster
        ans = self._raycaster.cast_rays(o3d.core.Tensor(rays))
        t_all = ans["t_hit"].numpy()
        index = np.flatnonzero(np.isfinite(t_all))
        return _RayHits(
            origin=origin,
            rays=rays,
            index=index,
            t_hit=t_all[index],
            normals=ans["primitive_normals"].numpy(),
            geometry_ids=ans["geometry_ids"].numpy(),
            triangle_ids=ans["primitive_ids"].numpy(),
            bary_uv=ans["primitive_uvs"].numpy(),
            projector_centre_world=(T_world_sensor[:3, :3] @ self._projector_centre_sensor + origin).astype(np.float32),
        )

    def _shade_hits(self, hits: _RayHits, sl: slice, out: dict[str, NDArray]) -> None:
        """Fill ``out[...][sl]`` for the hits ``sl``: camera-frame points, projector pixels, lit
        mask, projector irradiance (grey levels) and albedo."""
        s = self.settings
        proj = self.calibration.projector
        T_pc32 = self.calibration.T_projector_camera.astype(np.float32)
        c_proj_world = hits.projector_centre_world
        idx = hits.index[sl]
        t = hits.t_hit[sl]
        d_world = hits.rays[idx, 3:]
        pts_world = hits.origin.astype(np.float32) + t[:, None] * d_world
        out["pts_cam"][sl] = t.astype(np.float64)[:, None] * self._rays_camera[idx]
        nrm = hits.normals[idx]
        back = np.einsum("ij,ij->i", nrm, d_world) > 0
        nrm[back] *= -1.0  # two-sided surfaces: use the side the camera sees
        out["backfacing"][sl] = back
        pts_cam32 = t[:, None] * self._rays_camera32[idx]
        u_p, v_p, z_p = project_points(proj, T_pc32, pts_cam32)
        inside = (z_p > 0) & (u_p >= -0.5) & (u_p < proj.width - 0.5) & (v_p >= -0.5) & (v_p < proj.height - 0.5)
        to_proj = c_proj_world - pts_world
        dist_p = np.sqrt(np.einsum("ij,ij->i", to_proj, to_proj))
        cos_p = np.einsum("ij,ij->i", nrm, to_proj) / dist_p
        gids, tris, bary = hits.geometry_ids[idx], hits.triangle_ids[idx], hits.bary_uv[idx]
        cos_shade = cos_p
        if self._vertex_normals:
            smooth_n = self._interpolated_normals(gids, tris, bary, nrm)
            cos_shade = np.maximum(np.einsum("ij,ij->i", smooth_n, to_proj) / dist_p, np.float32(0.0))
        lit = self._unshadowed(inside & (cos_p > s.min_lit_cosine), pts_world, nrm, c_proj_world)
        falloff = (np.float32(s.irradiance_reference_m) / dist_p) ** 2 if s.inverse_square else np.float32(1.0)
        out["irradiance"][sl] = np.where(lit, np.float32(s.projector_irradiance_grey) * cos_shade * falloff, np.float32(0.0))
        out["lit"][sl] = lit
        out["u_p"][sl] = u_p
        out["v_p"][sl] = v_p
        out["albedo"][sl] = self._albedo_at(gids, tris, bary, pts_world)

    def _unshadowed(self, lit: NDArray, pts_world: NDArray, normals: NDArray, c_proj_world: NDArray) -> NDArray[np.bool_]:
        """``lit`` without the hits whose shadow ray towards the projector centre meets geometry."""
        cand = np.flatnonzero(lit)
        if not cand.size:
            return lit
        shadow = np.empty((cand.size, 6), dtype=np.float32)
        shadow[:, :3] = pts_world[cand] + np.float32(self.settings.shadow_offset_m) * normals[cand]
        shadow[:, 3:] = c_proj_world - shadow[:, :3]  # unnormalised: t = 1 at the projector
        occluded = self._raycaster.test_occlusions(o3d.core.Tensor(shadow), tnear=0.0, tfar=0.999, nthreads=1).numpy().astype(bool)
        lit[cand[occluded]] = False
        return lit

    def _albedo_at(self, gids: NDArray, tris: NDArray, bary: NDArray, pts_world: NDArray) -> NDArray[np.float32]:
        """Material albedo at hits on Open3D geometries ``gids``, triangles ``tris``, barycentrics ``bary``."""
        alb = np.zeros(gids.size, np.float32)
        present = np.flatnonzero(np.bincount(gids, minlength=1))  # only the parts this view sees
        for gid in present:
            pi = self._gid_to_part[int(gid)]
            sel = np.flatnonzero(gids == gid)
            if sel.size:
                alb[sel] = self._parts[pi].material.albedo(pts_world[sel], tris[sel].astype(np.int64), bary[sel])
        return alb

    def _ground_truth_maps(self, T_world_sensor: NDArray, index: NDArray, shading: dict[str, NDArray]) -> GroundTruth:
        """Per-pixel ground truth from the per-hit values (``index``: flat pixel of each hit)."""
        cam = self.calibration.camera
        H, W = cam.height, cam.width
        xyz = np.full((H * W, 3), np.nan)
        xyz[index] = shading["pts_cam"]
        lit_mask = np.zeros(H * W, dtype=bool)
        lit_mask[index[shading["lit"]]] = True
        albedo = np.zeros(H * W, dtype=np.float32)
        albedo[index] = shading["albedo"]
        return GroundTruth(
            T_world_sensor=T_world_sensor.copy(),
            xyz_map_m=xyz.reshape(H, W, 3),
            depth_m=xyz[:, 2].reshape(H, W).copy(),
            lit_mask=lit_mask.reshape(H, W),
            albedo=albedo.reshape(H, W),
        )

    def _interpolated_normals(self, gids: NDArray, tris: NDArray, bary: NDArray, face_normals: NDArray) -> NDArray[np.float32]:
        """Vertex normals interpolated at the hits (barycentric ``(u, v)`` of Open3D: weights
        ``1 - u - v, u, v``), turned to the side of the (camera-facing) face normals."""
        out = face_normals.copy()
        for gid in np.unique(gids):
            sel = np.flatnonzero(gids == gid)
            pi = self._gid_to_part[int(gid)]
            corners = self._vertex_normals[pi][self._parts[pi].triangles[tris[sel].astype(np.int64)]]  # (k, 3, 3)
            u, v = bary[sel, 0:1], bary[sel, 1:2]
            n = (1.0 - u - v) * corners[:, 0] + u * corners[:, 1] + v * corners[:, 2]
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            flip = np.einsum("ij,ij->i", n, face_normals[sel]) < 0
            n[flip] *= -1.0
            out[sel] = n
        return out

    def _check_sensor_outside(self, backfacing: NDArray, n: int, T_world_sensor: NDArray, where: str) -> None:
        frac_back = float(np.count_nonzero(backfacing)) / n if n else 0.0
        origin = o3d.core.Tensor(T_world_sensor[:3, 3].astype(np.float32)[None])
        dist = float(self._raycaster.compute_distance(origin).numpy()[0])
        if frac_back > 0.5 or dist < 1e-3:
            raise InputDataError(
                f"{where}: the sensor at {np.round(T_world_sensor[:3, 3], 4).tolist()} m is inside or touching scene "
                f"geometry ({100 * frac_back:.0f}% of camera rays hit the inside of a surface, nearest surface "
                f"{1000 * dist:.1f} mm); move the sensor or fix the mesh's face orientation"
            )

    # -- images ---------------------------------------------------------------------------------
    def render(self, T_world_sensor: NDArray, frame_index: int = 0) -> RenderedFrame:
        """Render the full pattern stack of one frame.

        Parameters
        ----------
        T_world_sensor : (4, 4) float64
            Sensor (camera) pose in the world frame.
        frame_index : int
            Seeds the noise together with ``settings.seed`` (reproducible captures).

        Returns
        -------
        RenderedFrame
            ``images`` (M, H, W) uint8 in capture order, plus ground truth.

        Raises
        ------
        InputDataError
            The sensor is inside scene geometry.
        """
        s = self.settings
        cam = self.calibration.camera
        H, W = cam.height, cam.width
        gt, sh = self.ground_truth(T_world_sensor, where=f"frame {frame_index}")
        index, lit = sh["index"], sh["lit"]
        lit_index = index[lit]
        ambient_img = np.zeros(H * W, dtype=np.float32)
        ambient_img[index] = sh["albedo"] * np.float32(s.ambient_grey)
        indirect = self._indirect_plan(index, sh["albedo"], H, W)
        gain_lit = sh["albedo"][lit] * sh["irradiance"][lit]
        u_lit, v_lit = sh["u_p"][lit], sh["v_p"][lit]
        blur = self._blur_plan(index, sh["depth"], H, W)
        proj = self.calibration.projector
        M = self.spec.image_count()
        out = np.empty((M, H, W), dtype=np.uint8)
        black = np.float32(s.pattern_black_level)

        def one(m: int) -> None:
            P = pattern_intensity(self.spec, m, u_lit, v_lit, proj.width, proj.height).astype(np.float32)
            if s.projector_gamma != s.projector_gamma_compensation:
                P = P ** np.float32(s.projector_gamma / s.projector_gamma_compensation)
            flat = ambient_img.copy()
            flat[lit_index] += gain_lit * (black + (np.float32(1.0) - black) * P)
            if indirect is not None:
                direct = np.zeros(H * W, dtype=np.float32)
                direct[lit_index] = flat[lit_index] - ambient_img[lit_index]
                flat += indirect(direct.reshape(H, W)).ravel()
            rng = np.random.default_rng([int(s.seed) & 0xFFFFFFFF, int(frame_index), m])
            out[m] = self._camera_response(blur(flat.reshape(H, W)), rng)

        if self._threads > 1:
            with ThreadPoolExecutor(self._threads) as pool:
                list(pool.map(one, range(M)))
        else:
            for m in range(M):
                one(m)
        return RenderedFrame(images=out, ground_truth=gt)

    def _indirect_plan(self, index: NDArray, albedo: NDArray, H: int, W: int):
        """A function from a direct radiance image to its indirect light (step 4), or None when off."""
        s = self.settings
        if s.interreflection_fraction <= 0.0:
            return None
        receiver = np.zeros(H * W, dtype=np.float32)
        receiver[index] = albedo * np.float32(s.interreflection_fraction)
        receiver = receiver.reshape(H, W)
        sigma = s.interreflection_sigma_px * self._pixel_scale
        return lambda direct: receiver * wide_gaussian_blur(direct, sigma)

    def _blur_plan(self, index: NDArray, depth: NDArray, H: int, W: int):
        """A function blurring one radiance image with depth-dependent defocus."""
        s = self.settings
        f_px = float(self.calibration.camera.K[0, 0])
        base = s.blur_sigma_px * self._pixel_scale
        # Thin lens: blur-circle diameter (pixels) = f_px * aperture * |1/z - 1/z_focus|;
        # a uniform disc of diameter c has sigma ~ c / 4, combined in quadrature with the base.
        c = f_px * s.aperture_diameter_m * np.abs(1.0 / depth - 1.0 / s.focus_distance_m)
        sigma_hits = np.minimum(np.sqrt(base**2 + (c / 4.0) ** 2), s.max_blur_sigma_px * self._pixel_scale)
        lo = float(base)
        hi = float(np.percentile(sigma_hits, 99)) if sigma_hits.size else lo
        if hi - lo < 0.05:
            sig = max(lo, hi)
            if sig < 0.05:
                return lambda img: img
            return lambda img: cv2.GaussianBlur(img, (0, 0), sig, borderType=cv2.BORDER_REPLICATE)
        sigma = np.full(H * W, lo, dtype=np.float32)
        sigma[index] = sigma_hits
        weight = np.clip((sigma - lo) / (hi - lo), 0.0, 1.0).reshape(H, W).astype(np.float32)
        lo = max(lo, 0.05)

        def blur(img: NDArray) -> NDArray:
            a = cv2.GaussianBlur(img, (0, 0), lo, borderType=cv2.BORDER_REPLICATE)
            b = cv2.GaussianBlur(img, (0, 0), hi, borderType=cv2.BORDER_REPLICATE)
            b -= a
            b *= weight
            return a + b

        return blur

    def _camera_response(self, signal: NDArray, rng: np.random.Generator) -> NDArray[np.uint8]:
        s = self.settings
        var = np.maximum(signal, 0) * np.float32(s.shot_noise_gain)
        var += np.float32(s.read_noise_grey**2)
        noise = rng.standard_normal(signal.shape, dtype=np.float32)
        noise *= np.sqrt(var)
        noisy = signal + noise
        if s.camera_gamma != 1.0:
            noisy = 255.0 * (np.clip(noisy, 0, None) / 255.0) ** (1.0 / s.camera_gamma)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def wide_gaussian_blur(image: NDArray[np.float32], sigma_px: float) -> NDArray[np.float32]:
    """Gaussian blur of a float32 image with a wide ``sigma_px``, computed on a reduced image.

    The image is area-averaged by an integer factor ``f <= sigma / 4``, blurred with
    ``sigma / f`` and bilinearly enlarged back: the averaging box and the interpolation add a
    variance of about ``f^2 / 4`` pixels^2, under 1.6 % of ``sigma^2``, and the cost falls by
    ``f^2``: a sigma of 60 pixels on a 1920 x 1200 image took 2.5 ms instead of 1.4 s, and differed
    from the full-size blur of a 100-grey-level checkerboard of 200 x 150-pixel cells by at most 0.43
    grey levels away from the border (1.7 at it). Borders reflect.
    """
    h, w = image.shape
    factor = max(1, min(int(sigma_px // 4), h, w))
    if factor == 1:
        return cv2.GaussianBlur(image, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT_101)
    small = cv2.resize(image, (max(1, round(w / factor)), max(1, round(h / factor))), interpolation=cv2.INTER_AREA)
    scale_x, scale_y = w / small.shape[1], h / small.shape[0]
    small = cv2.GaussianBlur(small, (0, 0), sigmaX=sigma_px / scale_x, sigmaY=sigma_px / scale_y, borderType=cv2.BORDER_REFLECT_101)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def parse_render_settings(data: dict[str, Any] | None, where: str) -> RenderSettings:
    """Validate a ``render:`` config section (unknown keys are errors)."""
    return validate_section(RenderSettings, data, where)
