"""Decoding a fringe-set capture (:class:`frontend.fpp.fringe_sets.FringeSetSpec`).

:class:`FringeSetDecoder` returns the :class:`frontend.fpp.phase.DecodeResult` of every other
decoder: for ``axis="both"`` the projector column in ``u_projector_px`` and the row in
``v_projector_px``; for one coded axis its coordinate in ``u_projector_px``. ``wrapped_phase``,
``modulation``, ``fringe_order`` and ``pitch_px`` are those of the finest set of the coded axis
(columns for both), ``texture`` its background.

Wrapped phase per set
---------------------
* ``phase_shift``: least-squares N-step phase shifting (eq. 2 of :mod:`frontend.fpp.phase`),
  the steps reordered so that the shift direction and the whole steps of the phase origin
  vanish, the rest of the origin subtracted. Phase noise ``sqrt(2 / N) sigma_I / b``.
* ``two_plus_one`` (Zhang and Yau 2006/2007): ``S = I_0 - I_2``, ``C = I_1 - I_2``,
  ``phi = atan2(s S, C)``, ``b = sqrt(S^2 + C^2)``, ``a = I_2``. ``S`` and ``C`` share the
  flat image's noise (variance ``2 sigma_I^2`` each, covariance ``sigma_I^2``), so first-order
  propagation gives ``sigma_phi = sqrt(2 - sin 2 phi) sigma_I / b``: a gain between 1 and
  ``sqrt 3``, ``sqrt 2`` RMS over the phase (3-step least squares: ``sqrt(2/3) = 0.82``).
* ``modulated_phase_shift``: the codec's ``wrapped_phase``, gain ``sigma_gain``.
* ``micro_phase_shift``: the codec's absolute coordinate, ``coordinate_sigma_gain_px sigma_I / b``.

Unwrapping and the fringe-order check
-------------------------------------
Each level of a hierarchical or heterodyne chain (:meth:`FringeSetSpec.plans`) takes the
absolute phase of the previous level ``Phi_prev`` (``P_prev`` periods across the axis) and the
wrapped phase ``phi`` of its own (``P``): ``x = (Phi_prev P / P_prev - phi) / 2 pi``,
``K = round(x)``, ``Phi = phi + 2 pi K``. The rounding residual ``e = x - K`` has the standard
deviation ``sigma_e = sqrt((P / P_prev sigma_prev)^2 + sigma_phi^2) / 2 pi`` (periods) from the
two levels' phase noise (a beat's noise is the root sum of squares of its two phases'). A pixel
is ``bad_order`` where ``|e| > z sigma_e`` with ``z = 4.89``, the two-sided normal quantile of
a per-pixel, per-level probability of 1e-6 (about one false alarm per megapixel level), or
where ``|e| > 1/4`` (beyond a quarter period a wrong order is as likely as the right one under
any noise model), and where the coordinate falls outside the projector (``[-0.5, L - 0.5]``).
A coarsest level whose pitch exceeds the axis puts its unused phase range half before the
projector and half after it, so noise near either end does not wrap the phase to the other; a
coarsest level of exactly one period, whose phase noise does wrap near the ends, puts the next
level a whole axis away: its order is moved back by the (integer) pitch ratio where that level
places the pixel beyond the projector's edge by more than ``z`` of its own noise; within ``z`` of
its noise from either edge, on either side, either end could be right and the pixel is ``bad_order``. A one-period set alone (no level
after it) marks ``bad_order`` the pixels whose phase lies within ``z`` of its noise from the wrap.
Gray code: the bits are binarised against their inverses, the references' mean or the phase
set's background and decoded as in :mod:`frontend.fpp.unwrapping` (plain or complementary);
an order beyond the stripes of the axis is ``bad_order``.

Spatial unwrapping
------------------
An axis whose only set asks for it (``unwrapping: spatial``) is unwrapped across the image:
the wrapped phase of the valid pixels (not low modulation, saturated or shadow on that axis)
goes to ``skimage.restoration.unwrap_phase`` (Herraez et al. 2002: edges sorted by the second
differences of their pixels, most reliable joined first), which unwraps every 4-connected
region of valid pixels on its own. A region's phase is then right up to one whole number ``k``
of periods, which the images do not hold. ``k`` is fixed per region by the projector's extent:
every pixel's coordinate ``c + k lambda`` must lie in ``[-0.5, L - 0.5]`` give or take ``z``
of its noise (``z`` = 4.89 as above), which leaves the integers
``k_low = ceil(max (-0.5 - z sigma_c - c) / lambda)`` to ``k_high = floor(min (L - 0.5 + z sigma_c - c) / lambda)``.
Exactly one: it is taken. None: the region's unwrapped phase spans more than the projector (a
wrong unwrapping path, e.g. across a depth edge), and the region is ``bad_order``. Several (the
region sees less than ``L - lambda`` of the axis, the common case): the region is
``bad_order`` unless it holds the camera's centre pixel ``(W // 2, H // 2)`` and the set gives
``centre_coordinate_px``, the projector coordinate that pixel sees (from the rig's geometry at
the working distance): ``k = round((centre_coordinate_px - c_centre) / lambda)``, right when
the anchor is within half a pitch of the truth; an anchor that puts the region beyond the
projector is refused as ``bad_order``. A region with no pixel whose whole 3x3 neighbourhood is
valid is ``bad_order`` whatever its extent: Herraez's reliability is the second difference over
that neighbourhood, so such a region (a line or speckle, typically mixed pixels at an edge) is
joined in no reliable order. Limits: a region that crosses a depth edge whose true phase jump
differs from its wrapped jump by whole periods (a jump of half a period or more) is unwrapped
with a wrong relative order on one side and nothing in the images shows it, unless its extent
then exceeds the projector; surfaces must be continuous within each region.

The image noise ``sigma_I`` is measured on the finest set of the coded axis
(:func:`frontend.fpp.phase_noise.estimate_image_noise_grey`, over the pixels without
low modulation, saturation or shadow), or on the axis's finest N >= 4 phase-shift set when the
finest is of another codec; a set without N equal shifts alone uses the second-difference
estimator on three of its images.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, stats

from fpp_graph.errors import ConfigError
from frontend.config import DecodeConfig
from frontend.fpp.fringe_unwrapping import AxisPlan
from frontend.fpp.phase import (
    INVALID_REASONS,
    DecodeResult,
    _as_stack,
    compute_wrapped_phase,
    no_valid_pixel_error,
)
from frontend.fpp.phase_noise import estimate_image_noise_grey, phase_sigma_rad
from frontend.fpp.unwrapping import order_from_gray, read_gray_code
from frontend.fpp.wrapped_phase import TWO_PI, Scratch

if TYPE_CHECKING:  # the spec builds its decoder (FringeSetSpec.make_decoder): types only here
    from frontend.fpp.fringe_sets import FringeSet, FringeSetSpec

log = logging.getLogger(__name__)

#: Per-pixel, per-level probability that a correct fringe order is flagged ``bad_order``.
ORDER_FALSE_ALARM_PROBABILITY = 1e-6
#: Its two-sided standard-normal quantile (4.89).
ORDER_RESIDUAL_QUANTILE = float(stats.norm.isf(0.5 * ORDER_FALSE_ALARM_PROBABILITY))
#: Beyond a quarter period the rounding of a fringe order is not trusted whatever the noise.
MAX_ORDER_RESIDUAL_PERIODS = 0.25


class SetPhase(NamedTuple):
    """One set's decoded maps: ``phase_rad`` wrapped in [0, 2 pi) with the origin removed (or the
    absolute coordinate for micro phase shifting), ``modulation_grey``, ``background_grey`` and
    the gain of its noise (scalar or per pixel): sigma = gain sigma_I / b."""

    phase_rad: NDArray[np.float32]
    modulation_grey: NDArray[np.float32]
    background_grey: NDArray[np.float32]
    gain: float | NDArray[np.float32]


class AxisResult(NamedTuple):
    coordinate_px: NDArray[np.float32]
    noise_px: NDArray[np.float32]
    order: NDArray[np.int64]
    reasons: dict[str, NDArray[np.bool_]]


def wrap_rad(phase: NDArray[np.float32]) -> NDArray[np.float32]:
    """Phase taken into [0, 2 pi) (float32 rounding can give exactly 2 pi: that is 0)."""
    out = np.mod(phase, np.float32(TWO_PI)).astype(np.float32, copy=False)
    out[out >= np.float32(TWO_PI)] = 0.0
    return out


def step_order(phase_set: FringeSet, by_step: list[int]) -> tuple[list[int], float]:
    """Image indices in eq. 1's step order (forward, origin 0) and the origin left to subtract.

    Step ``s`` shows ``cos(phi + phi_0 -+ 2 pi s / N)``; with ``phi_0 = m 2 pi / N + r`` it is
    step ``n = s - m`` (forward) or ``n = -s - m`` (reverse) of the phase ``phi + r``.
    """
    n = phase_set.steps
    m = round(phase_set.phase_origin_rad * n / TWO_PI)
    residual = float(np.angle(np.exp(1j * (phase_set.phase_origin_rad - m * TWO_PI / n))))
    if phase_set.shift_direction == "forward":
        return [by_step[(k + m) % n] for k in range(n)], residual
    return [by_step[(-k - m) % n] for k in range(n)], residual


class FringeSetDecoder:
    """Decoder of a :class:`FringeSetSpec` for one projector size (see the module docstring).

    Parameters
    ----------
    spec : FringeSetSpec
    projector_width, projector_height : int
        Projector size in pixels (axis lengths: pitches from ``periods``, coverage checks).
    config : DecodeConfig, optional
        Validity thresholds; the defaults when None.
    """

    def __init__(self, spec: FringeSetSpec, projector_width: int, projector_height: int, config: DecodeConfig | None = None) -> None:
        self.spec = spec
        self.plans = spec.check_projector(projector_width, projector_height)
        self.config = config if config is not None else DecodeConfig()
        self.lengths = {"columns": int(projector_width), "rows": int(projector_height)}
        self.image_count = spec.image_count()
        self._indices = {i: spec.set_image_indices(i) for i in range(len(spec.fringe_sets))}
        self._codecs = {
            i: s.codec_object(spec.set_name(i)) for i, s in enumerate(spec.fringe_sets) if s.codec in ("modulated_phase_shift", "micro_phase_shift")
        }
        for i, codec in self._codecs.items():
            if codec.image_count != len(self._indices[i]):
                raise ConfigError(f"fringe set {spec.set_name(i)}: its codec has {codec.image_count} images, the set {len(self._indices[i])}")
        self.coded_plan = self.plans[spec.coded_axis]
        finest = spec.fringe_sets[self.coded_plan.finest]
        self.pitch_px = finest.pitch(self.lengths[spec.coded_axis])

    def _describe(self) -> str:
        sets = ", ".join(f"{self.spec.set_name(i)} ({s.axis}, {s.image_count()} images)" for i, s in enumerate(self.spec.fringe_sets))
        return f"fringe-set capture [{sets}]"

    # ------------------------------------------------------------------ per set
    def set_phase(self, i: int, stack: NDArray) -> SetPhase:
        """Decode fringe set ``i`` of a checked (M, H, W) stack."""
        s = self.spec.fringe_sets[i]
        by_step = self._indices[i]
        if s.codec == "phase_shift":
            index, residual = step_order(s, by_step)
            phi, mod, background = compute_wrapped_phase(stack[index])
            if residual:
                phi = wrap_rad(phi - np.float32(residual))
            return SetPhase(phi, mod, background, math.sqrt(2.0 / s.steps))
        if s.codec == "two_plus_one":
            return self._two_plus_one(s, stack[by_step])
        codec = self._codecs[i]
        if s.codec == "modulated_phase_shift":
            phi, mod, background = codec.wrapped_phase(stack[by_step].astype(np.float32))
            phi = wrap_rad(np.asarray(phi, np.float32) - np.float32(s.phase_origin_rad))
            return SetPhase(phi, np.asarray(mod, np.float32), np.asarray(background, np.float32), float(codec.sigma_gain))
        coordinate, mod, background, gain_px = codec.decode(stack[by_step].astype(np.float32), self.lengths[s.axis])
        return SetPhase(np.asarray(coordinate, np.float32), np.asarray(mod, np.float32), np.asarray(background, np.float32), float(gain_px))

    @staticmethod
    def _two_plus_one(s: FringeSet, images: NDArray) -> SetPhase:
        flat = images[2].astype(np.float32)
        sin_part = images[0].astype(np.float32) - flat
        cos_part = images[1].astype(np.float32) - flat
        sign = np.float32(1.0 if s.shift_direction == "forward" else -1.0)
        mod, phi = cv2.cartToPolar(cos_part, sign * sin_part)
        # sigma_phi^2 b^2 / sigma_I^2 = 2 - sin 2 phi = 2 - 2 S C / b^2 (S, C share the flat image)
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = np.sqrt(np.float32(2.0) - np.float32(2.0) * sin_part * cos_part / (mod * mod)).astype(np.float32)
        gain[~np.isfinite(gain)] = math.sqrt(2.0)
        return SetPhase(wrap_rad(phi - np.float32(s.phase_origin_rad)), mod, flat, gain)

    # ------------------------------------------------------------------ decoding
    def decode(self, images: NDArray | Sequence[NDArray], out: DecodeResult | None = None) -> DecodeResult:
        """Decode one capture (M, H, W uint8/uint16 in capture order); ``out`` is accepted for
        the common decoder interface and not reused (fresh maps are returned).

        Raises
        ------
        InputDataError
            Wrong image count, mixed sizes or types, or no valid pixel.
        """
        stack = _as_stack(images, self.image_count, self._describe())
        phases = {i: self.set_phase(i, stack) for i in range(len(self.spec.fringe_sets))}
        screens = {axis: self._screen(plan, phases, stack) for axis, plan in self.plans.items()}
        coded = self.spec.coded_axis
        finest = self.coded_plan.finest
        usable = ~(screens[coded]["low_modulation"] | screens[coded]["saturated"] | screens[coded]["shadow"])
        noise_grey = self._image_noise(finest, stack, usable)
        results = {axis: self._axis(plan, phases, stack, screens[axis], noise_grey) for axis, plan in self.plans.items()}
        return self._result(results, phases[finest], noise_grey, stack.dtype)

    def _image_noise(self, finest: int, stack: NDArray, usable: NDArray[np.bool_]) -> float:
        """sigma_I from the finest set of the coded axis; from the finest N >= 4 phase-shift set of
        that axis when the finest is of another codec (a sinusoid fit's residual is blind to the
        scene and the pattern, while second differences also see a fine carrier or texture)."""
        axis = self.spec.fringe_sets[finest].axis
        fitted = [i for i, s in enumerate(self.spec.fringe_sets) if s.axis == axis and s.codec == "phase_shift" and s.steps >= 4]
        if self.spec.fringe_sets[finest].codec != "phase_shift" and fitted:
            finest = min(fitted, key=lambda i: self.spec.fringe_sets[i].pitch(self.lengths[axis]))
        s = self.spec.fringe_sets[finest]
        if s.codec == "phase_shift":
            index, _ = step_order(s, self._indices[finest])
        else:  # not N equal shifts: the second-difference estimator on three of its images
            index = self._indices[finest][:3]
        return estimate_image_noise_grey(stack[index], usable)

    def _screen(self, plan: AxisPlan, phases: dict[int, SetPhase], stack: NDArray) -> dict[str, NDArray[np.bool_]]:
        """low_modulation (the weakest set), saturated (any fringe image), shadow (finest background)."""
        cfg = self.config
        members = [i for i, s in enumerate(self.spec.fringe_sets) if s.axis == plan.axis]
        low = np.zeros(stack.shape[1:], bool)
        for i in members:
            with np.errstate(invalid="ignore"):
                low |= ~(phases[i].modulation_grey >= np.float32(cfg.min_modulation))
        saturated = np.zeros(stack.shape[1:], bool)
        if cfg.saturation_level <= np.iinfo(stack.dtype).max:
            level = math.ceil(cfg.saturation_level)
            for i in members:
                saturated |= stack[self._indices[i]].max(axis=0) >= level
        shadow = ~(phases[plan.finest].background_grey >= np.float32(cfg.min_background))
        return {"low_modulation": low, "saturated": saturated, "shadow": shadow}

    def _sigma_rad(self, phase: SetPhase, noise_grey: float) -> NDArray[np.float32]:
        if np.isscalar(phase.gain):
            return phase_sigma_rad(phase.modulation_grey, 1, noise_grey, gain=float(phase.gain))
        return phase_sigma_rad(phase.modulation_grey, 1, noise_grey, gain=1.0) * phase.gain

    def _axis(self, plan: AxisPlan, phases: dict[int, SetPhase], stack: NDArray, screen: dict, noise_grey: float) -> AxisResult:
        length = self.lengths[plan.axis]
        finest = phases[plan.finest]
        pitch = self.spec.fringe_sets[plan.finest].pitch(length)
        if plan.scheme == "micro":
            coordinate = finest.phase_rad.copy()
            noise = self._sigma_rad(finest, noise_grey)
            order = np.zeros(coordinate.shape, np.int64)
            bad = ~np.isfinite(coordinate)
        else:
            if plan.scheme == "gray":
                absolute, order, bad = self._gray(plan, finest, stack)
            elif plan.scheme == "spatial":
                valid = ~(screen["low_modulation"] | screen["saturated"] | screen["shadow"])
                anchor = self.spec.fringe_sets[plan.finest].centre_coordinate_px
                absolute, order, bad = unwrap_spatially(finest.phase_rad, self._sigma_rad(finest, noise_grey), valid, pitch, length, anchor)
            else:
                absolute, order, bad = self._chain(plan, phases, noise_grey)
            coordinate = (absolute * np.float32(pitch / TWO_PI)).astype(np.float32)
            noise = self._sigma_rad(finest, noise_grey) * np.float32(pitch / TWO_PI)
        with np.errstate(invalid="ignore"):
            bad |= ~((coordinate >= -0.5) & (coordinate <= length - 0.5))
        return AxisResult(coordinate, noise.astype(np.float32), order, {**screen, "bad_order": bad})

    def _chain(self, plan: AxisPlan, phases: dict[int, SetPhase], noise_grey: float) -> tuple[NDArray, NDArray, NDArray]:
        """Hierarchical or heterodyne unwrapping with the statistical order check (module docstring)."""
        made: dict[tuple, tuple[NDArray, NDArray]] = {}

        def phase_of(recipe: tuple) -> tuple[NDArray, NDArray]:
            if recipe not in made:
                if recipe[0] == "set":
                    p = phases[recipe[1]]
                    made[recipe] = (p.phase_rad, self._sigma_rad(p, noise_grey))
                else:
                    (phi_a, s_a), (phi_b, s_b) = phase_of(recipe[1]), phase_of(recipe[2])
                    made[recipe] = (wrap_rad(phi_a - phi_b), np.hypot(s_a, s_b))
            return made[recipe]

        periods_prev, recipe = plan.levels[0]
        absolute, sigma = phase_of(recipe)
        # One period exactly: the phase is periodic over the axis, so noise wraps pixels near its
        # ends to the other end; the next level's order is then known modulo the pitch ratio.
        periodic = abs(periods_prev - 1.0) < 1e-9
        if periods_prev < 1:
            # the projector spans phases [-pi / lambda, 2 pi P - pi / lambda]; split the unused rest
            length = self.lengths[plan.axis]
            split = math.pi * (1.0 + periods_prev) - math.pi * periods_prev / length
            absolute = np.where(absolute > np.float32(split), absolute - np.float32(TWO_PI), absolute)
        bad = np.zeros(absolute.shape, bool)
        order = np.zeros(absolute.shape, np.float32)
        if periodic and len(plan.levels) == 1:
            # one period alone: within z of its noise from the wrap, a pixel at either end of the
            # projector reads the same phase; nothing else tells the ends apart
            with np.errstate(invalid="ignore"):
                bad |= np.minimum(absolute, np.float32(TWO_PI) - absolute) < np.float32(ORDER_RESIDUAL_QUANTILE) * sigma
        for periods, recipe in plan.levels[1:]:
            wrapped, sigma_level = phase_of(recipe)
            ratio = np.float32(periods / periods_prev)
            x = (absolute * ratio - wrapped) * np.float32(1.0 / TWO_PI)
            order = np.rint(x)
            residual = np.abs(x - order)
            sigma_residual = np.hypot(ratio * sigma, sigma_level) * np.float32(1.0 / TWO_PI)
            if periodic and float(ratio).is_integer():
                bad |= self._undo_wrap(order, wrapped, sigma_level, float(ratio), self.lengths[plan.axis])
            periodic = False
            with np.errstate(invalid="ignore"):
                bad |= (residual > np.float32(ORDER_RESIDUAL_QUANTILE) * sigma_residual) | ~(residual <= np.float32(MAX_ORDER_RESIDUAL_PERIODS))
            absolute = wrapped + np.float32(TWO_PI) * order
            sigma, periods_prev = sigma_level, periods
        return absolute.astype(np.float32), np.nan_to_num(order, nan=-1).astype(np.int64), bad

    @staticmethod
    def _undo_wrap(order: NDArray, wrapped: NDArray, sigma_rad: NDArray, periods: float, length: int) -> NDArray[np.bool_]:
        """Orders of the level after a one-period level whose phase noise wrapped it to the other
        end: the coordinate then lies a whole axis beyond the projector. Moved back where it lies
        beyond the projector's edge by more than ``z`` of its own noise (a level-noise excursion
        that far has the order check's probability). Returns the pixels within ``z`` of their
        noise from either edge, on either side of it: there either end could be right (a pixel
        half a pixel inside the last column, wrapped, lands just inside the first), so they are
        ``bad_order``."""
        position = order + wrapped * np.float32(1.0 / TWO_PI)  # periods of this level
        half_pixel = np.float32(0.5 * periods / length)
        margin = np.float32(ORDER_RESIDUAL_QUANTILE / TWO_PI) * sigma_rad
        with np.errstate(invalid="ignore"):
            ambiguous = (np.abs(position + half_pixel) <= margin) | (np.abs(position - (np.float32(periods) - half_pixel)) <= margin)
            order[position > np.float32(periods) - half_pixel + margin] -= np.float32(periods)
            order[position < -half_pixel - margin] += np.float32(periods)
        return ambiguous

    def _gray(self, plan: AxisPlan, finest: SetPhase, stack: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Gray-code (or complementary Gray-code) fringe order of the axis's phase set."""
        code_index, inverse = self.spec.gray_image_indices(plan.axis)
        gray = self.spec.gray_codes[plan.gray]
        h, w = stack.shape[1:]
        work = Scratch(h, w)
        white, black = self.spec.reference_indices()
        if inverse:
            threshold = [stack[i] for i in inverse]
        elif white is not None:
            threshold = ((stack[white].astype(np.uint32) + stack[black]) >> 1).astype(stack.dtype)
        else:
            threshold = np.clip(np.rint(finest.background_grey), 0, np.iinfo(stack.dtype).max).astype(stack.dtype)
        code = read_gray_code(stack, code_index, threshold, work)
        unsigned = order_from_gray("complementary_gray" if gray.complementary else "gray", code, finest.phase_rad, work)
        stripes = math.ceil(self.lengths[plan.axis] / self.spec.fringe_sets[plan.finest].pitch(self.lengths[plan.axis]) - 1e-9)
        bad = unsigned > unsigned.dtype.type(min(stripes - 1, np.iinfo(unsigned.dtype).max))
        order = unsigned.astype(np.int64)
        absolute = finest.phase_rad + np.float32(TWO_PI) * order.astype(np.float32)
        return absolute, order, bad

    # ------------------------------------------------------------------ output
    def _result(self, results: dict[str, AxisResult], finest: SetPhase, noise_grey: float, dtype: np.dtype) -> DecodeResult:
        reasons = {r: np.logical_or.reduce([res.reasons[r] for res in results.values()]) for r in INVALID_REASONS}
        invalid = np.logical_or.reduce(list(reasons.values()))
        h, w = invalid.shape
        counts = {r: int(np.count_nonzero(m)) for r, m in reasons.items()}
        if invalid.all():
            raise no_valid_pixel_error(w, h, counts, self.config, ", or the pattern file does not describe them")
        coded = results[self.spec.coded_axis]
        rows = results.get("rows") if self.spec.axis == "both" else None
        u = np.where(invalid, np.float32(np.nan), coded.coordinate_px).astype(np.float32)
        v = np.where(invalid, np.float32(np.nan), rows.coordinate_px).astype(np.float32) if rows is not None else None
        scheme_is_micro = self.coded_plan.scheme == "micro"
        phase = np.full((h, w), np.nan, np.float32) if scheme_is_micro else finest.phase_rad
        scale = 1.0 if dtype == np.uint8 else 255.0 / self.config.saturation_level
        texture = np.clip(np.rint(finest.background_grey * np.float32(scale)), 0, 255).astype(np.uint8)
        order = np.where(invalid, -1, coded.order).astype(np.int16)
        log.debug("fringe sets: image noise %.2f grey, invalid %s", noise_grey, counts)
        return DecodeResult(
            wrapped_phase=phase, u_projector_px=u, modulation=finest.modulation_grey, texture=texture, mask=~invalid,
            fringe_order=order, invalid_counts=counts, pitch_px=float(self.pitch_px), axis=self.spec.axis, v_projector_px=v,
            u_noise_px=coded.noise_px, v_noise_px=rows.noise_px if rows is not None else None, image_noise_grey=float(noise_grey),
        )


