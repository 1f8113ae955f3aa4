"""A frame's organised map prepared for dense alignment (:mod:`frontend.dense_alignment`).

How a point finds its pixel and the surface there (projective data association, as in
KinectFusion, but on the map's own rays):

* A point ``X`` in a frame's camera is associated with the pixel whose ray passes through it.
  The pixel is found from a pinhole fitted to the map (:func:`fit_pinhole`) and then corrected
  with the map's own per-pixel ray directions (``x/z, y/z`` of each decoded point: a
  triangulated point lies on its pixel's ray whatever its range error, so this map is
  noise-free and carries the lens distortion). No calibration has to travel with a frame.
* The surface there is the bilinear interpolation of the four decoded points, its normal the
  cross product of central differences of a box-smoothed map (raw normals of 0.25 mm pixels
  with 0.2 mm noise are meaningless).

The normals and rays (binned) are what a surface costs to make (~50 ms of a 1920x1200 map); a
decode worker makes them once and stores them with the frame (:meth:`OrganisedSurface.to_arrays`,
:meth:`OrganisedSurface.from_arrays`).
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import finite_points

Array = NDArray[np.float64]

_BIN_PX = 2  # normals and rays live on b x b bins (see OrganisedSurface)
SURFACE_ARRAYS = ("surface.pinhole", "surface.rays", "surface.normals")
"""Names of :meth:`OrganisedSurface.to_arrays` (stored in :attr:`fpp_graph.types.Frame.prepared`)."""
_REMAP_ROW = 1024  # cv2.remap needs maps below 32767 rows: queries are laid out 1024 per row


def sample_bilinear(image: NDArray[np.float32], u_px: NDArray, v_px: NDArray) -> NDArray[np.float32]:
    """Bilinear samples of an (H, W, C) float32 image at pixel positions; NaN outside or next to NaN.

    Returns
    -------
    (N, C) float32
    """
    n = int(u_px.size)
    rows = max(1, -(-n // _REMAP_ROW))
    U = np.full(rows * _REMAP_ROW, -10.0, np.float32)
    V = np.full(rows * _REMAP_ROW, -10.0, np.float32)
    U[:n] = u_px
    V[:n] = v_px
    out = cv2.remap(image, U.reshape(rows, _REMAP_ROW), V.reshape(rows, _REMAP_ROW), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=(float("nan"),) * 4)
    channels = 1 if image.ndim == 2 else image.shape[2]
    return out.reshape(rows * _REMAP_ROW, channels)[:n]


def _normal_window_px(width_px: int, asked: int | None) -> int:
    """The normals' smoothing window: as asked, else 10 px at 1920 wide (scaled with the image)."""
    return int(asked) if asked else max(4, round(10 * width_px / 1920))


def fit_pinhole(xyz_map: NDArray, step_px: int = 8) -> tuple[NDArray[np.float64], float] | None:
    """Pinhole ``(fx, fy, cx, cy)`` of an organised map by least squares (``u = fx X/Z + cx``), and its RMS in pixels.

    The map's pixels are the camera's, so the projection comes from the frame itself: no
    calibration has to travel with a Frame. Lens distortion shows up in the RMS.
    """
    sub = np.asarray(xyz_map[::step_px, ::step_px], dtype=np.float64)
    v, u = np.mgrid[0 : sub.shape[0], 0 : sub.shape[1]] * float(step_px)
    ok = finite_points(sub) & (sub[..., 2] > 0)
    if int(ok.sum()) < 20:
        return None
    X, Y, Z = sub[ok, 0], sub[ok, 1], sub[ok, 2]
    params, res2 = [], 0.0
    for coord, pix in ((X / Z, u[ok]), (Y / Z, v[ok])):
        A = np.stack([coord, np.ones_like(coord)], axis=1)
        sol, *_ = np.linalg.lstsq(A, pix, rcond=None)
        params.append(sol)
        res2 += float(np.sum((A @ sol - pix) ** 2))
    (fx, cx), (fy, cy) = params
    if not (np.isfinite([fx, fy, cx, cy]).all() and abs(fx) > 1 and abs(fy) > 1):
        return None
    return np.array([fx, fy, cx, cy]), float(np.sqrt(res2 / (2 * X.size)))


