"""Directions of a pair's pose that the dense geometry does not constrain (a wall's in-plane
shifts and spin), how they are found (:func:`check_degeneracy`, :func:`plane_directions`), and
how they are taken from the keypoints instead (:func:`joint_keypoint_step`,
:func:`without_weak_directions`, :func:`weak_direction_pin`).

Directions are compared in centred, length-normalised coordinates: ``[rot, trans]`` about the
source cloud's centroid with rotations as arc length at its RMS radius, so rotational and
translational eigenvalues share one unit (m^-2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import invert, se3_exp, se3_log, transform_points
from frontend.dense_alignment import point_to_plane_jacobian
from frontend.registration.icp import organised_subsample, prepare_icp_cloud
from frontend.registration.keypoints import information_from_keypoints, keypoint_inliers

Array = NDArray[np.float64]


DEGENERACY_RATIO = 0.02
"""A direction whose information eigenvalue (rotations as arc length about the points' centroid)
is below this share of the trace of the translation block is unconstrained: its standard
deviation is over sqrt(1/0.02) ~ 7 times that of a direction holding the whole trace; a plane's
in-plane directions read 0.001-0.01 (only the normals' noise constrains them)."""

PLANE_DISAGREEMENT_PROBABILITY = 0.9999
"""Chi-square (3 dof) probability beyond which ICP's in-plane pose disagrees with the keypoints and
is replaced by theirs: a false alarm trades ICP's precise pose for the keypoints', so 1 in 10^4."""

JOINT_OPTIMUM_PROBABILITY = 0.999
"""Chi-square (6 dof) probability beyond which, on other weak pairs, ICP's pose moves to the joint
ICP + keypoint optimum."""

HOLD_RATIO = 1e6
"""A held direction's information over the trace of the rest's: its step is ~1e-6 of theirs, and
the normal equations stay ~10^10 from float64's precision limit."""


def joint_keypoint_step(
    T_target_source: NDArray, information_icp: NDArray, source_points: NDArray, target_points: NDArray, iterations: int = 3
) -> Array:
    """Step ``xi`` (``[rot, trans]``, right perturbation ``T Exp(xi)``) from ICP's optimum to the
    optimum of ICP's cost plus the keypoints' point-to-point cost.

    ICP's cost is modelled by its quadratic ``0.5 xi^T information_icp xi`` about its optimum;
    the keypoint cost is relinearised each Gauss-Newton iteration (its sigma as in
    :func:`information_from_keypoints`). Where ICP's cost is flat (a plane, an object on a table)
    the pose moves to where the keypoints put it; elsewhere ICP's information dominates and the
    step is negligible.
    """
    T0 = np.asarray(T_target_source, dtype=np.float64)
    L_icp = np.asarray(information_icp, dtype=np.float64)
    P = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    Q = np.asarray(target_points, dtype=np.float64).reshape(-1, 3)
    xi = np.zeros(6)
    if P.shape[0] < 3:
        return xi
    for _ in range(iterations):
        T = T0 @ se3_exp(xi)
        r = P @ T[:3, :3].T + T[:3, 3] - Q
        # mismatches the caller's threshold let through are re-trimmed at every linearisation
        keep = keypoint_inliers(np.linalg.norm(r, axis=1))
        if int(keep.sum()) < 3:
            break
        Pk, r = P[keep], r[keep]
        L_kp = information_from_keypoints(T, Pk, np.linalg.norm(r, axis=1))
        sigma2 = max(float(np.sum(r**2)) / (3 * Pk.shape[0]), 2e-5**2)
        u = r @ T[:3, :3]  # rows R^T r; J^T r = [-[p]x, I]^T R^T r = [p x u, u]
        g = np.concatenate([np.cross(Pk, u).sum(axis=0), u.sum(axis=0)]) / sigma2
        try:
            delta = -np.linalg.solve(L_icp + L_kp, L_icp @ xi + g)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(delta)):
            break
        xi = xi + delta
        if np.linalg.norm(delta) < 1e-9:
            break
    return xi


def centred_coordinates(source_points: NDArray) -> Array:
    """``M`` with ``xi = M xi_c``: ``xi`` in ``[rot, trans]`` about the origin, ``xi_c`` about the
    centroid of ``source_points`` with rotations as arc length at their RMS radius (the
    coordinates :func:`check_degeneracy` compares directions in)."""
    P = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    c = P.mean(axis=0) if P.size else np.zeros(3)
    radius = max(float(np.sqrt(np.mean(np.sum((P - c) ** 2, axis=1)))) if P.size else 1.0, 1e-6)
    # about the centroid: v = v_c - omega x c
    A = np.eye(6)
    A[3:, :3] = np.array([[0.0, c[2], -c[1]], [-c[2], 0.0, c[0]], [c[1], -c[0], 0.0]])  # -[c]x
    return A @ np.diag([1.0 / radius] * 3 + [1.0] * 3)  # omega = arc / radius


def _weak_basis(deg: Degeneracy) -> Array | None:
    """Orthonormal basis (6, k) of ``deg.directions`` (centred coordinates), None when there are none."""
    V = np.asarray(deg.directions, dtype=np.float64).reshape(-1, 6)
    if V.shape[0] == 0:
        return None
    return np.linalg.qr(V.T)[0]


def without_weak_directions(information: NDArray, deg: Degeneracy, source_points: NDArray) -> Array:
    """``information`` with its curvature along ``deg.directions`` removed (set to zero).

    On a plane the point-to-plane information still claims in-plane precision from the scatter
    of the estimated normals (~0.05 mm on a 1920x1200 wall pair), which is not information about
    the pose: left in, it biases the joint pose with the keypoints and makes the covariance
    overconfident along exactly the directions the keypoints must fix. The directions are those
    of :func:`check_degeneracy` (centred, length-normalised coordinates); the projection is done
    there and mapped back.
    """
    info = np.asarray(information, dtype=np.float64)
    Q = _weak_basis(deg)
    if Q is None:
        return info.copy()
    M = centred_coordinates(source_points)
    info_c = M.T @ info @ M
    proj = np.eye(6) - Q @ Q.T
    info_c = proj @ info_c @ proj
    M_inv = np.linalg.inv(M)
    out = M_inv.T @ info_c @ M_inv
    return 0.5 * (out + out.T)


def weak_direction_pin(deg: Degeneracy, source_points: NDArray, strength: float, complement: bool = False) -> Array:
    """An information matrix of ``strength`` along ``deg.directions`` only (centred,
    length-normalised coordinates of :func:`check_degeneracy`, mapped back to ``[rot, trans]``
    about the origin): a prior that holds those directions and leaves the others free.
    ``complement``: along every other direction instead (holds what the geometry fixes)."""
    Q = _weak_basis(deg)
    if Q is None:
        return float(strength) * np.eye(6) if complement else np.zeros((6, 6))
    M_inv = np.linalg.inv(centred_coordinates(source_points))
    P = Q @ Q.T
    out = M_inv.T @ (float(strength) * (np.eye(6) - P if complement else P)) @ M_inv
    return 0.5 * (out + out.T)


def max_motion_m(T_a: NDArray, T_b: NDArray, points: NDArray) -> float:
    """Largest distance between ``points`` moved by ``T_a`` and by ``T_b`` (0 without points)."""
    if not points.size:
        return 0.0
    return float(np.max(np.linalg.norm(transform_points(T_a, points) - transform_points(T_b, points), axis=1)))




def plane_directions(information: NDArray, source_points: NDArray) -> Degeneracy:
    """The three in-plane degrees of freedom of a plane-dominated pair, as a :class:`Degeneracy`.

    The plane's normal ``n`` is the best-constrained translation of ``information`` (its
    translation block's top eigenvector); the in-plane directions are the shifts along the two
    axes ``u, v`` orthogonal to it and the spin about ``n`` through the centroid of
    ``source_points``, in the centred, length-normalised coordinates of :func:`check_degeneracy`.
    Built from the plane's geometry rather than from the information's small eigenvectors, which
    on a tilted wall mix the spin with a tilt (normal-estimation noise sets them).
    """
    info = np.asarray(information, dtype=np.float64)
    w, V = np.linalg.eigh(0.5 * (info[3:, 3:] + info[3:, 3:].T))
    n = V[:, -1]
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    directions = np.zeros((3, 6))
    directions[0, 3:], directions[1, 3:], directions[2, :3] = u, v, n
    names = [f"translation along ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})" for a in (u, v)] + [f"rotation about ({n[0]:.2f}, {n[1]:.2f}, {n[2]:.2f})"]
    M = centred_coordinates(source_points)
    info_c = M.T @ info @ M
    norm = max(float(np.trace(info_c[3:, 3:])), 1e-300)
    # the information along each in-plane direction, on check_degeneracy's scale
    ratios = np.einsum("ki,ij,kj->k", directions, 0.5 * (info_c + info_c.T), directions) / norm
    return Degeneracy(True, ratios, names, directions)


def weak_directions_from(T_icp: NDArray, T_other: NDArray, deg: Degeneracy, source_points: NDArray) -> Array:
    """``T_icp`` moved to ``T_other`` along ``deg.directions`` only (centred, length-normalised
    coordinates of :func:`check_degeneracy`), kept along the others."""
    Q = _weak_basis(deg)
    if Q is None:
        return np.asarray(T_icp, dtype=np.float64).copy()
    M = centred_coordinates(source_points)
    xi = se3_log(invert(T_icp) @ np.asarray(T_other, dtype=np.float64))
    xi_c = np.linalg.solve(M, xi)  # xi = M xi_c
    return np.asarray(T_icp, dtype=np.float64) @ se3_exp(M @ (Q @ (Q.T @ xi_c)))


def disagreement_along(T_a: NDArray, T_b: NDArray, information_b: NDArray, deg: Degeneracy, source_points: NDArray) -> float:
    """Squared Mahalanobis distance of ``T_a`` from ``T_b`` along ``deg.directions`` only, under
    the covariance of ``T_b`` conditional on the other directions (centred, length-normalised
    coordinates of :func:`check_degeneracy`). Conditional, because the other directions are
    the ones ``T_a`` pins (a wall's tilts): keypoints in a narrow strip know the tilts poorly,
    and their marginal in-plane covariance would carry that through the lever arm."""
    V = np.asarray(deg.directions, dtype=np.float64).reshape(-1, 6)
    M = centred_coordinates(source_points)
    d_c = np.linalg.solve(M, se3_log(invert(np.asarray(T_b, dtype=np.float64)) @ np.asarray(T_a, dtype=np.float64)))
    info_c = M.T @ np.asarray(information_b, dtype=np.float64) @ M
    try:
        d_w = V @ d_c
        return float(d_w @ (V @ (0.5 * (info_c + info_c.T)) @ V.T) @ d_w)
    except np.linalg.LinAlgError:
        return 0.0


def weak_direction_sigma_m(information: NDArray, deg: Degeneracy, source_points: NDArray) -> float:
    """Largest standard deviation (m, rotations as arc length at the cloud's RMS radius) along the weak directions."""
    try:
        cov = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return float("inf")
    # covariance in the centred, length-normalised coordinates of check_degeneracy
    M = np.linalg.inv(centred_coordinates(source_points))
    cov_c = M @ cov @ M.T
    variances = [float(v @ cov_c @ v) for v in deg.directions]
    worst = max(variances) if variances and all(np.isfinite(variances)) else float("nan")
    # a non-positive variance is an inverse of a numerically singular matrix: unconstrained
    return float(np.sqrt(worst)) if np.isfinite(worst) and worst > 0 else float("inf")


@dataclass(frozen=True)
class Degeneracy:
    """Outcome of :func:`check_degeneracy`.

    Attributes
    ----------
    degenerate : bool
    eigenvalue_ratios : (6,) float64
        Eigenvalues of the length-normalised information over the trace of its translation
        block, ascending (a plane: three values near 0).
    unconstrained : list of str
        Human-readable weak directions, e.g. ``"translation along (0.00, 1.00, 0.00)"``.
    directions : (k, 6) float64
        The weak eigenvectors in ``[rot, trans]`` about the source cloud's centroid.
    """

    degenerate: bool
    eigenvalue_ratios: Array
    unconstrained: list[str]
    directions: Array

    @property
    def plane_like(self) -> bool:
        """At least the three directions one plane leaves free (two in-plane shifts and the spin)."""
        return len(self.unconstrained) >= 3


def check_degeneracy(information: NDArray, source_points: NDArray, ratio: float = 1e-4) -> Degeneracy:
    """Find directions the geometry does not constrain (one plane: 2 in-plane shifts + 1 spin).

    The information is re-expressed about the centroid of ``source_points`` with rotations in
    arc length at their RMS radius, so rotational and translational eigenvalues compare in the
    same unit (m^-2), and divided by the trace of its translation block; a direction whose
    normalised eigenvalue is below ``ratio`` is unconstrained.

    Parameters
    ----------
    information : (6, 6)
        ``[rot, trans]`` information of ``T_target_source`` (source-frame perturbation).
    source_points : (N, 3)
        Points that built it (source frame).
    ratio : float

    Returns
    -------
    Degeneracy
    """
    info = np.asarray(information, dtype=np.float64)
    M = centred_coordinates(source_points)
    info_c = M.T @ info @ M
    info_c = 0.5 * (info_c + info_c.T)
    w, V = np.linalg.eigh(info_c)
    # normalise by the trace of the translation block: the translational eigenvalues then sum
    # to 1 for any surface (mean of (m . d)^2 over three orthonormal d is 1/3 per direction),
    # so a direction's value is the mean squared normal component along it. A plane gives
    # {~0, ~0, 1} with the ~0 set by normal-estimation noise (a few degrees of normal scatter,
    # ~1e-3..1e-2); real relief gives more. Dividing by the largest eigenvalue instead made the
    # test depend on how strongly the *other* directions were constrained.
    norm = max(float(np.trace(info_c[3:, 3:])), 1e-300)
    ratios = w / norm
    weak = np.flatnonzero(ratios < ratio)
    names = []
    for k in weak:
        vec = V[:, k]
        rot, trans = vec[:3], vec[3:]
        if np.linalg.norm(rot) >= np.linalg.norm(trans):
            a = rot / np.linalg.norm(rot)
            names.append(f"rotation about ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})")
        else:
            a = trans / np.linalg.norm(trans)
            names.append(f"translation along ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})")
    return Degeneracy(bool(weak.size), ratios, names, V[:, weak].T.copy())


def surface_is_plane_like(xyz_map: NDArray, voxel_m: float, ratio: float) -> bool:
    """Whether a frame's whole surface leaves the three directions of a plane free
    (:attr:`Degeneracy.plane_like`), by the point-to-plane information of its own ICP cloud.

    Every pair the frame takes part in overlaps a part of that surface, so such a frame (a wall)
    gives weak pairs only; one with relief may still give weak pairs where the overlap is flat.
    ``voxel_m`` and ``ratio`` as the registrar's ICP voxel and :data:`DEGENERACY_RATIO`; 20-40 ms a
    1920x1200 frame.
    """
    role = prepare_icp_cloud(organised_subsample(xyz_map, voxel_m), voxel_m).source
    if len(role.points) < 7:
        return False
    J = point_to_plane_jacobian(np.eye(4), role.points, role.normals)
    return check_degeneracy(J.T @ J, role.points, ratio).plane_like
