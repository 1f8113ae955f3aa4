"""Micro phase shifting (Gupta and Nayar, "Micro Phase Shifting", CVPR 2012).

Every pattern is a sinusoid whose pitch lies in a narrow, high-frequency band. Global light
(interreflections, subsurface scattering) and projector defocus low-pass the projected light; a
high-frequency sinusoid low-passes to its mean, and sinusoids of nearly the same pitch are
attenuated alike, so over the whole set these effects add the same constant to every image of a
pixel and scale every fringe by the same factor. That constant and that factor are exactly the
offset and the amplitude the decoder solves for, so they cost no accuracy.

Patterns (pixel-centre convention of :mod:`frontend.fpp.patterns`: projector pixel ``j`` is
centred at ``u = j``; ``u`` runs along the coded axis)
---------------------------------------------------------------------------------------------
``F >= 2`` pitches ``lambda_1 .. lambda_F`` (projector pixels), ``omega_f = 2 pi / lambda_f``;
``F + 2`` images:

* images 0, 1, 2: ``0.5 + 0.5 cos(omega_1 u - 2 pi n / 3)``, ``n = 0, 1, 2`` (3-step phase
  shifting at the first pitch, forward, phase origin at pixel 0's centre);
* image ``2 + f`` for ``f = 1 .. F - 1``: ``0.5 + 0.5 cos(omega_(f+1) u + o_f)``, one image per
  further pitch, offsets ``o_f`` alternating ``0, pi, 0, ...`` (``o_f = pi`` for even ``f``), as
  in the published set (3 shifts at one pitch plus one image at each of nine nearby pitches).

Decoding (per pixel, vectorised over bands of rows)
---------------------------------------------------
1. The linear solve. With ``I_i = O + A cos(theta_i)`` the ``F + 2`` unknowns are the offset
   ``O``, ``A cos phi_1``, ``A sin phi_1`` and ``V_f = A cos(omega_f u + o_f)``; the system is
   square and block triangular: ``O`` and ``(A cos phi_1, A sin phi_1)`` come from the 3 shifts
   alone (``O = mean``, ``A e^{i phi_1} = (2/3) sum_n I_n e^{i 2 pi n / 3}``), ``V_f = I_(2+f) - O``.
2. The search. ``phi_1`` fixes ``u`` up to the period: the candidates are
   ``u_k = lambda_1 (phi_1 / 2 pi + k)`` inside ``[-0.5, L - 0.5)``, one per period, not one per
   projector pixel. The fixed-parameter residual ``RSS_k = sum_f (V_f - A cos(omega_f u_k +
   o_f))^2`` of every candidate comes from one matrix product: ``cos(a + k b)`` splits by the
   angle-sum rule into per-pixel and per-candidate factors (``O(F K)`` multiply-adds per pixel,
   no trigonometry per candidate).
3. The check. The exact statistic of a candidate is the residual of all ``F + 2`` images at
   ``u_k`` (zero for the shifts) projected off the model's tangent space (offset, amplitude,
   coordinate), a closed-form 3 x 3 solve. To first order it is ``sigma_I^2`` times a
   chi-square variable with ``F - 1`` degrees of freedom at the true candidate, whatever
   estimator gave the parameters. It is computed only for the candidates whose ``RSS_k`` does
   not already prove them inconsistent (:meth:`MicroPhaseShift._screen`: about 24 times the
   limit for ``F = 10``), 1.04 candidates per pixel on a 960 x 600 capture of a 912-pixel
   axis. The pixel is decoded, at its consistent candidate, only if exactly one candidate is
   consistent (chi-square below its ``1 - 1e-6`` quantile times the pixel's own ``sigma_I^2``):
   one period explains the images. Otherwise (too little modulation to tell periods apart, or
   images the model does not explain) the coordinate is NaN. ``sigma_I`` is the caller's
   constant when stated, else the noise model below, fitted to the capture.

Noise model
-----------
Image noise is not one number: shot noise grows with the light, and a projector response that
is not exactly linear (``x^1.1`` leaves a second harmonic of 3 % of the fringe) adds a misfit
to every image that no sinusoid explains, proportional to the amplitude. A single ``sigma_I``
measured over the lit pixels is then too small for the brightest: on a virtual-sensor capture
(sphere before a plate, 640 x 400, ``scripts/codec_accuracy.py``) the best candidate's
chi-square exceeded the global limit at 5 % of the pixels with fringes (``A > 10`` grey
levels) and at 25 % of those with ``A`` of 80-100. The limit is therefore per pixel, with

    sigma_I^2(O, A) = s0^2 + g O + (kappa A)^2

(read noise and quantisation; shot noise, variance ``g`` per grey level of the mean signal,
which is the offset ``O`` averaged over the images; the model error as a fraction ``kappa``
of the amplitude). The three parameters are measured on the capture: at almost every pixel
with visible fringes the best candidate (smallest ``RSS_k``) is the true one, so its exact
chi-square over the median of a chi-square with ``F - 1`` degrees of freedom estimates the
pixel's ``sigma_I^2``. These estimates (on up to 5e4 pixels of amplitude above 8 global noise
sigmas, where a wrong candidate is the best only near the few worst-separated coordinates)
are reduced to medians over 6 x 6 quantile bins of ``(O, A)`` and the model is fitted to the
medians by non-negative least squares in relative terms. ``O`` and ``A`` grow together on
matte surfaces, so the split between ``g`` and ``kappa`` is loosely determined; the limit
depends only on their sum at the observed ``(O, A)``, which the bins pin down. On the capture
above: ``s0^2 = 0.56``, ``g = 0.016``, ``kappa = 0.023`` (the simulator's 0.72 with
quantisation, 0.012 and the response harmonic's 0.032 / sqrt(2) = 0.023).

The misfit is deterministic, not Gaussian: its chi-square is a non-central one whose tail is
shorter, relative to its median, than that of the central chi-square the limit assumes, so the
``1 - 1e-6`` quantile of the scaled central chi-square still refuses the true period with
probability about 1e-6 and the uniqueness rule keeps bounding the wrong periods at that rate.
On the capture above, the best chi-square over the fitted ``sigma_I^2`` has 0.9, 0.99 and 0.999
quantiles 14.0, 20.1, 25.9 against the chi-square's 14.7, 21.7, 27.9 (9 degrees of freedom),
and 3 of 212797 pixels lie above its ``1 - 1e-6`` quantile. A larger limit lets more wrong
candidates pass too: near the coordinates whose candidates are closest
(:func:`candidate_separation`) bright pixels then have two consistent candidates and are
refused, as the uniqueness rule requires.
A capture with fewer than 300 such pixels (no fit of 3 parameters) falls back to the global
``sigma_I`` of :func:`frontend.fpp.phase_noise.estimate_image_noise_grey` on the three shifts.

Noise
-----
The coordinate is ``u = lambda_1 (phi_1 / 2 pi + k)``; the 3-step solve gives ``A cos phi_1`` and
``A sin phi_1`` with covariance ``(2/3) sigma_I^2 I``, so ``sigma_phi = sqrt(2/3) sigma_I / A`` and

    sigma_u = lambda_1 / (2 pi) * sqrt(2 / 3) * sigma_I / A = coordinate_sigma_gain_px * sigma_I / A.

The further images only choose the period; they do not enter the coordinate. Its random noise
follows the random part of the model, ``sigma_I^2 = s0^2 + g O``
(:meth:`ImageNoiseModel.random_variance_grey2`, from :meth:`MicroPhaseShift.decode_with_noise`);
the response harmonic biases the 3-step phase by the same amount at every capture of a pixel
and is not noise.

Speed: a 1920 x 1200 frame of a 912-pixel axis (59 candidates) decoded in 2.4 s on a shared
2-core machine (load 4), a 320 x 240 frame of a 320-pixel axis in 0.12 s. The noise-model fit
(5e4 pixels, all candidates) adds about 0.1 s (measured at 640 x 400 with a 1280-pixel axis).

Pitch choice (:func:`micro_pitches`)
------------------------------------
The candidates ``u`` and ``u + m lambda_1`` are told apart by the further images'
values ``cos(omega_f u + o_f)`` against ``cos(omega_f u + o_f + 2 pi m lambda_1 / lambda_f)``;
:func:`candidate_separation` is the smallest Euclidean distance between these vectors over the
axis (in units of ``A``). Gupta and Nayar choose the pitches in a narrow band around the mean
and, among such sets, one that keeps the phase vectors of all columns far apart;
:func:`micro_pitches` does that by a seeded random search over sets in the band.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, stats

from fpp_graph.errors import ConfigError, InputDataError
from frontend.fpp.phase_noise import QUANTISATION_NOISE_GREY, estimate_image_noise_grey

log = logging.getLogger(__name__)

TWO_PI = 2.0 * math.pi
#: A candidate is consistent when its chi-square is below the ``1 - this`` quantile. A correct
#: pixel is refused with this probability, and a wrong period can be accepted only when the true
#: one is refused, so at most this fraction of the pixels gets a wrong period (1e-6: about two
#: pixels of a 1920 x 1200 frame at worst).
FALSE_REFUSAL_PROBABILITY = 1e-6
# Each (pixels x candidates) float32 work array of a band stays below this size (a few exist at once).
_BAND_BYTES = 4 * 2**20
# A pitch set whose closest candidates differ by less than one 8-bit grey level at full 8-bit
# contrast (amplitude 127.5) cannot be decoded even from a noiseless capture.
_MIN_SEPARATION = 1.0 / 127.5
_THREE_STEP = np.array([0.0, TWO_PI / 3.0, 2.0 * TWO_PI / 3.0])
# The noise model is fitted to at most this many pixels (a regular subsample beyond it): 6 x 6
# bins of ~1400 pixels, whose medians then carry ~1.6 % relative error each (0.59 / sqrt(n) for
# a chi-square with 9 degrees of freedom).
_NOISE_SAMPLES = 50_000
# Pixels enter the fit when their amplitude is at least this many global noise sigmas: below it
# several candidates fit and the best one's chi-square is the smallest of several, biased low.
_NOISE_FIT_MIN_SNR = 8.0
# Quantile bins per variable (offset, amplitude) and the pixels a bin needs to count; 100 pixels
# give its median a relative error of 6 % (chi-square with 9 degrees of freedom).
_NOISE_BINS = 6
_NOISE_BIN_PIXELS = 100


class MicroPhaseDecode(NamedTuple):
    """One decoded micro phase shifting frame; all maps (H, W) float32 in camera pixels."""

    coordinate_px: NDArray[np.float32]
    """Absolute projector coordinate along the coded axis (pixel centres); NaN where no single
    period explains the images."""
    modulation_grey: NDArray[np.float32]
    """Fringe amplitude ``A`` of the first pitch (grey levels)."""
    background_grey: NDArray[np.float32]
    """Offset ``O`` (grey levels): ambient light, half the direct light and the global light."""
    coordinate_sigma_gain_px: float
    """``lambda_1 / (2 pi) sqrt(2/3)``: the coordinate's 1-sigma error is this times ``sigma_I / A``."""


