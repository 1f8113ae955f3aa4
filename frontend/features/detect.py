"""2D keypoints on FPP texture images and their matching.

Detectors (``registration.features.type`` in the config): ``surf`` (the project's own implementation,
:mod:`frontend.features.surf`, as the paper uses), and OpenCV's ``sift``, ``orb`` and ``akaze``. Images
wider than :data:`MAX_WIDTH_PX` are reduced by an integer factor before
detection (area averaging); keypoints are returned in full-image pixels, so the 2D-to-3D lift
reads the full-resolution ``xyz_map``.

Matching: nearest neighbour in descriptor space (L2 for float descriptors, Hamming for binary
ones), Lowe's ratio test against the second neighbour, and optionally the mutual check (the
match must also be the nearest neighbour in the other direction).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.types import Frame
from frontend.config import RegistrationConfig
from frontend.features.surf import SurfParams, surf_detect_and_compute

log = logging.getLogger(__name__)

Detector = Callable[[NDArray[np.uint8]], tuple[NDArray[np.float64], NDArray]]
"""A detector maps an (H, W) uint8 image to ``(keypoints_uv (K, 2) float64, descriptors (K, D))``."""


def _working_image(image: NDArray[np.uint8], max_width: int) -> tuple[NDArray[np.uint8], int]:
    factor = 1
    if max_width > 0 and image.shape[1] > max_width:
        factor = int(math.ceil(image.shape[1] / max_width))
    if factor == 1:
        return image, 1
    small = cv2.resize(image, (image.shape[1] // factor, image.shape[0] // factor), interpolation=cv2.INTER_AREA)
    return small, factor


def _opencv_detector(make: Callable[[], cv2.Feature2D], max_features: int, max_width: int) -> Detector:
    detector = make()

    def detect(image: NDArray[np.uint8]) -> tuple[NDArray[np.float64], NDArray]:
        small, factor = _working_image(image, max_width)
        kps, desc = detector.detectAndCompute(small, None)
        if desc is None or not kps:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        if len(kps) > max_features:
            order = np.argsort([-k.response for k in kps], kind="stable")[:max_features]
            kps = [kps[i] for i in order]
            desc = desc[order]
        uv = np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)
        # OpenCV keypoints use the pixel-centre convention too: map back to full-image pixels
        return (uv + 0.5) * factor - 0.5, desc

    return detect


MAX_WIDTH_PX = 1024
"""Wider textures are reduced by an integer factor before detection: a blob detector's finest
scales on a larger image are the sensor's noise, not the surface's texture."""

SURF_HESSIAN_THRESHOLD = 3e-6
"""SURF's det(H) threshold on the contrast-stretched image in [0, 1]: low, so weakly textured
surfaces still yield keypoints (``features.max_features`` keeps the strongest elsewhere)."""


MATCH_RATIO = 0.9
"""Lowe's ratio of best to second-best descriptor distance: permissive, because the mutual check
and 3D RANSAC reject outliers geometrically, and a strict ratio drops true matches on repetitive
texture and large viewpoint changes. Matches are also mutual nearest neighbours: a true
correspondence is the nearest neighbour both ways."""


def make_detector(config: RegistrationConfig) -> Detector:
    """Build the detector+descriptor selected by ``config.features.type``.

    Returns
    -------
    Detector
        ``detect(texture) -> (keypoints_uv (K, 2) float64 full-image pixels, descriptors (K, D))``;
        float32 descriptors for surf/sift, uint8 binary ones for orb/akaze.
    """
    features = config.features
    n = int(features.max_features)
    width = MAX_WIDTH_PX
    if features.type == "surf":
        params = SurfParams(hessian_threshold=SURF_HESSIAN_THRESHOLD, max_features=n, max_working_width=width)

        def surf(image: NDArray[np.uint8]) -> tuple[NDArray[np.float64], NDArray]:
            kp = surf_detect_and_compute(image, params)
            return kp.uv, kp.descriptors

        return surf
    if features.type == "sift":
        return _opencv_detector(lambda: cv2.SIFT_create(nfeatures=n), n, width)
    if features.type == "orb":
        return _opencv_detector(lambda: cv2.ORB_create(nfeatures=n, scaleFactor=1.2, nlevels=8, fastThreshold=10), n, width)
    if features.type == "akaze":
        # OpenCV 5 moved AKAZE to xfeatures2d; 4.x has it at top level
        factory = getattr(cv2, "AKAZE_create", None) or cv2.xfeatures2d.AKAZE_create
        return _opencv_detector(lambda: factory(threshold=5e-4), n, width)
    raise InputDataError(f"unknown feature type {features.type!r}; use surf, sift, orb or akaze")  # pragma: no cover


def feature_signature(config: RegistrationConfig) -> str:
    """What the keypoints of a frame were computed with: frames cached by an earlier run are
    re-described when any detector setting differs, not just the feature type."""
    features = config.features
    sig = f"{features.type}:n={int(features.max_features)}:w={MAX_WIDTH_PX}"
    if features.type == "surf":
        sig += f":h={SURF_HESSIAN_THRESHOLD:.3g}"
    return sig


def _check_texture(frame: Frame) -> NDArray[np.uint8]:
    if frame.texture is None:
        raise InputDataError(f"frame {frame.id}: no texture image, cannot detect keypoints")
    texture = frame.texture
    if min(texture.shape) < 32:
        raise InputDataError(f"frame {frame.id}: texture {texture.shape} is too small for keypoints (need >= 32x32)")
    return texture


def stretch_contrast(texture: NDArray[np.uint8], percentile: float = 99.0, floor: int = 8) -> NDArray[np.uint8]:
    """Scale a texture so the ``percentile`` of its lit pixels (grey > ``floor``) maps to 255.

    The detectors' thresholds (SURF's Hessian, SIFT's contrast, ORB's FAST) are absolute grey
    levels, but an FPP texture is the background term ``a`` of the fringes: at most about half
    the camera's range and often darker, so a fixed threshold finds a fraction of the keypoints
    it would on a full-range image (``scripts/registration_acceptance.py`` counts the matches).
    """
    hist = cv2.calcHist([texture], [0], None, [256], [0, 256]).ravel()
    hist[: floor + 1] = 0
    total = hist.sum()
    if total <= 0:
        return texture
    hi = int(np.searchsorted(np.cumsum(hist), percentile / 100.0 * total))
    if hi >= 254 or hi <= floor:
        return texture
    return cv2.convertScaleAbs(texture, alpha=255.0 / hi)


def detect_and_describe(frame: Frame, config: RegistrationConfig, detector: Detector | None = None) -> Frame:
    """Return ``frame`` with ``keypoints_uv`` and ``descriptors`` filled in (computed once per frame).

    Raises
    ------
    InputDataError
        The frame has no (or a too small) texture image.
    """
    texture = _check_texture(frame)
    detect = detector or make_detector(config)
    uv, desc = detect(np.ascontiguousarray(stretch_contrast(texture)))
    meta = dict(frame.metadata)
    meta["feature"] = config.features.type
    meta["feature_signature"] = feature_signature(config)
    return dataclasses.replace(frame, keypoints_uv=uv, descriptors=desc, metadata=meta)


def match_descriptors(
    descriptors_a: NDArray, descriptors_b: NDArray, ratio: float = 0.8, mutual: bool = True
) -> NDArray[np.int64]:
    """Match descriptors of image a against image b.

    Parameters
    ----------
    descriptors_a, descriptors_b : (Ka, D), (Kb, D)
        Float descriptors (L2 distance) or uint8 binary descriptors (Hamming distance); both
        of the same kind and length.
    ratio : float
        Keep a match when ``d1 < ratio * d2`` (Lowe's test; 1 disables it).
    mutual : bool
        Keep a match only when b's nearest neighbour in a is the same point.

    Returns
    -------
    (M, 2) int64
        Index pairs ``(i_a, i_b)``, best (lowest distance ratio) first.

    Raises
    ------
    InputDataError
        Descriptor arrays of different kinds or lengths.
    """
    a = np.asarray(descriptors_a)
    b = np.asarray(descriptors_b)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1] or a.dtype != b.dtype:
        raise InputDataError(
            f"descriptors do not match in kind: {a.dtype} {a.shape} vs {b.dtype} {b.shape}; "
            "both frames must be described with the same feature type"
        )
    if a.shape[0] < 2 or b.shape[0] < 2:
        return np.zeros((0, 2), np.int64)
    if a.dtype == np.uint8:
        ia_arr, ib_arr, score_arr, nn_ba = _hamming_nearest(a, b, ratio, mutual)
    else:
        ia_arr, ib_arr, score_arr, nn_ba = l2_nearest(np.ascontiguousarray(a, dtype=np.float32), np.ascontiguousarray(b, dtype=np.float32), ratio)
    if mutual:
        keep = nn_ba[ib_arr] == ia_arr
        ia_arr, ib_arr, score_arr = ia_arr[keep], ib_arr[keep], score_arr[keep]
    order = np.argsort(score_arr, kind="stable")
    return np.stack([ia_arr[order], ib_arr[order]], axis=1).astype(np.int64)


def l2_nearest(a: NDArray[np.float32], b: NDArray[np.float32], ratio: float, chunk_rows: int = 2048) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Ratio-test matches a -> b and b's nearest neighbour in a, by L2 distance.

    Squared distances ``|a|^2 + |b|^2 - 2 a.b`` come from one float32 matrix product per block of
    ``chunk_rows`` rows of ``a`` (bounded memory); the two nearest per row and the nearest per
    column are read from the same block. Returns ``(ia, ib, d1/d2, nn_ba)``.
    """
    na, nb = a.shape[0], b.shape[0]
    aa = np.einsum("ij,ij->i", a, a)
    bb = np.einsum("ij,ij->i", b, b)
    col_d = np.full(nb, np.inf, np.float32)
    col_i = np.zeros(nb, np.int64)
    cols = np.arange(nb)
    ia, ib, score = [], [], []
    for r0 in range(0, na, chunk_rows):
        A = a[r0 : r0 + chunk_rows]
        # -2 a.b with the factor on the small operand (scaling by a power of two is exact)
        D = (A * np.float32(-2.0)) @ b.T
        D += bb[None, :]
        D += aa[r0 : r0 + A.shape[0], None]
        rows = np.arange(A.shape[0])
        j1 = np.argmin(D, axis=1)
        d1 = D[rows, j1]
        # column minima before the row minima are masked for the second-nearest search.
        # argmin along axis 0 is a strided scan (4x slower than the whole matrix product here):
        # take the contiguous min, then the first row holding it from the flat positions of
        # the equal entries (one per column but for exact ties)
        cd = D.min(axis=0)
        flat = np.flatnonzero(D == cd)
        fj, first = np.unique(flat % nb, return_index=True)
        ci = np.zeros(nb, np.int64)
        ci[fj] = flat[first] // nb
        if fj.size < nb:  # a NaN column (no entry equals its min): the plain scan
            rest = np.setdiff1d(cols, fj)
            ci[rest] = np.argmin(D[:, rest], axis=0)
            cd[rest] = D[ci[rest], rest]
        better = cd < col_d
        col_d[better] = cd[better]
        col_i[better] = ci[better] + r0
        D[rows, j1] = np.inf
        d2 = D.min(axis=1)
        # rounding can leave a tiny negative squared distance for near-identical descriptors
        np.maximum(d1, np.float32(0.0), out=d1)
        np.maximum(d2, np.float32(0.0), out=d2)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.sqrt(d1 / np.maximum(d2, np.float32(1e-30)))
        ok = r < ratio
        ia.append(rows[ok] + r0)
        ib.append(j1[ok])
        score.append(r[ok].astype(np.float64))
    return np.concatenate(ia), np.concatenate(ib).astype(np.int64), np.concatenate(score), col_i


def _hamming_nearest(a: NDArray[np.uint8], b: NDArray[np.uint8], ratio: float, mutual: bool) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Ratio-test matches a -> b and b's nearest neighbour in a, by Hamming distance (OpenCV)."""
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    ia, ib, score = [], [], []
    for pair in matcher.knnMatch(a, b, k=2):
        if len(pair) < 2:
            continue
        m1, m2 = pair
        if m1.distance < ratio * m2.distance:
            ia.append(m1.queryIdx)
            ib.append(m1.trainIdx)
            score.append(m1.distance / max(m2.distance, 1e-12))
    nn_ba = np.full(b.shape[0], -1, np.int64)
    if mutual and ia:
        for m in matcher.match(b, a):
            nn_ba[m.queryIdx] = m.trainIdx
    return np.array(ia, np.int64), np.array(ib, np.int64), np.array(score, np.float64), nn_ba
