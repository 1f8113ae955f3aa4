"""Temporal phase unwrapping: the fringe order from the Gray code, the complementary Gray code or
the multi-frequency set (:mod:`frontend.fpp.phase`, section "Fringe order", gives the rules).

Each step works on one band of rows into reused :class:`~frontend.fpp.wrapped_phase.Scratch`
buffers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from frontend.fpp.patterns import unwrapping_scheme
from frontend.fpp.wrapped_phase import TWO_PI, Scratch


def unwrap_chain(periods: Sequence[int]) -> list[tuple]:
    """The coarse-to-fine unwrapping steps: a list of (periods, recipe) from one period up.

    A recipe is ``("freq", f)`` (the wrapped phase of frequency f) or ``("beat", a, b)``
    (``wrap(phase_a - phase_b)`` where a, b are recipes).
    """
    p = periods
    if unwrapping_scheme(p) == "hierarchical":
        return [(p[f], ("freq", f)) for f in np.argsort(p)]
    order = [int(i) for i in np.argsort(p)[::-1]]  # descending period counts
    if len(order) == 2:
        i1, i2 = order
        return [(1, ("beat", ("freq", i1), ("freq", i2))), (p[i1], ("freq", i1))]
    i1, i2, i3 = order
    p12, p23 = p[i1] - p[i2], p[i2] - p[i3]
    b12, b23 = ("beat", ("freq", i1), ("freq", i2)), ("beat", ("freq", i2), ("freq", i3))
    b123 = ("beat", b12, b23) if p12 > p23 else ("beat", b23, b12)
    return [(1, b123), (p12, b12), (p[i1], ("freq", i1))]


def read_gray_code(stack: NDArray, code_index: list[int], threshold: NDArray | list[NDArray], work: Scratch) -> NDArray:
    """Binarise the code images and Gray-decode them (MSB first) to an unsigned integer image.

    ``threshold`` is one image for every bit, or one per bit (e.g. each bit's inverse image).

    Gray to binary: bit k of the value is the XOR of the Gray bits 0..k (MSB first), so the
    value is the XOR over j of "Gray bit j, spread over bits j..last". For up to 8 code
    images each bit costs three same-type uint8 OpenCV passes (compare: 0/255; threshold:
    0/low-bits mask; XOR into the value); beyond 8 the value is uint16 (numpy).
    """
    r = stack.shape[1]
    nbits = len(code_index)
    thresholds = threshold if isinstance(threshold, list) else [threshold] * nbits
    bit = work.get("bit", np.uint8, r)
    if nbits <= 8:
        value = work.get("value", np.uint8, r)
        for j, i in enumerate(code_index):
            low_bits = (1 << (nbits - j)) - 1  # bits j..last of the value (MSB first)
            target = value if j == 0 else bit
            if low_bits == 0xFF:
                cv2.compare(stack[i], thresholds[j], cv2.CMP_GT, dst=target)
            else:
                cv2.compare(stack[i], thresholds[j], cv2.CMP_GT, dst=bit)
                cv2.threshold(bit, 0, low_bits, cv2.THRESH_BINARY, dst=target)
            if j > 0:
                cv2.bitwise_xor(value, bit, dst=value)
        return value
    binary = work.get("binary", np.uint8, r)
    value = work.get("value", np.uint16, r)
    for j, i in enumerate(code_index):
        # Gray to binary on the fly: b_j = b_(j-1) xor g_j; masks are 0/255.
        if j == 0:
            cv2.compare(stack[i], thresholds[j], cv2.CMP_GT, dst=binary)
        else:
            cv2.compare(stack[i], thresholds[j], cv2.CMP_GT, dst=bit)
            cv2.bitwise_xor(binary, bit, dst=binary)
        term = np.left_shift((binary & 1).astype(np.uint16), np.uint16(nbits - 1 - j))
        if j == 0:
            value[...] = term
        else:
            value |= term
    return value

def order_from_gray(kind: str, code: NDArray, phi: NDArray, work: Scratch) -> NDArray:
    """Fringe order from the Gray code value (plain) or the half-period index (complementary).

    Returns the order in the code's unsigned type; an order of -1 wraps to the type's
    maximum, so one unsigned comparison with ``P - 1`` finds every invalid order.
    """
    if kind == "gray":
        return code
    r = code.shape[0]
    zone = work.get("zone", np.uint8, r)
    k1 = work.get("k1", code.dtype, r)
    k2 = work.get("k2", code.dtype, r)
    np.right_shift(code, 1, out=k1)  # K1 = V2 >> 1: edges at the phase jumps
    np.subtract(code, k1, out=k2)  # K2 = (V2 + 1) >> 1 = V2 - K1: edges at mid-period
    np.less_equal(phi, np.float32(0.5 * math.pi), out=zone.view(np.bool_))
    cv2.copyTo(k2, zone, k1)
    np.subtract(k2, 1, out=k2)  # K2 - 1 (wraps for K2 = 0)
    np.greater_equal(phi, np.float32(1.5 * math.pi), out=zone.view(np.bool_))
    cv2.copyTo(k2, zone, k1)
    return k1

def order_multi_frequency(chain: list[tuple], phases: list[NDArray], order: NDArray, work: Scratch) -> None:
    """Fringe order of the finest frequency by hierarchical or heterodyne unwrapping."""
    r = order.shape[0]
    neg = work.get("neg", np.uint8, r)
    made: dict[tuple, NDArray] = {}

    def phase_of(recipe: tuple) -> NDArray:
        if recipe[0] == "freq":
            return phases[recipe[1]]
        if recipe not in made:
            buf = work.get("beat" + repr(recipe), np.float32, r)  # one buffer per distinct beat
            np.subtract(phase_of(recipe[1]), phase_of(recipe[2]), out=buf)
            np.less(buf, np.float32(0.0), out=neg.view(np.bool_))
            cv2.add(buf, TWO_PI, dst=buf, mask=neg)
            made[recipe] = buf
        return made[recipe]

    p_prev, recipe = chain[0]
    unwrapped = phase_of(recipe)  # one period: the wrapped phase is absolute
    guess = work.get("guess", np.float32, r)
    absolute = work.get("absolute", np.float32, r)
    for p, recipe in chain[1:]:
        wrapped = phase_of(recipe)
        # K = round((Phi_prev * p / p_prev - phi) / 2 pi), then Phi = phi + 2 pi K.
        np.multiply(unwrapped, np.float32(p / p_prev / TWO_PI), out=guess)
        cv2.scaleAdd(wrapped, -1.0 / TWO_PI, guess, dst=guess)
        np.rint(guess, out=guess)
        cv2.scaleAdd(guess, TWO_PI, wrapped, dst=absolute)
        unwrapped, p_prev = absolute, p
    np.copyto(order, guess, casting="unsafe")
