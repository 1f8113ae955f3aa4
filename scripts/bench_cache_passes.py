"""Per-pixel and per-voxel work in cache-sized passes, against the same work in one pass.

    .venv/bin/python -m scripts.bench_cache_passes RESULTS [--frames 4] [--repeat 3] [--voxels 400000]

``RESULTS`` is an ``fpp-slam run`` results folder that kept its frames (``frames/``, ``map.ply``,
``config.yaml``). On one core (libraries on one thread, as on a worker) it prints, for
``--frames`` cached frames from the middle of the run:

* the FPP edge filter (:func:`frontend.fpp.sensor.edge_filter_mask`) in bands of
  :data:`~frontend.fpp.sensor.EDGE_FILTER_BAND_ROWS` rows against the peer, the same filter
  over the decoded box at once (the code before commit 65a38c8), ms and their ratio;
* fusion's grazing weights (:func:`fpp_graph.fusion.voxel_map.grazing_weights`) the same way
  (:data:`~fpp_graph.fusion.voxel_map.GRAZING_BAND_ROWS`);
* the photometric reference's adaptive range smoothing
  (:func:`frontend.localization.surface.adaptive_smoothing_scale`, the widths the photometric step
  uses for the frame's width), its per-pixel arithmetic in bands of
  :data:`~frontend.localization.surface.SMOOTHING_BAND_ROWS` rows against one band (the code before commit 4a8d848);

and, on the first ``--voxels`` voxels of the run's ``map.ply`` (at the run's fusion voxel size),
the surface smoothing (:func:`fpp_graph.fusion.voxel_grid.project_to_local_planes`) in passes
of :data:`~fpp_graph.fusion.voxel_grid.ROWS_PER_PASS` voxels against one pass per chunk.
Each line says whether ours and the peer agree bit for bit. Minimum over ``--repeat`` runs.
"""

from __future__ import annotations

import numpy as np

from scripts.bench_fusion_prepare import _best_ms, cached_frames_parser, middle_frames


def _ours_and_peer(module, constant: str, fn, repeat: int) -> tuple[float, float, bool]:
    """``fn()`` timed with ``module.constant`` as it is (ours) and as one band (the peer)."""
    ours_ms, ours = _best_ms(fn, repeat)
    kept = getattr(module, constant)
    setattr(module, constant, 1 << 30)
    try:
        peer_ms, peer = _best_ms(fn, repeat)
    finally:
        setattr(module, constant, kept)
    return ours_ms, peer_ms, bool(np.array_equal(ours, peer, equal_nan=True))  # NaN where a map is invalid


def _line(name: str, ours_ms: float, peer_ms: float, same: bool) -> str:
    return f"{name} {ours_ms:.1f} ms vs one pass {peer_ms:.1f} ms ({ours_ms / peer_ms:.2f}x), {'bitwise the same' if same else 'DIFFERENT'}"


def main(argv: list[str] | None = None) -> int:
    parser = cached_frames_parser(__doc__, frames=4, repeat=3)
    parser.add_argument("--voxels", type=int, default=400_000)
    args = parser.parse_args(argv)

    import yaml

    from fpp_graph.fusion import voxel_grid, voxel_map
    from fpp_graph.slam.frame_store import load_frame
    from fpp_graph.slam.workers import single_threaded_libraries
    from frontend.fpp import sensor
    from frontend.localization import surface
    from frontend.localization.reference import smoothing_widths
    from frontend.organised_surface import fit_pinhole

    single_threaded_libraries()
    rows = []
    for path in middle_frames(parser, args.results, args.frames):
        frame = load_frame(path)
        xyz = np.asarray(frame.xyz_map)
        fitted = fit_pinhole(xyz)  # the camera's focal length, as the sensor has it from its calibration
        focal_px = float(fitted[0][0]) if fitted is not None else 1000.0
        edge = _ours_and_peer(sensor, "EDGE_FILTER_BAND_ROWS", lambda xyz=xyz, f=focal_px: sensor.edge_filter_mask(xyz, f), args.repeat)
        grazing = _ours_and_peer(voxel_map, "GRAZING_BAND_ROWS", lambda xyz=xyz: voxel_map.grazing_weights(xyz), args.repeat)
        widths = smoothing_widths(xyz.shape[1], None, None)
        adaptive = _ours_and_peer(surface, "SMOOTHING_BAND_ROWS", lambda z=xyz[..., 2], widths=widths: surface.adaptive_smoothing_scale(z, *widths), args.repeat)
        rows.append((*edge[:2], *grazing[:2], *adaptive[:2]))
        print(f"frame {frame.id} ({xyz.shape[1]}x{xyz.shape[0]}): {_line('edge filter', *edge)}; {_line('grazing weights', *grazing)}; "
              f"{_line('adaptive smoothing', *adaptive)}")
    medians = np.median(np.array(rows), axis=0)
    print(f"median of {len(rows)} frames: " + "; ".join(
        f"{name} {ours:.1f} vs {peer:.1f} ms ({ours / peer:.2f}x)"
        for name, ours, peer in zip(("edge filter", "grazing weights", "adaptive smoothing"), medians[0::2], medians[1::2], strict=True)
    ))

    import open3d as o3d

    voxel_m = float(yaml.safe_load((args.results / "config.yaml").read_text())["fusion"]["voxel_size_m"])
    points = np.asarray(o3d.io.read_point_cloud(str(args.results / "map.ply")).points)
    keys = voxel_grid.voxel_keys(points, voxel_m)
    first = np.argsort(keys, kind="stable")[: args.voxels]  # the first voxels in key order: a contiguous stretch of the map
    keys, points = keys[first], points[first]
    weights = np.ones(len(points))
    smoothing = _ours_and_peer(
        voxel_grid, "ROWS_PER_PASS", lambda: voxel_grid.project_to_local_planes(keys, points, weights, voxel_m), max(1, args.repeat - 1),
    )
    print(f"surface smoothing of {len(points)} voxels ({voxel_m * 1e3:g} mm): {_line('passes', *smoothing)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
