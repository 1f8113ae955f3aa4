"""Gray code alone (``kind="gray_code"``): the projector stripe of every camera pixel, per band.

No phase images: each bit is binarised against ``(white + black) / 2`` or against its inverse
image, the bits are Gray-decoded (:func:`frontend.fpp.unwrapping.read_gray_code`) to the stripe
index ``k`` and the projector coordinate is the centre of the stripe's projector pixels
``j0 .. j1`` (``j0 = ceil(k W / S)``, ``j1 = ceil((k + 1) W / S) - 1``): ``(j0 + j1) / 2``, which
is ``(k + 1/2) W / S - 1/2`` when ``W / S`` is an integer (pixel-centre convention,
:mod:`frontend.fpp.patterns`). Its error is uniform over the stripe: at most half a stripe and
``W / (S sqrt 12)`` RMS projector pixels, before camera blur and noise move code edges.

Validity, counted under the decoder's reasons: ``low_modulation`` where half the white - black
contrast (without references: half the smallest bit - inverse contrast) is below
``decode.min_modulation``, or a bit differs from its inverse by less than
``decode.min_code_contrast``; ``shadow`` where the mean of the reference pair is below
``decode.min_background``; ``bad_order`` where a code is not a stripe (``k >= S``). Binary
images are only thresholded, so their saturation is not checked.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError
from frontend.config import DecodeConfig
from frontend.fpp.patterns import PatternImage, PatternSpec
from frontend.fpp.unwrapping import read_gray_code
from frontend.fpp.wrapped_phase import Scratch


def binary_images(layout: Sequence[PatternImage], axis: str) -> tuple[list[int], list[int]]:
    """Indices of the code images of one axis (``""`` = the spec's, ``"rows"`` = row bits):
    Gray bits MSB first then the complementary bit; and their inverses in the same order
    (empty when the set has none)."""
    bits = sorted((im.bit, i) for i, im in enumerate(layout) if im.role == "gray" and im.axis == axis and not im.inverse)
    inv = {im.bit: i for i, im in enumerate(layout) if im.role == "gray" and im.axis == axis and im.inverse}
    index = [i for _, i in bits]
    inverse = [inv[b] for b, _ in bits if b in inv]
    if axis == "":
        index += [i for i, im in enumerate(layout) if im.role == "complementary" and not im.inverse]
        inverse += [i for i, im in enumerate(layout) if im.role == "complementary" and im.inverse]
    if inverse and len(inverse) != len(index):
        raise ConfigError(f"{len(inverse)} inverse images for {len(index)} code images: give every bit its inverse, or none")
    return index, inverse


def stripe_centres(length_px: int, stripes: int, bits: int) -> NDArray[np.float32]:
    """Projector coordinate of each code's stripe centre (NaN for codes that are no stripe)."""
    k = np.arange(2**bits, dtype=np.int64)
    first = -((-k * length_px) // stripes)  # ceil(k W / S), exact in integers
    last = -((-(k + 1) * length_px) // stripes) - 1
    return np.where(k < stripes, 0.5 * (first + last), np.nan).astype(np.float32)


class StripeCode:
    """Decodes the bands of a Gray-code-only set (see the module docstring)."""

    def __init__(self, spec: PatternSpec, projector_width: int, projector_height: int, white_index: int | None, black_index: int | None) -> None:
        layout = spec.layout()
        self.axes = [("", "u", spec.coded_axis)] + ([("rows", "v", "rows")] if spec.axis == "both" else [])
        self.codes = {name: binary_images(layout, name) for name, _, _ in self.axes}
        self.stripes = {name: spec.periods[k] for k, (name, _, _) in enumerate(self.axes)}
        self.centre_px = {
            name: stripe_centres(projector_height if axis == "rows" else projector_width, self.stripes[name], bits)
            for (name, _, axis), bits in zip(self.axes, (spec.gray_bits, spec.gray_bits_rows), strict=False)
        }
        self.white_index, self.black_index = white_index, black_index

    def decode_band(self, stack: NDArray, out: dict[str, NDArray], work: Scratch, config: DecodeConfig) -> NDArray[np.int64]:
        """One band of rows into the decoder's output views; returns the invalid counts."""
        r = stack.shape[1]
        invalid = work.get("invalid", np.uint8, r)
        low_mod = self._modulation(stack, out, work, config)
        shadow = work.get("shadow", np.uint8, r)
        total = work.get("total", np.float32, r)
        np.less(total, np.float32(2.0 * config.min_background), out=shadow.view(np.bool_))
        cv2.bitwise_or(low_mod, shadow, dst=invalid)
        bad = work.get("bad", np.uint8, r)
        bad.fill(0)
        out["phi"].fill(np.nan)
        for name, key, _ in self.axes:
            index, inverse = self.codes[name]
            threshold = [stack[i] for i in inverse] if inverse else self._reference_threshold(stack, work)
            code = read_gray_code(stack, index, threshold, work)
            order = out["order"] if name == "" else work.get("row_order", np.int16, r)
            np.copyto(order, code, casting="unsafe")
            tmp = work.get("tmp8", np.uint8, r)
            # codes of n bits reach 2 ** n - 1: compare with S - 1 in the code's own type
            np.greater(code, code.dtype.type(min(self.stripes[name] - 1, np.iinfo(code.dtype).max)), out=tmp.view(np.bool_))
            cv2.bitwise_or(bad, tmp, dst=bad)
            np.take(self.centre_px[name], code, out=out[key], mode="clip")
        cv2.bitwise_or(invalid, bad, dst=invalid)
        for _, key, _ in self.axes:
            cv2.copyTo(work.const("nan", np.nan, np.float32, r), invalid, out[key])
        cv2.copyTo(work.const("minus_one", -1, np.int16, r), invalid, out["order"])
        np.equal(invalid, 0, out=out["mask"].view(np.bool_))
        return np.array([cv2.countNonZero(low_mod), 0, cv2.countNonZero(shadow), cv2.countNonZero(bad), cv2.countNonZero(invalid)], dtype=np.int64)

    def _reference_threshold(self, stack: NDArray, work: Scratch) -> NDArray:
        r = stack.shape[1]
        threshold = work.get("ref_threshold", stack.dtype, r)
        acc = work.get("ref_sum", np.uint32 if stack.dtype == np.uint16 else np.uint16, r)
        np.add(stack[self.white_index], stack[self.black_index], out=acc, dtype=acc.dtype)
        np.right_shift(acc, 1, out=acc)
        np.copyto(threshold, acc, casting="unsafe")
        return threshold

    def _modulation(self, stack: NDArray, out: dict[str, NDArray], work: Scratch, config: DecodeConfig) -> NDArray:
        """Modulation, background sum (``work["total"]``) and texture; returns the low-modulation mask."""
        r = stack.shape[1]
        pairs = [(i, j) for name in self.codes for i, j in zip(*self.codes[name], strict=False)]
        hi, lo = (self.white_index, self.black_index) if self.white_index is not None else pairs[0]
        total = work.get("total", np.float32, r)
        np.add(stack[hi], stack[lo], out=total, dtype=np.float32)
        mod = out["mod"]
        np.subtract(stack[hi], stack[lo], out=mod, dtype=np.float32)
        np.multiply(mod, np.float32(0.5), out=mod)
        low_mod = work.get("low_mod", np.uint8, r)
        tmp = work.get("tmp_float", np.float32, r)
        low_contrast = work.get("tmp8", np.uint8, r)
        check_pairs = pairs if (self.white_index is None or config.min_code_contrast > 0) else []
        if self.white_index is None:
            np.abs(mod, out=mod)
        np.less(mod, np.float32(config.min_modulation), out=low_mod.view(np.bool_))
        for i, j in check_pairs:
            np.subtract(stack[i], stack[j], out=tmp, dtype=np.float32)
            np.abs(tmp, out=tmp)
            if self.white_index is None:  # the weakest bit is the modulation
                np.multiply(tmp, np.float32(0.5), out=tmp)
                np.minimum(mod, tmp, out=mod)
                np.multiply(tmp, np.float32(2.0), out=tmp)
            np.less(tmp, np.float32(config.min_code_contrast), out=low_contrast.view(np.bool_))
            cv2.bitwise_or(low_mod, low_contrast, dst=low_mod)
        if self.white_index is None:
            np.less(mod, np.float32(config.min_modulation), out=low_contrast.view(np.bool_))
            cv2.bitwise_or(low_mod, low_contrast, dst=low_mod)
        scale = 0.5 if stack.dtype == np.uint8 else 0.5 * 255.0 / config.saturation_level
        cv2.convertScaleAbs(total, dst=out["tex"], alpha=scale)
        return low_mod