@dataclass(frozen=True)
class ImageNoiseModel:
    """Per-pixel image noise of one capture (module docstring, "Noise model"):
    ``sigma_I^2 = read_variance_grey2 + shot_gain_grey * O + (model_error_fraction * A)^2``.

    ``read_variance_grey2`` (grey levels^2) holds read noise and quantisation,
    ``shot_gain_grey`` (grey levels^2 per grey level of offset) the shot noise, and
    ``model_error_fraction`` (dimensionless, of the amplitude ``A``) the part of the images that
    no sinusoid explains (projector response harmonics), counted as if it were noise.
    """

    read_variance_grey2: float
    shot_gain_grey: float = 0.0
    model_error_fraction: float = 0.0

    def variance_grey2(self, offset_grey: NDArray, amplitude_grey: NDArray) -> NDArray[np.float32]:
        """``sigma_I^2`` (grey levels^2) at pixels of offset ``O`` and amplitude ``A`` (same shapes)."""
        offset = np.maximum(np.asarray(offset_grey, np.float32), np.float32(0.0))
        amplitude = np.asarray(amplitude_grey, np.float32)
        return (np.float32(self.read_variance_grey2) + np.float32(self.shot_gain_grey) * offset
                + np.float32(self.model_error_fraction**2) * amplitude * amplitude)

    def random_variance_grey2(self, offset_grey: NDArray) -> NDArray[np.float32]:
        """The random part alone, ``read_variance_grey2 + shot_gain_grey * O``: what the coordinate's
        noise follows (the model error is the same at every capture of the pixel, a bias)."""
        offset = np.maximum(np.asarray(offset_grey, np.float32), np.float32(0.0))
        return np.float32(self.read_variance_grey2) + np.float32(self.shot_gain_grey) * offset


