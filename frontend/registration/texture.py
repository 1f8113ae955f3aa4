"""The texture side of a pair: whether two frames' textures agree over their overlap (the
look-alike test of appearance-only loop candidates) and the camera model that predicts one
frame's texture from another (:class:`TextureCamera`, for the photometric step)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import finite_points, transform_points
from fpp_graph.types import Frame
from frontend.organised_surface import fit_pinhole

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TextureAgreement:
    """How well two frames' texture images agree over their overlap under a pose.

    Attributes
    ----------
    fraction : float
        Share of the informative overlap blocks whose normalised cross-correlation reaches the
        threshold (NaN when no block is informative).
    blocks : int
        Informative blocks: at least half their samples overlap and both textures vary there.
    overlap : float
        Seen blocks over the source blocks with 3D points: how much of the source view the
        agreement speaks for.
    """

    fraction: float
    blocks: int
    overlap: float = float("nan")


MIN_BLOCK_NCC = 0.8
"""Two views' textures of one block agree at this normalised cross-correlation: per block, the
projector's shading (a smooth gain that changes with the pose) cancels, camera noise does not."""
MIN_BLOCK_STD_GREY = 2.0
"""A block whose texture varies less than about the camera's noise (grey levels) is uniform: it
tells nothing about agreement and is left out."""
MAX_PROJECTION_RMS_PX = 3.0
"""A target map whose fitted pinhole reprojects its own points worse than this cannot place the
source's samples on its pixels: no verdict."""


