"""Every script under scripts/ imports: a moved or renamed library name breaks the build, not the
next person who runs the benchmark."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the 25-line plain-gtsam peer runs at import (it is what a user would write, no main guard)
RUNS_AT_IMPORT = {"scripts.plain_gtsam_g2o"}


def script_modules() -> list[str]:
    names = []
    for path in sorted((ROOT / "scripts").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if name not in RUNS_AT_IMPORT:
            names.append(name)
    return names


def test_every_script_imports():
    names = script_modules()
    assert "scripts.calibrate_real" in names and "scripts.experimental.dense_localization" in names
    code = "import importlib, sys\nfailed = []\nfor name in sys.argv[1:]:\n    try:\n        importlib.import_module(name)\n    except Exception as exc:\n        failed.append(f'{name}: {type(exc).__name__}: {exc}')\nprint('\\n'.join(failed))\nsys.exit(1 if failed else 0)\n"
    result = subprocess.run([sys.executable, "-c", code, *names], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