def unwrap_spatially(
    phase_rad: NDArray[np.float32], sigma_rad: NDArray[np.float32], valid: NDArray[np.bool_], pitch_px: float, length_px: int,
    centre_coordinate_px: float | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.bool_]]:
    """Spatial unwrapping of one wrapped phase per region of valid pixels (module docstring).

    Parameters
    ----------
    phase_rad, sigma_rad : (H, W) float32
        Wrapped phase in [0, 2 pi) and its noise, radians.
    valid : (H, W) bool
        Pixels to unwrap.
    pitch_px : float
        Fringe pitch, projector pixels.
    length_px : int
        Projector pixels along the axis.
    centre_coordinate_px : float, optional
        Projector coordinate seen by the camera's centre pixel, within half a pitch.

    Returns
    -------
    absolute_rad : (H, W) float32
        Absolute phase (the wrapped phase where not valid).
    order : (H, W) int64
        Fringe order (-1 where refused, 0 where not valid).
    bad_order : (H, W) bool
        Valid pixels of refused regions.
    """
    from skimage.restoration import unwrap_phase  # loaded when a file asks for spatial unwrapping

    valid = valid & np.isfinite(phase_rad) & np.isfinite(sigma_rad)
    count, labels = cv2.connectedComponents(valid.astype(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    if count <= 1:
        return phase_rad, np.zeros(phase_rad.shape, np.int64), np.zeros(phase_rad.shape, bool)
    unwrapped = np.asarray(unwrap_phase(np.ma.masked_array(phase_rad.astype(np.float64), ~valid)).filled(0.0))
    regions = np.arange(1, count)
    k_low, k_high = _order_range(unwrapped, sigma_rad, labels, regions, pitch_px, length_px)
    interior = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    trusted = np.bincount(labels[interior], minlength=count)[1:] > 0
    offset = np.where(k_low == k_high, k_low, np.nan)
    h, w = phase_rad.shape
    centre = labels[h // 2, w // 2]
    if centre_coordinate_px is not None and centre > 0:
        k = round((centre_coordinate_px - unwrapped[h // 2, w // 2] * pitch_px / TWO_PI) / pitch_px)
        offset[centre - 1] = k if k_low[centre - 1] <= k <= k_high[centre - 1] else np.nan
    offset[~trusted] = np.nan
    region_offset = np.concatenate([[0.0], offset])[labels]
    refused = valid & np.isnan(region_offset)
    absolute = np.where(valid & ~refused, unwrapped + TWO_PI * region_offset, phase_rad).astype(np.float32)
    order = np.rint((absolute.astype(np.float64) - phase_rad) / TWO_PI).astype(np.int64)
    order[refused] = -1
    log.debug(
        "spatial unwrapping: %d regions, %d fixed by the projector's extent, %d refused (%d pixels)",
        count - 1, int(np.count_nonzero(k_low == k_high)), int(np.count_nonzero(np.isnan(offset))), int(np.count_nonzero(refused)),
    )
    return absolute, order, refused


def _order_range(unwrapped_rad: NDArray, sigma_rad: NDArray, labels: NDArray, regions: NDArray, pitch_px: float, length_px: int) -> tuple[NDArray, NDArray]:
    """Per region, the whole periods ``k`` that keep every pixel's coordinate on the projector
    (``[-0.5, L - 0.5]`` widened by ``z`` of its noise): ``k_low..k_high`` (empty when k_low > k_high)."""
    to_px = pitch_px / TWO_PI
    coordinate = unwrapped_rad * to_px
    margin = ORDER_RESIDUAL_QUANTILE * sigma_rad.astype(np.float64) * to_px
    low = ndimage.maximum((-0.5 - margin - coordinate) / pitch_px, labels, regions)
    high = ndimage.minimum((length_px - 0.5 + margin - coordinate) / pitch_px, labels, regions)
    return np.ceil(np.asarray(low)), np.floor(np.asarray(high))
