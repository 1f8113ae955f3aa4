"""A frame's points picked from its organised map: ``masked_pixels`` against boolean indexing.

    .venv/bin/python -m scripts.bench_frame_points RESULTS [--frames 6] [--repeat 5]

``RESULTS`` is an ``fpp-slam run`` results folder with cached frames (``frames/``). For
``--frames`` frames from the middle of the run, on one core (libraries on one thread, as on a
decode worker), it times the points every decoded frame is built with: the map's valid pixels in
row-major order, by :func:`fpp_graph.geometry.masked_pixels` (``np.compress`` over the flat map,
since commit 60709e2) against the peer ``xyz_map[valid]`` (the readers' code before), on the float64 map a
reader holds. Each line gives both times, their ratio and whether the two agree bit for bit; the
last line their medians. Minimum over ``--repeat`` runs.
"""

from __future__ import annotations

import numpy as np

from scripts.bench_fusion_prepare import _best_ms, cached_frames_parser, middle_frames


def main(argv: list[str] | None = None) -> int:
    parser = cached_frames_parser(__doc__, frames=6, repeat=5)
    args = parser.parse_args(argv)

    from fpp_graph.geometry import masked_pixels
    from fpp_graph.slam.frame_store import load_frame
    from fpp_graph.slam.workers import single_threaded_libraries

    single_threaded_libraries()
    rows = []
    for path in middle_frames(parser, args.results, args.frames):
        frame = load_frame(path)
        xyz = np.ascontiguousarray(frame.xyz_map, dtype=np.float64)
        valid = np.isfinite(xyz[..., 2])
        ours_ms, ours = _best_ms(lambda xyz=xyz, valid=valid: masked_pixels(xyz, valid), args.repeat)
        peer_ms, peer = _best_ms(lambda xyz=xyz, valid=valid: xyz[valid], args.repeat)
        same = bool(np.array_equal(ours, peer))
        rows.append((ours_ms, peer_ms))
        print(f"frame {frame.id} ({xyz.shape[1]}x{xyz.shape[0]}, {100 * valid.mean():.0f} % valid): masked_pixels {ours_ms:.2f} ms "
              f"vs boolean indexing {peer_ms:.2f} ms ({ours_ms / peer_ms:.2f}x), {'bitwise the same' if same else 'DIFFERENT'}")
    ours_ms, peer_ms = np.median(np.array(rows), axis=0)
    print(f"median of {len(rows)} frames: masked_pixels {ours_ms:.2f} vs {peer_ms:.2f} ms ({ours_ms / peer_ms:.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
