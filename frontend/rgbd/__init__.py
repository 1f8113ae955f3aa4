"""RGB-D recordings (7-Scenes, TUM RGB-D) as an ``fpp_graph`` frame source (``source.RgbdSource``)."""
