"""The expected noise of a decoded projector coordinate, from the codec and the camera's image noise.

Least-squares N-step phase shifting with independent image noise ``sigma_I`` (grey levels) on
every image and fringe modulation ``b`` gives a phase error of standard deviation

    sigma_phi = sigma_I / b * sqrt(2 / N)                     (rad)

and, for a fringe pitch ``lambda`` projector pixels, a projector-coordinate error

    sigma_u = lambda / (2 pi) * sigma_phi                     (projector pixels)

(the first-order propagation through ``phi = atan2(S, C)``; e.g. Zuo et al., "Phase shifting
algorithms for fringe projection profilometry: a review", 2018, section 5). A codec whose phase
comes from another linear estimator states its own ``sqrt(2 / N)`` factor (``gain``).

``sigma_I`` is measured on the capture itself (:func:`estimate_image_noise_grey`): with N >= 4
steps from the residual of each pixel's sinusoid fit (``N - 3`` degrees of freedom), with 3
steps, where the fit leaves no residual, from the images' second differences (Immerkaer,
"Fast noise variance estimation", 1996), robustly (a median) so that texture and edges do not
count as noise. It is never below the 8-bit quantisation noise ``1 / sqrt(12)`` grey levels.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import stats

from fpp_graph.errors import InputDataError

#: Uniform quantisation of an integer grey level: the smallest noise a camera image can have.
QUANTISATION_NOISE_GREY = 1.0 / math.sqrt(12.0)
# At most this many pixels enter the robust noise estimate (a regular subsample beyond it): the
# median of a million samples is as good as that of ten million, at a tenth of the cost.
_MAX_SAMPLES = 400_000
# The 3x3 Laplacian-difference mask of Immerkaer: zero on any locally linear image, and
# 6 sigma standard deviation on white noise of standard deviation sigma.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_HALF_NORMAL_MEDIAN = 0.6744897501960817  # median of |x| for x ~ N(0, 1)


def phase_sigma_rad(modulation_grey: NDArray, steps: int, image_noise_grey: float, gain: float | None = None) -> NDArray[np.float32]:
    """Expected phase noise (1 sigma, rad) per pixel: ``gain * sigma_I / b``, ``gain = sqrt(2 / N)`` by default.

    NaN or non-positive modulation gives ``inf``.
    """
    factor = math.sqrt(2.0 / steps) if gain is None else float(gain)
    b = np.asarray(modulation_grey, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.float32(factor * image_noise_grey) / b
    out[~(b > 0)] = np.inf
    return out


def projector_coordinate_sigma_px(modulation_grey: NDArray, steps: int, pitch_px: float, image_noise_grey: float, gain: float | None = None) -> NDArray[np.float32]:
    """Expected noise (1 sigma, projector pixels) of the decoded coordinate: ``lambda / (2 pi) * sigma_phi``."""
    sigma = phase_sigma_rad(modulation_grey, steps, image_noise_grey, gain)
    sigma *= np.float32(pitch_px / (2.0 * math.pi))
    return sigma


def _subsample(values: NDArray) -> NDArray:
    """A regular subsample of at most :data:`_MAX_SAMPLES` along the last axis."""
    count = values.shape[-1]
    if count <= _MAX_SAMPLES:
        return values
    return values[..., :: -(-count // _MAX_SAMPLES)]


def estimate_image_noise_grey(step_images: NDArray, valid: NDArray | None = None) -> float:
    """The camera's image noise ``sigma_I`` (grey levels) measured on one set of N phase-shift images.

    Parameters
    ----------
    step_images : (N, H, W) array
        The N equally shifted images of one fringe set, in any order of the steps.
    valid : (H, W) bool, optional
        Pixels that see the fringes unsaturated (the decoder's mask); all pixels when None.

    Returns
    -------
    float
        N >= 4: ``median(RSS / (N - 3)) / m``, with ``RSS = sum I_n^2 - N a^2 - (N / 2) b^2`` the
        residual of the pixel's sinusoid fit and ``m`` the median of a chi-square variable with
        ``N - 3`` degrees of freedom over ``N - 3`` (so that it estimates ``sigma_I^2`` without
        bias where noise is Gaussian). N = 3: the median absolute response of Immerkaer's mask
        over the valid pixels (whose 3x3 neighbourhood is valid), divided by its value on
        unit white noise, averaged over the three images. At least the quantisation noise.
        A model error in the fit (a projector gamma that the capture did not correct) also
        shows in the residual: the estimate then bounds the noise from above.
    """
    stack = np.asarray(step_images)
    if stack.ndim != 3 or stack.shape[0] < 3:
        raise InputDataError(f"noise estimate: need (N, H, W) phase-shift images with N >= 3, got shape {stack.shape}")
    n = stack.shape[0]
    mask = np.ones(stack.shape[1:], bool) if valid is None else np.asarray(valid, bool)
    if not mask.any():
        return QUANTISATION_NOISE_GREY
    if n >= 4:
        samples = _subsample(stack[:, mask].astype(np.float64))  # (N, K)
        delta = 2.0 * np.pi * np.arange(n) / n
        a = samples.mean(axis=0)
        c = (2.0 / n) * (np.cos(delta) @ samples)
        s = (2.0 / n) * (np.sin(delta) @ samples)
        rss = np.einsum("nk,nk->k", samples, samples) - n * a * a - 0.5 * n * (c * c + s * s)
        dof = n - 3
        variance = float(np.median(np.maximum(rss, 0.0) / dof)) / (stats.chi2.median(dof) / dof)
        return max(math.sqrt(max(variance, 0.0)), QUANTISATION_NOISE_GREY)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
    if not inner.any():
        return QUANTISATION_NOISE_GREY
    sigmas = []
    for image in stack:
        response = cv2.filter2D(image.astype(np.float32), cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REPLICATE)
        sigmas.append(float(np.median(np.abs(_subsample(response[inner])))) / (6.0 * _HALF_NORMAL_MEDIAN))
    return max(float(np.mean(sigmas)), QUANTISATION_NOISE_GREY)
