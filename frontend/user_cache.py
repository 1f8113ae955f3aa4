"""Where the front-end keeps what it computes once and reuses across runs (estimated simulator
calibrations, camera rays): ``$FPP_GRAPH_CACHE``, or ``~/.cache/fpp-graph``."""

from __future__ import annotations

import os
from pathlib import Path


def user_cache_dir(name: str) -> Path:
    """``$FPP_GRAPH_CACHE/<name>`` or ``~/.cache/fpp-graph/<name>`` (not created)."""
    root = os.environ.get("FPP_GRAPH_CACHE") or Path.home() / ".cache" / "fpp-graph"
    return Path(root) / name


__all__ = ["user_cache_dir"]
