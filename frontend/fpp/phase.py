"""FPP decoding: least-squares phase retrieval, validity mask, temporal phase unwrapping.

:func:`decode` (or a reusable :class:`Decoder`) turns one frame's captured pattern images into
the wrapped and absolute phase, the projector coordinate of every camera pixel, the fringe
modulation, the texture image and a validity mask. It follows the conventions of
:mod:`frontend.fpp.patterns` (read its docstring); in short:

* eq. 1: ``I_n = a + b cos(phi - delta_n)``, ``delta_n = 2 pi (n - 1) / N``;
* eq. 2: ``phi = atan2(S, C)``, ``S = sum I_n sin delta_n``, ``C = sum I_n cos delta_n``, taken in
  ``[0, 2 pi)``; modulation ``b = (2/N) sqrt(S^2 + C^2)``; background ``a = mean I_n``;
* eq. 3: ``Phi = phi + 2 pi K`` with the fringe order ``K`` from the Gray code, the complementary
  Gray code or the multi-frequency set;
* eq. 8: ``u_p = Phi * lambda / (2 pi)``, ``lambda = W / P`` projector pixels, pixel-centre
  coordinates (projector pixel ``j`` centred at ``u_p = j``). For ``axis="rows"`` the same
  numbers are the projector row ``v_p``.

Fringe order
------------
* Gray code: each bit image is binarised against a per-pixel threshold, the background ``a``
  (or ``(white + black) / 2`` when the set has references), and Gray-decoded to ``K``. A code
  edge lies between projector pixels while the phase jump lies on a pixel centre (half a pixel
  apart), and the camera blurs the edge: plain Gray code makes +-1 order errors along every
  code edge.
* Complementary Gray code (Zhang et al.): the bits plus the extra half-period bit decode to the
  half-period index ``V2``; ``K1 = V2 >> 1`` (edges at the phase jumps) and
  ``K2 = (V2 + 1) >> 1`` (edges at mid-period). ``K = K2`` where ``phi <= pi/2``, ``K1`` where
  ``pi/2 < phi < 3 pi/2`` and ``K2 - 1`` where ``phi >= 3 pi/2``: every read code is a quarter
  period away from its edges, so blur and noise up to that size cause no order errors.
* Multi-frequency: hierarchical (one frequency has one period: unwrap coarse to fine,
  ``K_f = round((Phi_prev P_f / P_prev - phi_f) / 2 pi)``) or heterodyne (beats
  ``phi_12 = phi_1 - phi_2``, ``phi_23 = phi_2 - phi_3`` and their beat of one period, then the
  same coarse-to-fine rule back to the highest frequency).

Validity
--------
A pixel is invalid for any of these reasons, counted separately in ``invalid_counts``:
``low_modulation`` (``b < decode.min_modulation``; for several frequencies, the lowest),
``saturated`` (a phase-shift image at or above ``decode.saturation_level``: clipping biases the
phase; binary and reference images are only thresholded, so their clipping is harmless and not
checked), ``shadow`` (``a < decode.min_background``) and ``bad_order`` (a fringe order outside
``0 .. P-1``: an invalid Gray code word or a failed multi-frequency unwrap).

Speed
-----
The frame is processed in bands of rows that fit the CPU cache; each band is a short sequence
of OpenCV/numpy operations in float32, uint8 and int16, in place into reused buffers, with no
Python loop over pixels. The Gray code is read with same-type uint8 operations (mixed-type
passes cost several times more) and the fringe order stays uint8 until the output. A streaming
loop can pass the previous frame's result as ``decode(images, out=previous)`` so that the output
maps are overwritten instead of allocated (fresh 37 MB of maps page-fault on first write: ~3 ms
of a 1920x1200 frame). The arctangent is OpenCV's (``cv2.cartToPolar``, as ``cv2.phase``): its error is below 2e-4 rad (3e-5 of
a fringe period), far below the phase noise of any real capture; float rounding can make it
return exactly ``2 pi`` for phases a hair below it, which the unwrapping handles.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError, InputDataError
from frontend.config import DecodeConfig
from frontend.fpp.patterns import PatternImage, PatternSpec
from frontend.fpp.stripe_decoding import StripeCode, binary_images
from frontend.fpp.unwrapping import (
    order_from_gray,
    order_multi_frequency,
    read_gray_code,
    unwrap_chain,
)
from frontend.fpp.wrapped_phase import TWO_PI, Scratch, phase_weights, wrapped_phase_band

INVALID_REASONS = ("low_modulation", "saturated", "shadow", "bad_order")
# The decoder's output maps (keys of its band dictionaries) and their pixel types.
_OUTPUT_DTYPES = {"phi": np.float32, "u": np.float32, "mod": np.float32, "tex": np.uint8, "mask": np.uint8, "order": np.int16}


@dataclass(frozen=True, eq=False)
class DecodeResult:
    """One decoded FPP frame. All maps are (H, W) in camera pixels.

    Attributes
    ----------
    wrapped_phase : float32, rad in [0, 2 pi)
        Wrapped phase of the highest frequency, at every pixel (also invalid ones; see the
        module docstring on ``cv2.phase`` rounding).
    u_projector_px : float32, projector pixels
        Projector coordinate along the encoded axis (``u_p`` for vertical fringes, ``v_p`` for
        horizontal), pixel-centre convention; NaN where invalid.
    modulation : float32, grey levels
        Fringe modulation ``b`` (of the highest frequency).
    texture : uint8
        Background ``a`` (the mean of the phase-shift images): the texture image. 16-bit input
        is scaled by ``255 / decode.saturation_level``.
    mask : bool
        True where valid.
    fringe_order : int16
        Fringe order ``K`` of the highest frequency; -1 where invalid.
    invalid_counts : dict[str, int]
        Pixels failing each check (``low_modulation``, ``saturated``, ``shadow``, ``bad_order``);
        a pixel may fail several.
    pitch_px : float
        Fringe pitch ``lambda`` of the highest frequency (Gray code alone: the stripe width),
        projector pixels.
    axis : {"columns", "rows", "both"}
        The encoded projector axis (``u_projector_px`` holds the columns for ``"both"``).
    v_projector_px : float32 or None
        The projector row of an ``axis="both"`` set; NaN where invalid.
    u_noise_px, v_noise_px : float32 or None
        Expected noise (1 sigma, projector pixels) of ``u_projector_px`` and ``v_projector_px``
        per pixel, from the codec and the measured image noise
        (:mod:`frontend.fpp.phase_noise`); None when the decoder does not state it.
    image_noise_grey : float or None
        The camera's image noise measured on this capture, grey levels (1 sigma).

    For Gray code alone (``kind="gray_code"``) there is no phase: ``wrapped_phase`` is NaN,
    ``modulation`` is half the white - black (or bit - inverse) contrast, ``texture`` the mean of
    those two images and ``fringe_order`` the stripe index.
    """

    wrapped_phase: NDArray[np.float32]
    u_projector_px: NDArray[np.float32]
    modulation: NDArray[np.float32]
    texture: NDArray[np.uint8]
    mask: NDArray[np.bool_]
    fringe_order: NDArray[np.int16]
    invalid_counts: dict[str, int]
    pitch_px: float
    axis: str = "columns"
    v_projector_px: NDArray[np.float32] | None = None
    u_noise_px: NDArray[np.float32] | None = None
    v_noise_px: NDArray[np.float32] | None = None
    image_noise_grey: float | None = None

    @cached_property
    def absolute_phase(self) -> NDArray[np.float32]:
        """Absolute phase ``Phi`` (eq. 3) of the highest frequency, rad; NaN where invalid."""
        # Derived on demand: the hot path only needs u_p, and Phi = 2 pi u_p / lambda exactly.
        return np.multiply(self.u_projector_px, np.float32(TWO_PI / self.pitch_px))

    @property
    def valid_fraction(self) -> float:
        return float(np.count_nonzero(self.mask)) / max(self.mask.size, 1)


def no_valid_pixel_error(width: int, height: int, invalid_counts: dict[str, int], config: DecodeConfig, cause: str = "") -> InputDataError:
    """The error of a frame where no pixel decodes: the counts per reason and what to check."""
    detail = ", ".join(f"{k} {v}" for k, v in invalid_counts.items())
    return InputDataError(
        f"no valid pixel in the {width}x{height} frame ({detail} of {width * height} pixels): the images are all dark, saturated or "
        f"show no fringes{cause}; check exposure and projector, or the decode thresholds (min_modulation={config.min_modulation}, "
        f"min_background={config.min_background}, saturation_level={config.saturation_level})"
    )


def _as_stack(images: NDArray | Sequence[NDArray], expected: int, what: str) -> NDArray:
    """Validate a frame's images and return them as one C-contiguous (M, H, W) stack."""
    if isinstance(images, np.ndarray):
        stack = images
        if stack.ndim != 3:
            hint = " (colour images? convert them to grey, e.g. with frontend.fpp.images.load_image_stack)" if stack.ndim == 4 else ""
            raise InputDataError(f"pattern images must be a (M, H, W) stack of single-channel 2D images, got an array of shape {stack.shape}{hint}")
    else:
        imgs = [np.asarray(im) for im in images]
        if not imgs:
            raise InputDataError(f"no pattern images given; {what} needs {expected}")
        for i, im in enumerate(imgs):
            if im.ndim != 2:
                raise InputDataError(f"pattern image {i} has shape {im.shape}; every image must be single-channel 2D (H, W)")
        if len({im.shape for im in imgs}) > 1:
            detail = ", ".join(f"#{i} {im.shape[1]}x{im.shape[0]}" for i, im in enumerate(imgs))
            raise InputDataError(f"pattern images have mixed sizes (W x H: {detail}); all images of a frame must have the camera's size")
        if len({im.dtype for im in imgs}) > 1:
            detail = ", ".join(f"#{i} {im.dtype}" for i, im in enumerate(imgs))
            raise InputDataError(f"pattern images have mixed pixel types ({detail}); all must be uint8 or all uint16")
        stack = np.stack(imgs)
    if stack.dtype not in (np.uint8, np.uint16):
        raise InputDataError(f"pattern images must be 8- or 16-bit unsigned (uint8/uint16), got {stack.dtype}; convert float or signed images first")
    if stack.shape[0] != expected:
        raise InputDataError(f"wrong image count: {what} needs {expected} images, got {stack.shape[0]}")
    if stack.shape[1] == 0 or stack.shape[2] == 0:
        raise InputDataError(f"pattern images are empty ({stack.shape[2]}x{stack.shape[1]} pixels)")
    return np.ascontiguousarray(stack)


