"""SE(3) helpers on 4x4 numpy matrices.

Convention: ``T_a_b`` maps points expressed in frame ``b`` into frame ``a``:
``p_a = T_a_b[:3, :3] @ p_b + T_a_b[:3, 3]``. Tangent vectors are ordered
``[rotation (rad), translation (m)]`` as in GTSAM, so 6x6 information and covariance matrices
share that order. Quaternions are ``quat_xyzw`` (scipy and TUM order) unless a name says
otherwise.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fpp_graph.errors import InputDataError

Array = NDArray[np.float64]


def make_pose(rotation: ArrayLike | None = None, translation: ArrayLike | None = None) -> Array:
    """Build a 4x4 pose from a 3x3 rotation matrix and a 3-vector translation (metres)."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = np.asarray(rotation, dtype=np.float64)
    if translation is not None:
        T[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return T


def invert(T_a_b: ArrayLike) -> Array:
    """Return ``T_b_a`` for a rigid ``T_a_b``, (4, 4) or a stack (..., 4, 4) (exact, using R^T);
    planar (3, 3) poses likewise."""
    T = np.asarray(T_a_b, dtype=np.float64)
    d = T.shape[-1] - 1
    Rt = np.swapaxes(T[..., :d, :d], -1, -2)
    out = np.zeros(T.shape)
    out[..., :d, :d] = Rt
    out[..., :d, d] = -(Rt @ T[..., :d, d, None])[..., 0]
    out[..., d, d] = 1.0
    return out


def compose(*transforms: ArrayLike) -> Array:
    """Compose poses left to right: ``compose(T_a_b, T_b_c) == T_a_c``."""
    out = np.eye(4)
    for T in transforms:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> Array:
    """Map N x 3 points from frame b into frame a."""
    T = np.asarray(T_a_b, dtype=np.float64)
    P = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    # R^T as a contiguous 3x3: numpy's matmul takes its BLAS path only then (the strided view of
    # a 4x4 costs 8x more on a million points); the result is bit-identical
    return P @ np.ascontiguousarray(T[:3, :3].T) + T[:3, 3]


def rotations_from_quats_xyzw(quats_xyzw: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in ``x y z w`` order, normalised first.

    The products are scipy's (``Rotation.from_quat(q).as_matrix()``), written out here because
    importing ``scipy.spatial`` costs a short ``fpp-slam optimize`` about 0.07 s.
    """
    q = np.asarray(quats_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = x2 - y2 - z2 + w2
    R[..., 1, 0] = 2 * (xy + zw)
    R[..., 2, 0] = 2 * (xz - yw)
    R[..., 0, 1] = 2 * (xy - zw)
    R[..., 1, 1] = -x2 + y2 - z2 + w2
    R[..., 2, 1] = 2 * (yz + xw)
    R[..., 0, 2] = 2 * (xz + yw)
    R[..., 1, 2] = 2 * (yz - xw)
    R[..., 2, 2] = -x2 - y2 + z2 + w2
    return R


def quat_xyzw_from_pose(T: ArrayLike) -> Array:
    """Unit quaternion ``x y z w`` of a pose's rotation, with ``w >= 0``."""
    from scipy.spatial.transform import Rotation  # imported on use: see rotations_from_quats_xyzw

    q = Rotation.from_matrix(np.asarray(T, dtype=np.float64)[:3, :3]).as_quat()
    return -q if q[3] < 0 else q


def _skew(w: Array) -> Array:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _left_jacobian_so3(omega: Array) -> Array:
    theta = float(np.linalg.norm(omega))
    K = _skew(omega)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (
        np.eye(3)
        + (1.0 - np.cos(theta)) / theta**2 * K
        + (theta - np.sin(theta)) / theta**3 * (K @ K)
    )


def se3_exp(xi_rot_trans: ArrayLike) -> Array:
    """Exponential map of a twist ``[omega (rad), v (m)]`` to a 4x4 pose (GTSAM's Pose3.Expmap)."""
    from scipy.spatial.transform import Rotation  # imported on use: see rotations_from_quats_xyzw

    xi = np.asarray(xi_rot_trans, dtype=np.float64).reshape(6)
    omega, v = xi[:3], xi[3:]
    return make_pose(Rotation.from_rotvec(omega).as_matrix(), _left_jacobian_so3(omega) @ v)


def se3_log(T: ArrayLike) -> Array:
    """Logarithm of a 4x4 pose as a twist ``[omega (rad), v (m)]`` (GTSAM's Pose3.Logmap)."""
    from scipy.spatial.transform import Rotation  # imported on use: see rotations_from_quats_xyzw

    T = np.asarray(T, dtype=np.float64)
    omega = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    v = np.linalg.solve(_left_jacobian_so3(omega), T[:3, 3])
    return np.concatenate([omega, v])


def finite_points(points: NDArray) -> NDArray[np.bool_]:
    """Which points of an (..., 3) array have all three coordinates finite (an (N, 3) cloud or an
    (H, W, 3) map). A NaN or inf in any coordinate makes their sum non-finite: one pass over the
    array, 5x faster than ``all(isfinite(points), axis=-1)``'s reduction over the short last axis."""
    with np.errstate(invalid="ignore"):  # inf + -inf is NaN by design here, not an accident
        return np.isfinite(points[..., 0] + points[..., 1] + points[..., 2])


def masked_pixels(xyz_map: NDArray, mask: NDArray[np.bool_]) -> NDArray:
    """``xyz_map[mask]`` of an (H, W, C) map and an (H, W) mask, row-major, via ``np.compress``:
    the same values in the same order, 3-4x faster than boolean indexing for a map's (N, 3) float64
    points (``python -m scripts.bench_frame_points R``: 7-Scenes chess 1.1 against 4.4 ms, the FPP
    doll 3.9 against 13.8 ms; for one-byte (H, W) images boolean indexing is the faster, so this
    takes maps only)."""
    if xyz_map.ndim != 3 or xyz_map.shape[:2] != np.shape(mask):
        raise ValueError(f"masked_pixels: an (H, W, C) map and an (H, W) mask, got {xyz_map.shape} and {np.shape(mask)}")
    return np.compress(np.asarray(mask).ravel(), xyz_map.reshape(-1, xyz_map.shape[2]), axis=0)


def finite_box(xyz: NDArray[np.float64], finite: NDArray[np.bool_] | None = None) -> tuple[slice, slice]:
    """Rows and columns of the box around the pixels whose three coordinates are finite, widened
    by one pixel within the image (empty slices when there is none). ``finite``: the map's
    :func:`finite_points` when the caller has it already."""
    if finite is None:
        finite = finite_points(xyz)
    row_any, col_any = finite.any(axis=1), finite.any(axis=0)
    if not row_any.any():
        return slice(0, 0), slice(0, 0)
    r = np.flatnonzero(row_any)
    c = np.flatnonzero(col_any)
    h, w = finite.shape
    return slice(max(r[0] - 1, 0), min(r[-1] + 2, h)), slice(max(c[0] - 1, 0), min(c[-1] + 2, w))


def in_row_bands(local: Callable[[NDArray], NDArray], image: NDArray, out: NDArray, band_rows: int) -> NDArray:
    """``out[:] = local(image)`` computed band by band of ``band_rows`` rows, for a ``local`` whose
    value at a pixel depends only on its 3x3 neighbourhood and, on an image's first and last
    rows, on the rows inside (one-sided differences, replicated borders): each band is handed
    with one neighbouring row above and below, and only its own rows are kept, so the result is
    ``local(image)``'s, element for element. Why: a 1920-wide image's per-pixel arithmetic over
    whole frames makes each float plane a few MB that go out to memory between passes; a band's
    planes stay in the core's cache (the FPP edge filter and the fusion's grazing weights took
    0.55-0.6x the time on 1920x1200 maps). Returns ``out``."""
    height = image.shape[0]
    for band in row_bands(height, band_rows):
        r0, r1 = band.start, band.stop
        a, b = max(r0 - 1, 0), min(r1 + 1, height)
        out[r0:r1] = local(image[a:b])[r0 - a : r1 - a]
    return out


def row_bands(height: int, band_rows: int) -> list[slice]:
    """Slices of ``band_rows`` consecutive rows (at least 1; the last one shorter) covering ``height`` rows."""
    step = max(1, int(band_rows))
    return [slice(r, min(r + step, height)) for r in range(0, height, step)]


def rotation_angle_rad(R: ArrayLike) -> float:
    """Angle of a rotation matrix in radians, numerically safe near 0 and pi."""
    from scipy.spatial.transform import Rotation  # imported on use: see rotations_from_quats_xyzw

    return float(np.linalg.norm(Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()))


def pose_error(T_estimate: ArrayLike, T_reference: ArrayLike) -> tuple[float, float]:
    """Rotation error (rad) and translation error (m) of ``T_estimate`` against ``T_reference``."""
    E = invert(T_reference) @ np.asarray(T_estimate, dtype=np.float64)
    return rotation_angle_rad(E[:3, :3]), float(np.linalg.norm(np.asarray(T_estimate)[:3, 3] - np.asarray(T_reference)[:3, 3]))


def is_rigid(T: ArrayLike, atol: float = 1e-6) -> bool:
    """True when ``T`` is a finite 4x4 rigid transform (orthonormal, det +1, last row 0 0 0 1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(R.T @ R, np.eye(3), atol=atol)
        and abs(np.linalg.det(R) - 1.0) < atol
        and np.allclose(T[3], [0, 0, 0, 1], atol=atol)
    )


def adjoint(T: ArrayLike) -> Array:
    """6x6 adjoint of a pose, or (..., 6, 6) of a stack (..., 4, 4), in ``[rot, trans]`` tangent
    order (GTSAM's Pose3.AdjointMap)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[..., :3, :3], T[..., :3, 3]
    skew = np.zeros(T.shape[:-2] + (3, 3))
    skew[..., 0, 1], skew[..., 0, 2] = -t[..., 2], t[..., 1]
    skew[..., 1, 0], skew[..., 1, 2] = t[..., 2], -t[..., 0]
    skew[..., 2, 0], skew[..., 2, 1] = -t[..., 1], t[..., 0]
    Ad = np.zeros(T.shape[:-2] + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., 3:, 3:] = R
    Ad[..., 3:, :3] = skew @ R
    return Ad


def kabsch(P_target: NDArray, P_source: NDArray, weights: NDArray | None = None) -> Array:
    """Closed-form ``T_target_source`` minimising ``sum w ||P_target - R P_source - t||^2`` (eq. 10).

    Parameters
    ----------
    P_target, P_source : (N, 3) float64
        Corresponding points (N >= 3, not collinear), metres.
    weights : (N,) float64, optional
        Non-negative weights.

    Returns
    -------
    (4, 4) float64
        Rigid transform (det +1; reflections are corrected as in Umeyama 1991). No scale.

    Raises
    ------
    InputDataError
        Fewer than 3 points or mismatched shapes.
    """
    Pt = np.asarray(P_target, dtype=np.float64).reshape(-1, 3)
    Ps = np.asarray(P_source, dtype=np.float64).reshape(-1, 3)
    if Pt.shape != Ps.shape or Pt.shape[0] < 3:
        raise InputDataError(f"kabsch needs two N x 3 arrays of the same shape with N >= 3, got {Pt.shape} and {Ps.shape}")
    w = np.ones(Pt.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    w = w / max(w.sum(), 1e-300)
    ct = w @ Pt
    cs = w @ Ps
    Hm = (Ps - cs).T @ ((Pt - ct) * w[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    d = 1.0 if np.linalg.det(Vt.T @ U.T) >= 0 else -1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = ct - R @ cs
    return T
