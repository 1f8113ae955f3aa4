"""Pattern sets as data: the YAML file that describes what the projector showed, image by image.

:data:`SCHEMA` below is the file's documentation (``fpp-slam patterns --help`` prints it);
:func:`load_pattern_spec` reads one into a :class:`frontend.fpp.patterns.PatternSpec` (or, for
the fringe-set form, a :class:`frontend.fpp.fringe_sets.FringeSetSpec`), and also accepts a
sequence folder's ``sequence.yaml`` (its ``patterns`` section, read as is).
"""

from __future__ import annotations

import os
from pathlib import Path

from fpp_graph.errors import ConfigError
from fpp_graph.yaml_files import read_yaml_file
from frontend.fpp.fringe_sets import FringeSetSpec
from frontend.fpp.patterns import ORDER_TOKENS, PatternSpec

FORMAT = "fpp-graph patterns v1"
_FREE_KEYS = ("format", "description", "source")

SCHEMA = f"""\
A pattern file (YAML) describes one capture's images, in capture order:

  format: {FORMAT}          # optional
  description: free text                # optional; also 'source'
  kind: complementary_gray   # gray | complementary_gray | multi_frequency | single_frequency | gray_code
  axis: columns              # columns (vertical fringes encode the projector column) | rows | both
  phase_steps: 4             # N >= 3 phase shifts per frequency (not for gray_code)
  periods: [64]              # fringe periods across the axis: one with a Gray code, 2-3 for
                             # multi_frequency (heterodyne e.g. [64, 58, 53], or hierarchical
                             # [1, 8, 64]), [1] for single_frequency; for gray_code the number of
                             # stripes S (default 2**gray_bits; [cols, rows] for axis both)
  shift_direction: forward   # forward: I_n = a + b cos(phi + phi0 - 2 pi n / N); reverse: + 2 pi n / N
  phase_origin_rad: 0.0      # phi0: the projected phase at the centre of projector pixel 0
  gray_bits: 6               # Gray-code bits (bit 0 = most significant); 2**gray_bits >= periods
  gray_bits_rows: 0          # row bits of an axis-both set (0 = gray_bits)
  gray_order: msb_first      # msb_first | lsb_first (default order only)
  gray_inverse: false        # every binary image followed by its inverse
  with_reference: false      # a white and a black image ...
  reference_position: end    # ... at the end or the start (default order only)
  order: [...]               # optional explicit order, one role per image; replaces the default
                             # order and decides references and inverses by itself

Default order: [white, black if start], phase images (frequency by frequency, step 0..N-1),
Gray bits (each with its inverse; columns then rows), complementary bit, [white, black if end].

Roles of an explicit order:
""" + "\n".join(f"  {token:18s} {meaning}" for token, meaning in ORDER_TOKENS.items()) + """

Gray code alone decodes the stripe centre: its error is up to half a stripe, W / (S sqrt 12)
projector pixels RMS for stripes W / S pixels wide (OpenCV's column code: S = W, 0.29 px).

Examples: datasets/patterns/*.yaml. Gray-only, references first, 10 bits MSB first:
  kind: gray_code
  gray_bits: 10
  order: [white, black, gray.0, gray.1, gray.2, gray.3, gray.4, gray.5, gray.6, gray.7, gray.8, gray.9]

Fringe-set form (a top-level 'fringe_sets' list instead of 'kind'): any number of fringe sets,
each with its own axis, pitch, steps and images; both axes in one capture:

  fringe_sets:
    - name: columns_1        # optional; lists and errors use it
      axis: columns          # columns | rows
      periods: 1             # periods across the axis (fractions allowed) ... or
      # pitch_px: 1280       # ... the pitch in projector pixels (exactly one of the two)
      steps: 4               # N >= 3
      shift_direction: forward    # as above: I_n = a + b cos(theta - 2 pi n / N), theta = 2 pi c / pitch + phi0
      phase_origin_rad: 0.0
      first_step: 0          # the set's first image (in capture order) holds this step, then wrapping
      # images: [3, 0, 1, 2] # or: the capture index of each step 0..N-1
      codec: phase_shift     # phase_shift | two_plus_one (3 images: sin, cos, flat) |
                             # modulated_phase_shift (steps, carrier_steps, carrier_pitch_px) |
                             # micro_phase_shift (pitches_px: [...] instead of pitch/periods/steps)
      # unwrapping: spatial  # opt-in for an axis's only set of several periods: unwrapped across
                             # the image per region of valid pixels; a region's fringe order is
                             # the one that keeps it on the projector, else it is refused
      # centre_coordinate_px: 590  # with spatial: the projector coordinate the centre camera
                             # pixel sees (within half a pitch); fixes the order of its region
  gray_codes:                # optional, at most one per axis; unwraps the axis's one phase set
    - {axis: columns, bits: 7, order: msb_first, inverse: false, complementary: false}
  references: end            # optional: start | end | {white: INDEX, black: INDEX}

Images: named indices first; then references at the start, the sets in list order (each the
next N free images), the Gray codes (bits, each with its inverse, the complementary bit), the
references at the end. Per axis the unwrapping is inferred: hierarchical (the coarsest pitch
covers the axis), heterodyne (two sets whose beat, or three whose beat of beats, covers it), a
Gray code, micro phase shifting alone, or spatial where a set asks for it; anything else is
refused naming the sets. Example: datasets/patterns/both_axes_hierarchical_4446.yaml.
"""


def load_pattern_spec(path: str | os.PathLike[str]) -> PatternSpec | FringeSetSpec:
    """Read a pattern file (or a sequence's ``sequence.yaml``) into a :class:`PatternSpec`, or a
    :class:`frontend.fpp.fringe_sets.FringeSetSpec` when it has a top-level ``fringe_sets`` list.

    Raises
    ------
    ConfigError
        Unreadable file, not a mapping, unknown keys or roles, inconsistent settings; the message
        names the file.
    """
    path = Path(path)
    if path.is_dir() and (path / "sequence.yaml").is_file():
        path = path / "sequence.yaml"
    if not path.is_file():
        raise ConfigError(f"pattern file {path} does not exist; write one as `fpp-slam patterns --help` describes")
    data = read_yaml_file(path, ConfigError, "pattern file")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a pattern file is a mapping of keys (see `fpp-slam patterns --help`), got {type(data).__name__}")
    if "patterns" in data and "frames" in data:  # a sequence.yaml: its pattern section as is
        return pattern_spec_from_dict(data["patterns"], where=f"{path}: patterns")
    if "format" in data and data["format"] != FORMAT:
        raise ConfigError(f"{path}: format is {data['format']!r}, expected {FORMAT!r}")
    spec_data = {k: v for k, v in data.items() if k not in _FREE_KEYS}
    if "fringe_sets" in spec_data:
        return FringeSetSpec.from_dict(spec_data, where=str(path))
    return pattern_spec_from_dict(spec_data, where=str(path))


def pattern_spec_from_dict(data: dict, where: str) -> PatternSpec | FringeSetSpec:
    """A pattern spec from a mapping of either form: a :class:`FringeSetSpec` when it has a
    ``fringe_sets`` key, else a :class:`PatternSpec` (ConfigError naming ``where`` when invalid)."""
    if isinstance(data, dict) and "fringe_sets" in data:
        return FringeSetSpec.from_dict(data, where)
    return PatternSpec.from_dict(data, where)