class Decoder:
    """A decoder for one pattern spec and projector size; precomputes its tables once.

    Parameters
    ----------
    spec : PatternSpec
    projector_width, projector_height : int
        Projector size in pixels (the encoded axis length sets the fringe pitch).
    config : DecodeConfig, optional
        Validity thresholds; the defaults of ``fpp_graph.config`` when None.
    band_rows : int
        The frame is decoded in bands of this many rows so that the ~20 intermediate images of a
        band stay in the CPU cache; 0 = the whole frame at once. Results do not depend on it.

    A Decoder may be shared between threads: its work buffers are per thread.
    """

    def __init__(
        self,
        spec: PatternSpec,
        projector_width: int,
        projector_height: int,
        config: DecodeConfig | None = None,
        band_rows: int = 128,
    ) -> None:
        if int(projector_width) <= 0 or int(projector_height) <= 0:
            raise ConfigError(f"projector size must be positive, got {projector_width}x{projector_height}")
        if band_rows < 0:
            raise ConfigError(f"band_rows must be >= 0 (0 = whole frame), got {band_rows}")
        self.spec = spec
        self.projector_width = int(projector_width)
        self.projector_height = int(projector_height)
        self.config = config if config is not None else DecodeConfig()
        self.band_rows = int(band_rows)
        self.axis_length = self.projector_height if spec.coded_axis == "rows" else self.projector_width
        layout = spec.layout()
        self.image_count = len(layout)
        self._phase_index = [self._phase_steps_of(layout, f) for f in range(spec.n_frequencies)]
        m = round(spec.phase_origin_rad * spec.phase_steps / TWO_PI)
        # the part of the phase origin that reordering the steps cannot remove, subtracted from phi
        self._origin_residual = float(np.angle(np.exp(1j * (spec.phase_origin_rad - m * TWO_PI / spec.phase_steps))))
        self._code_index, self._code_inverse = binary_images(layout, "")
        binary_images(layout, "rows")  # refuses row bits given inverses for some but not all
        self._white_index = next((i for i, im in enumerate(layout) if im.role == "white"), None)
        self._black_index = next((i for i, im in enumerate(layout) if im.role == "black"), None)
        self._sin, self._cos = phase_weights(spec.phase_steps)
        self._finest = int(np.argmax(spec.periods)) if spec.kind != "gray_code" else 0
        self.periods_finest = spec.periods[self._finest]
        self.pitch_px = self.axis_length / self.periods_finest
        if spec.kind == "gray_code":
            self._stripes = StripeCode(spec, self.projector_width, self.projector_height, self._white_index, self._black_index)
        if spec.kind == "multi_frequency":
            self._chain = unwrap_chain(spec.periods)
        self._local = threading.local()

    def _phase_steps_of(self, layout: Sequence[PatternImage], frequency: int) -> list[int]:
        """Image indices of one frequency in the order of eq. 1's steps (forward, origin 0).

        A projected step ``s`` shows ``cos(phi + phi_0 -+ delta_s)``; with ``phi_0 = m 2 pi / N
        + r`` that is our step ``n = s - m`` (forward) or ``n = -s - m`` (reverse) of the phase
        ``phi + r``: reordering removes the direction and ``m``, ``r`` is subtracted after eq. 2.
        """
        spec = self.spec
        n_steps = spec.phase_steps
        by_step = {im.step: i for i, im in enumerate(layout) if im.role == "phase" and im.frequency == frequency}
        m = round(spec.phase_origin_rad * n_steps / TWO_PI)
        if spec.shift_direction == "forward":
            return [by_step[(n + m) % n_steps] for n in range(n_steps)]
        return [by_step[(-n - m) % n_steps] for n in range(n_steps)]

    # ------------------------------------------------------------------ input checks
    def _describe(self) -> str:
        s = self.spec
        parts = [s.kind] if s.kind == "gray_code" else [s.kind, f"{s.phase_steps}-step"]
        if s.kind in ("multi_frequency", "single_frequency"):
            parts.append(f"x {len(s.periods)} frequencies {s.periods}")
        else:
            bits = f"{s.gray_bits}" + (f" + {s.gray_bits_rows} row" if s.axis == "both" else "")
            parts.append(f"+ {bits} Gray bits" + (" + 1 complementary bit" if s.kind == "complementary_gray" else ""))
            if s.gray_inverse:
                parts.append("with inverses")
        if s.with_reference:
            parts.append("+ white + black")
        if s.order:
            parts.append("in the spec's explicit order")
        return " ".join(parts)

    def _check_images(self, images: NDArray | Sequence[NDArray]) -> NDArray:
        return _as_stack(images, self.image_count, f"pattern set {self._describe()}")

    # ------------------------------------------------------------------ decoding
    def decode(self, images: NDArray | Sequence[NDArray], out: DecodeResult | None = None) -> DecodeResult:
        """Decode one frame.

        Parameters
        ----------
        images : (M, H, W) uint8 or uint16, or a sequence of M such (H, W) images
            The captured pattern images in the capture order of the spec.
        out : DecodeResult, optional
            A previous result of the same image size whose arrays are overwritten and returned
            in the new result (a streaming loop then allocates, and page-faults, nothing: ~3 ms
            of a 1920x1200 frame). The previous result's maps then hold this frame's values.

        Returns
        -------
        DecodeResult

        Raises
        ------
        InputDataError
            Wrong image count, mixed sizes or types, images that are not 2D or not 8/16-bit,
            or a frame where no pixel is valid (all dark, saturated or without fringes).
        """
        stack = self._check_images(images)
        h, w = stack.shape[1:]
        rows = self.band_rows if 0 < self.band_rows < h else h
        scratch = getattr(self._local, "scratch", None)
        if scratch is None or scratch.rows != rows or scratch.width != w:
            scratch = Scratch(rows, w)
            self._local.scratch = scratch
        out = self._output_arrays(h, w) if out is None else self._reuse_outputs(out, h, w)
        if self.spec.axis == "both" and "v" not in out:
            out["v"] = np.empty((h, w), np.float32)
        counts = np.zeros(5, dtype=np.int64)  # the four reasons, then all invalid
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            band = {k: v[r0:r1] for k, v in out.items()}
            if self.spec.kind == "gray_code":
                counts += self._stripes.decode_band(stack[:, r0:r1], band, scratch, self.config)
            else:
                counts += self._decode_band(stack[:, r0:r1], band, scratch)
        invalid_counts = dict(zip(INVALID_REASONS, (int(c) for c in counts[:4]), strict=True))
        if counts[4] == h * w:
            raise no_valid_pixel_error(w, h, invalid_counts, self.config)
        return DecodeResult(
            wrapped_phase=out["phi"],
            u_projector_px=out["u"],
            modulation=out["mod"],
            texture=out["tex"],
            mask=out["mask"].view(np.bool_),
            fringe_order=out["order"],
            invalid_counts=invalid_counts,
            pitch_px=self.pitch_px,
            axis=self.spec.axis,
            v_projector_px=out.get("v"),
        )

    @staticmethod
    def _output_arrays(h: int, w: int) -> dict[str, NDArray]:
        return {k: np.empty((h, w), dt) for k, dt in _OUTPUT_DTYPES.items()}

    @staticmethod
    def _reuse_outputs(previous: DecodeResult, h: int, w: int) -> dict[str, NDArray]:
        if not isinstance(previous, DecodeResult):
            raise InputDataError(f"decode: out must be a DecodeResult of an earlier frame, got {type(previous).__name__}")
        arrays = {
            "phi": previous.wrapped_phase,
            "u": previous.u_projector_px,
            "mod": previous.modulation,
            "tex": previous.texture,
            "mask": previous.mask.view(np.uint8) if previous.mask.dtype == np.bool_ else previous.mask,
            "order": previous.fringe_order,
        }
        if previous.v_projector_px is not None:
            arrays["v"] = previous.v_projector_px
        for k, a in arrays.items():
            if a.shape != (h, w) or a.dtype != _OUTPUT_DTYPES.get(k, np.float32) or not a.flags.c_contiguous or not a.flags.writeable:
                raise InputDataError(
                    f"decode: out holds a {a.shape[1] if a.ndim > 1 else '?'}x{a.shape[0]} {a.dtype} map where this frame needs a "
                    f"writable {w}x{h} {np.dtype(_OUTPUT_DTYPES.get(k, np.float32))} one; pass a result of a frame of the same size, or none"
                )
        return arrays

    def _decode_band(self, stack: NDArray, out: dict[str, NDArray], work: Scratch) -> NDArray[np.int64]:
        """Decode rows of a frame into the given output views; returns the invalid counts."""
        cfg = self.config
        n = self.spec.phase_steps
        r = stack.shape[1]
        wide = stack.dtype == np.uint16
        phases = []
        low_mod = work.get("low_mod", np.uint8, r)
        tmp8 = work.get("tmp8", np.uint8, r)
        saturated = None
        for f, idx in enumerate(self._phase_index):
            imgs = [stack[i] for i in idx]
            finest = f == self._finest
            phi = out["phi"] if finest else work.get(f"phi{f}", np.float32, r)
            mod = out["mod"] if finest else work.get("mod", np.float32, r)
            self._wrapped_phase(imgs, phi, mod, work)
            if self._origin_residual:
                self._remove_origin_residual(phi, work)
            phases.append(phi)
            np.less(mod, np.float32(cfg.min_modulation), out=(low_mod if f == 0 else tmp8).view(np.bool_))
            if f > 0:
                cv2.bitwise_or(low_mod, tmp8, dst=low_mod)
            if cfg.saturation_level <= np.iinfo(stack.dtype).max:
                saturated = self._saturation(imgs, work, first=saturated is None)
            if finest:
                total = self._background_sum(imgs, work)
        # Texture (the background a) and the binarisation threshold, of the finest frequency.
        if not wide:
            cv2.convertScaleAbs(total, dst=out["tex"], alpha=1.0 / n)
            threshold = out["tex"]
        else:
            cv2.convertScaleAbs(total, dst=out["tex"], alpha=255.0 / (n * cfg.saturation_level))
            threshold = work.get("threshold", np.uint16, r)
            np.multiply(total, np.float32(1.0 / n), out=total)
            np.rint(total, out=total)
            np.copyto(threshold, total, casting="unsafe")
        shadow = work.get("shadow", np.uint8, r)
        # a < min_background <=> sum < min_background N; an integer sum compares with the ceiling.
        limit = np.float32(cfg.min_background * n) if total.dtype == np.float32 else total.dtype.type(min(math.ceil(cfg.min_background * n), np.iinfo(total.dtype).max))
        np.less(total, limit, out=shadow.view(np.bool_))
        invalid = cv2.bitwise_or(low_mod, shadow, dst=work.get("invalid", np.uint8, r))
        if saturated is not None:
            cv2.bitwise_or(invalid, saturated, dst=invalid)

        order, unsigned_order = self._fringe_order(stack, phases, threshold, out, work)

        # Orders outside 0..P-1 (negative ones wrap to huge unsigned values) are invalid code words.
        bad = work.get("bad", np.uint8, r)
        np.greater(unsigned_order, unsigned_order.dtype.type(self.periods_finest - 1), out=bad.view(np.bool_))
        cv2.bitwise_or(invalid, bad, dst=invalid)

        # eq. 3 and eq. 8 in one pass: u_p = (K + phi / 2 pi) lambda.
        u = out["u"]
        k = unsigned_order if unsigned_order.dtype == np.uint8 else order
        cv2.addWeighted(k, self.pitch_px, out["phi"], self.pitch_px / TWO_PI, 0.0, dst=u, dtype=cv2.CV_32F)
        cv2.copyTo(work.const("nan", np.nan, np.float32, r), invalid, u)
        cv2.copyTo(work.const("minus_one", -1, np.int16, r), invalid, order)
        np.equal(invalid, 0, out=out["mask"].view(np.bool_))
        return np.array(
            [
                cv2.countNonZero(low_mod),
                cv2.countNonZero(saturated) if saturated is not None else 0,
                cv2.countNonZero(shadow),
                cv2.countNonZero(bad),
                cv2.countNonZero(invalid),
            ],
            dtype=np.int64,
        )

    def _fringe_order(self, stack: NDArray, phases: list[NDArray], threshold: NDArray, out: dict[str, NDArray], work: Scratch) -> tuple[NDArray, NDArray]:
        """The band's fringe order into ``out["order"]``; returns it and its unsigned view (or code type)."""
        if self.spec.kind == "multi_frequency":
            order = out["order"]
            order_multi_frequency(self._chain, phases, order, work)
            return order, order.view(np.uint16)
        if self.spec.kind == "single_frequency":  # one period: the wrapped phase is absolute
            order = out["order"]
            order.fill(0)
            return order, order.view(np.uint16)
        if self._code_inverse:  # each bit against its own inverse image
            threshold = [stack[i] for i in self._code_inverse]
        elif self._white_index is not None:
            # (white + black) / 2; rounding down costs at most half a grey level.
            r = stack.shape[1]
            threshold = work.get("ref_threshold", stack.dtype, r)
            acc = work.get("ref_sum", np.uint32 if stack.dtype == np.uint16 else np.uint16, r)
            np.add(stack[self._white_index], stack[self._black_index], out=acc, dtype=acc.dtype)
            np.right_shift(acc, 1, out=acc)
            np.copyto(threshold, acc, casting="unsafe")
        code = read_gray_code(stack, self._code_index, threshold, work)
        unsigned_order = order_from_gray(self.spec.kind, code, out["phi"], work)
        order = out["order"]
        np.copyto(order, unsigned_order, casting="unsafe")
        return order, unsigned_order

    def _remove_origin_residual(self, phi: NDArray, work: Scratch) -> None:
        """phi - r, wrapped back into [0, 2 pi) (see :meth:`_phase_steps_of`)."""
        np.subtract(phi, np.float32(self._origin_residual), out=phi)
        neg = work.get("neg", np.uint8, phi.shape[0])
        np.less(phi, np.float32(0.0), out=neg.view(np.bool_))
        cv2.add(phi, TWO_PI, dst=phi, mask=neg)
        np.greater_equal(phi, np.float32(TWO_PI), out=neg.view(np.bool_))
        cv2.subtract(phi, TWO_PI, dst=phi, mask=neg)

    def _wrapped_phase(self, imgs: list[NDArray], phi: NDArray, mod: NDArray, work: Scratch) -> None:
        wrapped_phase_band(imgs, self._sin, self._cos, phi, mod, work)

    def _background_sum(self, imgs: list[NDArray], work: Scratch) -> NDArray:
        """Sum of the N images (uint16 for 8-bit input, float32 for 16-bit: exact either way)."""
        acc_dtype = np.uint16 if imgs[0].dtype == np.uint8 and len(imgs) <= 257 else np.float32
        total = work.get("total", acc_dtype, imgs[0].shape[0])
        np.add(imgs[0], imgs[1], out=total, dtype=acc_dtype)
        for img in imgs[2:]:
            np.add(total, img, out=total, casting="unsafe")
        return total

    def _saturation(self, imgs: list[NDArray], work: Scratch, first: bool) -> NDArray:
        """OR the saturation of these images into the band's saturation mask."""
        r = imgs[0].shape[0]
        peak = work.get("peak", imgs[0].dtype, r)
        cv2.max(imgs[0], imgs[1], dst=peak)
        for img in imgs[2:]:
            cv2.max(peak, img, dst=peak)
        sat = work.get("saturated", np.uint8, r)
        level = peak.dtype.type(math.ceil(self.config.saturation_level))
        if first:
            np.greater_equal(peak, level, out=sat.view(np.bool_))
        else:
            tmp = work.get("tmp8", np.uint8, r)
            np.greater_equal(peak, level, out=tmp.view(np.bool_))
            cv2.bitwise_or(sat, tmp, dst=sat)
        return sat

