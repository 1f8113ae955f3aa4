"""FPP pattern sets: N-step phase shifting, Gray code, complementary Gray code, multi-frequency.

A :class:`PatternSpec` says what the projector shows for one 3D frame, in capture order;
:func:`generate_patterns` renders it as 8-bit images for a projector of any size, and
:func:`pattern_intensity` gives the continuous value of any pattern image at sub-pixel projector
coordinates (for renderers that sample the patterns exactly).

Conventions (the decoder in :mod:`frontend.fpp.phase` relies on every one of them)
------------------------------------------------------------------------------
* Encoded axis. ``axis="columns"``: vertical fringes, the intensity varies along projector
  columns and encodes ``u_p``; the "width" ``W`` below is the projector width. ``axis="rows"``:
  horizontal fringes encode ``v_p`` and ``W`` is the projector height.
* Pixel-centre coordinates. ``u_p`` is continuous and projector pixel ``j`` has its *centre* at
  ``u_p = j`` (it covers ``[j - 0.5, j + 0.5)``). Image pixel ``j`` of a pattern holds the
  pattern's value at ``u_p = j``; a binary pattern at a continuous ``u_p`` takes the value of
  pixel ``floor(u_p + 0.5)``.
* Phase (eq. 1). Phase-shift image ``n = 1..N`` of a frequency with ``P`` periods is
  ``I_n = a + b cos(phi - delta_n)``, ``delta_n = 2 pi (n - 1) / N``, with
  ``phi = 2 pi P u_p / W``: the phase origin is the centre of projector pixel 0. Hence (eq. 8)
  ``u_p = Phi * lambda / (2 pi)`` with the pitch ``lambda = W / P`` projector pixels.
* Fringe order. The wrapped phase is taken in ``[0, 2 pi)``, so it jumps where ``u_p`` is a
  multiple of ``lambda``; fringe order ``k = floor(P u_p / W)`` and ``Phi = phi + 2 pi k``.
* Gray code. Bit images encode ``gray(k) = k ^ (k >> 1)`` on ``gray_bits`` bits, most
  significant bit first; a bit image is bright (``offset + amplitude``) where the bit is 1.
* Complementary Gray code (Zhang et al.). One extra image after the Gray-code bits: the least
  significant bit of the ``gray_bits + 1``-bit Gray code of the half-period index
  ``floor(2 P u_p / W)``. Its code edges lie half a period away from the Gray code's, so a
  decoder switches between the two orders on the wrapped phase and never reads a code near its
  edge. (The upper ``gray_bits`` bits of that longer code are exactly the plain Gray code.)
* Levels. Sinusoids span ``offset +- amplitude``; binary images and the white/black references
  use exactly ``offset + amplitude`` and ``offset - amplitude``, so the per-pixel background
  ``a`` of the sinusoids is the ideal binarisation threshold of the bits.
* Capture order. ``gray`` / ``complementary_gray``: N phase-shift images, Gray-code bits (MSB
  first), the complementary bit (``complementary_gray`` only), then white and black if
  ``with_reference``. ``multi_frequency``: N phase-shift images per frequency, frequencies in
  the order of ``periods``, then white and black if ``with_reference``.
* Multi-frequency sets must be unwrappable: either hierarchical (one frequency has exactly one
  period over the axis, e.g. ``(1, 8, 64)``) or heterodyne (the beat of the beats of the sorted
  periods is one period, e.g. ``(64, 58, 53)``: 64 - 58 = 6, 58 - 53 = 5, 6 - 5 = 1; for two
  frequencies their difference must be 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError

PatternKind = Literal["gray", "complementary_gray", "multi_frequency"]
_KINDS = ("gray", "complementary_gray", "multi_frequency")
_AXES = ("columns", "rows")
_DEFAULT_PERIODS = {"gray": (128,), "complementary_gray": (128,), "multi_frequency": (64, 58, 53)}


class PatternImage(NamedTuple):
    """What one image of a pattern set shows.

    ``role`` is ``"phase"`` (``frequency`` indexes ``PatternSpec.periods``, ``step`` is n - 1),
    ``"gray"`` (``bit`` counts from the most significant bit, 0 = MSB), ``"complementary"``,
    ``"white"`` or ``"black"``. Unused fields are -1.
    """

    role: str
    frequency: int = -1
    step: int = -1
    bit: int = -1


@dataclass(frozen=True)
class PatternSpec:
    """What a projector shows for one 3D frame, in capture order (see the module docstring).

    Attributes
    ----------
    kind : {"gray", "complementary_gray", "multi_frequency"}
    phase_steps : int
        N >= 3 phase shifts per frequency.
    periods : tuple of int
        Number of fringe periods across the encoded axis. One entry for the Gray kinds, 2 or 3
        for ``multi_frequency`` (heterodyne, e.g. ``(64, 58, 53)``, or hierarchical, e.g.
        ``(1, 8, 64)``). Empty means the default of the kind: ``(128,)`` or ``(64, 58, 53)``.
    gray_bits : int
        Gray-code bits (Gray kinds only); ``2 ** gray_bits >= periods[0]``.
    axis : {"columns", "rows"}
        ``"columns"``: vertical fringes encode the projector column ``u_p``.
    with_reference : bool
        Append a white and a black image.
    """

    kind: PatternKind
    phase_steps: int = 4
    periods: tuple[int, ...] = ()
    gray_bits: int = 7
    axis: Literal["columns", "rows"] = "columns"
    with_reference: bool = False

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ConfigError(f"pattern kind {self.kind!r} is unknown; use one of {', '.join(_KINDS)}")
        if self.axis not in _AXES:
            raise ConfigError(f"pattern axis {self.axis!r} is unknown; use 'columns' (vertical fringes) or 'rows'")
        if isinstance(self.phase_steps, bool) or not isinstance(self.phase_steps, (int, np.integer)) or self.phase_steps < 3:
            raise ConfigError(f"phase_steps must be an integer >= 3 (N-step phase shifting), got {self.phase_steps!r}")
        if isinstance(self.gray_bits, bool) or not isinstance(self.gray_bits, (int, np.integer)) or not 1 <= self.gray_bits <= 16:
            raise ConfigError(f"gray_bits must be an integer in 1..16, got {self.gray_bits!r}")
        periods = tuple(self.periods) if self.periods is not None else ()
        if not periods:
            periods = _DEFAULT_PERIODS[self.kind]
        if not all(isinstance(p, (int, np.integer)) and not isinstance(p, bool) and p >= 1 for p in periods):
            raise ConfigError(f"periods must be positive integers (fringe periods across the projector), got {periods!r}")
        periods = tuple(int(p) for p in periods)
        object.__setattr__(self, "periods", periods)
        object.__setattr__(self, "phase_steps", int(self.phase_steps))
        object.__setattr__(self, "gray_bits", int(self.gray_bits))
        object.__setattr__(self, "with_reference", bool(self.with_reference))
        if self.kind == "multi_frequency":
            if len(periods) not in (2, 3):
                raise ConfigError(f"multi_frequency needs 2 or 3 frequencies, got periods={periods!r}")
            if len(set(periods)) != len(periods):
                raise ConfigError(f"multi_frequency periods must differ, got {periods!r}")
            if unwrapping_scheme(periods) is None:
                raise ConfigError(
                    f"multi_frequency periods {periods!r} cannot be unwrapped: use a hierarchical set that contains "
                    "a single-period frequency, e.g. (1, 8, 64), or a heterodyne set whose beat of beats is one "
                    "period, e.g. (64, 58, 53) or (64, 63)"
                )
        else:
            if len(periods) != 1:
                raise ConfigError(f"{self.kind} uses exactly one frequency, got periods={periods!r}")
            if 2**self.gray_bits < periods[0]:
                raise ConfigError(
                    f"{self.gray_bits} Gray-code bits distinguish only {2**self.gray_bits} fringe orders but periods="
                    f"{periods[0]}; use gray_bits >= {int(np.ceil(np.log2(periods[0])))}"
                )

    def image_count(self) -> int:
        """Number of images of one frame."""
        return len(self.layout())

    def layout(self) -> tuple[PatternImage, ...]:
        """What each image shows, in capture order."""
        out: list[PatternImage] = []
        freqs = range(len(self.periods)) if self.kind == "multi_frequency" else range(1)
        for f in freqs:
            out.extend(PatternImage("phase", frequency=f, step=n) for n in range(self.phase_steps))
        if self.kind != "multi_frequency":
            out.extend(PatternImage("gray", bit=b) for b in range(self.gray_bits))
            if self.kind == "complementary_gray":
                out.append(PatternImage("complementary"))
        if self.with_reference:
            out.extend([PatternImage("white"), PatternImage("black")])
        return tuple(out)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "phase_steps": self.phase_steps,
            "periods": list(self.periods),
            "gray_bits": self.gray_bits,
            "axis": self.axis,
            "with_reference": self.with_reference,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str) -> PatternSpec:
        """Build from a mapping (e.g. the ``patterns`` section of ``sequence.yaml``).

        Raises
        ------
        ConfigError
            Unknown or missing keys, or bad values; the message starts with ``where``.
        """
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: a pattern spec must be a mapping, got {type(d).__name__}")
        known = {"kind", "phase_steps", "periods", "gray_bits", "axis", "with_reference"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"{where}: unknown pattern key(s) {', '.join(map(repr, unknown))}; valid keys: {', '.join(sorted(known))}")
        if "kind" not in d:
            raise ConfigError(f"{where}: pattern spec needs 'kind' ({', '.join(_KINDS)})")
        kwargs = dict(d)
        if "periods" in kwargs:
            p = kwargs["periods"]
            if isinstance(p, (int, np.integer)) and not isinstance(p, bool):
                p = [p]
            if not isinstance(p, (list, tuple)):
                raise ConfigError(f"{where}: periods must be a list of integers, got {p!r}")
            kwargs["periods"] = tuple(p)
        if "with_reference" in kwargs and not isinstance(kwargs["with_reference"], bool):
            raise ConfigError(f"{where}: with_reference must be true or false, got {kwargs['with_reference']!r}")
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None


def unwrapping_scheme(periods: tuple[int, ...]) -> str | None:
    """``"hierarchical"``, ``"heterodyne"`` or None (not unwrappable) for multi-frequency periods."""
    if 1 in periods:
        return "hierarchical"
    p = sorted(periods, reverse=True)
    if len(p) == 2 and p[0] - p[1] == 1:
        return "heterodyne"
    if len(p) == 3 and abs((p[0] - p[1]) - (p[1] - p[2])) == 1 and min(p[0] - p[1], p[1] - p[2]) >= 1:
        return "heterodyne"
    return None


def gray_encode(k: NDArray[np.integer]) -> NDArray[np.integer]:
    """Binary-reflected Gray code of non-negative integers."""
    k = np.asarray(k)
    return k ^ (k >> 1)


def _axis_length(spec: PatternSpec, projector_width: int, projector_height: int) -> int:
    return int(projector_width if spec.axis == "columns" else projector_height)


def pattern_intensity(
    spec: PatternSpec,
    index: int,
    u_projector_px: NDArray[np.floating],
    v_projector_px: NDArray[np.floating],
    projector_width: int,
    projector_height: int,
) -> NDArray[np.float64]:
    """Continuous value in [0, 1] of pattern image ``index`` at sub-pixel projector coordinates.

    Parameters
    ----------
    spec : PatternSpec
    index : int
        Image index in capture order, ``0 <= index < spec.image_count()``.
    u_projector_px, v_projector_px : array_like, same shape
        Projector coordinates in pixels, pixel-centre convention (pixel ``j`` centred at ``j``).
    projector_width, projector_height : int
        Projector size in pixels.

    Returns
    -------
    ndarray float64, the broadcast shape of the inputs
        Sinusoids: ``0.5 + 0.5 cos(phi - delta_n)``, un-quantised. Binary images (Gray bits,
        complementary bit): 0 or 1 from the projector pixel that contains the point. White 1,
        black 0. No gamma; :func:`generate_patterns` maps 0/1 to ``offset -+ amplitude``.
    """
    layout = spec.layout()
    if not 0 <= index < len(layout):
        raise ConfigError(f"pattern index {index} out of range: {spec.kind} set has {len(layout)} images")
    if int(projector_width) <= 0 or int(projector_height) <= 0:
        raise ConfigError(f"projector size must be positive, got {projector_width}x{projector_height}")
    u = np.asarray(u_projector_px, dtype=np.float64)
    v = np.asarray(v_projector_px, dtype=np.float64)
    coord = u if spec.axis == "columns" else v
    other = v if spec.axis == "columns" else u
    length = _axis_length(spec, projector_width, projector_height)
    img = layout[index]
    if img.role == "phase":
        periods = spec.periods[img.frequency]
        phi = (2.0 * np.pi * periods / length) * coord
        delta = 2.0 * np.pi * img.step / spec.phase_steps
        out = 0.5 + 0.5 * np.cos(phi - delta)
        shape = np.broadcast_shapes(coord.shape, other.shape)
        return out if out.shape == shape else np.broadcast_to(out, shape).copy()
    shape = np.broadcast_shapes(coord.shape, other.shape)
    if img.role == "white":
        return np.ones(shape)
    if img.role == "black":
        return np.zeros(shape)
    pixel = np.floor(coord + 0.5)
    periods = spec.periods[0]
    if img.role == "gray":
        k = np.floor(pixel * periods / length).astype(np.int64)
        code = gray_encode(np.clip(k, 0, None))
        bit = (code >> (spec.gray_bits - 1 - img.bit)) & 1
    else:  # complementary: LSB of the (gray_bits + 1)-bit Gray code of the half-period index
        k2 = np.floor(pixel * (2 * periods) / length).astype(np.int64)
        bit = gray_encode(np.clip(k2, 0, None)) & 1
    return np.broadcast_to(bit.astype(np.float64), shape).copy()


def generate_patterns(
    spec: PatternSpec,
    projector_width: int,
    projector_height: int,
    gamma: float = 1.0,
    amplitude: float = 127.5,
    offset: float = 127.5,
) -> NDArray[np.uint8]:
    """Render the pattern set as 8-bit projector images.

    Parameters
    ----------
    spec : PatternSpec
    projector_width, projector_height : int
        Projector size in pixels.
    gamma : float
        Projector gamma to pre-correct: the written level is ``255 (L / 255) ** (1 / gamma)``
        for the intended linear level ``L``, so a projector with response ``x ** gamma`` emits
        the intended sinusoid. 1.0 = no correction.
    amplitude, offset : float
        Intended (linear) levels: sinusoids ``offset + amplitude cos(...)``; binary and reference
        images ``offset +- amplitude``. Must stay within [0, 255].

    Returns
    -------
    (M, H, W) uint8
        ``M = spec.image_count()`` images in capture order, rounded to the nearest level.
    """
    width, height = int(projector_width), int(projector_height)
    if width <= 0 or height <= 0:
        raise ConfigError(f"projector size must be positive, got {projector_width}x{projector_height}")
    if not (gamma > 0 and np.isfinite(gamma)):
        raise ConfigError(f"gamma must be a positive finite number, got {gamma!r}")
    if amplitude < 0 or offset - amplitude < -1e-9 or offset + amplitude > 255 + 1e-9:
        raise ConfigError(f"pattern levels offset +- amplitude = {offset} +- {amplitude} leave the 8-bit range [0, 255]")
    length = _axis_length(spec, width, height)
    coord = np.arange(length, dtype=np.float64)
    zero = np.zeros(1)
    out = np.empty((spec.image_count(), height, width), dtype=np.uint8)
    for i in range(spec.image_count()):
        # The patterns are constant across the other axis: render one profile, then broadcast.
        u, v = (coord, zero) if spec.axis == "columns" else (zero, coord)
        profile = pattern_intensity(spec, i, u, v, width, height)
        level = np.clip(offset + amplitude * (2.0 * profile - 1.0), 0.0, 255.0)
        if gamma != 1.0:
            level = 255.0 * (level / 255.0) ** (1.0 / gamma)
        row = np.rint(level).astype(np.uint8)
        out[i] = row[None, :] if spec.axis == "columns" else row[:, None]
    return out
