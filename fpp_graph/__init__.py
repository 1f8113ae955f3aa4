"""fpp-graph: the front-end agnostic back-end of FPP indoor SLAM.

Import what you need from the submodules (``fpp_graph.types``, ``fpp_graph.trajectory``, ...).
The names below are re-exported lazily so that ``import fpp_graph`` (and ``fpp-slam --help``)
stays fast.
"""

from __future__ import annotations

import importlib
from typing import Any

from fpp_graph.errors import (
    CalibrationError,
    ConfigError,
    FppError,
    GraphError,
    InputDataError,
    OutputError,
    RegistrationError,
)

__version__ = "0.1.0"

_LAZY = {
    "Frame": "fpp_graph.types",
    "Constraint": "fpp_graph.types",
    "ConstraintKind": "fpp_graph.types",
    "PairRegistrar": "fpp_graph.types",
    "LoopDetector": "fpp_graph.types",
    "LoopCandidate": "fpp_graph.types",
    "MapFuser": "fpp_graph.types",
    "ParallelMapFuser": "fpp_graph.types",
    "Trajectory": "fpp_graph.trajectory",
    "Config": "fpp_graph.config",
    "load_config": "fpp_graph.config",
}

__all__ = [
    "CalibrationError",
    "ConfigError",
    "FppError",
    "GraphError",
    "InputDataError",
    "OutputError",
    "RegistrationError",
    "__version__",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'fpp_graph' has no attribute {name!r}")