def make_decoder(spec, projector_width: int, projector_height: int, config: DecodeConfig | None = None):
    """The decoder of any pattern spec: a :class:`Decoder` for a :class:`PatternSpec`, else the
    spec's own (``spec.make_decoder(projector_width, projector_height, config)``). Every decoder
    has ``decode(images) -> DecodeResult`` and ``image_count``."""
    if isinstance(spec, PatternSpec):
        return Decoder(spec, projector_width, projector_height, config)
    return spec.make_decoder(projector_width, projector_height, config)


def decode(
    images: NDArray | Sequence[NDArray],
    spec: PatternSpec,
    projector_width: int,
    projector_height: int,
    config: DecodeConfig | None = None,
) -> DecodeResult:
    """Decode one frame (see :class:`Decoder`; build one Decoder to decode many frames)."""
    return make_decoder(spec, projector_width, projector_height, config).decode(images)


def compute_wrapped_phase(images: NDArray | Sequence[NDArray], band_rows: int = 128) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """eq. 2 alone: wrapped phase, modulation and background of N phase-shifted images.

    Parameters
    ----------
    images : (N, H, W) uint8 or uint16, N >= 3
        ``I_n = a + b cos(phi - 2 pi n / N)``, n = 0..N-1 (the convention of
        :mod:`frontend.fpp.patterns`).
    band_rows : int
        Rows per band (cache blocking); 0 = whole image.

    Returns
    -------
    wrapped_phase : (H, W) float32, rad in [0, 2 pi)
    modulation : (H, W) float32, ``b`` in grey levels
    background : (H, W) float32, ``a`` in grey levels
    """
    n = len(images)
    if n < 3:
        raise InputDataError(f"phase shifting needs at least 3 images, got {n}")
    stack = _as_stack(images, n, f"{n}-step phase shifting")
    h, w = stack.shape[1:]
    rows = band_rows if 0 < band_rows < h else h
    sin, cos = phase_weights(n)
    phi = np.empty((h, w), np.float32)
    mod = np.empty((h, w), np.float32)
    background = np.empty((h, w), np.float32)
    work = Scratch(rows, w)
    acc_dtype = np.uint16 if stack.dtype == np.uint8 and n <= 257 else np.float32
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        imgs = [stack[i, r0:r1] for i in range(n)]
        wrapped_phase_band(imgs, sin, cos, phi[r0:r1], mod[r0:r1], work)
        total = work.get("total", acc_dtype, r1 - r0)
        np.add(imgs[0], imgs[1], out=total, dtype=acc_dtype)
        for img in imgs[2:]:
            np.add(total, img, out=total, casting="unsafe")
        np.multiply(total, np.float32(1.0 / n), out=background[r0:r1])
    return phi, mod, background
