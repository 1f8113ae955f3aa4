"""Which unwrapping each projector axis of a fringe-set capture uses (the rules are in
:mod:`frontend.fpp.fringe_sets`, section "Unwrapping"): micro phase shifting alone, a Gray code,
hierarchical (the coarsest pitch covers the axis), heterodyne (a beat, or a beat of beats,
covers it) or, where the file asks for it, spatial (one set of several periods unwrapped across
the image). Anything else is a ConfigError naming the sets."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

from fpp_graph.errors import ConfigError

if TYPE_CHECKING:
    from frontend.fpp.fringe_sets import FringeSetSpec

# Periods are compared with this relative slack: pitch_px gives L / pitch in floating point.
_TOLERANCE = 1e-9


class AxisPlan(NamedTuple):
    """How one axis is unwrapped: ``scheme`` and the chain of levels coarse to fine.

    ``levels`` is a list of ``(periods across the axis, recipe)``; a recipe is ``("set", i)``
    (the wrapped phase of fringe set ``i``) or ``("beat", a, b)`` (``wrap(phase_a - phase_b)``).
    ``finest`` is the set whose phase gives the coordinate; ``gray`` the Gray code's index.
    """

    axis: str
    scheme: str
    levels: list
    finest: int
    gray: int = -1


def set_periods(spec: FringeSetSpec, i: int, length: int | None) -> float | None:
    """Periods of set ``i`` across an axis of ``length`` pixels (None: a pitch and no length)."""
    s = spec.fringe_sets[i]
    if s.periods is not None:
        return s.periods
    return None if length is None else length / s.pitch(length)


def plan_axis(spec: FringeSetSpec, axis: str, members: list[int], length: int | None) -> AxisPlan | None:
    """The plan of one axis whose fringe sets are ``members``; None when pitches need the axis
    length to be checked and ``length`` is None."""
    names = ", ".join(spec.set_name(i) for i in members)
    micro = [i for i in members if spec.fringe_sets[i].codec == "micro_phase_shift"]
    gray = spec.gray_code(axis)
    if micro:
        if len(members) > 1 or gray is not None:
            raise ConfigError(f"fringe sets {names} on axis {axis}: a micro_phase_shift set is absolute and must be the axis's only set (no Gray code)")
        return AxisPlan(axis, "micro", [], micro[0])
    spatial = [i for i in members if spec.fringe_sets[i].unwrapping == "spatial"]
    if spatial:
        return _spatial_plan(spec, axis, members, length, names)
    if gray is not None:
        return _gray_plan(spec, axis, members, length, names)
    by_periods = [(set_periods(spec, i, length), i) for i in members]
    if any(p is None for p, _ in by_periods):
        pitches = [spec.fringe_sets[i].pitch_px for i in members if spec.fringe_sets[i].pitch_px is not None]
        if len(set(pitches)) != len(pitches):
            raise ConfigError(f"fringe sets {names} on axis {axis} repeat a pitch; every level needs its own pitch")
        return None
    by_periods.sort()
    values = [p for p, _ in by_periods]
    if any(b - a < _TOLERANCE * b for a, b in zip(values, values[1:], strict=False)):
        raise ConfigError(f"fringe sets {names} on axis {axis} repeat a pitch; every level needs its own pitch")
    plan = _chain_plan(axis, by_periods)
    if plan is None:
        shown = ", ".join(f"{spec.set_name(i)} {p:g}" for p, i in by_periods)
        raise ConfigError(
            f"fringe sets on axis {axis} cannot be unwrapped (periods across the axis: {shown}): give a set whose pitch covers "
            "the axis (hierarchical), two sets whose beat covers it or three whose beat of beats does (heterodyne), or a Gray code"
        )
    return plan


def _gray_plan(spec: FringeSetSpec, axis: str, members: list[int], length: int | None, names: str) -> AxisPlan:
    gray = spec.gray_code(axis)
    if len(members) != 1:
        raise ConfigError(f"fringe sets {names} on axis {axis}: a Gray code unwraps exactly one phase set on its axis")
    periods = set_periods(spec, members[0], length)
    stripes = None if periods is None else math.ceil(periods - _TOLERANCE)
    if stripes is not None and 2**gray.bits < stripes:
        raise ConfigError(
            f"fringe set {names} on axis {axis}: {gray.bits} Gray bits distinguish {2**gray.bits} orders but the axis holds "
            f"{periods:g} periods; use bits >= {math.ceil(math.log2(stripes))}"
        )
    return AxisPlan(axis, "gray", [(periods, ("set", members[0]))], members[0], spec.gray_codes.index(gray))


def _spatial_plan(spec: FringeSetSpec, axis: str, members: list[int], length: int | None, names: str) -> AxisPlan | None:
    if len(members) != 1 or spec.gray_code(axis) is not None:
        raise ConfigError(
            f"fringe sets {names} on axis {axis}: unwrapping: spatial is for an axis's only set (no Gray code); "
            "with several sets or a Gray code the axis is unwrapped per pixel, so drop the key"
        )
    periods = set_periods(spec, members[0], length)
    if periods is None:
        return None
    if periods <= 1 + _TOLERANCE:
        raise ConfigError(f"fringe set {names} on axis {axis} has {periods:g} period(s) across the axis: its phase is already absolute; drop unwrapping: spatial")
    return AxisPlan(axis, "spatial", [(periods, ("set", members[0]))], members[0])


def _chain_plan(axis: str, by_periods: list[tuple[float, int]]) -> AxisPlan | None:
    """Hierarchical or heterodyne levels of sets sorted by their periods, or None."""
    values = [p for p, _ in by_periods]
    finest = by_periods[-1][1]
    if values[0] <= 1 + _TOLERANCE:
        return AxisPlan(axis, "hierarchical", [(p, ("set", i)) for p, i in by_periods], finest)
    if len(values) == 2 and values[1] - values[0] <= 1 + _TOLERANCE:
        (p2, i2), (p1, i1) = by_periods
        return AxisPlan(axis, "heterodyne", [(p1 - p2, ("beat", ("set", i1), ("set", i2))), (p1, ("set", i1))], finest)
    if len(values) == 3:
        (p3, i3), (p2, i2), (p1, i1) = by_periods
        p12, p23 = p1 - p2, p2 - p3
        if p12 != p23 and abs(p12 - p23) <= 1 + _TOLERANCE:
            b12, b23 = ("beat", ("set", i1), ("set", i2)), ("beat", ("set", i2), ("set", i3))
            wide, narrow = (b12, b23) if p12 > p23 else (b23, b12)
            return AxisPlan(axis, "heterodyne", [(abs(p12 - p23), ("beat", wide, narrow)), (max(p12, p23), wide), (p1, ("set", i1))], finest)
    return None
