"""The voxel grid under the fused map: packed integer voxel keys (:func:`voxel_keys`), per-key
sums (:func:`_reduce`), and the surface smoothing of a voxel map on its 3x3x3 neighbourhoods
(:func:`project_to_local_planes`, used by :class:`~fpp_graph.fusion.voxel_map.VoxelMapFuser`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError

# Voxel indices are packed into one int64 key, 21 bits per axis (signed): +-2^20 voxels, i.e.
# +-1048 m at 1 mm voxels, far beyond any indoor map.
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def voxel_keys(points_m: NDArray[np.float64], voxel_size_m: float) -> NDArray[np.int64]:
    """Pack the voxel index ``floor(p / voxel_size_m)`` of each point into one int64 key.

    Raises
    ------
    InputDataError
        If a point lies beyond the +-2^20 voxel range of the key.
    """
    idx = np.floor(np.asarray(points_m, dtype=np.float64) / voxel_size_m).astype(np.int64)
    if idx.size and (idx.min() < -_KEY_OFFSET or idx.max() >= _KEY_OFFSET):
        far = float(np.abs(points_m).max())
        raise InputDataError(
            f"map fusion: a point lies {far:.6g} m from the world origin, beyond the "
            f"{_KEY_OFFSET * voxel_size_m:.6g} m the voxel grid of {voxel_size_m} m covers; "
            "check the poses or use a larger fusion.voxel_size_m"
        )
    idx += _KEY_OFFSET
    return (idx[:, 0] << (2 * _KEY_BITS)) | (idx[:, 1] << _KEY_BITS) | idx[:, 2]


def _reduce(
    keys: NDArray[np.int64], planes: NDArray[np.float64], sorted_runs: bool = False
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Sum the values that share a key, per plane of ``planes`` (C, M: one contiguous row of M
    values per column); returns sorted unique keys and their sums (C, unique). ``sorted_runs``:
    ``keys`` are a few sorted runs end to end (a map's keys and frames' shares being merged)."""
    # np.unique(return_inverse=True) by hand. The sort's order within equal keys does not
    # matter (np.bincount adds each key's values in their input order, whichever sort found the
    # key), so the faster sort for the input serves: numpy's vectorised quicksort for a frame's
    # keys in pixel order (2.1 M keys of a 1920x1200 FPP frame: 49.5 against 93.8 ms for the stable
    # sort), the stable sort (a merge of runs) for sorted runs end to end (6.9 M: 131 against 184)
    order = np.argsort(keys, kind="stable" if sorted_runs else "quicksort")
    sorted_keys = keys[order]
    new_key = np.empty(len(keys), dtype=bool)
    new_key[:1] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=new_key[1:])
    unique = sorted_keys[new_key]
    inverse = np.empty(len(keys), dtype=np.intp)
    inverse[order] = np.cumsum(new_key) - 1
    # contiguous planes: np.bincount reading every 7th double of (M, 7) rows took 91 against 33 ms
    sums = np.empty((planes.shape[0], unique.size))
    for c in range(planes.shape[0]):
        sums[c] = np.bincount(inverse, weights=planes[c], minlength=unique.size)
    return unique, sums


def _neighbour_indices(keys: NDArray[np.int64], query: NDArray[np.int64]):
    """Yield ``(i, j)``: ``query[i]``'s occupied 3x3x3 voxel neighbour is ``keys[j]`` (sorted
    ``keys``), one offset at a time, ``dz`` fastest."""
    n = len(keys)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            # the packed key of a neighbour is the key plus the packed offset (the fields never
            # overflow for voxels inside the map's range). z is the key's lowest field, so the
            # column's three keys are consecutive integers: one search finds the first, and each
            # next one, if occupied, sits right after the previous hit (keys are unique; 9
            # searches instead of 27)
            below = query + ((dx << (2 * _KEY_BITS)) + (dy << _KEY_BITS) - 1)
            pos = np.searchsorted(keys, below)
            for dz in (-1, 0, 1):
                at = np.minimum(pos, n - 1)
                hit = keys[at] == below + (dz + 1)
                i = np.flatnonzero(hit)
                yield i, at[i]
                pos += hit


