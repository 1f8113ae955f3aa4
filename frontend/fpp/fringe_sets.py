"""Pattern sets as lists of fringe sets: any axis, pitch, step count and image order per set.

A :class:`FringeSetSpec` describes one capture as a list of fringe sets (each with its own
axis, pitch, number of steps, shift convention and image positions), optional Gray codes per
axis and optional white/black references. It is what a pattern file with a top-level
``fringe_sets`` key holds (:mod:`frontend.fpp.pattern_file`), e.g. a commercial camera's
36-image capture: per axis 1, 8, 32 and 128 periods (pitches 1280, 160, 40 and 10 px) with 4,
4, 4 and 6 steps, the 6-step set stored from its fourth step.

Conventions (those of :mod:`frontend.fpp.patterns`, per set)
-----------------------------------------------------------
* A set on ``axis: columns`` varies along projector columns and encodes ``u_p``; ``rows``
  encodes ``v_p``. The axis length ``L`` is the projector width or height.
* Pitch ``lambda`` (projector pixels): ``pitch_px``, or ``L / periods`` (fractions allowed:
  0.5625 periods across 720 rows is a 1280-px pitch). The projected phase is
  ``theta = 2 pi c / lambda + phi_0`` at coordinate ``c`` (pixel-centre convention).
* ``codec: phase_shift`` (default): step ``n = 0..N-1`` shows ``0.5 + 0.5 cos(theta - s 2 pi n / N)``,
  ``s = +1`` forward, ``-1`` reverse.
* ``codec: two_plus_one`` (Zhang and Yau 2006/2007), 3 images: step 0 ``0.5 + 0.5 s sin(theta)``,
  step 1 ``0.5 + 0.5 cos(theta)``, step 2 flat ``0.5``; ``phi = atan2(s (I_0 - I_2), I_1 - I_2)``.
* ``codec: modulated_phase_shift`` and ``micro_phase_shift``: the images of
  :mod:`frontend.fpp.modulated_phase_shift` and :mod:`frontend.fpp.micro_phase_shift` (loaded
  when a set uses them).
* Image positions: ``images`` lists the capture index of each step 0..N-1; without it a set
  takes the next N free images in capture order, the first of them holding step
  ``first_step`` (then ``first_step + 1``, ... wrapping to 0). Images named by index are taken
  first; references at the ``start`` take the first free images, then the sets in list order,
  then the Gray codes, then references at the ``end``.
* Gray code (per axis, the conventions of :mod:`frontend.fpp.patterns`): stripe
  ``k = floor(j / lambda)`` of projector pixel ``j`` for the pitch ``lambda`` of the one phase
  set on that axis it unwraps; ``bits`` bits (bit 0 the most significant, ``order`` in capture
  order), optionally each followed by its inverse, optionally the complementary half-period bit.

Unwrapping (per axis, inferred by :mod:`frontend.fpp.fringe_unwrapping`; anything else is a
ConfigError naming the sets)
-------------------------------------------------------------------------------------------
* micro phase shifting: the set's coordinate is absolute; it is the axis's only set.
* Gray code: one phase set on the axis, ``2 ** bits >= ceil(L / lambda)``.
* hierarchical: sorted coarse to fine, the coarsest covers the axis (``lambda >= L``); each
  level is unwrapped from the previous one (any pitch ratio > 1).
* heterodyne: two sets whose beat ``lambda_1 lambda_2 / |lambda_1 - lambda_2|`` covers the
  axis, or three whose beat of beats does.
* spatial (opt-in, ``unwrapping: spatial`` on the axis's only set, of more than one period):
  the phase is unwrapped across the image per connected region of valid pixels, and each
  region's fringe order fixed by the projector's extent or by the anchor
  ``centre_coordinate_px`` (:mod:`frontend.fpp.fringe_decoding`, "Spatial unwrapping").
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import ConfigError
from frontend.fpp.fringe_unwrapping import AxisPlan, plan_axis
from frontend.fpp.patterns import gray_encode

AXES = ("columns", "rows")
CODECS = ("phase_shift", "two_plus_one", "modulated_phase_shift", "micro_phase_shift")
# Codecs whose wrapped phase joins hierarchical/heterodyne/Gray-code (or spatial) unwrapping.
PHASE_CODECS = ("phase_shift", "two_plus_one", "modulated_phase_shift")
_CODEC_MODULES = {"modulated_phase_shift": "ModulatedPhaseShift", "micro_phase_shift": "MicroPhaseShift"}


class FringeImage(NamedTuple):
    """What one image of a fringe-set capture shows.

    ``role`` is ``"phase"`` (image ``step`` of fringe set ``set_index``, named ``name``),
    ``"gray"`` (bit ``bit``, 0 = most significant, of the Gray code on ``axis``),
    ``"complementary"``, ``"white"`` or ``"black"``; ``inverse`` marks an inverse image.
    """

    role: str
    axis: str = ""
    set_index: int = -1
    name: str = ""
    step: int = -1
    bit: int = -1
    inverse: bool = False

    def token(self) -> str:
        """The image's role as ``fpp-slam patterns FILE`` lists it."""
        inv = ".inv" if self.inverse else ""
        if self.role == "phase":
            return f"{self.name}.{self.step}"
        if self.role == "gray":
            return f"gray_{self.axis}.{self.bit}{inv}"
        if self.role == "complementary":
            return f"complementary_{self.axis}{inv}"
        return self.role