# One body: projection and the per-block statistics share the sample layout (h, w, b) end to end.
def _score_blocks(in_view: NDArray, geo: NDArray, tex_s: NDArray, tex_t: NDArray, valid_s: NDArray, h: int, w: int, b: int) -> TextureAgreement:
    """Per ``b x b`` block of the (h, w) sample grid: seen, same shape, textured, NCC; the agreement over the informative blocks."""

    def blocks(a: NDArray) -> NDArray:
        return a.reshape(h // b, b, w // b, b).swapaxes(1, 2).reshape(h // b, w // b, b * b)

    n_view = blocks(in_view).sum(axis=2)
    m = blocks(geo)
    n = m.sum(axis=2)
    xs, xt = blocks(tex_s) * m, blocks(tex_t) * m
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_s, mean_t = xs.sum(axis=2) / n, xt.sum(axis=2) / n
        var_s = (xs * xs).sum(axis=2) / n - mean_s**2
        var_t = (xt * xt).sum(axis=2) / n - mean_t**2
        cov = (xs * xt).sum(axis=2) / n - mean_s * mean_t
        ncc = cov / np.sqrt(np.maximum(var_s, 0) * np.maximum(var_t, 0))
    seen = n_view >= 0.5 * b * b
    shape_ok = n >= 0.8 * n_view
    textured = (var_s > MIN_BLOCK_STD_GREY**2) & (var_t > MIN_BLOCK_STD_GREY**2)
    informative = seen & (~shape_ok | textured)
    agree = seen & shape_ok & textured & (ncc >= MIN_BLOCK_NCC)
    count = int(informative.sum())
    source_blocks = int((blocks(valid_s.astype(np.float32)).sum(axis=2) >= 0.5 * b * b).sum())
    overlap = float(seen.sum()) / max(source_blocks, 1)
    if count == 0:
        return TextureAgreement(float("nan"), 0, overlap)
    return TextureAgreement(float(agree.sum()) / count, count, overlap)


def texture_agreement(
    target: Frame,
    source: Frame,
    T_target_source: NDArray,
    block_px: int | None = None,
    sample_px: int | None = None,
    max_distance_m: float = 0.003,
) -> TextureAgreement:
    """Blockwise agreement of the two frames' surfaces and textures over the overlap under ``T_target_source``.

    Every ``sample_px``-th source pixel with a 3D point is moved into the target and projected
    with the target's own pinhole (:func:`fit_pinhole`). The source image is cut into
    ``block_px`` squares. A block is *seen* when half its samples land on target pixels with a
    3D point; it agrees when the target's surface lies within ``max_distance_m`` of 80 % of
    them and the two textures there correlate (normalised cross-correlation, per block, so the
    projector's shading, which changes with the pose, cancels) to :data:`MIN_BLOCK_NCC`. Seen blocks
    whose surfaces differ count against; blocks of uniform texture are left out.

    Why: keypoint inliers of a look-alike place (a repeated print or object) all sit on the repeated
    object, while around it the walls differ in texture, or in shape (a handrail in one view
    where the other sees the flat wall): over the whole overlap only a true revisit agrees.
    """
    if source.xyz_map is None or target.xyz_map is None or source.texture is None or target.texture is None:
        return TextureAgreement(float("nan"), 0)
    cam = fit_pinhole(target.xyz_map)
    if cam is None or not cam[1] <= MAX_PROJECTION_RMS_PX:
        return TextureAgreement(float("nan"), 0)
    fx, fy, cx, cy = cam[0]
    T = np.asarray(T_target_source, dtype=np.float64)
    # defaults scale with the image: 96 px blocks sampled every 8 px at 1920 wide. Large blocks
    # matter: a smooth texture looks like a linear ramp in a small block, and two unrelated
    # ramps correlate by chance (48 px blocks at NCC 0.5 let look-alikes reach 0.94)
    width = int(source.texture.shape[1])
    block_px = int(block_px) if block_px else max(8, round(width / 20))
    sample_px = int(sample_px) if sample_px else max(1, block_px // 12)
    b = max(2, block_px // sample_px)
    xyz_s = np.asarray(source.xyz_map[::sample_px, ::sample_px], dtype=np.float64)
    tex_s = np.asarray(source.texture[::sample_px, ::sample_px], dtype=np.float32)
    h, w = (xyz_s.shape[0] // b) * b, (xyz_s.shape[1] // b) * b
    if h == 0 or w == 0:
        return TextureAgreement(float("nan"), 0)
    xyz_s, tex_s = xyz_s[:h, :w].reshape(-1, 3), tex_s[:h, :w].reshape(-1)
    valid_s = finite_points(xyz_s)
    H_t, W_t = target.xyz_map.shape[:2]
    idx = np.flatnonzero(valid_s)
    moved = transform_points(T, xyz_s[idx])
    front = moved[:, 2] > 1e-6
    idx, moved = idx[front], moved[front]
    u = np.rint(fx * moved[:, 0] / moved[:, 2] + cx).astype(np.int64)
    v = np.rint(fy * moved[:, 1] / moved[:, 2] + cy).astype(np.int64)
    inside = (u >= 0) & (u < W_t) & (v >= 0) & (v < H_t)
    idx, moved, u, v = idx[inside], moved[inside], u[inside], v[inside]
    z_t = np.asarray(target.xyz_map[v, u, 2], dtype=np.float64)
    seen_t = np.isfinite(z_t)
    idx, moved, u, v, z_t = idx[seen_t], moved[seen_t], u[seen_t], v[seen_t], z_t[seen_t]
    same = np.abs(moved[:, 2] - z_t) < max_distance_m
    n_px = h * w
    in_view = np.zeros(n_px, np.float32)
    in_view[idx] = 1.0
    geo = np.zeros(n_px, np.float32)
    geo[idx[same]] = 1.0
    tex_t = np.zeros(n_px, np.float32)
    tex_t[idx[same]] = np.asarray(target.texture[v[same], u[same]], dtype=np.float32)

    return _score_blocks(in_view, geo, tex_s, tex_t, valid_s, h, w, b)


@dataclass(frozen=True)
class TextureCamera:
    """What predicting one FPP frame's texture from another needs: the camera's ``K`` and
    OpenCV ``dist``, and the projector's centre in the camera (sensor) frame, whose light shades
    the texture and moves with the camera. From a rig: :meth:`from_rig`."""

    K: Array
    dist: Array
    projector_centre_m: Array | None = None

    @classmethod
    def from_rig(cls, rig: Any) -> TextureCamera:
        """From a :class:`frontend.fpp.rig.RigCalibration` (camera intrinsics, ``T_projector_camera``)."""
        T = np.asarray(rig.T_projector_camera, dtype=np.float64)
        return cls(np.asarray(rig.camera.K, dtype=np.float64), np.asarray(rig.camera.dist, dtype=np.float64).reshape(-1), -T[:3, :3].T @ T[:3, 3])

