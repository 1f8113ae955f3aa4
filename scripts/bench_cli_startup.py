"""Benchmark: wall time of `fpp-slam --help` (target < 1 s) against `python -c pass` as a peer.

Run: .venv/bin/python scripts/bench_cli_startup.py [--repeat N]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path


def time_command(cmd: list[str], repeat: int) -> list[float]:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    exe = Path(sys.executable).parent / "fpp-slam"
    cli = [str(exe)] if exe.exists() else [shutil.which("fpp-slam") or "fpp-slam"]
    help_times = time_command([*cli, "--help"], args.repeat)
    python_times = time_command([sys.executable, "-c", "pass"], args.repeat)
    med_help, med_py = statistics.median(help_times), statistics.median(python_times)
    print(f"fpp-slam --help   median {med_help * 1000:7.1f} ms  max {max(help_times) * 1000:7.1f} ms  (target < 1000 ms)")
    print(f"python -c pass    median {med_py * 1000:7.1f} ms")
    print(f"ratio help/python-startup: {med_help / med_py:.1f}x")
    print("PASS" if max(help_times) < 1.0 else "FAIL")


if __name__ == "__main__":
    main()