def _number(value: Any, what: str, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not math.isfinite(value):
        raise ConfigError(f"{what} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{what} must be positive, got {value!r}")
    return float(value)


def _integer(value: Any, what: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ConfigError(f"{what} must be an integer >= {low}, got {value!r}")
    return int(value)


def _indices(value: Any, what: str) -> tuple[int, ...]:
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{what} must be a list of capture indices, got {value!r}")
    return tuple(_integer(v, f"{what} entry", 0) for v in value)


def load_codec(name: str, where: str):
    """The codec module's class (``ModulatedPhaseShift`` / ``MicroPhaseShift``), or ConfigError."""
    try:
        module = importlib.import_module(f"frontend.fpp.{name}")
    except ImportError:
        prefix = f"{where}: " if where else ""
        raise ConfigError(f"{prefix}codec {name} needs frontend/fpp/{name}.py, which this installation does not have") from None
    return getattr(module, _CODEC_MODULES[name])


@dataclass(frozen=True)
class FringeSet:
    """One fringe set (see the module docstring). ``pitch_px`` or ``periods``, exactly one."""

    axis: str
    steps: int = 0
    pitch_px: float | None = None
    periods: float | None = None
    shift_direction: str = "forward"
    phase_origin_rad: float = 0.0
    images: tuple[int, ...] = ()
    first_step: int = 0
    name: str = ""
    codec: str = "phase_shift"
    carrier_steps: int = 0
    carrier_pitch_px: float = 0.0
    pitches_px: tuple[float, ...] = ()
    unwrapping: str = ""
    centre_coordinate_px: float | None = None

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ConfigError(f"axis {self.axis!r} is unknown; use columns or rows")
        if self.codec not in CODECS:
            raise ConfigError(f"codec {self.codec!r} is unknown; use one of {', '.join(CODECS)}")
        if self.shift_direction not in ("forward", "reverse"):
            raise ConfigError(f"shift_direction {self.shift_direction!r} is unknown; use forward or reverse")
        object.__setattr__(self, "phase_origin_rad", _number(self.phase_origin_rad, "phase_origin_rad", positive=False))
        self._check_unwrapping()
        if self.codec == "micro_phase_shift":
            self._check_micro()
        else:
            self._check_phase()
        object.__setattr__(self, "first_step", _integer(self.first_step, "first_step", 0))
        object.__setattr__(self, "images", tuple(self.images))
        count = self.image_count()
        if self.images and len(self.images) != count:
            raise ConfigError(f"images lists {len(self.images)} capture indices for a set of {count} images")
        if len(set(self.images)) != len(self.images):
            raise ConfigError(f"images {list(self.images)} names a capture index twice")
        if self.first_step >= count:
            raise ConfigError(f"first_step {self.first_step} is not a step of a {count}-image set (0..{count - 1})")

    def _check_phase(self) -> None:
        if (self.pitch_px is None) == (self.periods is None):
            raise ConfigError("give exactly one of pitch_px (projector pixels) or periods (across the axis)")
        if self.pitch_px is not None:
            object.__setattr__(self, "pitch_px", _number(self.pitch_px, "pitch_px"))
        else:
            object.__setattr__(self, "periods", _number(self.periods, "periods"))
        if self.pitches_px:
            raise ConfigError(f"pitches_px is for codec micro_phase_shift, not {self.codec}")
        if self.codec == "two_plus_one":
            steps = 3 if self.steps in (0, 3) else self.steps
            if steps != 3:
                raise ConfigError(f"codec two_plus_one has 3 images (sin, cos, flat), got steps {self.steps!r}")
            object.__setattr__(self, "steps", 3)
        else:
            object.__setattr__(self, "steps", _integer(self.steps, "steps (phase shifts N)", 3))
        if self.codec == "modulated_phase_shift":
            object.__setattr__(self, "carrier_steps", _integer(self.carrier_steps, "carrier_steps", 2))
            object.__setattr__(self, "carrier_pitch_px", _number(self.carrier_pitch_px, "carrier_pitch_px"))
        elif self.carrier_steps or self.carrier_pitch_px:
            raise ConfigError(f"carrier_steps and carrier_pitch_px are for codec modulated_phase_shift, not {self.codec}")

    def _check_unwrapping(self) -> None:
        if self.unwrapping not in ("", "spatial"):
            raise ConfigError(f"unwrapping {self.unwrapping!r} is unknown; use spatial (or leave it out: inferred per axis)")
        if self.unwrapping and self.codec not in PHASE_CODECS:
            raise ConfigError(f"unwrapping: spatial is for a wrapped phase; codec {self.codec} is absolute")
        if self.centre_coordinate_px is not None:
            if not self.unwrapping:
                raise ConfigError("centre_coordinate_px anchors spatial unwrapping; give it with unwrapping: spatial")
            object.__setattr__(self, "centre_coordinate_px", _number(self.centre_coordinate_px, "centre_coordinate_px", positive=False))

    def _check_micro(self) -> None:
        if self.pitch_px is not None or self.periods is not None or self.steps:
            raise ConfigError("a micro_phase_shift set gives pitches_px: [...] instead of pitch_px, periods and steps")
        if not isinstance(self.pitches_px, (list, tuple)) or len(self.pitches_px) < 2:
            raise ConfigError(f"pitches_px must list at least two pitches (projector pixels), got {self.pitches_px!r}")
        object.__setattr__(self, "pitches_px", tuple(_number(p, "pitches_px entry") for p in self.pitches_px))

    @property
    def is_phase(self) -> bool:
        """Gives a wrapped phase that the axis's unwrapping uses."""
        return self.codec in PHASE_CODECS

    def image_count(self) -> int:
        if self.codec == "modulated_phase_shift":
            return self.steps * self.carrier_steps
        if self.codec == "micro_phase_shift":
            return int(self.codec_object("").image_count)
        return self.steps

    def pitch(self, axis_length_px: int) -> float:
        """Fringe pitch, projector pixels, for an axis of ``axis_length_px`` pixels."""
        if self.codec == "micro_phase_shift":
            return min(self.pitches_px)
        return float(self.pitch_px) if self.pitch_px is not None else axis_length_px / float(self.periods)

    def codec_object(self, where: str):
        """The codec instance of a modulated or micro phase-shift set."""
        cls = load_codec(self.codec, where)
        if self.codec == "micro_phase_shift":
            return cls(self.pitches_px)
        return cls(self.steps, self.carrier_steps, self.carrier_pitch_px)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        defaults = {f.name: f.default for f in fields(self)}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "axis" or value != defaults[f.name]:
                out[f.name] = list(value) if isinstance(value, tuple) else value
        return out


@dataclass(frozen=True)
class GrayCodeSet:
    """A Gray code on one axis that unwraps the axis's phase set (see the module docstring)."""

    axis: str
    bits: int
    order: str = "msb_first"
    inverse: bool = False
    complementary: bool = False
    images: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ConfigError(f"axis {self.axis!r} is unknown; use columns or rows")
        object.__setattr__(self, "bits", _integer(self.bits, "bits", 1))
        if self.bits > 16:
            raise ConfigError(f"bits must be at most 16, got {self.bits}")
        if self.order not in ("msb_first", "lsb_first"):
            raise ConfigError(f"order {self.order!r} is unknown; use msb_first or lsb_first")
        for name in ("inverse", "complementary"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name} must be true or false, got {getattr(self, name)!r}")
        object.__setattr__(self, "images", tuple(self.images))
        if self.images and len(self.images) != len(self.roles()):
            raise ConfigError(f"images lists {len(self.images)} capture indices for a Gray code of {len(self.roles())} images")

    def roles(self) -> list[FringeImage]:
        """Its images in its own capture order: bits (each followed by its inverse), complementary bit."""
        bits = range(self.bits) if self.order == "msb_first" else range(self.bits - 1, -1, -1)
        out = []
        for b in bits:
            out.append(FringeImage("gray", axis=self.axis, bit=b))
            if self.inverse:
                out.append(FringeImage("gray", axis=self.axis, bit=b, inverse=True))
        if self.complementary:
            out.append(FringeImage("complementary", axis=self.axis))
            if self.inverse:
                out.append(FringeImage("complementary", axis=self.axis, inverse=True))
        return out

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"axis": self.axis, "bits": self.bits}
        for key, default in (("order", "msb_first"), ("inverse", False), ("complementary", False)):
            if getattr(self, key) != default:
                out[key] = getattr(self, key)
        if self.images:
            out["images"] = list(self.images)
        return out


@dataclass(frozen=True)
class FringeSetSpec:
    """A capture as a list of fringe sets (module docstring); duck-types :class:`PatternSpec`.

    Attributes
    ----------
    fringe_sets : tuple of FringeSet
    gray_codes : tuple of GrayCodeSet
        At most one per axis.
    references : {"", "start", "end", "index"}
        White/black references: none, first, last, or at ``white_index`` / ``black_index``.
    """

    fringe_sets: tuple[FringeSet, ...]
    gray_codes: tuple[GrayCodeSet, ...] = ()
    references: str = ""
    white_index: int | None = None
    black_index: int | None = None

    kind = "fringe_sets"

    def __post_init__(self) -> None:
        if not self.fringe_sets:
            raise ConfigError("fringe_sets is empty: list at least one fringe set")
        names = [self.set_name(i) for i in range(len(self.fringe_sets))]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"fringe set names {', '.join(dup)} are used twice; give every set its own name")
        axes = [g.axis for g in self.gray_codes]
        if len(set(axes)) != len(axes):
            raise ConfigError("two Gray codes on one axis; give at most one per axis")
        if self.references not in ("", "start", "end", "index"):
            raise ConfigError(f"references {self.references!r} is unknown; use start, end or {{white: INDEX, black: INDEX}}")
        object.__setattr__(self, "_layout", self._place_images())
        self.plans(None, None)  # what can be checked without the projector size

    # ------------------------------------------------------------------ layout
    def set_name(self, i: int) -> str:
        return self.fringe_sets[i].name or f"set{i}"

    def _place_images(self) -> tuple[FringeImage, ...]:
        groups: list[tuple[list[FringeImage], tuple[int, ...]]] = []
        refs = [FringeImage("white"), FringeImage("black")]
        if self.references == "start":
            groups.append((refs, ()))
        for i, s in enumerate(self.fringe_sets):
            n = s.image_count()
            roles = [FringeImage("phase", s.axis, i, self.set_name(i), step) for step in range(n)]
            if not s.images:  # capture order from first_step, wrapping
                roles = roles[s.first_step:] + roles[:s.first_step]
            groups.append((roles, s.images))
        for g in self.gray_codes:
            groups.append((g.roles(), g.images))
        if self.references == "end":
            groups.append((refs, ()))
        elif self.references == "index":
            if self.white_index is None or self.black_index is None:
                raise ConfigError("references by index need both white and black capture indices")
            groups.append((refs, (self.white_index, self.black_index)))
        total = sum(len(r) for r, _ in groups)
        slots: list[FringeImage | None] = [None] * total
        for roles, index in groups:
            for role, j in zip(roles, index, strict=False):
                if j >= total:
                    raise ConfigError(f"capture index {j} ({role.token()}) is beyond the {total} images of this capture (0..{total - 1})")
                if slots[j] is not None:
                    raise ConfigError(f"capture index {j} is given to both {slots[j].token()} and {role.token()}")
                slots[j] = role
        free = iter(j for j in range(total) if slots[j] is None)
        for roles, index in groups:
            if not index:
                for role in roles:
                    slots[next(free)] = role
        return tuple(slots)  # type: ignore[arg-type]

    def layout(self) -> tuple[FringeImage, ...]:
        """What each image shows, in capture order."""
        return self._layout

    def image_count(self) -> int:
        return len(self._layout)

    def set_image_indices(self, i: int) -> list[int]:
        """Capture indices of set ``i``'s images, in its step order 0..N-1."""
        by_step = {im.step: j for j, im in enumerate(self._layout) if im.role == "phase" and im.set_index == i}
        return [by_step[n] for n in range(len(by_step))]

    def gray_image_indices(self, axis: str) -> tuple[list[int], list[int]]:
        """Code images of the axis's Gray code (bits MSB first, then the complementary bit) and their inverses."""
        def index(role: str, bit: int, inverse: bool) -> int:
            return next(j for j, im in enumerate(self._layout) if im.role == role and im.axis == axis and im.bit == bit and im.inverse == inverse)

        gray = self.gray_code(axis)
        if gray is None:
            return [], []
        code = [index("gray", b, False) for b in range(gray.bits)]
        inverse = [index("gray", b, True) for b in range(gray.bits)] if gray.inverse else []
        if gray.complementary:
            code.append(index("complementary", -1, False))
            if gray.inverse:
                inverse.append(index("complementary", -1, True))
        return code, inverse

    def reference_indices(self) -> tuple[int | None, int | None]:
        white = next((j for j, im in enumerate(self._layout) if im.role == "white"), None)
        black = next((j for j, im in enumerate(self._layout) if im.role == "black"), None)
        return white, black

    def gray_code(self, axis: str) -> GrayCodeSet | None:
        return next((g for g in self.gray_codes if g.axis == axis), None)

    @property
    def axis(self) -> str:
        """``"columns"``, ``"rows"`` or ``"both"``: the axes the sets encode."""
        axes = {s.axis for s in self.fringe_sets}
        return "both" if len(axes) == 2 else axes.pop()

    @property
    def coded_axis(self) -> str:
        """The axis triangulation uses (``"columns"`` for ``"both"``)."""
        return "columns" if self.axis == "both" else self.axis

    # ------------------------------------------------------------------ unwrapping
    def plans(self, projector_width: int | None, projector_height: int | None) -> dict[str, AxisPlan]:
        """The unwrapping of each axis; ConfigError naming the sets when one cannot be unwrapped.

        Without the projector size, only axes whose sets all give ``periods`` are fully checked
        (a pitch needs the axis length to say whether it covers the axis).
        """
        out = {}
        for axis in AXES:
            members = [i for i, s in enumerate(self.fringe_sets) if s.axis == axis]
            if not members:
                if self.gray_code(axis) is not None:
                    raise ConfigError(f"a Gray code on axis {axis} but no fringe set there to unwrap; Gray code alone is kind gray_code")
                continue
            length = projector_width if axis == "columns" else projector_height
            plan = plan_axis(self, axis, members, length)
            if plan is not None:
                out[axis] = plan
        return out

    def check_projector(self, projector_width: int, projector_height: int) -> dict[str, AxisPlan]:
        """The unwrapping plans for this projector (ConfigError when an axis cannot be unwrapped)."""
        if int(projector_width) <= 0 or int(projector_height) <= 0:
            raise ConfigError(f"projector size must be positive, got {projector_width}x{projector_height}")
        return self.plans(int(projector_width), int(projector_height))

    # ------------------------------------------------------------------ patterns
    def intensity(self, index: int, u_projector_px: NDArray, v_projector_px: NDArray, projector_width: int, projector_height: int) -> NDArray[np.float64]:
        """Continuous value in [0, 1] of image ``index`` at sub-pixel projector coordinates
        (as :func:`frontend.fpp.patterns.pattern_intensity`): sinusoids un-quantised, binary
        images 0/1 from the projector pixel that contains the point, white 1, black 0."""
        if not 0 <= index < self.image_count():
            raise ConfigError(f"pattern index {index} out of range: this fringe-set capture has {self.image_count()} images")
        self.check_projector(projector_width, projector_height)
        image = self._layout[index]
        u = np.asarray(u_projector_px, dtype=np.float64)
        v = np.asarray(v_projector_px, dtype=np.float64)
        shape = np.broadcast_shapes(u.shape, v.shape)
        if image.role in ("white", "black"):
            return np.full(shape, 1.0 if image.role == "white" else 0.0)
        coord, other = (v, u) if image.axis == "rows" else (u, v)
        length = int(projector_height if image.axis == "rows" else projector_width)
        if image.role == "phase":
            out = self._phase_intensity(self.fringe_sets[image.set_index], image.step, coord, other, length)
        else:
            out = self._binary_intensity(image, coord, length)
        return np.broadcast_to(out, shape).astype(np.float64, copy=True)

    def _phase_intensity(self, s: FringeSet, step: int, coord: NDArray, other: NDArray, length: int) -> NDArray:
        if s.codec == "micro_phase_shift":
            return np.asarray(s.codec_object(s.name).profile(step, coord), np.float64)
        theta = (2.0 * np.pi / s.pitch(length)) * coord + s.phase_origin_rad
        sign = 1.0 if s.shift_direction == "forward" else -1.0
        if s.codec == "modulated_phase_shift":
            return np.asarray(s.codec_object(s.name).profile(step, theta, other), np.float64)
        if s.codec == "two_plus_one":
            if step == 2:
                return np.full_like(theta, 0.5)
            return 0.5 + 0.5 * (sign * np.sin(theta) if step == 0 else np.cos(theta))
        return 0.5 + 0.5 * np.cos(theta - sign * 2.0 * np.pi * step / s.steps)

    def _binary_intensity(self, image: FringeImage, coord: NDArray, length: int) -> NDArray:
        phase_set = next(s for s in self.fringe_sets if s.axis == image.axis)
        pitch = phase_set.pitch(length)
        pixel = np.floor(coord + 0.5)
        if image.role == "gray":
            nbits = self.gray_code(image.axis).bits
            code = gray_encode(np.clip(np.floor(pixel / pitch), 0, None).astype(np.int64))
            bit = (code >> (nbits - 1 - image.bit)) & 1
        else:  # LSB of the Gray code of the half-period index
            bit = gray_encode(np.clip(np.floor(2.0 * pixel / pitch), 0, None).astype(np.int64)) & 1
        return (1 - bit if image.inverse else bit).astype(np.float64)

    def image_is_2d(self, index: int) -> bool:
        """Image ``index`` varies along both projector axes (a modulated set's carrier)."""
        image = self._layout[index]
        return image.role == "phase" and self.fringe_sets[image.set_index].codec == "modulated_phase_shift"

    def make_decoder(self, projector_width: int, projector_height: int, config=None):
        """The decoder of this capture (:class:`frontend.fpp.fringe_decoding.FringeSetDecoder`)."""
        from frontend.fpp.fringe_decoding import FringeSetDecoder

        return FringeSetDecoder(self, projector_width, projector_height, config)

    # ------------------------------------------------------------------ data
    def to_dict(self) -> dict[str, Any]:
        """The spec as plain data (a pattern file's keys, or a ``sequence.yaml`` ``patterns`` section)."""
        out: dict[str, Any] = {"fringe_sets": [s.to_dict() for s in self.fringe_sets]}
        if self.gray_codes:
            out["gray_codes"] = [g.to_dict() for g in self.gray_codes]
        if self.references in ("start", "end"):
            out["references"] = self.references
        elif self.references == "index":
            out["references"] = {"white": self.white_index, "black": self.black_index}
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str) -> FringeSetSpec:
        """Build from a mapping; ConfigError whose message starts with ``where`` and names the set."""
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: a pattern spec must be a mapping, got {type(d).__name__}")
        known = ("fringe_sets", "gray_codes", "references")
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} next to fringe_sets; valid keys: {', '.join(known)}")
        sets = tuple(_build(FringeSet, entry, f"{where}: fringe_sets[{i}]") for i, entry in enumerate(_listed(d["fringe_sets"], f"{where}: fringe_sets")))
        grays = tuple(_build(GrayCodeSet, entry, f"{where}: gray_codes[{i}]") for i, entry in enumerate(_listed(d.get("gray_codes", []), f"{where}: gray_codes")))
        refs, white, black = _references(d.get("references"), where)
        try:
            return cls(sets, grays, refs, white, black)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None


