"""Acceptance figures of the FPP decoder on synthetic captures with known ground truth.

Run: .venv/bin/python scripts/accuracy_frontend.py [--json PATH]

1. Phase accuracy: RMS wrapped-phase error against the least-squares bound sqrt(2/N) sigma / B
   for N = 3, 4, 8, 12 on 1M pixels (16-bit images with B = 20000, sigma = 200, so quantisation
   is negligible; target ratio <= 1.05), plus the same on realistic 8-bit images (B = 80,
   sigma = 2: quantisation adds ~1/12 grey^2 of noise, i.e. the ratio may exceed 1 a little).
2. Unwrapping at full size: 1920x1200 camera, 1920x1080 projector, a smooth non-linear scene
   (the camera sees the projector at a varying, non-integer scale), Gaussian blur across code
   edges, sigma = 2 grey levels: fringe-order errors of plain Gray code, complementary Gray
   code, 3-frequency heterodyne (64/58/53) and hierarchical (1/8/64) unwrapping, and the blur
   at which plain Gray code starts to fail while the complementary bit keeps zero errors.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from frontend.config import DecodeConfig
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import decode
from frontend.testing.synthetic_captures import render_captures, smooth_projector_map

CAMERA_W, CAMERA_H = 1920, 1200
PROJECTOR_W, PROJECTOR_H = 1920, 1080


def wrap_pm_pi(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def phase_accuracy() -> list[dict]:
    """Print the phase-accuracy lines; return them as records (images, N, RMS, bound, ratio)."""
    rows = []
    print("1. wrapped-phase RMS error vs the least-squares bound sqrt(2/N) sigma/B (1M pixels each)")
    h, w = 1000, 1000
    for label, dtype, background, modulation, sigma, level in [
        ("16-bit, B 20000, sigma 200", np.uint16, 30000.0, 20000.0, 200.0, 65535),
        (" 8-bit, B 80,    sigma 2  ", np.uint8, 110.0, 80.0, 2.0, 254),
    ]:
        for n in (3, 4, 8, 12):
            rng = np.random.default_rng(100 + n)
            spec = PatternSpec("gray", phase_steps=n, periods=(40,), gray_bits=6)
            u = np.tile(np.linspace(0.0, 1278.0, w), (h, 1)) + rng.uniform(0, 1, (h, 1))
            images = render_captures(spec, u, np.zeros_like(u), 1280, 800, background, modulation, sigma, rng=rng, dtype=dtype)
            result = decode(images, spec, 1280, 800, DecodeConfig(saturation_level=level))
            truth = 2 * np.pi * 40 * u / 1280
            rms = float(np.sqrt(np.mean(wrap_pm_pi(result.wrapped_phase.astype(np.float64) - truth) ** 2)))
            bound = np.sqrt(2.0 / n) * sigma / modulation
            verdict = "PASS" if rms <= 1.05 * bound else ("(quantisation)" if dtype == np.uint8 else "FAIL")
            print(f"   {label}  N={n:2d}: RMS {rms:.5f} rad  bound {bound:.5f} rad  ratio {rms / bound:.4f}  {verdict}")
            rows.append({"images": " ".join(label.split()), "steps": n, "rms_rad": rms, "bound_rad": float(bound), "ratio": rms / bound})
    return rows


def order_errors(result, u_true: np.ndarray) -> tuple[int, float]:
    err = np.abs(result.u_projector_px - u_true)
    wrong = result.mask & (err > result.pitch_px / 2)
    return int(np.count_nonzero(wrong)), float(np.sqrt(np.nanmean(np.where(wrong, np.nan, result.u_projector_px - u_true) ** 2)))


def unwrapping() -> list[dict]:
    """Print the fringe-order lines; return them as records (blur, method, order errors, valid, u_p RMS)."""
    rows = []
    print(f"2. unwrapping at full size: {CAMERA_W}x{CAMERA_H} camera, {PROJECTOR_W}x{PROJECTOR_H} projector, smooth scene, sigma 2 grey, B 80")
    u, v = smooth_projector_map(CAMERA_W, CAMERA_H, PROJECTOR_W, PROJECTOR_H)
    scale = np.median(np.diff(u, axis=1))
    print(f"   the camera sees {scale:.3f} projector px per camera px (varies {np.percentile(np.diff(u, axis=1), 1):.3f}..{np.percentile(np.diff(u, axis=1), 99):.3f})")
    cases = [
        ("plain Gray code (4-step + 7 bits, 128 periods)", PatternSpec("gray", periods=(128,), gray_bits=7)),
        ("complementary Gray code (+1 half-period bit)  ", PatternSpec("complementary_gray", periods=(128,), gray_bits=7)),
        ("3-frequency heterodyne 64/58/53 (4-step each) ", PatternSpec("multi_frequency", periods=(64, 58, 53))),
        ("hierarchical 1/8/64 (4-step each)             ", PatternSpec("multi_frequency", periods=(1, 8, 64))),
    ]
    for blur in (1.0, 2.0):
        print(f"   blur sigma {blur} camera px:")
        for label, spec in cases:
            rng = np.random.default_rng(11)
            images = render_captures(spec, u, v, PROJECTOR_W, PROJECTOR_H, 110.0, 80.0, noise_sigma=2.0, blur_sigma_px=blur, rng=rng)
            result = decode(images, spec, PROJECTOR_W, PROJECTOR_H)
            n_wrong, rms = order_errors(result, u)
            extra = ""
            if n_wrong and spec.kind == "gray":
                pitch = PROJECTOR_W / spec.periods[0]
                wrong = result.mask & (np.abs(result.u_projector_px - u) > result.pitch_px / 2)
                dist = np.abs(u / pitch - np.rint(u / pitch)) * pitch / scale
                extra = f"  (all within {dist[wrong].max():.2f} camera px of a code edge)"
            print(f"     {label} order errors {n_wrong:7d} of {result.mask.sum():8d} valid ({100 * result.valid_fraction:.2f} %), "
                  f"u_p RMS {rms:.4f} px{extra}")
            rows.append({"blur_px": blur, "method": label.strip(), "kind": spec.kind, "order_errors": n_wrong,
                         "valid": int(result.mask.sum()), "u_p_rms_px": rms})
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=None, help="also write the printed figures to this JSON file")
    args = parser.parse_args(argv)
    figures = {"phase_accuracy": phase_accuracy(), "unwrapping": unwrapping()}
    if args.json is not None:
        from fpp_graph.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps(figures, indent=1, default=float))


if __name__ == "__main__":
    main()
