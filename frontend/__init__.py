"""The FPP sensor side: patterns, phase decoding, triangulation, calibration, simulator,
2D features, pairwise registration and DLT localisation. Implements ``fpp_graph``'s protocols."""
