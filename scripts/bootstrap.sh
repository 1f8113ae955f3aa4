#!/usr/bin/env bash
# Set up a fresh Debian/Ubuntu machine for fpp-graph: the system library Open3D needs, a .venv
# with Python >= 3.11, and the package installed editable with the extras given as arguments.
# Usage: scripts/bootstrap.sh [EXTRAS]   e.g. scripts/bootstrap.sh dev,eval,dask (the default: what `make test` needs)
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-dev,eval,dask}"

# Open3D's wheels link libusb-1.0 dynamically; without it `import open3d` fails.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "bootstrap: installing libusb-1.0-0 (needed by Open3D) with apt-get"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "bootstrap: Open3D needs the system library libusb-1.0-0: run 'sudo apt-get install libusb-1.0-0' and retry" >&2
    exit 1
  fi
fi

# The report's browser test (tests/evaluation/test_report.py) opens report.html in Debian's
# chromium, headless; a test setup (the dev extra) installs it, the demo's (eval alone) does not.
case ",${extras}," in
  *,dev,*)
    if ! command -v chromium >/dev/null; then
      if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
        echo "bootstrap: installing chromium (the report's browser test opens report.html in it) with apt-get"
        { DEBIAN_FRONTEND=noninteractive apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } \
          || echo "bootstrap: apt-get could not install chromium; the report's browser test will be skipped" >&2
      else
        echo "bootstrap: the report's browser test needs Debian's chromium: run 'sudo apt-get install chromium' (the test is skipped without it)" >&2
      fi
    fi
    ;;
esac

# Probe each interpreter by running it, quietly: a pyenv shim exists for every version pyenv
# knows of and fails ("pyenv: python3.13: command not found") when that version is not selected.
python_bin=""
for candidate in python3.13 python3.12 python3.11 python3; do
  if "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 11))' >/dev/null 2>&1; then
    python_bin="$candidate"; break
  fi
done
if [ -z "$python_bin" ]; then
  echo "bootstrap: fpp-graph needs Python >= 3.11; install it (e.g. 'apt-get install python3.11 python3.11-venv') and retry" >&2
  exit 1
fi

if [ ! -x .venv/bin/python ]; then
  "$python_bin" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[${extras}]"
# An editable install is not byte-compiled (a wheel install is): compile once, so that a
# process that may not write bytecode (PYTHONDONTWRITEBYTECODE) does not recompile every module
# at each start (about 0.1 s of `fpp-slam optimize` on a small graph).
.venv/bin/python -m compileall -q fpp_graph frontend >/dev/null
echo "bootstrap: ready (.venv with fpp-graph[${extras}])"
