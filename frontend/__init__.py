"""The FPP sensor side: patterns, phase decoding, triangulation, calibration, simulator,
2D features, pairwise registration and DLT localisation. Implements ``fpp_graph``'s protocols."""

# the front-end's config sections (decode, registration) join fpp_graph.config.Config on import
from frontend import config as _config  # noqa: E402,F401