class OrganisedSurface:
    """A frame's organised map prepared for dense alignment (as target and as source).

    Parameters
    ----------
    xyz_map : (H, W, 3)
        Sensor-frame points in metres, NaN where invalid.
    normal_window_px : int, optional
        Width of the box that smooths the map before normals are taken; default scales
        with the image (10 px at 1920 wide: a 2.75 mm window at 0.5 m).

    Raises
    ------
    InputDataError
        The map is not (H, W, 3), or has too few valid pixels to fit its pinhole.
    """

    def __init__(self, xyz_map: NDArray, normal_window_px: int | None = None):
        xyz = self._checked_map(xyz_map)
        H, W = xyz.shape[:2]
        cam = fit_pinhole(xyz) if self.num_valid >= 20 else None
        if cam is None:
            raise InputDataError(f"dense alignment: only {self.num_valid} valid pixels in a {W}x{H} map; a surface needs more")
        self.fx, self.fy, self.cx, self.cy = (float(c) for c in cam[0])
        # Normals and rays on a b x b binned map: normals come from a box-smoothed map anyway, and a
        # pixel's ray is smooth across pixels (the lens), so bilinear on 2 px is exact to ~1e-6 px
        # (4 px bins smooth away relief a few pixels across).
        b = self.bin_px = _BIN_PX
        Hb, Wb = H // b, W // b
        # b x b means (INTER_AREA at an integer factor); NaN where any of them is invalid
        binned = cv2.resize(xyz[: b * Hb, : b * Wb], (Wb, Hb), interpolation=cv2.INTER_AREA)
        bx, by, bz = cv2.split(binned)  # contiguous planes: numpy's broadcasts over 3 channels are 5-10x slower
        valid_b = np.isfinite(bz)
        # the mean ray of a bin is mean(x)/mean(z) up to the bin's relative depth noise (~1e-3 of
        # the ray's change across the bin): negligible
        np.divide(bx, bz, out=bx)
        np.divide(by, bz, out=by)
        self.rays_binned = cv2.merge([bx, by])
        # filled at the first projection: a tracked frame's map is often only sampled, never
        # projected into (10-15 ms of a 640x480 frame's preparation)
        self._valid_bins: NDArray[np.bool_] | None = valid_b
        window_px = self.normal_window_px = _normal_window_px(W, normal_window_px)
        k = max(3, 2 * (round(window_px / b) // 2) + 1)  # odd, in bins
        count = cv2.boxFilter(valid_b.astype(np.float32), -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        cv2.patchNaNs(binned, 0.0)
        sx, sy, sz = cv2.split(cv2.boxFilter(binned, -1, (k, k), normalize=True, borderType=cv2.BORDER_CONSTANT))
        # the whole window valid: no mixing across depth edges or holes. NaN in one plane is
        # enough: every normal whose differences touch it has a NaN norm below
        np.copyto(sx, np.float32(np.nan), where=count < k * k - 0.1)
        h = max(1, k // 4)
        # cross product of central differences, on contiguous planes (np.cross on (H, W, 3) is 5x slower)
        def differences(plane: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
            du = np.full_like(plane, np.nan)
            dv = np.full_like(plane, np.nan)
            np.subtract(plane[:, 2 * h :], plane[:, : -2 * h], out=du[:, h:-h])
            np.subtract(plane[2 * h :], plane[: -2 * h], out=dv[h:-h])
            return du, dv
        (ux, vx), (uy, vy), (uz, vz) = differences(sx), differences(sy), differences(sz)
        # in place: every full-size temporary costs page faults
        nx, ny, nz = uy * vz, uz * vx, ux * vy
        nx -= np.multiply(uz, vy, out=uz)
        ny -= np.multiply(ux, vz, out=ux)
        nz -= np.multiply(uy, vx, out=uy)
        # the norm in numpy, not cv2.magnitude: OpenCV's SIMD and scalar paths round differently
        # and which one a pixel takes depends on the buffer's alignment, so the same map gave
        # normals 1 ulp apart from one allocation to the next and runs were not reproducible
        inv_norm = np.multiply(nx, nx)
        inv_norm += ny * ny
        inv_norm += nz * nz
        np.sqrt(inv_norm, out=inv_norm)
        np.divide(np.float32(1.0), inv_norm, out=inv_norm)
        # towards the camera (the map's image axes may be mirrored relative to the sensor's)
        facing = np.multiply(nx, sx, out=sx)
        facing += np.multiply(ny, sy, out=sy)
        facing += np.multiply(nz, sz, out=sz)
        inv_norm[facing > 0] *= -1.0
        n = cv2.merge([np.multiply(nx, inv_norm, out=nx), np.multiply(ny, inv_norm, out=ny), np.multiply(nz, inv_norm, out=nz)])
        self.normals_binned = n
        self._samples: dict[int, tuple[Array, Array]] = {}

    def _checked_map(self, xyz_map: NDArray) -> NDArray[np.float32]:
        """The map as this surface keeps it (float32, contiguous, NaN where z <= 0); sets the size
        and :attr:`num_valid`."""
        xyz = np.asarray(xyz_map)
        if xyz.ndim != 3 or xyz.shape[2] != 3:
            raise InputDataError(f"dense alignment needs an (H, W, 3) xyz map, got shape {xyz.shape}")
        source_map = xyz
        xyz = np.ascontiguousarray(xyz, dtype=np.float32)
        self.height, self.width = xyz.shape[:2]
        # Full-resolution work is kept to the float32 copy and two scans of z: every further
        # full-size temporary costs ~5-10 ms per 1920x1200 map (page faults included).
        z = xyz[..., 2]
        with np.errstate(invalid="ignore"):
            self.num_valid = int(np.count_nonzero(z > 0))  # NaN compares False
        if self.num_valid != int(np.count_nonzero(np.isfinite(z))):
            # points on or behind the camera are not surface samples (never from a decoder)
            if np.shares_memory(xyz, source_map):
                xyz = xyz.copy()  # never write into the caller's frame
            with np.errstate(invalid="ignore"):
                xyz[~(xyz[..., 2] > 0)] = np.nan
        # (a point with NaN x or y only is dropped where it is sampled: samples() and lookup())
        self.xyz = xyz
        return xyz

    def to_arrays(self) -> dict[str, NDArray]:
        """What :meth:`from_arrays` needs besides the map (:data:`SURFACE_ARRAYS`): the pinhole,
        the binned rays (filled near the surface) and normals, about 5 bytes a pixel. A decode
        worker stores them with the frame (:meth:`TexturedSurfaceRegistrar.prepare`), so every process
        that aligns the frame reads them instead of making them again (a 1920x1200 map: ~50 ms)."""
        self._fill_pending_rays()
        return {
            "surface.pinhole": np.array([self.fx, self.fy, self.cx, self.cy, self.bin_px, self.normal_window_px], dtype=np.float64),
            "surface.rays": self.rays_binned,
            "surface.normals": self.normals_binned,
        }

    @classmethod
    def from_arrays(cls, xyz_map: NDArray, arrays: Mapping[str, NDArray], normal_window_px: int | None = None) -> OrganisedSurface | None:
        """The surface of ``xyz_map`` from its :meth:`to_arrays` (the same numbers as making it
        again); None when ``arrays`` lack them or were made for another map size, bin or normal window."""
        if not all(name in arrays for name in SURFACE_ARRAYS):
            return None
        pinhole = np.asarray(arrays["surface.pinhole"], dtype=np.float64)
        rays, normals = np.asarray(arrays["surface.rays"]), np.asarray(arrays["surface.normals"])
        shape = np.shape(xyz_map)
        if len(shape) != 3 or pinhole.shape != (6,) or int(pinhole[4]) != _BIN_PX:
            return None
        if int(pinhole[5]) != _normal_window_px(shape[1], normal_window_px):
            return None
        binned = (shape[0] // _BIN_PX, shape[1] // _BIN_PX)
        if rays.shape != (*binned, 2) or normals.shape != (*binned, 3) or rays.dtype != np.float32 or normals.dtype != np.float32:
            return None
        surface = cls.__new__(cls)
        surface._checked_map(xyz_map)
        surface.fx, surface.fy, surface.cx, surface.cy = (float(c) for c in pinhole[:4])
        surface.bin_px, surface.normal_window_px = _BIN_PX, int(pinhole[5])
        surface.rays_binned, surface.normals_binned = rays, normals
        surface._valid_bins = None  # stored filled
        surface._samples = {}
        return surface

    def _fill_pending_rays(self) -> None:
        if self._valid_bins is not None:
            self._fill_rays_near_surface(self._valid_bins)
            self._valid_bins = None

    def _fill_rays_near_surface(self, valid_b: NDArray[np.bool_], degree: int = 5, ring_bins: int = 8) -> None:
        """Rays for invalid bins within ``ring_bins`` of the surface, from a polynomial lens model.

        A lookup starts at the fitted pinhole's pixel, which near a silhouette can be an invalid
        pixel (up to ~2 px off at a Brown k1 = -0.075 lens corner); without a ray there it would
        stay uncorrected. The map's rays minus the pinhole's are smooth (radial and tangential
        distortion are polynomials of degree <= 5 in the normalised coordinates): a least-squares
        fit over the valid bins fills the ring.
        """
        Hb, Wb = valid_b.shape
        ring = cv2.dilate(valid_b.astype(np.uint8), np.ones((2 * ring_bins + 1,) * 2, np.uint8)).astype(bool) & ~valid_b
        if not ring.any():
            return
        def pinhole_rays(rows: NDArray, cols: NDArray) -> tuple[NDArray, NDArray]:
            c0 = 0.5 * (self.bin_px - 1)  # a bin's centre in pixels
            return (self.bin_px * cols + c0 - self.cx) / self.fx, (self.bin_px * rows + c0 - self.cy) / self.fy
        def monomials(x: NDArray, y: NDArray) -> NDArray:
            # powers by repeated products: 2.5x faster than numpy's general pow (0.4 vs 0.9 ms at 4800 bins)
            xp, yp = [np.ones_like(x)], [np.ones_like(y)]
            for _ in range(degree):
                xp.append(xp[-1] * x)
                yp.append(yp[-1] * y)
            return np.stack([xp[i] * yp[j] for i in range(degree + 1) for j in range(degree + 1 - i)], axis=1)
        rows, cols = np.nonzero(valid_b[::4, ::4])
        rows, cols = 4 * rows, 4 * cols
        x, y = pinhole_rays(rows, cols)
        A = monomials(x, y)
        if rows.size < 3 * A.shape[1]:
            return
        scale = np.abs(A).max(axis=0) + 1e-12  # conditioning of the high powers
        residual = self.rays_binned[rows, cols].astype(np.float64) - np.stack([x, y], axis=1)
        coef, *_ = np.linalg.lstsq(A / scale, residual, rcond=None)
        # the model is smooth: evaluated every 8th bin and resized (bilinear) to the binned grid
        step = 8
        gr, gc = np.mgrid[0 : Hb + step : step, 0 : Wb + step : step]
        x, y = pinhole_rays(gr.ravel(), gc.ravel())
        model = (np.stack([x, y], axis=1) + (monomials(x, y) / scale) @ coef).astype(np.float32).reshape(gr.shape + (2,))
        # bin (r, c) is grid point (r / step, c / step)
        dense_model = cv2.warpAffine(model, np.array([[1.0 / step, 0, 0], [0, 1.0 / step, 0]]), (Wb, Hb), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        self.rays_binned[ring] = dense_model[ring]

    def samples(self, stride_px: int) -> tuple[Array, Array]:
        """Points and normals (N, 3) of every ``stride_px``-th pixel with both (cached)."""
        s = max(1, int(stride_px))
        if s not in self._samples:
            P = self.xyz[::s, ::s].reshape(-1, 3)
            rows, cols = -(-self.height // s), -(-self.width // s)
            # normals at full-resolution pixels (s i, s j) = binned positions (s/2 j - 1/4, s/2 i - 1/4):
            # one affine warp of the binned map instead of a lookup per pixel
            b = self.bin_px
            M = np.array([[s / b, 0.0, -0.5 * (b - 1) / b], [0.0, s / b, -0.5 * (b - 1) / b]])
            N = cv2.warpAffine(self.normals_binned, M, (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=(float("nan"),) * 4).reshape(-1, 3)
            keep = np.flatnonzero(np.isfinite(P[:, 0] + P[:, 1] + P[:, 2] + N[:, 0]))
            N = N[keep]
            N /= np.sqrt(np.einsum("ij,ij->i", N, N))[:, None]
            self._samples[s] = (P[keep].astype(np.float64), N.astype(np.float64))
        return self._samples[s]

    def _binned_position(self, u_px: NDArray[np.float32], v_px: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Full-resolution pixel positions on the binned maps (bin j covers pixels b j .. b j + b - 1)."""
        scale, offset = np.float32(1.0 / self.bin_px), np.float32(0.5 * (self.bin_px - 1))
        return (u_px - offset) * scale, (v_px - offset) * scale

    def normals_at(self, u_px: NDArray, v_px: NDArray) -> NDArray[np.float32]:
        """Unit normals (N, 3) at full-resolution pixel positions (bilinear on the binned map)."""
        n = sample_bilinear(self.normals_binned, *self._binned_position(np.asarray(u_px, np.float32), np.asarray(v_px, np.float32)))
        n /= np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
        return n

    def project(self, points_m: Array, corrections: int = 3) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Pixel ``(u, v)`` (float32, full resolution) whose ray passes through each point (camera frame).

        The fitted pinhole's pixel, corrected with the map's own rays (lens distortion included);
        where the map has no ray nearby the pinhole's pixel is returned.
        """
        self._fill_pending_rays()
        z = points_m[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ax = (points_m[:, 0] / z).astype(np.float32)
            ay = (points_m[:, 1] / z).astype(np.float32)
        u = np.float32(self.fx) * ax + np.float32(self.cx)
        v = np.float32(self.fy) * ay + np.float32(self.cy)
        fx, fy = np.float32(self.fx), np.float32(self.fy)
        for _ in range(corrections):
            ray = sample_bilinear(self.rays_binned, *self._binned_position(u, v))
            du = np.nan_to_num(fx * (ax - ray[:, 0]), nan=0.0)
            dv = np.nan_to_num(fy * (ay - ray[:, 1]), nan=0.0)
            u += du
            v += dv
            # the fixed point converges by the lens's distortion gradient per step; cv2.remap
            # quantises positions to 1/32 of a bin (b/32 px): steps below ~1.6 quanta are that noise
            if max(float(np.max(np.abs(du), initial=0.0)), float(np.max(np.abs(dv), initial=0.0))) < self.bin_px / 20.0:
                break
        return u, v

    def lookup(self, points_m: Array, corrections: int = 3) -> tuple[Array, Array]:
        """Surface point and normal where each point's ray meets this map (NaN off the surface).

        Parameters
        ----------
        points_m : (N, 3)
            Points in this map's camera frame.

        Returns
        -------
        surface_points_m, normals : (N, 3) float64
        """
        z = points_m[:, 2]
        u, v = self.project(points_m, corrections)
        q = sample_bilinear(self.xyz, u, v).astype(np.float64)
        n = self.normals_at(u, v).astype(np.float64)
        behind = ~(z > 0)
        q[behind] = np.nan
        return q, n


__all__ = ["SURFACE_ARRAYS", "OrganisedSurface", "fit_pinhole", "lift_keypoints", "sample_bilinear"]


def lift_keypoints(
    xyz_map: NDArray, keypoints_uv: NDArray, max_depth_step_m: float = 0.005
) -> tuple[Array, NDArray[np.bool_]]:
    """3D points (sensor frame, metres) under sub-pixel keypoints, by bilinear interpolation.

    Parameters
    ----------
    xyz_map : (H, W, 3) float64
        Organised points, NaN where invalid.
    keypoints_uv : (K, 2) float64
        ``(u = column, v = row)`` pixel coordinates, pixel-centre convention.
    max_depth_step_m : float
        Skip a keypoint whose four neighbours span more depth than this (an edge: interpolating
        across it would invent a point in mid-air).

    Returns
    -------
    points : (K, 3) float64
        Interpolated points; NaN rows where ``valid`` is False.
    valid : (K,) bool
        All four neighbours inside the image, finite, and on one surface.
    """
    xyz = np.asarray(xyz_map, dtype=np.float64)
    uv = np.asarray(keypoints_uv, dtype=np.float64).reshape(-1, 2)
    H, W = xyz.shape[:2]
    out = np.full((uv.shape[0], 3), np.nan)
    valid = np.zeros(uv.shape[0], dtype=bool)
    if uv.shape[0] == 0:
        return out, valid
    finite_uv = np.all(np.isfinite(uv), axis=1)
    u = np.where(finite_uv, uv[:, 0], -10.0)
    v = np.where(finite_uv, uv[:, 1], -10.0)
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < W) & (v0 + 1 < H)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return out, valid
    a, b = u0[idx], v0[idx]
    p00, p10, p01, p11 = xyz[b, a], xyz[b, a + 1], xyz[b + 1, a], xyz[b + 1, a + 1]
    corners = np.stack([p00, p10, p01, p11], axis=1)  # (k, 4, 3)
    ok = np.all(np.isfinite(corners), axis=(1, 2))
    z = corners[..., 2]
    with np.errstate(invalid="ignore"):
        ok &= (z.max(axis=1) - z.min(axis=1)) <= max_depth_step_m
    fu = (u[idx] - a)[:, None]
    fv = (v[idx] - b)[:, None]
    interp = (1 - fv) * ((1 - fu) * p00 + fu * p10) + fv * ((1 - fu) * p01 + fu * p11)
    sel = idx[ok]
    out[sel] = interp[ok]
    valid[sel] = True
    return out, valid
