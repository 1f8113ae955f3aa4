"""The FPP sensor: pattern sets, phase retrieval and unwrapping, triangulation, the rig and its
calibration, and captures -> :class:`~fpp_graph.types.Frame` (``sensor.FppSensor``), recorded
sequences and their ``fpp_graph`` frame source (``source.FppSequenceSource``)."""