def project_to_local_planes(
    keys: NDArray[np.int64],
    points: NDArray[np.float64],
    weights: NDArray[np.float64],
    voxel_size_m: float,
    min_neighbours: int = 8,
    max_flatness: float = 0.05,
    chunk: int = 50_000,
    map_chunks: Callable[[Callable[[tuple], NDArray[np.float64]], Iterable[tuple]], Iterable[NDArray[np.float64]]] = map,
) -> NDArray[np.float64]:
    """Move each voxel point onto the local surface fitted to its 3x3x3 voxel neighbourhood.

    See :func:`_project_chunk`; the map is processed ``chunk`` voxels at a time so the work
    arrays stay bounded (about 27 neighbour pairs x ~20 float64 columns per voxel of a chunk,
    ~200 MB at 50 000) whatever the map's size. Each chunk carries only the keys its neighbours
    can have (a packed key's neighbours lie within :data:`_NEIGHBOUR_KEY_REACH` of it), so
    ``map_chunks`` (builtin ``map``, or an executor's windowed map) can run chunks in other
    processes; the result does not depend on it.
    """
    keys = np.asarray(keys)
    out = np.asarray(points, dtype=np.float64).copy()
    tasks = (_chunk_task(keys, points, weights, voxel_size_m, start, min(start + chunk, len(keys)), min_neighbours, max_flatness)
             for start in range(0, len(keys), chunk))
    for start, moved in zip(range(0, len(keys), chunk), map_chunks(project_chunk_task, tasks), strict=True):
        out[start : start + len(moved)] = moved
    return out


# the largest difference between a packed key and the key of one of its 3x3x3 neighbours
_NEIGHBOUR_KEY_REACH = (1 << (2 * _KEY_BITS)) + (1 << _KEY_BITS) + 1


def _chunk_task(keys, points, weights, voxel_size_m, start, stop, min_neighbours, max_flatness) -> tuple:
    """The arguments of :func:`project_chunk_task` for map rows ``start:stop``: the rows and every
    voxel whose key lies within the neighbours' reach of theirs (keys are sorted)."""
    lo = int(np.searchsorted(keys, keys[start] - _NEIGHBOUR_KEY_REACH, side="left"))
    hi = int(np.searchsorted(keys, keys[stop - 1] + _NEIGHBOUR_KEY_REACH, side="right"))
    return (keys[lo:hi], np.asarray(points[lo:hi], dtype=np.float64), np.asarray(weights[lo:hi], dtype=np.float64), voxel_size_m,
            np.arange(start - lo, stop - lo), min_neighbours, max_flatness)


def project_chunk_task(task: tuple) -> NDArray[np.float64]:
    """:func:`_project_chunk` of one :func:`_chunk_task` (module level: picklable for worker
    processes), its rows :data:`ROWS_PER_PASS` at a time: each row's sums are its own, added in
    the same order either way, and a pass's ~20 pair columns stay in the core's cache."""
    keys, points, weights, voxel_size_m, rows, min_neighbours, max_flatness = task
    if len(rows) <= ROWS_PER_PASS:
        return _project_chunk(*task)
    return np.concatenate([
        _project_chunk(keys, points, weights, voxel_size_m, rows[start : start + ROWS_PER_PASS], min_neighbours, max_flatness)
        for start in range(0, len(rows), ROWS_PER_PASS)
    ])


ROWS_PER_PASS = 8192
"""Voxels whose surfaces :func:`project_chunk_task` fits in one pass: ~27 neighbour pairs each, so a
float64 pair column is ~1.8 MB and a pass's working set stays near a 4 MB L2 cache (a chunk of
50 000 voxels at once: 0.77 s for 400 000 voxels of a room-sized FPP map on one core; 10 000 a
pass: 0.54 s, 5 000: 0.53, 2 500: 0.58). A chunk handed to another process stays large: it
carries every voxel its neighbours can be, 3.5x its rows at 50 000 but 13x at 10 000."""