def _checked_pitches(pitches_px) -> tuple[float, ...]:
    try:
        pitches = tuple(float(p) for p in pitches_px)
    except (TypeError, ValueError):
        raise ConfigError(f"micro phase shifting pitches_px must be a list of numbers (projector pixels), got {pitches_px!r}") from None
    if len(pitches) < 2:
        raise ConfigError(f"micro phase shifting needs at least 2 pitches (one 3-step pitch plus one image per further pitch), got {pitches!r}")
    bad = [p for p in pitches if not math.isfinite(p) or p <= 2.0]
    if bad:
        raise ConfigError(f"micro phase shifting pitches must be finite and above 2 projector pixels (the projector's Nyquist limit), got {bad!r} in {pitches!r}")
    if len(set(pitches)) != len(pitches):
        raise ConfigError(f"micro phase shifting pitches must differ (a repeated pitch adds no information), got {pitches!r}")
    return pitches


def _offsets(count: int) -> NDArray[np.float64]:
    """Offsets ``o_f`` of the further images f = 1 .. count: 0, pi, 0, pi, ..."""
    return np.where(np.arange(1, count + 1) % 2 == 0, np.pi, 0.0)


class MicroPhaseShift:
    """Micro phase shifting codec (see the module docstring).

    Parameters
    ----------
    pitches_px : tuple of float
        ``F >= 2`` fringe pitches in projector pixels, each above 2 and all different; the first
        is phase-shifted in 3 steps, each further one is shown once. Choose them in a narrow
        band (e.g. with :func:`micro_pitches`).
    """

    def __init__(self, pitches_px: tuple[float, ...]) -> None:
        self.pitches_px = _checked_pitches(pitches_px)
        self._omega = TWO_PI / np.asarray(self.pitches_px)
        self._offsets = _offsets(len(self.pitches_px) - 1)

    @property
    def image_count(self) -> int:
        """``F + 2`` images per frame."""
        return len(self.pitches_px) + 2

    @property
    def coordinate_sigma_gain_px(self) -> float:
        """``lambda_1 / (2 pi) * sqrt(2 / 3)`` (see the module docstring)."""
        return self.pitches_px[0] / TWO_PI * math.sqrt(2.0 / 3.0)

    def profile(self, image: int, coord_px: NDArray) -> NDArray[np.float64]:
        """Continuous value in [0, 1] of pattern ``image`` at projector coordinates ``coord_px``."""
        if isinstance(image, bool) or not isinstance(image, (int, np.integer)) or not 0 <= image < self.image_count:
            raise ConfigError(f"micro phase shifting image index {image!r} out of range: the set has {self.image_count} images (0..{self.image_count - 1})")
        u = np.asarray(coord_px, dtype=np.float64)
        if image < 3:
            return 0.5 + 0.5 * np.cos(self._omega[0] * u - _THREE_STEP[image])
        f = int(image) - 2
        return 0.5 + 0.5 * np.cos(self._omega[f] * u + self._offsets[f - 1])

    def decode(self, images: NDArray, axis_length_px: int, image_noise_grey: float | None = None) -> MicroPhaseDecode:
        """Decode one frame.

        Parameters
        ----------
        images : (F + 2, H, W) uint8, uint16 or float array
            The captured images in the order of :meth:`profile`.
        axis_length_px : int
            Projector pixels along the coded axis (``L``): candidates lie in ``[-0.5, L - 0.5)``.
        image_noise_grey : float, optional
            The camera's image noise ``sigma_I`` (grey levels), the same at every pixel; when
            None, a per-pixel noise model is fitted to the capture (:meth:`decode_with_noise`).

        Returns
        -------
        MicroPhaseDecode
            ``(coordinate_px, modulation_grey, background_grey, coordinate_sigma_gain_px)``.

        Raises
        ------
        InputDataError
            Wrong image count, shape or pixel type.
        ConfigError
            A bad axis length, or pitches that cannot tell the periods of this axis apart.
        """
        return self.decode_with_noise(images, axis_length_px, image_noise_grey)[0]

    def decode_with_noise(self, images: NDArray, axis_length_px: int, image_noise_grey: float | None = None) -> tuple[MicroPhaseDecode, ImageNoiseModel]:
        """:meth:`decode`, and the image noise model whose per-pixel limit it applied.

        With ``image_noise_grey`` stated the model is that constant; otherwise it is fitted to
        the capture (module docstring, "Noise model"). The coordinate's 1-sigma noise is
        ``coordinate_sigma_gain_px * sqrt(model.random_variance_grey2(O)) / A``.
        """
        stack = _checked_stack(images, self.image_count)
        length = _checked_axis_length(axis_length_px)
        separation = candidate_separation(self.pitches_px, length)
        if separation < _MIN_SEPARATION:
            raise ConfigError(
                f"micro phase shifting pitches {self.pitches_px} cannot tell the periods of a {length}-pixel axis apart "
                f"(closest candidates differ by {separation:.2g} of the amplitude); choose them with micro_pitches({length}, ...)"
            )
        _, h, w = stack.shape
        shifts = self._three_step(stack)
        k_all = np.arange(-1, math.ceil(length / self.pitches_px[0]) + 1)
        tables = _candidate_tables(self._omega, self._offsets, self.pitches_px[0], k_all)
        if image_noise_grey is not None:
            model = ImageNoiseModel(_checked_noise(image_noise_grey) ** 2)
        else:
            model = self._fit_noise(stack, shifts, length, k_all, tables)
        quantile = np.float32(stats.chi2.ppf(1.0 - FALSE_REFUSAL_PROBABILITY, self.image_count - 3))
        coordinate = np.empty((h, w), np.float32)
        rows = max(1, min(h, _BAND_BYTES // max(1, 4 * w * k_all.size)))
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            further = stack[3:, r0:r1].reshape(stack.shape[0] - 3, -1).astype(np.float32)
            offset, amplitude, u0 = (m[r0:r1].ravel() for m in shifts)
            limit = quantile * model.variance_grey2(offset, amplitude)
            coordinate[r0:r1] = self._search_band(further - offset, amplitude, u0, length, k_all, tables, limit).reshape(r1 - r0, w)
        log.debug("micro phase shifting: %s, %d of %d pixels decoded", model, int(np.isfinite(coordinate).sum()), coordinate.size)
        return MicroPhaseDecode(coordinate, shifts[1], shifts[0], self.coordinate_sigma_gain_px), model

    def _three_step(self, stack: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """Step 1 on the 3 shifts: offset ``O``, amplitude ``A`` and ``u`` within the first period."""
        shifts = stack[:3].astype(np.float32)
        offset = shifts.mean(axis=0)
        c1 = np.tensordot(np.float32(2.0 / 3.0) * np.cos(_THREE_STEP).astype(np.float32), shifts, axes=1)
        s1 = np.tensordot(np.float32(2.0 / 3.0) * np.sin(_THREE_STEP).astype(np.float32), shifts, axes=1)
        amplitude = np.hypot(c1, s1)
        u0 = np.float32(self.pitches_px[0] / TWO_PI) * (np.arctan2(s1, c1) % np.float32(TWO_PI))
        return offset, amplitude, np.minimum(u0, np.float32(np.nextafter(self.pitches_px[0], 0)))

    def _fit_noise(self, stack: NDArray, shifts: tuple[NDArray, NDArray, NDArray], length: int, k_all: NDArray, tables: tuple[NDArray, NDArray]) -> ImageNoiseModel:
        """The noise model fitted to the best candidates' chi-square (module docstring, "Noise model")."""
        offset, amplitude, u0 = (m.ravel() for m in shifts)
        # the global noise of the lit pixels: a scale for which pixels see fringes, and the fallback
        lit = shifts[1] >= 0.5 * np.percentile(shifts[1], 90)
        sigma = estimate_image_noise_grey(stack[:3], valid=lit)
        fallback = ImageNoiseModel(sigma**2)
        pix = np.flatnonzero(amplitude >= np.float32(_NOISE_FIT_MIN_SNR * sigma))
        pix = pix[:: max(1, pix.size // _NOISE_SAMPLES)]
        if pix.size < 3 * _NOISE_BIN_PIXELS:
            log.debug("micro phase shifting: %d pixels with fringes, too few to fit a noise model; sigma_I %.3g grey", pix.size, sigma)
            return fallback
        further = stack[3:].reshape(stack.shape[0] - 3, -1)[:, pix].astype(np.float32) - offset[pix]
        a = (self._omega[1:, None] * u0[pix] + self._offsets[:, None]).astype(np.float32)
        rss = self._mask_off_axis(_candidate_costs(further, amplitude[pix], a, tables), u0[pix], length, k_all)
        best = np.argmin(rss, axis=1)
        chi = _pair_chi2(further, amplitude[pix], a, self._omega, self.pitches_px[0], np.arange(pix.size), k_all[best])
        fitted = _fit_variance_model(offset[pix], amplitude[pix], chi / np.float32(stats.chi2.median(further.shape[0])))
        return fallback if fitted is None else fitted

    def _mask_off_axis(self, rss: NDArray, u0: NDArray, length: int, k_all: NDArray) -> NDArray:
        """``rss`` with the candidates outside ``[-0.5, L - 0.5)`` set to inf (in place)."""
        # u_k < -0.5 can only happen at k = -1, u_k >= L - 0.5 only in the last columns
        rss[u0 < self.pitches_px[0] - 0.5, 0] = np.inf
        first_off = math.floor((length - 0.5) / self.pitches_px[0]) + 1  # index of k = first_off - 1 ... in k_all
        for col in range(max(0, first_off - 1), k_all.size):
            rss[u0 + self.pitches_px[0] * k_all[col] >= length - 0.5, col] = np.inf
        return rss

    def _search_band(self, further: NDArray, amplitude: NDArray, u0: NDArray, length: int, k_all: NDArray, tables: tuple[NDArray, NDArray], limit: NDArray) -> NDArray[np.float32]:
        """Steps 2-3 on n pixels: the coordinate where exactly one candidate is consistent, else NaN.

        ``further`` holds ``V_f`` (F - 1, n), ``limit`` each pixel's chi-square limit (n,). Every
        candidate's fixed-parameter residual ``RSS_k = sum_f (V_f - A cos t_fk)^2`` comes from two matrix products; the exact
        chi-square (:func:`_pair_chi2`) is computed only where ``RSS_k`` does not already prove
        the candidate inconsistent (:meth:`_screen`): first for the two smallest ``RSS_k`` (two
        consistent candidates refuse the pixel at once, the common case in the dark), then for
        the other candidates that pass the screen.
        """
        n = u0.size
        rows = np.arange(n)
        # phases at k = 0: u0 < lambda_1, so a stays below ~3 pi and float32 holds it to 1e-6 rad
        a = (self._omega[1:, None] * u0 + self._offsets[:, None]).astype(np.float32)
        # RSS_k less its per-pixel constant sum V^2 + A^2 (F - 1) / 2, and the screen less it
        rss = _candidate_costs(further, amplitude, a, tables)
        constant = np.einsum("fn,fn->n", further, further) + (0.5 * further.shape[0]) * amplitude**2
        # float32 sums of 4 (F - 1) products round to ~4 (F - 1) 2^-24 of their size: allow 1e-5
        bound = self._screen() * limit - constant + 1e-5 * (constant + 0.5 * further.shape[0] * amplitude**2)
        self._mask_off_axis(rss, u0, length, k_all)
        best = np.argmin(rss, axis=1)
        saved = rss[rows, best]
        rss[rows, best] = np.inf
        second = np.argmin(rss, axis=1)
        rss[rows, best] = saved
        possible = rss <= bound[:, None]
        pix = np.concatenate([rows, rows])
        cand = np.concatenate([best, second])
        keep = possible[pix, cand]
        pix, cand = pix[keep], cand[keep]
        chi = _pair_chi2(further, amplitude, a, self._omega, self.pitches_px[0], pix, k_all[cand])
        consistent = np.bincount(pix[chi <= limit[pix]], minlength=n)
        possible[pix, cand] = False  # done
        possible[consistent >= 2] = False  # already ambiguous
        need = np.flatnonzero(possible.any(axis=1))  # few pixels: the screen passes ~1 candidate
        sub_pix, more_cand = np.nonzero(possible[need])
        more_pix = need[sub_pix]
        pix, cand = np.concatenate([pix, more_pix]), np.concatenate([cand, more_cand])
        chi = np.concatenate([chi, _pair_chi2(further, amplitude, a, self._omega, self.pitches_px[0], more_pix, k_all[more_cand])])
        ok = chi <= limit[pix]
        consistent = np.bincount(pix[ok], minlength=n)
        out = np.full(n, np.nan, np.float32)
        one = consistent[pix[ok]] == 1
        out[pix[ok][one]] = u0[pix[ok][one]] + np.float32(self.pitches_px[0]) * k_all[cand[ok][one]]
        return out

    def _screen(self) -> float:
        """``RSS_k`` above this many times the chi-square limit proves a candidate inconsistent.

        The exact statistic is ``min_d |r - J d|^2`` over the tangent space. The 3 shifts have
        zero residual, so they alone cost ``d^T D d``, ``D = diag(3, 3/2, 3/2)``: a consistent
        fit has ``|D^(1/2) d|^2 <= limit``, and then ``|J_e d| <= sqrt(tau limit)`` with
        ``tau = ||J_e D^(-1/2)||_F^2 <= (F - 1) / 3 + (F - 1) / 1.5 + sum rho_f^2 / 1.5`` (the
        further images' rows, ``|cos| <= 1``, ``|rho sin| <= rho``). So
        ``|r_e| > (1 + sqrt(tau)) sqrt(limit)`` leaves every fit above the limit.
        """
        rho2 = (self._omega[1:] / self._omega[0]) ** 2
        count = rho2.size
        tau = count / 3.0 + count / 1.5 + float(rho2.sum()) / 1.5
        return (1.0 + math.sqrt(tau)) ** 2


def _fit_variance_model(offset: NDArray, amplitude: NDArray, variance: NDArray) -> ImageNoiseModel | None:
    """``s0^2 + g O + (kappa A)^2`` fitted to per-pixel variance estimates (each ``sigma_I^2`` times
    a chi-square over its median): medians over quantile bins of (O, A), then non-negative least
    squares in relative terms (a bin's median has a relative error ~ 1 / sqrt(pixels)). None when
    fewer than 3 bins are filled (no fit of 3 parameters)."""
    edges_o = np.quantile(offset, np.linspace(0.0, 1.0, _NOISE_BINS + 1)[1:-1])
    edges_a = np.quantile(amplitude, np.linspace(0.0, 1.0, _NOISE_BINS + 1)[1:-1])
    bin_id = np.searchsorted(edges_o, offset) * _NOISE_BINS + np.searchsorted(edges_a, amplitude)
    order = np.argsort(bin_id, kind="stable")
    ids, starts, counts = np.unique(bin_id[order], return_index=True, return_counts=True)
    design, target, weight = [], [], []
    for start, count in zip(starts, counts, strict=True):  # at most _NOISE_BINS^2 bins
        if count < _NOISE_BIN_PIXELS:
            continue
        members = order[start : start + count]
        median = float(np.median(variance[members]))
        if median <= 0.0:
            continue
        design.append([1.0, float(np.median(offset[members])), float(np.median(amplitude[members])) ** 2])
        target.append(median)
        weight.append(math.sqrt(count) / median)
    if len(target) < 3:
        return None
    x = np.asarray(design) * np.asarray(weight)[:, None]
    params, _ = optimize.nnls(x, np.asarray(target) * np.asarray(weight))
    read_variance = max(float(params[0]), QUANTISATION_NOISE_GREY**2)
    return ImageNoiseModel(read_variance, float(params[1]), math.sqrt(float(params[2])))


def _checked_noise(given) -> float:
    if not (isinstance(given, (int, float, np.floating)) and not isinstance(given, bool) and math.isfinite(given) and given > 0):
        raise ConfigError(f"image_noise_grey must be a positive number of grey levels, got {given!r}")
    return float(given)


def _candidate_tables(omega: NDArray, offsets: NDArray, pitch_1: float, k_all: NDArray) -> tuple[NDArray, NDArray]:
    """Per-candidate factors ``[cos kb; sin kb]`` and ``[cos 2kb; sin 2kb]``, ``b = omega_f lambda_1`` (float32)."""
    beta = (omega[1:, None] * pitch_1) * k_all[None, :]  # (F - 1, K)
    single = np.concatenate([np.cos(beta), np.sin(beta)]).astype(np.float32)
    double = np.concatenate([np.cos(2 * beta), np.sin(2 * beta)]).astype(np.float32)
    return single, double


def _candidate_costs(further: NDArray, amplitude: NDArray, a: NDArray, tables: tuple[NDArray, NDArray]) -> NDArray[np.float32]:
    """``RSS_k - sum V^2 - A^2 (F - 1) / 2`` for every pixel (rows) and candidate (columns).

    ``sum_f (V_f - A cos t_fk)^2 = sum V^2 - 2 A sum_f V_f cos t_fk + A^2 sum_f cos^2 t_fk`` with
    ``t_fk = a_f + k b_f``; ``cos t = cos a cos kb - sin a sin kb`` and
    ``cos^2 t = 1/2 + 1/2 (cos 2a cos 2kb - sin 2a sin 2kb)``: one matrix product of per-pixel
    features (the amplitude folded in) with the per-candidate tables.
    """
    single, double = tables
    amp = amplitude.astype(np.float32)
    ca, sa = np.cos(a), np.sin(a)
    va = (np.float32(-2.0) * amp) * further
    half_a2 = np.float32(0.5) * amp * amp
    # cos 2a = 2 cos^2 a - 1, sin 2a = 2 sin a cos a
    features = np.concatenate([va * ca, -va * sa, half_a2 * (np.float32(2.0) * ca * ca - np.float32(1.0)), -half_a2 * (np.float32(2.0) * sa * ca)])
    return features.T @ np.concatenate([single, double])


def _pair_chi2(further: NDArray, amplitude: NDArray, a: NDArray, omega: NDArray, pitch_1: float, pix: NDArray, k: NDArray) -> NDArray[np.float32]:
    """The exact statistic of step 2 for (pixel, candidate) pairs: the residual of all F + 2
    images at candidate ``k`` of pixel ``pix``, off the tangent space of (O, A, u).

    The model columns are ``1``, ``c_f = cos t_f`` (amplitude) and ``s_f = -rho_f sin t_f``
    (coordinate, per unit ``A omega_1``; ``rho_f = omega_f / omega_1``). The 3 shifts are fitted
    exactly (zero residual) and add ``diag(3, 3/2, 3/2)`` to the normal matrix (equal shifts:
    their cross sums vanish); the 3 x 3 normal equations are solved in closed form.
    """
    if pix.size == 0:
        return np.zeros(0, np.float32)
    # k b reaches thousands of radians: add and reduce in float64, then work in float32
    theta = np.remainder(a[:, pix] + (omega[1:, None] * pitch_1) * k[None, :], TWO_PI).astype(np.float32)
    c = np.cos(theta)
    s = (-(omega[1:, None] / omega[0])).astype(np.float32) * np.sin(theta)
    r = further[:, pix] - amplitude[pix] * c
    count = r.shape[0]
    n00, n01, n02 = float(count + 3), c.sum(axis=0), s.sum(axis=0)
    n11, n12, n22 = 1.5 + np.einsum("fp,fp->p", c, c), np.einsum("fp,fp->p", c, s), 1.5 + np.einsum("fp,fp->p", s, s)
    b0, b1, b2 = r.sum(axis=0), np.einsum("fp,fp->p", c, r), np.einsum("fp,fp->p", s, r)
    # b^T N^-1 b with the adjugate of the symmetric N
    a00, a01, a02 = n11 * n22 - n12 * n12, n02 * n12 - n01 * n22, n01 * n12 - n02 * n11
    a11, a12, a22 = n00 * n22 - n02 * n02, n01 * n02 - n00 * n12, n00 * n11 - n01 * n01
    det = n00 * a00 + n01 * a01 + n02 * a02
    quad = (a00 * b0 * b0 + a11 * b1 * b1 + a22 * b2 * b2 + 2.0 * (a01 * b0 * b1 + a02 * b0 * b2 + a12 * b1 * b2)) / det
    return np.maximum(np.einsum("fp,fp->p", r, r) - quad, 0.0)


def _checked_stack(images: NDArray, expected: int) -> NDArray:
    stack = np.asarray(images)
    if stack.ndim != 3:
        raise InputDataError(f"micro phase shifting images must be a (M, H, W) stack of single-channel images, got shape {stack.shape}")
    if stack.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise InputDataError(f"micro phase shifting images must be uint8, uint16 or float, got {stack.dtype}")
    if stack.shape[0] != expected:
        raise InputDataError(f"wrong image count: micro phase shifting with {expected - 2} pitches needs {expected} images, got {stack.shape[0]}")
    if stack.shape[1] == 0 or stack.shape[2] == 0:
        raise InputDataError(f"micro phase shifting images are empty ({stack.shape[2]}x{stack.shape[1]} pixels)")
    return stack


def _checked_axis_length(axis_length_px) -> int:
    if isinstance(axis_length_px, bool) or not isinstance(axis_length_px, (int, np.integer)) or axis_length_px < 1:
        raise ConfigError(f"axis_length_px must be a positive integer (projector pixels along the coded axis), got {axis_length_px!r}")
    return int(axis_length_px)


def candidate_separation(pitches_px: tuple[float, ...], axis_length_px: int, step_px: float = 0.25) -> float:
    """Smallest distance (units of the amplitude ``A``) between the further images' predicted values
    at a coordinate ``u`` and at ``u + m lambda_1``, over the axis and all ``m != 0``.

    ``u`` runs over ``[-0.5, L - 0.5)`` in steps of ``step_px``; a quarter pixel is a
    ``pi / 32`` phase step at a pitch of 16, fine enough to find the minima.
    """
    return _separation_cached(_checked_pitches(pitches_px), _checked_axis_length(axis_length_px), float(step_px))


@lru_cache(maxsize=16)
def _separation_cached(pitches: tuple[float, ...], length: int, step_px: float) -> float:
    omega = TWO_PI / np.asarray(pitches)
    offsets = _offsets(len(pitches) - 1)
    periods = math.ceil(length / pitches[0])
    if periods < 2:
        return math.inf  # one period covers the axis: nothing to tell apart
    u = np.arange(-0.5, length - 0.5, step_px)
    cos_u = np.cos(omega[1:] * u[:, None] + offsets)  # (U, F - 1)
    theta = omega[1:] * u[:, None] + offsets
    smallest = math.inf
    for m in range(1, periods + 1):  # one shift at a time keeps the work arrays (U, F - 1)
        inside = u + pitches[0] * m < length - 0.5
        if not inside.any():
            break
        diff = np.cos(theta[inside] + omega[1:] * pitches[0] * m) - cos_u[inside]
        smallest = min(smallest, float(np.einsum("uf,uf->u", diff, diff).min()))
    return math.sqrt(smallest)


def micro_pitches(axis_length_px: int, mean_pitch_px: float = 16.0, count: int = 10, band_fraction: float = 0.15, trials: int = 64, seed: int = 0) -> tuple[float, ...]:
    """A set of ``count`` pitches for an axis of ``axis_length_px`` projector pixels.

    The first pitch (the 3-step one) is ``mean_pitch_px``; the others are drawn uniformly in
    frequency from the band ``mean frequency * (1 -+ band_fraction / 2)``, ``trials`` times with
    a fixed seed, and the set whose :func:`candidate_separation` is largest is returned
    (Gupta and Nayar's rule: a narrow band around the mean, pitches that keep every column's
    phase vector far from every other's). The default band, +-7.5 % of the frequency, keeps the
    pitches of a 16-pixel mean between 14.9 and 17.3 pixels, so global light and defocus treat
    them alike.

    Raises
    ------
    ConfigError
        Bad arguments, or no set in the band separates the periods of the axis.
    """
    length = _checked_axis_length(axis_length_px)
    if not (math.isfinite(mean_pitch_px) and mean_pitch_px > 2.0):
        raise ConfigError(f"mean_pitch_px must be a finite number above 2 projector pixels, got {mean_pitch_px!r}")
    if isinstance(count, bool) or not isinstance(count, int) or count < 2:
        raise ConfigError(f"count must be an integer >= 2 pitches, got {count!r}")
    if not 0.0 < band_fraction < 1.0:
        raise ConfigError(f"band_fraction must be in (0, 1), got {band_fraction!r}")
    rng = np.random.default_rng(seed)
    mean_frequency = 1.0 / mean_pitch_px
    best, best_separation = None, -1.0
    for _ in range(max(1, int(trials))):
        frequency = mean_frequency * (1.0 + band_fraction * rng.uniform(-0.5, 0.5, count - 1))
        pitches = (float(mean_pitch_px),) + tuple(float(p) for p in np.round(1.0 / frequency, 3))
        if len(set(pitches)) != count or any(p <= 2.0 for p in pitches):
            continue
        separation = candidate_separation(pitches, length, step_px=0.5)
        if separation > best_separation:
            best, best_separation = pitches, separation
    if best is None or best_separation < _MIN_SEPARATION:
        raise ConfigError(f"no set of {count} pitches within {band_fraction:.0%} of {mean_pitch_px} px separates the periods of a {length}-pixel axis; widen band_fraction or add pitches")
    return best
