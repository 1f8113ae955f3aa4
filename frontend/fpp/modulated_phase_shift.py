"""Modulated phase shifting (Chen, Seidel and Lensch, "Modulated phase-shifting for 3D scanning", CVPR 2008).

Each coded sinusoid is multiplied by a high-frequency sinusoidal carrier along the other
projector axis, and the carrier is shifted in ``N_c`` steps for each of the ``N`` coded steps.
Global light (interreflections, subsurface scattering) reaches a point from many others and
averages the carrier out (Nayar et al. 2006): it is the same in the ``N_c`` images of one coded
step, however strongly it carries the coded sinusoid. Demodulating the carrier per coded step
therefore keeps the direct light alone, as ``N`` ordinary phase-shift samples.

Patterns (image ``i = n N_c + m``: coded step ``n`` major, carrier step ``m`` minor)
-------------------------------------------------------------------------------------
``P_i = L_n M_m`` with ``L_n = 0.5 + 0.5 cos(phi - 2 pi n / N)`` (``phi`` the coded phase,
``2 pi u / lambda`` for a coded pitch ``lambda``) and ``M_m = 0.5 + 0.5 cos(2 pi v / lambda_c -
2 pi m / N_c)`` (``v`` the coordinate along the other axis, pixel-centre convention: projector
pixel ``j`` is centred at ``v = j``, carrier phase 0 there).

Demodulation (per pixel, a fixed linear map of the images and one normalisation)
-------------------------------------------------------------------------------
With direct light ``d_n`` (of coded step ``n``) and global light ``g_n``, image ``(n, m)`` is
``g_n + d_n / 2 + (d_n / 2) cos(psi - 2 pi m / N_c)``, ``psi`` the pixel's carrier phase. The
carrier's first harmonic ``C_n = sum_m I_nm e^{i 2 pi m / N_c} = (N_c / 4) d_n e^{i psi}`` holds
no ``g_n``. The carrier phase is the same for every coded step, and ``sum_n d_n > 0``, so it is
taken from ``sum_n C_n`` (strong: all images), and each step's direct sample is the projection

    D_n = (4 / N_c) Re(C_n e^{-i psi}) = d_n + noise,

linear in the images (unlike ``|C_n|``, whose noise is Rician and biases dark samples upward).
``D_n = a + b cos(phi - 2 pi n / N)`` is then N-step phase shifting (eq. 2 of
:mod:`frontend.fpp.phase`): ``phi = atan2(sum D_n sin, sum D_n cos)`` in ``[0, 2 pi)``,
``b = (2 / N) |.|``, ``a = mean D_n``. ``a`` and ``b`` are the *direct* light's offset and
amplitude (for a pattern peak of ``A`` grey levels of direct light, ``a = b = A / 2``).

Noise
-----
With image noise ``sigma_I``, ``Re(C_n e^{-i psi})`` has variance ``sigma_I^2 N_c / 2`` (for
``N_c >= 3``), so ``sigma_D = (4 / N_c) sigma_I sqrt(N_c / 2) = sigma_I sqrt(8 / N_c)``, and
N-step phase shifting of the ``D_n`` gives ``sigma_phi = sqrt(2 / N) sigma_D / b``:

    sigma_phi = sigma_gain * sigma_I / b,    sigma_gain = 4 / sqrt(N N_c).

(The carrier-phase estimate's error scales all ``D_n`` alike and leaves ``phi`` unchanged to
first order.) The price of the separation: for ``N = N_c = 3`` the gain is 4/3, against
``sqrt(2/3) = 0.82`` for plain 3-step phase shifting of the same amplitude, with three times the
images.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError, InputDataError

TWO_PI = 2.0 * math.pi
# Pixels per band of the demodulation: its float64 work arrays (M + 8 rows of this) stay small.
_BAND_PIXELS = 1 << 16


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


class ModulatedPhaseShift:
    """Modulated phase shifting codec (see the module docstring).

    Parameters
    ----------
    steps : int
        ``N >= 3`` shifts of the coded sinusoid.
    carrier_steps : int
        ``N_c >= 3`` shifts of the carrier (three unknowns per coded step: global plus direct
        offset, carrier amplitude, carrier phase).
    carrier_pitch_px : float
        Carrier pitch along the other projector axis, projector pixels, above 2 (the
        projector's Nyquist limit). It must be short against the distance over which global
        light mixes, and long enough for the camera to resolve.
    """

    def __init__(self, steps: int, carrier_steps: int, carrier_pitch_px: float) -> None:
        for name, value in (("steps", steps), ("carrier_steps", carrier_steps)):
            if not _is_int(value) or value < 3:
                raise ConfigError(f"modulated phase shifting {name} must be an integer >= 3, got {value!r}")
        if isinstance(carrier_pitch_px, bool) or not isinstance(carrier_pitch_px, (int, float, np.integer, np.floating)) or not math.isfinite(carrier_pitch_px) or carrier_pitch_px <= 2.0:
            raise ConfigError(f"modulated phase shifting carrier_pitch_px must be a finite number above 2 projector pixels (the projector's Nyquist limit), got {carrier_pitch_px!r}")
        self.steps = int(steps)
        self.carrier_steps = int(carrier_steps)
        self.carrier_pitch_px = float(carrier_pitch_px)
        self._weights = self._demodulation_weights()

    @property
    def image_count(self) -> int:
        """``N N_c`` images per frame."""
        return self.steps * self.carrier_steps

    @property
    def sigma_gain(self) -> float:
        """``4 / sqrt(N N_c)``: the phase's 1-sigma error is this times ``sigma_I / b`` (rad)."""
        return 4.0 / math.sqrt(self.steps * self.carrier_steps)

    def profile(self, image: int, coded_phase_rad: NDArray, carrier_coord_px: NDArray) -> NDArray[np.float64]:
        """Continuous value in [0, 1] of pattern ``image`` at coded phase ``coded_phase_rad`` and
        carrier-axis coordinate ``carrier_coord_px`` (projector pixels)."""
        if not _is_int(image) or not 0 <= image < self.image_count:
            raise ConfigError(f"modulated phase shifting image index {image!r} out of range: the set has {self.image_count} images (0..{self.image_count - 1})")
        n, m = divmod(int(image), self.carrier_steps)
        coded = 0.5 + 0.5 * np.cos(np.asarray(coded_phase_rad, np.float64) - TWO_PI * n / self.steps)
        carrier = 0.5 + 0.5 * np.cos(TWO_PI * np.asarray(carrier_coord_px, np.float64) / self.carrier_pitch_px - TWO_PI * m / self.carrier_steps)
        return coded * carrier

    def _demodulation_weights(self) -> NDArray[np.float64]:
        """(6, M): carrier harmonic (cos, sin) summed over the coded steps, and weighted by
        ``sin delta_n`` and by ``cos delta_n``."""
        delta = TWO_PI * np.arange(self.steps) / self.steps
        carrier = TWO_PI * np.arange(self.carrier_steps) / self.carrier_steps
        rows = []
        for coded in (np.ones(self.steps), np.sin(delta), np.cos(delta)):
            rows.append(np.outer(coded, np.cos(carrier)).ravel())
            rows.append(np.outer(coded, np.sin(carrier)).ravel())
        return np.array(rows)

    def wrapped_phase(self, images: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """Demodulate the carrier and phase-shift the direct light (see the module docstring).

        Parameters
        ----------
        images : (N N_c, H, W) uint8, uint16 or float array
            Step-major, carrier step minor (the order of :meth:`profile`).

        Returns
        -------
        phase_rad : (H, W) float32 in [0, 2 pi)
            Coded phase, ``D_n = a + b cos(phi - 2 pi n / N)`` (forward, origin 0).
        modulation_grey : (H, W) float32
            ``b`` of the direct light.
        background_grey : (H, W) float32
            ``a`` of the direct light (global and ambient light removed).

        Raises
        ------
        InputDataError
            Wrong image count, shape or pixel type.
        """
        stack = np.asarray(images)
        if stack.ndim != 3:
            raise InputDataError(f"modulated phase shifting images must be a (M, H, W) stack of single-channel images, got shape {stack.shape}")
        if stack.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
            raise InputDataError(f"modulated phase shifting images must be uint8, uint16 or float, got {stack.dtype}")
        if stack.shape[0] != self.image_count:
            raise InputDataError(
                f"wrong image count: modulated phase shifting with {self.steps} steps x {self.carrier_steps} carrier steps "
                f"needs {self.image_count} images, got {stack.shape[0]}"
            )
        if stack.shape[1] == 0 or stack.shape[2] == 0:
            raise InputDataError(f"modulated phase shifting images are empty ({stack.shape[2]}x{stack.shape[1]} pixels)")
        h, w = stack.shape[1:]
        flat = stack.reshape(self.image_count, h * w)
        out = [np.empty(h * w, np.float32) for _ in range(3)]
        for p0 in range(0, h * w, _BAND_PIXELS):
            p1 = min(h * w, p0 + _BAND_PIXELS)
            phase, modulation, background = self._demodulate(flat[:, p0:p1].astype(np.float64))
            out[0][p0:p1], out[1][p0:p1], out[2][p0:p1] = phase, modulation, background
        phase = out[0].reshape(h, w)
        phase[phase >= np.float32(TWO_PI)] = 0.0  # float32 rounding of phases a hair below 2 pi
        return phase, out[1].reshape(h, w), out[2].reshape(h, w)

    def _demodulate(self, band: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """(M, n) images -> phase, b, a of the direct samples ``D_n``."""
        cc, cs, scc, scs, ccc, ccs = self._weights @ band
        norm = np.hypot(cc, cs)
        safe = np.where(norm > 0, norm, 1.0)
        cos_psi, sin_psi = np.where(norm > 0, cc / safe, 1.0), np.where(norm > 0, cs / safe, 0.0)
        scale = 4.0 / self.carrier_steps
        s = scale * (cos_psi * scc + sin_psi * scs)
        c = scale * (cos_psi * ccc + sin_psi * ccs)
        phase = np.arctan2(s, c) % TWO_PI
        modulation = (2.0 / self.steps) * np.hypot(s, c)
        background = scale * norm / self.steps
        return phase, modulation, background
