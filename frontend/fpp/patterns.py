"""FPP pattern sets: N-step phase shifting, Gray code, complementary Gray code, multi-frequency,
single-period phase shifting and Gray code alone, in any image order.

A :class:`PatternSpec` says what the projector shows for one 3D frame, in capture order;
:func:`generate_patterns` renders it as 8-bit images for a projector of any size, and
:func:`pattern_intensity` gives the continuous value of any pattern image at sub-pixel projector
coordinates (for renderers that sample the patterns exactly). :mod:`frontend.fpp.pattern_file`
reads a spec from a YAML file (its docstring is the file's schema).

Conventions (the decoder in :mod:`frontend.fpp.phase` relies on every one of them)
------------------------------------------------------------------------------
* Encoded axis. ``axis="columns"``: vertical fringes, the intensity varies along projector
  columns and encodes ``u_p``; the "width" ``W`` below is the projector width. ``axis="rows"``:
  horizontal fringes encode ``v_p`` and ``W`` is the projector height. ``axis="both"`` (Gray
  code alone): column bits and row bits, both coordinates decoded.
* Pixel-centre coordinates. ``u_p`` is continuous and projector pixel ``j`` has its *centre* at
  ``u_p = j`` (it covers ``[j - 0.5, j + 0.5)``). Image pixel ``j`` of a pattern holds the
  pattern's value at ``u_p = j``; a binary pattern at a continuous ``u_p`` takes the value of
  pixel ``floor(u_p + 0.5)``.
* Phase (eq. 1). Phase-shift image ``n = 1..N`` of a frequency with ``P`` periods is
  ``I_n = a + b cos(phi + phi_0 - s delta_n)``, ``delta_n = 2 pi (n - 1) / N``, with
  ``phi = 2 pi P u_p / W``, ``phi_0 = phase_origin_rad`` (default 0: the phase origin is the
  centre of projector pixel 0) and ``s = +1`` for ``shift_direction="forward"`` (default),
  ``-1`` for ``"reverse"``. Hence (eq. 8) ``u_p = Phi * lambda / (2 pi)`` with the pitch
  ``lambda = W / P`` projector pixels; the decoder removes ``phi_0`` and ``s``.
* Fringe order. The wrapped phase is taken in ``[0, 2 pi)``, so it jumps where ``u_p`` is a
  multiple of ``lambda``; fringe order ``k = floor(P u_p / W)`` and ``Phi = phi + 2 pi k``.
* Gray code. Bit images encode ``gray(k) = k ^ (k >> 1)`` on ``gray_bits`` bits; bit ``0`` is
  the most significant; a bit image is bright (``offset + amplitude``) where the bit is 1, its
  inverse image (``gray_inverse``) is dark there. The default order is MSB first
  (``gray_order="lsb_first"`` reverses it).
* Gray code alone (``kind="gray_code"``): ``periods[0]`` = ``S`` stripes across the axis (default
  ``2 ** gray_bits``), stripe ``k = floor(S j / W)`` of projector pixel ``j``; the decoder returns
  the centre of the stripe's pixels (``(k + 1/2) W / S - 1/2`` when ``W / S`` is an integer),
  exact to half a stripe (RMS ``W / (S sqrt 12)``). ``S = W`` with ``gray_bits = ceil(log2 W)`` is OpenCV's column code.
  It needs either white/black references or inverse images to binarise the bits.
* Single period (``kind="single_frequency"``, ``periods=(1,)``): one fringe across the axis,
  the wrapped phase is already absolute.
* Complementary Gray code (Zhang et al.). One extra image after the Gray-code bits: the least
  significant bit of the ``gray_bits + 1``-bit Gray code of the half-period index
  ``floor(2 P u_p / W)``. Its code edges lie half a period away from the Gray code's, so a
  decoder switches between the two orders on the wrapped phase and never reads a code near its
  edge. (The upper ``gray_bits`` bits of that longer code are exactly the plain Gray code.)
* Levels. Sinusoids span ``offset +- amplitude``; binary images and the white/black references
  use exactly ``offset + amplitude`` and ``offset - amplitude``, so the per-pixel background
  ``a`` of the sinusoids is the ideal binarisation threshold of the bits.
* Capture order. Default (``order`` empty): white and black first if ``with_reference`` and
  ``reference_position="start"``; the N phase-shift images per frequency, frequencies in the
  order of ``periods``; the Gray-code bits (each followed by its inverse if ``gray_inverse``;
  for ``axis="both"`` the column bits, then the row bits); the complementary bit (and its
  inverse); white and black if ``with_reference`` at the ``"end"``. An explicit ``order``
  names each image's role with the tokens of :data:`ORDER_TOKENS` and replaces all of that.
* Multi-frequency sets must be unwrappable: either hierarchical (one frequency has exactly one
  period over the axis, e.g. ``(1, 8, 64)``) or heterodyne (the beat of the beats of the sorted
  periods is one period, e.g. ``(64, 58, 53)``: 64 - 58 = 6, 58 - 53 = 5, 6 - 5 = 1; for two
  frequencies their difference must be 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError

PatternKind = Literal["gray", "complementary_gray", "multi_frequency", "single_frequency", "gray_code"]
_KINDS = ("gray", "complementary_gray", "multi_frequency", "single_frequency", "gray_code")
_AXES = ("columns", "rows", "both")
_DEFAULT_PERIODS = {"gray": (128,), "complementary_gray": (128,), "multi_frequency": (64, 58, 53), "single_frequency": (1,)}
_GRAY_KINDS = ("gray", "complementary_gray", "gray_code")

#: The role names of an explicit image ``order`` (F = frequency index in ``periods``, N = phase
#: step 0..N-1 as projected, B = Gray bit, 0 = most significant).
ORDER_TOKENS = {
    "phase.F.N": "phase-shift image N of frequency F",
    "gray.B": "Gray-code bit B (column bit when axis is both)",
    "gray.B.inv": "inverse of Gray-code bit B",
    "gray_rows.B": "row Gray-code bit B (axis both only)",
    "gray_rows.B.inv": "inverse of row Gray-code bit B (axis both only)",
    "complementary": "the complementary Gray-code bit",
    "complementary.inv": "inverse of the complementary bit",
    "white": "white reference (full illumination)",
    "black": "black reference (projector dark)",
    "skip": "an image the decoder ignores",
}


class PatternImage(NamedTuple):
    """What one image of a pattern set shows.

    ``role`` is ``"phase"`` (``frequency`` indexes ``PatternSpec.periods``, ``step`` is n - 1 as
    projected), ``"gray"`` (``bit`` counts from the most significant bit, 0 = MSB),
    ``"complementary"``, ``"white"``, ``"black"`` or ``"skip"``. ``inverse`` marks the inverse
    of a binary image; ``axis`` is ``"rows"`` for the row bits of an ``axis="both"`` set, else
    ``""`` (the spec's axis). Unused fields are -1.
    """

    role: str
    frequency: int = -1
    step: int = -1
    bit: int = -1
    inverse: bool = False
    axis: str = ""

    def token(self) -> str:
        """The image's name in an explicit ``order`` (see :data:`ORDER_TOKENS`)."""
        if self.role == "phase":
            return f"phase.{self.frequency}.{self.step}"
        inv = ".inv" if self.inverse else ""
        if self.role == "gray":
            return f"{'gray_rows' if self.axis == 'rows' else 'gray'}.{self.bit}{inv}"
        if self.role == "complementary":
            return "complementary" + inv
        return self.role


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def parse_order_token(token: Any, spec: PatternSpec) -> PatternImage:
    """One explicit-order role name -> :class:`PatternImage`; ConfigError when unknown."""
    names = ", ".join(ORDER_TOKENS)
    if not isinstance(token, str):
        raise ConfigError(f"image role {token!r} is not a name; known roles: {names}")
    parts = token.strip().split(".")
    head, rest = parts[0], parts[1:]
    inverse = bool(rest) and rest[-1] == "inv"
    if inverse:
        rest = rest[:-1]
    try:
        numbers = [int(p) for p in rest]
    except ValueError:
        numbers = None
    bad = ConfigError(f"unknown image role {token!r}; known roles: {names}")
    if numbers is None:
        raise bad
    if head in ("white", "black", "skip") and not rest and not inverse:
        return PatternImage(head)
    if head == "complementary" and not numbers:
        return PatternImage("complementary", inverse=inverse)
    if head == "phase" and len(numbers) == 2 and not inverse:
        return PatternImage("phase", frequency=numbers[0], step=numbers[1])
    if head in ("gray", "gray_rows") and len(numbers) == 1:
        if head == "gray_rows" and spec.axis != "both":
            raise ConfigError(f"image role {token!r}: row bits exist only with axis 'both'; use gray.B for the {spec.axis} bits")
        return PatternImage("gray", bit=numbers[0], inverse=inverse, axis="rows" if head == "gray_rows" else "")
    raise bad


@dataclass(frozen=True)
class PatternSpec:
    """What a projector shows for one 3D frame, in capture order (see the module docstring).

    Attributes
    ----------
    kind : {"gray", "complementary_gray", "multi_frequency", "single_frequency", "gray_code"}
        Phase shifting with a Gray-code fringe order, with a complementary Gray code, with 2-3
        frequencies, with one period across the axis, or Gray code alone.
    phase_steps : int
        N >= 3 phase shifts per frequency (ignored by ``gray_code``).
    periods : tuple of int
        Fringe periods across the encoded axis. One entry for the Gray kinds, 2 or 3 for
        ``multi_frequency`` (heterodyne, e.g. ``(64, 58, 53)``, or hierarchical, e.g.
        ``(1, 8, 64)``), ``(1,)`` for ``single_frequency``; for ``gray_code`` the number of
        stripes (two entries, columns then rows, for ``axis="both"``). Empty means the default.
    gray_bits : int
        Gray-code bits; ``2 ** gray_bits >= periods[0]``.
    gray_bits_rows : int
        Row bits of an ``axis="both"`` set (0 = ``gray_bits``).
    axis : {"columns", "rows", "both"}
        ``"columns"``: vertical fringes encode the projector column ``u_p``.
    with_reference : bool
        A white and a black image.
    reference_position : {"end", "start"}
        Where the default order puts them.
    shift_direction : {"forward", "reverse"}
        Sign of the phase shift: ``cos(phi + phi_0 -+ delta_n)``.
    phase_origin_rad : float
        ``phi_0``, the projected phase at the centre of projector pixel 0.
    gray_order : {"msb_first", "lsb_first"}
        Bit order of the default order.
    gray_inverse : bool
        Each binary image is followed by its inverse (binarised against it).
    order : tuple of str
        Explicit capture order (role names, :data:`ORDER_TOKENS`); replaces the default order,
        and then decides ``with_reference`` and ``gray_inverse`` itself.
    """

    kind: PatternKind
    phase_steps: int = 4
    periods: tuple[int, ...] = ()
    gray_bits: int = 7
    axis: Literal["columns", "rows", "both"] = "columns"
    with_reference: bool = False
    reference_position: Literal["end", "start"] = "end"
    shift_direction: Literal["forward", "reverse"] = "forward"
    phase_origin_rad: float = 0.0
    gray_order: Literal["msb_first", "lsb_first"] = "msb_first"
    gray_inverse: bool = False
    gray_bits_rows: int = 0
    order: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        self._check_choices()
        if isinstance(self.phase_steps, bool) or not _is_int(self.phase_steps) or self.phase_steps < 3:
            raise ConfigError(f"phase_steps must be an integer >= 3 (N-step phase shifting), got {self.phase_steps!r}")
        for name in ("gray_bits", "gray_bits_rows"):
            value = getattr(self, name)
            if not _is_int(value) or not (0 if name == "gray_bits_rows" else 1) <= value <= 16:
                raise ConfigError(f"{name} must be an integer in 1..16, got {value!r}")
        if isinstance(self.phase_origin_rad, bool) or not isinstance(self.phase_origin_rad, (int, float, np.floating)) or not math.isfinite(self.phase_origin_rad):
            raise ConfigError(f"phase_origin_rad must be a finite number of radians, got {self.phase_origin_rad!r}")
        for name in ("with_reference", "gray_inverse"):
            object.__setattr__(self, name, bool(getattr(self, name)))
        object.__setattr__(self, "phase_steps", int(self.phase_steps))
        object.__setattr__(self, "gray_bits", int(self.gray_bits))
        object.__setattr__(self, "gray_bits_rows", int(self.gray_bits_rows) or int(self.gray_bits))
        object.__setattr__(self, "phase_origin_rad", float(self.phase_origin_rad))
        object.__setattr__(self, "periods", self._checked_periods())
        if self.kind == "gray_code" and not self.with_reference and not self.gray_inverse and not self.order:
            raise ConfigError("a gray_code set needs white/black references (with_reference: true) or inverse images (gray_inverse: true) to binarise its bits")
        if self.order:
            self._adopt_order()

    def _check_choices(self) -> None:
        choices = {
            "kind": _KINDS, "axis": _AXES, "reference_position": ("end", "start"),
            "shift_direction": ("forward", "reverse"), "gray_order": ("msb_first", "lsb_first"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(f"pattern {name} {getattr(self, name)!r} is unknown; use one of {', '.join(allowed)}")
        if self.axis == "both" and self.kind != "gray_code":
            raise ConfigError(f"axis 'both' is for Gray code alone (kind gray_code); a {self.kind} set encodes 'columns' or 'rows'")

    def _checked_periods(self) -> tuple[int, ...]:
        periods = tuple(self.periods) if self.periods is not None else ()
        if not periods:
            if self.kind == "gray_code":
                periods = (2**self.gray_bits,) + ((2**self.gray_bits_rows,) if self.axis == "both" else ())
            else:
                periods = _DEFAULT_PERIODS[self.kind]
        if not all(_is_int(p) and p >= 1 for p in periods):
            raise ConfigError(f"periods must be positive integers (fringe periods across the projector), got {periods!r}")
        periods = tuple(int(p) for p in periods)
        if self.kind == "multi_frequency":
            if len(periods) not in (2, 3):
                raise ConfigError(f"multi_frequency needs 2 or 3 frequencies, got periods={periods!r}; one period across the projector is kind single_frequency")
            if len(set(periods)) != len(periods):
                raise ConfigError(f"multi_frequency periods must differ, got {periods!r}")
            if unwrapping_scheme(periods) is None:
                raise ConfigError(
                    f"multi_frequency periods {periods!r} cannot be unwrapped: use a hierarchical set that contains "
                    "a single-period frequency, e.g. (1, 8, 64), or a heterodyne set whose beat of beats is one "
                    "period, e.g. (64, 58, 53) or (64, 63)"
                )
        elif self.kind == "single_frequency":
            if periods != (1,):
                raise ConfigError(f"single_frequency is one period across the projector (periods [1]), got {periods!r}; more periods need a Gray code (kind gray or complementary_gray) or several frequencies")
        else:
            count = 2 if self.axis == "both" else 1
            if len(periods) != count:
                what = "one frequency" if count == 1 else "two stripe counts (columns, rows)"
                raise ConfigError(f"{self.kind} with axis {self.axis} uses exactly {what}, got periods={periods!r}")
            for p, bits in zip(periods, (self.gray_bits, self.gray_bits_rows), strict=False):
                if 2**bits < p:
                    raise ConfigError(f"{bits} Gray-code bits distinguish only {2**bits} fringe orders but periods={p}; use gray_bits >= {math.ceil(math.log2(p))}")
        return periods

    def _adopt_order(self) -> None:
        """Check an explicit order against the set and take references/inverses from it."""
        images = [parse_order_token(t, self) for t in self.order]
        tokens = [im.token() for im in images]
        dup = sorted({t for t in tokens if tokens.count(t) > 1 and t != "skip"})
        if dup:
            raise ConfigError(f"image order names {', '.join(dup)} more than once")
        has = set(tokens)
        object.__setattr__(self, "order", tuple(tokens))
        object.__setattr__(self, "with_reference", "white" in has or "black" in has)
        object.__setattr__(self, "gray_inverse", any(im.inverse for im in images))
        needed = [im.token() for im in self._default_layout()]
        missing = [t for t in needed if t not in has]
        extra = sorted(has - set(needed) - {"skip"})
        if missing or extra:
            what = (f"misses {', '.join(missing)}" if missing else "") + ("; " if missing and extra else "") + (f"has roles this set does not use: {', '.join(extra)}" if extra else "")
            raise ConfigError(f"image order {what} (a {self.kind} set with these settings has {', '.join(needed)})")
        if self.kind == "gray_code" and not self.with_reference and not self.gray_inverse:
            raise ConfigError("a gray_code set needs white/black references or inverse images in its order to binarise its bits")

    @property
    def n_frequencies(self) -> int:
        return len(self.periods) if self.kind in ("multi_frequency", "single_frequency") else (0 if self.kind == "gray_code" else 1)

    @property
    def coded_axis(self) -> Literal["columns", "rows"]:
        """The axis triangulation uses (``"columns"`` for ``axis="both"``)."""
        return "columns" if self.axis == "both" else self.axis

    def image_count(self) -> int:
        """Number of images of one frame."""
        return len(self.layout())

    def layout(self) -> tuple[PatternImage, ...]:
        """What each image shows, in capture order."""
        if self.order:
            return tuple(parse_order_token(t, self) for t in self.order)
        return self._default_layout()

    def _default_layout(self) -> tuple[PatternImage, ...]:
        out: list[PatternImage] = []
        refs = [PatternImage("white"), PatternImage("black")] if self.with_reference else []
        if self.reference_position == "start":
            out.extend(refs)
        for f in range(self.n_frequencies if self.kind != "gray_code" else 0):
            out.extend(PatternImage("phase", frequency=f, step=n) for n in range(self.phase_steps))
        if self.kind in _GRAY_KINDS:
            axes = [("", self.gray_bits)] + ([("rows", self.gray_bits_rows)] if self.axis == "both" else [])
            for axis, nbits in axes:
                bits = range(nbits) if self.gray_order == "msb_first" else range(nbits - 1, -1, -1)
                for b in bits:
                    out.append(PatternImage("gray", bit=b, axis=axis))
                    if self.gray_inverse:
                        out.append(PatternImage("gray", bit=b, inverse=True, axis=axis))
            if self.kind == "complementary_gray":
                out.append(PatternImage("complementary"))
                if self.gray_inverse:
                    out.append(PatternImage("complementary", inverse=True))
        if self.reference_position == "end":
            out.extend(refs)
        return tuple(out)

    def to_dict(self) -> dict[str, Any]:
        """The spec as plain data; keys at their defaults beyond the original six are left out."""
        out: dict[str, Any] = {
            "kind": self.kind,
            "phase_steps": self.phase_steps,
            "periods": list(self.periods),
            "gray_bits": self.gray_bits,
            "axis": self.axis,
            "with_reference": self.with_reference,
        }
        defaults = {"reference_position": "end", "shift_direction": "forward", "phase_origin_rad": 0.0, "gray_order": "msb_first", "gray_inverse": False}
        for key, default in defaults.items():
            if getattr(self, key) != default:
                out[key] = getattr(self, key)
        if self.gray_bits_rows != self.gray_bits:
            out["gray_bits_rows"] = self.gray_bits_rows
        if self.order:
            out["order"] = list(self.order)
            out.pop("with_reference")
            out.pop("gray_inverse", None)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str) -> PatternSpec:
        """Build from a mapping (e.g. the ``patterns`` section of ``sequence.yaml``).

        Raises
        ------
        ConfigError
            Unknown or missing keys, or bad values; the message starts with ``where``.

        A mapping with a ``fringe_sets`` key is the fringe-set form: read it with
        :func:`frontend.fpp.pattern_file.pattern_spec_from_dict`, which takes either form.
        """
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: a pattern spec must be a mapping, got {type(d).__name__}")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"{where}: unknown pattern key(s) {', '.join(map(repr, unknown))}; valid keys: {', '.join(sorted(known))}")
        if "kind" not in d:
            raise ConfigError(f"{where}: pattern spec needs 'kind' ({', '.join(_KINDS)})")
        kwargs = dict(d)
        for key in ("periods", "order"):
            if key not in kwargs:
                continue
            p = kwargs[key]
            if key == "periods" and _is_int(p):
                p = [p]
            if not isinstance(p, (list, tuple)):
                raise ConfigError(f"{where}: {key} must be a list, got {p!r}")
            kwargs[key] = tuple(p)
        for key in ("with_reference", "gray_inverse"):
            if key in kwargs and not isinstance(kwargs[key], bool):
                raise ConfigError(f"{where}: {key} must be true or false, got {kwargs[key]!r}")
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


def opencv_gray_code_spec(projector_width: int, projector_height: int, step: int = 1) -> PatternSpec:
    """OpenCV ``structured_light.GrayCodePattern`` as procam-calibration captures it.

    ``ceil(log2 S)`` column bits, then row bits, MSB first, each image followed by its inverse,
    then white and black; ``S = ceil(W / step)`` column and ``ceil(H / step)`` row stripes of
    ``step`` projector pixels (checked against procam-calibration's pattern PNGs and OpenCV's
    ``GrayCodePattern.generate`` by the tests). The decoder gives each stripe's centre.
    """
    width, height, step = int(projector_width), int(projector_height), int(step)
    if width <= 0 or height <= 0 or step <= 0:
        raise ConfigError(f"Gray-code set for a {projector_width}x{projector_height} projector with step {step}: sizes and step must be positive")
    columns, rows = (width - 1) // step + 1, (height - 1) // step + 1
    return PatternSpec(
        kind="gray_code", axis="both", periods=(columns, rows), gray_bits=max(1, math.ceil(math.log2(columns))),
        gray_bits_rows=max(1, math.ceil(math.log2(rows))), gray_inverse=True, with_reference=True, reference_position="end",
    )


def gray_encode(k: NDArray[np.integer]) -> NDArray[np.integer]:
    """Binary-reflected Gray code of non-negative integers."""
    k = np.asarray(k)
    return k ^ (k >> 1)


def _axis_length(spec: PatternSpec, projector_width: int, projector_height: int, image: PatternImage | None = None) -> int:
    return int(projector_height if _image_axis(spec, image) == "rows" else projector_width)


def _image_axis(spec: PatternSpec, image: PatternImage | None) -> str:
    """The projector axis along which an image varies."""
    if image is not None and image.axis:
        return image.axis
    return spec.coded_axis


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
    spec : PatternSpec or frontend.fpp.fringe_sets.FringeSetSpec
        (the latter gives its own ``spec.intensity``)
    index : int
        Image index in capture order, ``0 <= index < spec.image_count()``.
    u_projector_px, v_projector_px : array_like, same shape
        Projector coordinates in pixels, pixel-centre convention (pixel ``j`` centred at ``j``).
    projector_width, projector_height : int
        Projector size in pixels.

    Returns
    -------
    ndarray float64, the broadcast shape of the inputs
        Sinusoids: ``0.5 + 0.5 cos(phi + phi_0 -+ delta_n)``, un-quantised. Binary images (Gray
        bits, complementary bit): 0 or 1 from the projector pixel that contains the point
        (inverses 1 or 0). White 1, black and ``skip`` 0. No gamma; :func:`generate_patterns`
        maps 0/1 to ``offset -+ amplitude``.
    """
    if not isinstance(spec, PatternSpec):  # a fringe-set spec renders its own images
        return spec.intensity(index, u_projector_px, v_projector_px, projector_width, projector_height)
    layout = spec.layout()
    if not 0 <= index < len(layout):
        raise ConfigError(f"pattern index {index} out of range: {spec.kind} set has {len(layout)} images")
    if int(projector_width) <= 0 or int(projector_height) <= 0:
        raise ConfigError(f"projector size must be positive, got {projector_width}x{projector_height}")
    img = layout[index]
    u = np.asarray(u_projector_px, dtype=np.float64)
    v = np.asarray(v_projector_px, dtype=np.float64)
    rows = _image_axis(spec, img) == "rows"
    coord = v if rows else u
    length = _axis_length(spec, projector_width, projector_height, img)
    shape = np.broadcast_shapes(u.shape, v.shape)
    if img.role == "phase":
        periods = spec.periods[img.frequency]
        phi = (2.0 * np.pi * periods / length) * coord
        sign = 1.0 if spec.shift_direction == "forward" else -1.0
        delta = 2.0 * np.pi * img.step / spec.phase_steps
        out = 0.5 + 0.5 * np.cos(phi + spec.phase_origin_rad - sign * delta)
        return out if out.shape == shape else np.broadcast_to(out, shape).copy()
    if img.role == "white":
        return np.ones(shape)
    if img.role in ("black", "skip"):
        return np.zeros(shape)
    pixel = np.floor(coord + 0.5)
    periods = spec.periods[1 if rows and spec.axis == "both" else 0]
    if img.role == "gray":
        k = np.floor(pixel * periods / length).astype(np.int64)
        code = gray_encode(np.clip(k, 0, None))
        nbits = spec.gray_bits_rows if img.axis == "rows" else spec.gray_bits
        bit = (code >> (nbits - 1 - img.bit)) & 1
    else:  # complementary: LSB of the (gray_bits + 1)-bit Gray code of the half-period index
        k2 = np.floor(pixel * (2 * periods) / length).astype(np.int64)
        bit = gray_encode(np.clip(k2, 0, None)) & 1
    if img.inverse:
        bit = 1 - bit
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
    spec : PatternSpec or frontend.fpp.fringe_sets.FringeSetSpec
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
    zero = np.zeros(1)
    layout = spec.layout()
    out = np.empty((len(layout), height, width), dtype=np.uint8)
    for i, image in enumerate(layout):
        # The patterns are constant across the other axis: render one profile, then broadcast
        # (a fringe-set image that varies along both axes is rendered whole).
        if not isinstance(spec, PatternSpec) and spec.image_is_2d(i):
            profile = pattern_intensity(spec, i, np.arange(width, dtype=np.float64)[None, :], np.arange(height, dtype=np.float64)[:, None], width, height)
            out[i] = np.rint(_levels(profile, amplitude, offset, gamma)).astype(np.uint8)
            continue
        rows = (image.axis if not isinstance(spec, PatternSpec) else _image_axis(spec, image)) == "rows"
        coord = np.arange(height if rows else width, dtype=np.float64)
        u, v = (zero, coord) if rows else (coord, zero)
        profile = pattern_intensity(spec, i, u, v, width, height)
        row = np.rint(_levels(profile, amplitude, offset, gamma)).astype(np.uint8)
        out[i] = row[:, None] if rows else row[None, :]
    return out


def _levels(profile: NDArray, amplitude: float, offset: float, gamma: float) -> NDArray:
    """Pattern values in [0, 1] -> written grey levels (gamma pre-corrected)."""
    level = np.clip(offset + amplitude * (2.0 * profile - 1.0), 0.0, 255.0)
    if gamma != 1.0:
        level = 255.0 * (level / 255.0) ** (1.0 / gamma)
    return level
