"""Decode the real SLMaster captures under ../shared/data/real_fpp with frontend.fpp.phase.

Run: .venv/bin/python scripts/decode_real.py [--data DIR] [--out results/frontend] [--json PATH]

Prints the SLMaster regression values for ``slmaster_heterodyne``, the convention check of
``slmaster_monocular`` and saves PNGs of wrapped phase / u_p / mask / modulation / texture.
For use from Python (e.g. to triangulate the monocular capture)::

    import runpy
    decode_real = runpy.run_path("scripts/decode_real.py")
    result = decode_real["decode_slmaster_monocular"]()      # a frontend.fpp.phase.DecodeResult

SLMaster's conventions (Practice3DVision/SLMaster, ``sinusCompleGraycodePattern.cpp`` and
``threeFrequencyHeterodynePattern.cpp``), and how they map onto ours
-------------------------------------------------------------------------------------------
* Its sinusoid for shift ``s`` is ``127.5 + 127.5 cos(theta + 2 pi s / N)`` with
  ``theta = 2 pi (k mod p) / p - pi`` at projector column ``k`` (pitch ``p``), and it decodes
  ``theta = -atan2(sum I sin, sum I cos)`` in ``[-pi, pi)``. Ours is ``cos(phi - 2 pi n / N)``
  with ``phi = 2 pi k / p`` (mod 2 pi), i.e. ``phi = theta + pi``: the opposite shift direction
  and a half-period offset. Their image ``s = (N/2 - n) mod N`` is our image ``n`` (N even),
  after which our wrapped phase equals their ``theta + pi`` and our absolute phase equals their
  "unwrapped phase" (``theta + 2 pi floor + pi``) and our fringe order their "floor".
* Complementary Gray code: bit images MSB first (first image: left half dark, right half
  bright), bright = 1, then the half-period bit last: exactly :mod:`frontend.fpp.patterns`.
* Three-frequency heterodyne: periods ``(P, P - 6, P - 11)`` = (64, 58, 53), 4 steps each, in
  that order; unwrapped to the 64-period phase.
* Their regression test (``test/testThreeFrequencyHeterodynePattern.cpp``, testUnwrap) reads
  ``floorMap.ptr<uint16_t>(480)[590] == 30`` and ``unwrapPhaseMap.ptr<float>(470)[590] ~ 191.95``:
  OpenCV's ``ptr(row)[col]``, so the pixels are (row 480, col 590) and (row 470, col 590),
  i.e. x = 590. (The issue text's "(x=480, y=590)" has x and y swapped; at row 590, col 480
  the camera sees the black background and there is no phase at all.)

How the monocular conventions were established from the images (not just from the source)
------------------------------------------------------------------------------------------
:func:`monocular_convention_table` decodes the 18 images under each of the 8 combinations of
shift direction (ours / reversed), half-period offset (0 / pi) and Gray-bit order (MSB / LSB
first) and measures, over valid horizontally adjacent pixels, the fraction whose ``u_p`` differs
by more than a quarter pitch. A wrong convention leaves steps of a pitch or more across the
surface (fraction 2-10 %); only "reversed shift + pi offset, MSB first" gives a smooth map
(fraction ~0) with ``u_p`` increasing left to right. The images show it too: image 12 (first
bit) is bright on the right half, image 17 (last) has the finest stripes.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from frontend.config import DecodeConfig
from frontend.fpp.images import load_image_stack
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import Decoder, DecodeResult

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_fpp"
PROJECTOR_WIDTH, PROJECTOR_HEIGHT = 1920, 1080  # both SLMaster sets: 1920-wide projector

HETERODYNE_SPEC = PatternSpec("multi_frequency", phase_steps=4, periods=(64, 58, 53))
MONOCULAR_SPEC = PatternSpec("complementary_gray", phase_steps=12, periods=(32,), gray_bits=5)


def slmaster_phase_order(n_steps: int) -> list[int]:
    """Index of SLMaster's shift image that is our shift image n, for n = 0..N-1 (N even)."""
    if n_steps % 2:
        raise ValueError("the SLMaster mapping by reordering needs an even number of steps")
    return [(n_steps // 2 - n) % n_steps for n in range(n_steps)]


def _stack(folder: Path) -> np.ndarray:
    paths = sorted(folder.glob("*.png"))
    return load_image_stack(paths)


def decode_slmaster_heterodyne(folder: Path | None = None, config: DecodeConfig | None = None) -> DecodeResult:
    """Decode ``slmaster_heterodyne`` (3 x 4 images, periods 64/58/53, 1280x1024 camera)."""
    folder = folder or DEFAULT_DATA / "slmaster_heterodyne"
    images = _stack(folder)
    order = slmaster_phase_order(4)
    index = [f * 4 + s for f in range(3) for s in order]
    return Decoder(HETERODYNE_SPEC, PROJECTOR_WIDTH, PROJECTOR_HEIGHT, config).decode(images[index])


def monocular_index(shift: str = "slmaster", bits: str = "msb_first") -> list[int]:
    """Image order of the monocular capture for a convention (default: the right one)."""
    n = 12
    phase = {
        "ours": list(range(n)),
        "reversed": [(-k) % n for k in range(n)],
        "ours+pi": [(k + n // 2) % n for k in range(n)],
        "slmaster": slmaster_phase_order(n),  # = reversed + pi
    }[shift]
    gray = list(range(12, 17)) if bits == "msb_first" else list(range(16, 11, -1))
    return phase + gray + [17]


def decode_slmaster_monocular(folder: Path | None = None, config: DecodeConfig | None = None) -> DecodeResult:
    """Decode ``slmaster_monocular``: 12-step + 5 Gray bits + 1 complementary bit, 32 periods.

    Returns the :class:`frontend.fpp.phase.DecodeResult` (1280x1024 camera); ``u_projector_px`` is
    the projector column (1920-wide projector, pitch 60 px), NaN where invalid.
    """
    folder = folder or DEFAULT_DATA / "slmaster_monocular"
    images = _stack(folder)
    return Decoder(MONOCULAR_SPEC, PROJECTOR_WIDTH, PROJECTOR_HEIGHT, config).decode(images[monocular_index()])


def jump_fraction(result: DecodeResult) -> float:
    """Fraction of valid horizontal neighbours whose u_p differ by more than a quarter pitch."""
    d = np.abs(np.diff(result.u_projector_px, axis=1))
    ok = np.isfinite(d)
    return float(np.mean(d[ok] > result.pitch_px / 4)) if ok.any() else float("nan")


def monocular_convention_table(folder: Path | None = None) -> list[tuple[str, str, float, float, float]]:
    """(shift, bit order, valid fraction, jump fraction, median du_p/dx) for each convention."""
    folder = folder or DEFAULT_DATA / "slmaster_monocular"
    images = _stack(folder)
    decoder = Decoder(MONOCULAR_SPEC, PROJECTOR_WIDTH, PROJECTOR_HEIGHT)
    rows = []
    for shift in ("ours", "reversed", "ours+pi", "slmaster"):
        for bits in ("msb_first", "lsb_first"):
            r = decoder.decode(images[monocular_index(shift, bits)])
            du = np.diff(r.u_projector_px, axis=1)
            rows.append((shift, bits, r.valid_fraction, jump_fraction(r), float(np.nanmedian(du))))
    return rows


def save_figure(result: DecodeResult, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5))
    panels = [
        ("wrapped phase [rad] (finest frequency)", result.wrapped_phase, {"cmap": "twilight"}),
        ("u_projector_px (NaN = invalid)", result.u_projector_px, {"cmap": "viridis"}),
        ("mask (valid)", result.mask, {"cmap": "gray"}),
        ("modulation b [grey]", result.modulation, {"cmap": "magma", "vmax": float(np.percentile(result.modulation, 99.5))}),
        ("texture a", result.texture, {"cmap": "gray"}),
        ("fringe order K (-1 invalid)", result.fringe_order, {"cmap": "nipy_spectral"}),
    ]
    for ax, (name, image, kw) in zip(axes.flat, panels, strict=True):
        handle = ax.imshow(image, **kw)
        ax.set_title(name)
        fig.colorbar(handle, ax=ax, fraction=0.04)
    counts = ", ".join(f"{k} {v}" for k, v in result.invalid_counts.items())
    fig.suptitle(f"{title}: valid {100 * result.valid_fraction:.1f} %  (invalid: {counts})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=Path("results/frontend"))
    parser.add_argument("--json", type=Path, default=None, help="also write the printed figures to this JSON file")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    het = decode_slmaster_heterodyne(args.data / "slmaster_heterodyne")
    k = int(het.fringe_order[480, 590])
    phi = float(het.absolute_phase[470, 590])
    print("slmaster_heterodyne (64/58/53, 4-step, heterodyne):")
    print(f"  valid {100 * het.valid_fraction:.1f} %, invalid {het.invalid_counts}")
    print(f"  fringe order at (row 480, col 590) = {k}          (SLMaster: 30)  {'OK' if k == 30 else 'MISMATCH'}")
    print(f"  absolute phase at (row 470, col 590) = {phi:.3f} rad (SLMaster: 191.95 +- 0.1)  {'OK' if abs(phi - 191.95) <= 0.1 else 'MISMATCH'}")
    print(f"  unwrapping jump fraction {jump_fraction(het):.5f}")
    figures: dict[str, dict] = {"heterodyne": {
        "valid_fraction": het.valid_fraction, "fringe_order_r480_c590": k, "fringe_order_expected": 30,
        "absolute_phase_r470_c590_rad": phi, "absolute_phase_expected_rad": 191.95, "jump_fraction": jump_fraction(het)}}
    save_figure(het, "slmaster_heterodyne", args.out / "slmaster_heterodyne_decode.png")

    print("slmaster_monocular (12-step + 5 Gray bits + complementary bit, 32 periods over 1920 px):")
    print("  convention check (fraction of neighbours with u_p steps > pitch/4; the right one is ~0):")
    conventions = monocular_convention_table(args.data / "slmaster_monocular")
    for shift, bits, valid, jumps, slope in conventions:
        print(f"    shift {shift:9s} bits {bits:9s}  valid {100 * valid:5.1f} %  jumps {jumps:.4f}  median du_p/dx {slope:+.3f}")
    mono = decode_slmaster_monocular(args.data / "slmaster_monocular")
    u = mono.u_projector_px[mono.mask]
    print(f"  decoded: valid {100 * mono.valid_fraction:.1f} %, invalid {mono.invalid_counts}, u_p in [{u.min():.1f}, {u.max():.1f}] px, jumps {jump_fraction(mono):.5f}")
    save_figure(mono, "slmaster_monocular", args.out / "slmaster_monocular_decode.png")
    figures["monocular"] = {
        "valid_fraction": mono.valid_fraction, "u_p_min_px": float(u.min()), "u_p_max_px": float(u.max()), "jump_fraction": jump_fraction(mono),
        "conventions": [{"shift": a, "bits": b, "valid_fraction": v, "jump_fraction": j, "median_du_p_dx": d} for a, b, v, j, d in conventions],
    }
    print(f"  figures: {args.out / 'slmaster_heterodyne_decode.png'}, {args.out / 'slmaster_monocular_decode.png'}")
    if args.json is not None:
        from fpp_graph.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps(figures, indent=1, default=float))


if __name__ == "__main__":
    main()
