"""Render a scene definition into a recorded FPP sequence folder (images + ground truth).

    .venv/bin/python scripts/simulate.py datasets/turntable.yaml --out datasets/generated/turntable [--preview]
    .venv/bin/python scripts/simulate.py datasets/corridor.yaml --out datasets/generated/corridor --preview --frames 10

``--preview`` renders 640x400 instead of 1920x1200; ``--frames N`` keeps the first N frames;
``--overwrite`` replaces an existing sequence folder; ``--look PNG`` saves a fringe and a texture
image of the first frame side by side.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from fpp_graph.errors import FppError  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="scene definition YAML (datasets/*.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="sequence folder to write")
    parser.add_argument("--preview", action="store_true", help="640x400 camera (fast)")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing sequence folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from frontend.sim import simulate_sequence

    start = time.perf_counter()

    def progress(done: int, total: int) -> None:
        print(f"\rframe {done}/{total}  {time.perf_counter() - start:.0f} s", end="", flush=True)

    try:
        out = simulate_sequence(args.config, args.out, preview=args.preview, max_frames=args.frames, overwrite=args.overwrite, progress=progress)
    except FppError as exc:
        print(f"\nerror: {exc}", file=sys.stderr)
        return exc.exit_code
    print(f"\nwrote {out} in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