def _sums(pair_rows: NDArray[np.int64], weights: NDArray[np.float64], columns: list[NDArray[np.float64] | None], n: int) -> NDArray[np.float64]:
    """``(n, len(columns))``: per row ``i``, the weighted sum of each column over its pairs (one
    ``np.bincount`` per column: linear in the pairs, where scattered in-place adds on (n, 3, 3)
    blocks cost ~10x more). A column of None is all ones: the weights' own sum (``w * 1.0`` is
    ``w``, so the same doubles without the product)."""
    return np.stack([np.bincount(pair_rows, weights if c is None else weights * c, minlength=n) for c in columns], axis=1)


# the quadratic height field's normal equations: basis 0..5 = 1, u, v, u^2, u v, v^2 and 6 = h;
# the products of basis pairs (a, b), a <= b, then of each basis with h
_PAIRS6 = [(a, b) for a in range(6) for b in range(a, 6)]
_HEIGHT_PAIRS = [(a, 6) for a in range(6)]
_UPPER3 = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def _project_chunk(
    keys: NDArray[np.int64],
    points: NDArray[np.float64],
    weights: NDArray[np.float64],
    voxel_size_m: float,
    rows: NDArray[np.int64],
    min_neighbours: int,
    max_flatness: float,
) -> NDArray[np.float64]:
    """Move each voxel point onto the local surface fitted to its 3x3x3 voxel neighbourhood.

    ``keys`` are the sorted voxel keys of :func:`voxel_keys` (one per point). A weighted plane
    (through the neighbourhood's centroid, normal along the smallest eigenvector of the weighted
    covariance) gives a local frame; in it a weighted quadratic height field
    ``h = a + b u + c v + d u^2 + e u v + f v^2`` is fitted around the point, so curved surfaces
    are not flattened, and the point moves along the normal to ``h(0, 0) = a``. Points whose
    neighbourhood has fewer than ``min_neighbours`` occupied voxels or is not a surface
    (smallest eigenvalue above ``max_flatness`` times the middle one: edges, thin parts, noise)
    keep their voxel mean. Returns the new points of ``rows``.
    """
    n = len(rows)
    out = points[rows].copy()
    if n == 0:
        return out
    pairs = list(_neighbour_indices(keys, keys[rows]))
    rows_of_pair = np.concatenate([i for i, _ in pairs])
    neighbour_of_pair = np.concatenate([j for _, j in pairs])
    own = points[rows]
    w = weights[neighbour_of_pair]
    # neighbours relative to the point (in voxels): the covariance is translation invariant, and
    # map coordinates of metres would cancel digits in E[p p^T] - E[p] E[p]^T
    d = (points[neighbour_of_pair] - own[rows_of_pair]) / voxel_size_m
    count = np.bincount(rows_of_pair, minlength=n)
    sums = _sums(rows_of_pair, w, [None, d[:, 0], d[:, 1], d[:, 2]] + [d[:, a] * d[:, b] for a, b in _UPPER3], n)
    ok = count >= min_neighbours
    if not np.any(ok):
        return out
    s_w = sums[ok, 0]
    mean = sums[ok, 1:4] / s_w[:, None]
    second = np.empty((len(s_w), 3, 3))
    for k, (a, b) in enumerate(_UPPER3):
        second[:, a, b] = second[:, b, a] = sums[ok, 4 + k] / s_w
    cov = second - mean[:, :, None] * mean[:, None, :]
    idx, eigvec = _surface_neighbourhoods(cov, max_flatness)
    idx = np.flatnonzero(ok)[idx]
    if len(idx) == 0:
        return out
    frame = np.zeros((n, 3, 3))  # rows: tangent u, tangent v, normal
    frame[idx, 0] = eigvec[:, :, 2]
    frame[idx, 1] = eigvec[:, :, 1]
    frame[idx, 2] = eigvec[:, :, 0]
    use = np.zeros(n, dtype=bool)
    use[idx] = True
    # weighted least squares of the quadratic height field around each point, in its frame
    keep = use[rows_of_pair]
    rows_of_pair, w, d = rows_of_pair[keep], w[keep], d[keep]
    local = np.einsum("nab,nb->na", frame[rows_of_pair], d)  # unitless, O(1)
    offset = _height_at_origin(rows_of_pair, w, local, n, idx, sums[idx, 0]) * voxel_size_m
    good = np.isfinite(offset)
    out[idx[good]] = own[idx[good]] + offset[good, None] * frame[idx[good], 2]
    return out


