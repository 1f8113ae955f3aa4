"""Synthetic FPP captures with known ground truth, for tests and acceptance scripts.

A camera looks at a smooth scene: every camera pixel sees a known (sub-pixel) projector
coordinate, a background ``A`` and a modulation ``B`` (camera grey levels). Pattern image ``i``
is rendered as ``A + B (2 p_i - 1)`` with ``p_i`` the exact pattern value from
:func:`frontend.fpp.patterns.pattern_intensity` (so binary patterns are ``A -+ B``), optionally
blurred (camera defocus across code edges), plus Gaussian noise, then quantised. This is not the
project's sensor simulator (no geometry, no lens model): it isolates the decoder.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from frontend.fpp.patterns import PatternSpec, pattern_intensity


def smooth_projector_map(
    camera_width: int,
    camera_height: int,
    projector_width: int,
    projector_height: int,
    margin: float = 0.02,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A smooth, non-linear, monotonic camera-to-projector map (a gently curved scene).

    The camera sees the projector at a non-integer, varying scale: ``u_p`` spans
    ``[margin, 1 - margin]`` of the projector width across the camera, with a smooth bulge that
    depends on the row, and ``v_p`` likewise. Returns ``(u_projector_px, v_projector_px)``, each
    (H, W) float64, pixel-centre convention.
    """
    y, x = np.mgrid[0:camera_height, 0:camera_width].astype(np.float64)
    xn, yn = x / max(camera_width - 1, 1), y / max(camera_height - 1, 1)
    # d/dxn of the bracket is 1 + 0.1 pi cos(.) (0.5 + 0.3 yn) > 0: monotonic in x, curved in y.
    fx = xn + 0.05 * np.sin(np.pi * xn) * (0.5 + 0.3 * yn) + 0.01 * np.sin(2 * np.pi * yn)
    fy = yn + 0.04 * np.sin(np.pi * yn) * (0.5 + 0.3 * xn) + 0.01 * np.sin(2 * np.pi * xn)
    fx = (fx - fx.min()) / (fx.max() - fx.min())
    fy = (fy - fy.min()) / (fy.max() - fy.min())
    u = (margin + (1 - 2 * margin) * fx) * (projector_width - 1)
    v = (margin + (1 - 2 * margin) * fy) * (projector_height - 1)
    return u, v


def render_captures(
    spec: PatternSpec,
    u_projector_px: NDArray[np.floating],
    v_projector_px: NDArray[np.floating],
    projector_width: int,
    projector_height: int,
    background: float | NDArray[np.floating] = 120.0,
    modulation: float | NDArray[np.floating] = 90.0,
    noise_sigma: float = 0.0,
    blur_sigma_px: float = 0.0,
    rng: np.random.Generator | None = None,
    dtype: type | None = np.uint8,
) -> NDArray:
    """Render a frame's captured pattern images.

    Parameters
    ----------
    spec : PatternSpec
    u_projector_px, v_projector_px : (H, W) float
        Projector coordinates seen by each camera pixel.
    projector_width, projector_height : int
    background, modulation : float or (H, W)
        Camera-side ``A`` and ``B``, grey levels.
    noise_sigma : float
        Standard deviation of additive Gaussian noise, grey levels.
    blur_sigma_px : float
        Gaussian blur of every image, camera pixels (0 = none).
    rng : numpy Generator, optional
    dtype : uint8, uint16 or None
        Rounded and clipped to this type; None keeps float64 (no quantisation).

    Returns
    -------
    (M, H, W) array of ``dtype``
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    h, w = np.shape(u_projector_px)
    out = np.empty((spec.image_count(), h, w), dtype=np.float64 if dtype is None else dtype)
    for i in range(spec.image_count()):
        p = pattern_intensity(spec, i, u_projector_px, v_projector_px, projector_width, projector_height)
        img = background + modulation * (2.0 * p - 1.0)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT)
        if noise_sigma > 0:
            img = img + rng.normal(0.0, noise_sigma, size=img.shape)
        if dtype is None:
            out[i] = img
        else:
            out[i] = np.clip(np.rint(img), 0, np.iinfo(dtype).max)
    return out
