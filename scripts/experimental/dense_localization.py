"""Dense-correspondence camera localisation: experimental, not part of the product.

The library's localisation (``frontend.localization``) is the paper's: :func:`localize_dlt` on map
points and their keypoints, then :func:`localize_photometric`. The alternatives here refine the
DLT with the FPP's own 3D points at exact reference pixels tracked into the query image (KLT on
local contrast, or an affine + gain/bias tracker), hundreds to thousands of correspondences
instead of tens of descriptor matches at ~0.5 px. The photometric alignment supersedes them (corridor,
12 frames against their two neighbours: median camera-centre error 0.039 mm, KLT corners 0.070 mm);
``scripts/registration_acceptance.py`` still reports both side by side.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from frontend.localization import DenseReference, DltSettings, LocalizationResult, localize_dlt
from frontend.localization.photometric import sample_bilinear_clamped

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


def _local_contrast(image: NDArray, window_px: int) -> NDArray[np.uint8]:
    """``100 * I / blur(I)`` (Gaussian sigma about two thirds of the window), as uint8 for KLT."""
    f = image.astype(np.float32)
    m = cv2.GaussianBlur(f, (0, 0), max(1.0, 0.65 * window_px))
    return cv2.convertScaleAbs(f / np.maximum(m, np.float32(2.0)), alpha=100.0)


def localize_dense(
    xyz_map_reference: NDArray,
    texture_reference: NDArray,
    texture_query: NDArray,
    T_query_reference_init: NDArray,
    K: NDArray,
    dist: NDArray | None = None,
    **options: Any,
) -> LocalizationResult:
    """:func:`localize_dense_map` with one reference frame whose sensor frame is the world."""
    return localize_dense_map([DenseReference(xyz_map_reference, texture_reference)], texture_query, T_query_reference_init, K, dist, **options)

def _smooth_surface_mask(depth_m: NDArray, window_px: int, max_step_fraction: float) -> NDArray[np.bool_]:
    """Pixels whose whole ``window_px`` window is valid and spans less depth than
    ``max_step_fraction`` of the median depth (no depth edge, no mixed pixel under it)."""
    z = np.asarray(depth_m)
    finite = np.isfinite(z)
    if not finite.any():
        return finite
    kernel = np.ones((window_px, window_px), np.uint8)
    zf = np.where(finite, z, 0.0).astype(np.float32)
    dz = cv2.dilate(zf, kernel) - cv2.erode(np.where(finite, zf, np.float32(1e9)).astype(np.float32), kernel)
    return (cv2.erode(finite.astype(np.uint8), kernel) > 0) & (dz < max_step_fraction * float(np.median(z[finite])))


def _reference_points(ref: DenseReference, win: int, mind: int, max_points: int) -> tuple[Array, Array, NDArray[np.uint8]]:
    """Corner pixels on smooth valid surface, their world points ``(N, 5, 3)`` (the point, then
    its neighbours half a window away along +u, -u, +v, -v), and the local-contrast image."""
    xyz = np.asarray(ref.xyz_map, dtype=np.float64)
    tex = np.asarray(ref.texture)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise InputDataError(f"dense localisation needs (H, W, 3) reference xyz maps, got {xyz.shape}")
    if tex.ndim != 2 or tex.dtype != np.uint8 or tex.shape != xyz.shape[:2]:
        raise InputDataError(f"dense localisation needs an H x W uint8 reference texture of the xyz map's size, got {tex.dtype} {tex.shape} for {xyz.shape[:2]}")
    T = np.asarray(ref.T_world_reference, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputDataError("dense localisation: T_world_reference must be a finite 4x4 pose")
    # smooth, valid surface under the whole KLT window (no depth edges, no mixed pixels)
    z = xyz[..., 2]
    finite = np.isfinite(z)
    empty = (np.zeros((0, 2)), np.zeros((0, 5, 3)), tex)
    if not finite.any():
        return empty
    mask = _smooth_surface_mask(z, win, 0.01).astype(np.uint8) * 255
    contrast = _local_contrast(tex, win)
    if not mask.any():
        return empty[0], empty[1], contrast
    corners = cv2.goodFeaturesToTrack(contrast, maxCorners=int(max_points), qualityLevel=0.01, minDistance=mind, mask=mask, blockSize=7)
    if corners is None:
        return empty[0], empty[1], contrast
    px = np.rint(corners.reshape(-1, 2)).astype(np.int64)
    k = max(1, win // 2)
    Hh, Ww = z.shape
    px = px[(px[:, 0] >= k) & (px[:, 1] >= k) & (px[:, 0] < Ww - k) & (px[:, 1] < Hh - k)]
    # the point and its neighbours +-k px along u and v (for the predicted local affine map)
    pts = np.stack([xyz[px[:, 1] + dv, px[:, 0] + du] for du, dv in ((0, 0), (k, 0), (-k, 0), (0, k), (0, -k))], axis=1)
    keep = np.all(np.isfinite(pts), axis=(1, 2))
    pts = pts[keep] @ T[:3, :3].T + T[:3, 3]
    return px[keep].astype(np.float64), pts, contrast


# Long only by its docstring; 52 lines of code.
def localize_dense_map(
    references: Sequence[DenseReference],
    texture_query: NDArray,
    T_query_world_init: NDArray,
    K: NDArray,
    dist: NDArray | None = None,
    max_points: int = 4000,
    min_distance_px: int | None = None,
    window_px: int | None = None,
    max_fb_error_px: float = 0.05,
    ransac_threshold_px: float = 1.0,
    min_inliers: int = 50,
    iterations: int = 2,
    tracker: str = "affine",
) -> LocalizationResult:
    """Refine a camera pose with dense FPP correspondences tracked by KLT, then DLT + LM.

    Descriptor keypoints are few and each is located only to a few tenths of a pixel in either
    image, and the 3D point is lifted at the reference keypoint while the 2D observation is a
    *different* detection in the query image. Here the 3D points are the FPP's own measurements
    at exact reference pixels (texture corners, ``cv2.goodFeaturesToTrack``, on valid, smooth
    surface) of one or more map frames, projected into the query image with the current pose,
    tracked there (``tracker="affine"``: :func:`track_affine_photometric`, started from the
    local affine map the 3D points predict; ``"klt"``: pyramidal Lucas-Kanade on local-contrast
    images, kept when tracking back lands within ``max_fb_error_px``), and the pose is re-estimated by :func:`localize_dlt` on all of them
    (DLT in RANSAC, LM on the reprojection error). ``iterations`` repeats predict-track-estimate.

    The texture is lit by the projector, which moves with the camera, so a point's brightness
    changes between views (20-40 % on simulator frames): the affine tracker fits a gain and a
    bias per window, the KLT runs on ``I / blur(I)``.

    The camera centre's precision is set by the spread of the points as much as by their
    number: points on one narrow planar strip (one-third overlap with one wall frame) couple
    rotation and translation (predicted centre sigma 0.19 mm for 660 points at 0.39 px on the
    corridor); map frames covering the whole query view give about 4x less.

    Parameters
    ----------
    references : sequence of DenseReference
        Map frames with their poses in the world.
    texture_query : (H, W) uint8
        Texture image of the camera to locate (same camera model as the references).
    T_query_world_init : (4, 4)
        Initial ``T_camera_world`` (e.g. :func:`localize_dlt` on descriptor matches); good to
        about a pixel of reprojection.
    K, dist : camera intrinsics and OpenCV distortion of the query camera.
    max_points : int
        Corners per reference frame.
    min_distance_px, window_px : int, optional
        Corner spacing and KLT window; default to image width / 160 and / 60, odd (12 and 33 px
        at 1920 wide).

    Returns
    -------
    LocalizationResult
        ``success`` False (and the pose NaN) when fewer than ``min_inliers`` points track.

    Raises
    ------
    InputDataError
        Images not uint8 H x W of the map's size, or a non-finite initial pose.
    """
    b = np.asarray(texture_query)
    T0 = np.asarray(T_query_world_init, dtype=np.float64)
    if b.ndim != 2 or b.dtype != np.uint8:
        raise InputDataError(f"dense localisation needs an H x W uint8 query texture, got {b.dtype} {b.shape}")
    if T0.shape != (4, 4) or not np.all(np.isfinite(T0)):
        raise InputDataError("dense localisation needs a finite 4x4 initial pose (run localize_dlt on descriptor matches first)")
    if not references:
        raise InputDataError("dense localisation needs at least one reference frame")
    if tracker not in ("affine", "klt"):
        raise InputDataError(f"dense localisation: tracker must be 'affine' or 'klt', got {tracker!r}")
    H, W = b.shape
    mind = int(min_distance_px or max(3, round(W / 160)))
    win = int(window_px or max(7, round(W / 60)))
    win += 1 - win % 2
    Km = np.asarray(K, dtype=np.float64)
    dist_arr = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    result = LocalizationResult(np.full((4, 4), np.nan), np.full(3, np.nan), np.zeros(0, bool), float("nan"), 0, False)
    refs = [_reference_points(r, win, mind, max_points) for r in references]
    if sum(len(r[0]) for r in refs) < max(6, min_inliers):
        return result
    bq = _local_contrast(b, win)
    T = T0
    for _ in range(max(1, iterations)):
        X_all, uv_all = [], []
        for (px, P, a), ref in zip(refs, references, strict=True):
            tracked = _track_into_query(px, P, a, ref.texture, b, bq, T, Km, dist_arr, win, tracker, max_fb_error_px)
            if tracked is not None:
                X_all.append(tracked[0])
                uv_all.append(tracked[1])
        if not X_all or sum(len(x) for x in X_all) < max(6, min_inliers):
            return result
        res = localize_dlt(np.concatenate(X_all), np.concatenate(uv_all), Km, dist_arr, DltSettings(ransac_threshold_px=ransac_threshold_px, min_inliers=min_inliers))
        if not res.success:
            return result
        result, T = res, res.T_camera_world
    log.debug("dense localisation: %d tracked points inliers, rms %.3f px", result.num_inliers, result.reprojection_rms_px)
    return result


def _track_into_query(
    px: Array, P: Array, contrast_ref: NDArray[np.uint8], texture_ref: NDArray, b: NDArray, bq: NDArray[np.uint8], T: Array, Km: Array,
    dist_arr: Array, win: int, tracker: str, max_fb_error_px: float,
) -> tuple[Array, Array] | None:
    """One reference's corner points (world, with their +-u, +-v neighbours) projected into the query at
    pose ``T`` and tracked there: the world points and query pixels that tracked (None: none inside)."""
    if len(P) == 0:
        return None
    H, W = b.shape
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    X = P[:, 0]
    pred = cv2.projectPoints(P.reshape(-1, 1, 3), rvec, T[:3, 3].reshape(3, 1), Km, dist_arr)[0].reshape(-1, 5, 2)
    depth = X @ T[2, :3] + T[2, 3]
    q = pred[:, 0]
    inside = (depth > 0) & (q[:, 0] >= win) & (q[:, 1] >= win) & (q[:, 0] < W - win) & (q[:, 1] < H - win)
    if not inside.any():
        return None
    if tracker == "affine":
        k = max(1, win // 2)
        A0 = np.stack([(pred[inside, 1] - pred[inside, 2]) / (2 * k), (pred[inside, 3] - pred[inside, 4]) / (2 * k)], axis=2)
        uv, ok, _ = track_affine_photometric(texture_ref, b, px[inside], q[inside], A0, window_px=win)
    else:
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
        p0 = px[inside].astype(np.float32).reshape(-1, 1, 2)
        p1 = q[inside].astype(np.float32).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(contrast_ref, bq, p0, p1.copy(), winSize=(win, win), maxLevel=1, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(bq, contrast_ref, p1, p0.copy(), winSize=(win, win), maxLevel=1, criteria=crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb < max_fb_error_px)
        uv = p1.reshape(-1, 2).astype(np.float64)
    return X[inside][ok], uv[ok]


# Long by its docstring; the 64 lines of code are one batched Gauss-Newton loop.
def track_affine_photometric(
    image_reference: NDArray,
    image_query: NDArray,
    uv_reference: NDArray,
    uv_query_initial: NDArray,
    A_initial: NDArray | None = None,
    window_px: int = 31,
    iterations: int = 15,
    min_ncc: float = 0.95,
) -> tuple[Array, NDArray[np.bool_], Array]:
    """Sub-pixel positions in the query image of exact reference pixels: affine + gain/bias KLT.

    Each reference window ``T(x)`` (integer pixel offsets ``x`` around ``uv_reference``, no
    interpolation) is matched to the query image as ``T(x) = g Q(c + A x) + h`` by Gauss-Newton
    on ``(c, A, g, h)`` (8 parameters per point, all points at once). The affine part absorbs
    the perspective change of the surface under the window (turntable steps of 28 deg skew a
    window by tens of percent), the gain/bias the change of the projector's lighting between
    views; plain translational KLT is biased by both.

    Parameters
    ----------
    image_reference, image_query : (H, W) uint8 or float
    uv_reference : (N, 2)
        Reference pixel centres (rounded to integers).
    uv_query_initial : (N, 2)
        Predicted query positions, good to about a pixel.
    A_initial : (N, 2, 2), optional
        Predicted local affine maps d(query px) / d(reference px) (identity when absent).
    window_px : int
        Odd window size.
    min_ncc : float
        Kept when the normalised cross-correlation of the final fit reaches this.

    Returns
    -------
    uv_query : (N, 2) float64
    ok : (N,) bool
        Converged (step < 0.01 px), well conditioned, inside the image, NCC >= ``min_ncc``.
    ncc : (N,) float64
    """
    R = np.asarray(image_reference, dtype=np.float32)
    Q = np.asarray(image_query, dtype=np.float32)
    p = np.rint(np.asarray(uv_reference, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    c = np.asarray(uv_query_initial, dtype=np.float64).reshape(-1, 2).copy()
    n = p.shape[0]
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0)
    A = np.tile(np.eye(2), (n, 1, 1)) if A_initial is None else np.asarray(A_initial, dtype=np.float64).reshape(n, 2, 2).copy()
    r = window_px // 2
    off = np.arange(-r, r + 1, dtype=np.float64)
    ox, oy = np.meshgrid(off, off)
    ox, oy = ox.ravel(), oy.ravel()  # (m,)
    H, W = R.shape
    inside_ref = (p[:, 0] >= r) & (p[:, 1] >= r) & (p[:, 0] < W - r) & (p[:, 1] < H - r)
    pc = np.clip(p, r, [W - r - 1, H - r - 1])
    T = R[pc[:, 1, None] + oy.astype(np.int64)[None], pc[:, 0, None] + ox.astype(np.int64)[None]]  # (n, m)
    gx = cv2.Sobel(Q, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    gy = cv2.Sobel(Q, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
    g = np.ones(n)
    h = np.zeros(n)
    step = np.full(n, np.inf)
    good = inside_ref.copy()
    for _ in range(iterations):
        xs, ys = _warped_window(c, A, ox, oy)
        Iq = sample_bilinear_clamped(Q, xs, ys)
        Ix = sample_bilinear_clamped(gx, xs, ys) * g[:, None].astype(np.float32)
        Iy = sample_bilinear_clamped(gy, xs, ys) * g[:, None].astype(np.float32)
        res = (g[:, None] * Iq + h[:, None] - T).astype(np.float32)
        J = np.stack([Ix, Iy, Ix * ox, Ix * oy, Iy * ox, Iy * oy, Iq, np.ones_like(Iq)], axis=2)  # (n, m, 8)
        Jt = J.transpose(0, 2, 1)
        JtJ = (Jt @ J).astype(np.float64)  # batched BLAS; float32 sums over <= a few thousand samples
        Jtr = (Jt @ res[..., None])[..., 0].astype(np.float64)
        JtJ += 1e-9 * np.eye(8)[None] * np.trace(JtJ, axis1=1, axis2=2)[:, None, None]
        try:
            d = -np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return c, np.zeros(n, bool), np.zeros(n)
        d[~good] = 0.0
        c += d[:, :2]
        A[:, 0, 0] += d[:, 2]
        A[:, 0, 1] += d[:, 3]
        A[:, 1, 0] += d[:, 4]
        A[:, 1, 1] += d[:, 5]
        g += d[:, 6]
        h += d[:, 7]
        step = np.hypot(d[:, 0], d[:, 1])
        good &= np.isfinite(step) & (np.abs(np.linalg.det(A)) > 0.2) & (np.abs(np.linalg.det(A)) < 5.0) & (g > 0.2) & (g < 5.0)
        if np.all(step[good] < 1e-3):
            break
    xs, ys = _warped_window(c, A, ox, oy)
    ncc = _ncc_rows(T, sample_bilinear_clamped(Q, xs, ys).astype(np.float64))
    inside_q = (xs.min(axis=1) >= 0) & (ys.min(axis=1) >= 0) & (xs.max(axis=1) < W - 1) & (ys.max(axis=1) < H - 1)
    ok = good & inside_q & (step < 0.01) & (ncc >= min_ncc)
    return c, ok, ncc


def _warped_window(c: Array, A: Array, ox: Array, oy: Array) -> tuple[Array, Array]:
    """Query positions ``c + A (ox, oy)`` of each point's window offsets, (N, m) each."""
    xs = c[:, 0, None] + A[:, 0, 0, None] * ox + A[:, 0, 1, None] * oy
    ys = c[:, 1, None] + A[:, 1, 0, None] * ox + A[:, 1, 1, None] * oy
    return xs, ys


def _ncc_rows(T: NDArray, Iq: Array) -> Array:
    """Normalised cross-correlation of each row of ``T`` with the same row of ``Iq``."""
    Tc = T - T.mean(axis=1, keepdims=True)
    Qc = Iq - Iq.mean(axis=1, keepdims=True)
    return np.sum(Tc * Qc, axis=1) / np.maximum(np.sqrt(np.sum(Tc**2, axis=1) * np.sum(Qc**2, axis=1)), 1e-12)
