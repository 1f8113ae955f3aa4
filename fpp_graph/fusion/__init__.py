"""The global map: frames fused under optimised poses (``voxel_map.VoxelMapFuser``, the default
:class:`~fpp_graph.types.MapFuser`), and PLY output."""