def _listed(value: Any, where: str) -> list:
    if not isinstance(value, list):
        raise ConfigError(f"{where} must be a list of mappings, got {value!r}")
    return value


def _build(cls, entry: Any, where: str):
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a mapping of keys, got {entry!r}")
    known = {f.name for f in fields(cls)}
    name = entry.get("name")
    where = f"{where} ({name})" if name else where
    unknown = sorted(set(entry) - known)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; valid keys: {', '.join(sorted(known))}")
    if "axis" not in entry:
        raise ConfigError(f"{where}: needs 'axis' (columns or rows)")
    kwargs = dict(entry)
    try:
        for key in ("images", "pitches_px"):
            if key in kwargs:
                kwargs[key] = _indices(kwargs[key], key) if key == "images" else tuple(_listed(kwargs[key], key))
        if "name" in kwargs and not isinstance(kwargs["name"], str):
            raise ConfigError(f"name must be text, got {kwargs['name']!r}")
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _references(value: Any, where: str) -> tuple[str, int | None, int | None]:
    if value is None:
        return "", None, None
    if value in ("start", "end"):
        return value, None, None
    if isinstance(value, dict) and set(value) == {"white", "black"}:
        return "index", _integer(value["white"], f"{where}: references white", 0), _integer(value["black"], f"{where}: references black", 0)
    raise ConfigError(f"{where}: references must be start, end or {{white: INDEX, black: INDEX}}, got {value!r}")