def _surface_neighbourhoods(cov: NDArray[np.float64], max_flatness: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Which of the (m, 3, 3) covariances are a surface's (smallest eigenvalue at most
    ``max_flatness`` times the middle one, by LAPACK's ``eigh``), and their eigenvectors.

    ``eigh`` runs only on those a closed-form screen cannot rule out: the trigonometric
    eigenvalues of a symmetric 3x3 (Smith 1961) are within ~1e-7 of the largest of LAPACK's,
    so a neighbourhood whose smallest is above twice the bound plus 1e-6 of the largest is not
    flat by LAPACK's either. The surfaces and eigenvectors are LAPACK's, as without the screen
    (on real RGB-D maps, where Kinect noise thickens most 1 cm neighbourhoods, the screen leaves
    ``eigh`` a fraction of them)."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = np.arccos(np.clip(det / (2.0 * p**3), -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    clearly_not_flat = (smallest > 2.0 * max_flatness * middle + 1e-6 * np.abs(largest)) & (p > 0) & (np.abs(largest) > 1e-20)
    screened = np.flatnonzero(~clearly_not_flat)
    eigval, eigvec = np.linalg.eigh(cov[screened])
    surface = eigval[:, 0] <= max_flatness * np.maximum(eigval[:, 1], 1e-30)
    return screened[surface], eigvec[surface]


def _height_at_origin(
    rows_of_pair: NDArray[np.int64], w: NDArray[np.float64], local: NDArray[np.float64], n: int, idx: NDArray[np.int64],
    weight_sums: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``a`` of the weighted quadratic height field ``h(u, v)`` of each row ``idx`` (NaN where
    its normal equations are singular); ``local``: each pair's (u, v, h), ``weight_sums``: the
    rows' sums of ``w`` (the normal equations' (0, 0) entry)."""
    u, v, h = local[:, 0], local[:, 1], local[:, 2]
    basis = [None, u, v, u * u, u * v, v * v, h]
    # each distinct product once: 1 * x is x, and u * u, u * v, v * v are basis 3, 4, 5 already
    # (the same doubles: the sums equal those of every pair's own product)
    distinct: dict[tuple[int, int], tuple[int, int]] = {(1, 1): (0, 3), (1, 2): (0, 4), (2, 2): (0, 5)}
    wanted = [pair for pair in _PAIRS6 + _HEIGHT_PAIRS if pair not in distinct and pair != (0, 0)]
    columns = [basis[b] if a == 0 else basis[a] * basis[b] for a, b in wanted]
    computed = dict(zip(wanted, _sums(rows_of_pair, w, columns, n)[idx].T, strict=True))
    computed[(0, 0)] = weight_sums
    for pair, same in distinct.items():
        computed[pair] = computed[same]
    ata = np.empty((len(idx), 6, 6))
    for a, b in _PAIRS6:
        ata[:, a, b] = ata[:, b, a] = computed[(a, b)]
    atb = np.stack([computed[pair] for pair in _HEIGHT_PAIRS], axis=1)
    # a tiny ridge keeps sparse neighbourhoods solvable (quadratic terms only)
    scale = np.einsum("nii->n", ata)[:, None] * 1e-9
    ata[:, 3:, 3:] += scale[:, :, None] * np.eye(3)
    try:
        return np.linalg.solve(ata, atb[:, :, None])[:, 0, 0]
    except np.linalg.LinAlgError:
        return np.full(len(idx), np.nan)


__all__ = ["project_chunk_task", "project_to_local_planes", "voxel_keys"]
