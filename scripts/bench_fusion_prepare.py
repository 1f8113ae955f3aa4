"""Fusion's per-keyframe work on a finished run's frames, against its peer reduction.

    .venv/bin/python -m scripts.bench_fusion_prepare RESULTS [--frames 6] [--repeat 3]

``RESULTS`` is an ``fpp-slam run`` results folder that kept its frames (``frames/``,
``trajectory.tum``, ``config.yaml``). For ``--frames`` keyframes from the middle of the run it prints:

* reading a cached frame (:func:`fpp_graph.slam.frame_store.load_frame`), ms;
* preparing it for the map (:class:`fpp_graph.fusion.voxel_map.FramePreparer`: grazing weights,
  voxel sums, depth rendering), ms;
* the voxel sums alone (:func:`fpp_graph.fusion.voxel_grid._reduce`: a quicksort of the frame's
  keys, ``np.bincount`` over contiguous planes) against a peer, ``np.unique(return_inverse=True)``
  and ``np.bincount`` over the columns of (points, 7) rows, ms and their ratio, and whether the
  two agree bit for bit.

Minimum over ``--repeat`` runs of each, one process, libraries on one thread (as on a worker).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def _peer_reduce(keys: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    unique, inverse = np.unique(keys, return_inverse=True)
    sums = np.empty((unique.size, columns.shape[1]))
    for c in range(columns.shape[1]):
        sums[:, c] = np.bincount(inverse, weights=columns[:, c], minlength=unique.size)
    return unique, sums


def _best_ms(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        started = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - started)
    return 1e3 * best, out


def cached_frames_parser(description: str | None, frames: int, repeat: int) -> argparse.ArgumentParser:
    """The arguments of a benchmark on a run's cached frames: ``RESULTS``, ``--frames`` (how many,
    from the middle of the run: :func:`middle_frames`) and ``--repeat`` (the minimum over that many runs)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path)
    parser.add_argument("--frames", type=int, default=frames)
    parser.add_argument("--repeat", type=int, default=repeat)
    return parser


def middle_frames(parser: argparse.ArgumentParser, results: Path, count: int) -> list[Path]:
    """The cached frames ``count`` from the middle of the run in ``results`` (a usage error without any)."""
    paths = sorted((results / "frames").glob("frame_*.npz"))
    if not paths:
        parser.error(f"{results / 'frames'} holds no cached frames; run with run.keep_frames: all or keyframes")
    middle = max(0, len(paths) // 2 - count // 2)
    return paths[middle : middle + count]


def main(argv: list[str] | None = None) -> int:
    parser = cached_frames_parser(__doc__, frames=6, repeat=3)
    args = parser.parse_args(argv)

    import yaml

    from fpp_graph.fusion.voxel_grid import _reduce, voxel_keys
    from fpp_graph.fusion.voxel_map import VoxelMapFuser
    from fpp_graph.geometry import transform_points
    from fpp_graph.slam.frame_store import load_frame
    from fpp_graph.slam.workers import single_threaded_libraries
    from fpp_graph.trajectory import read_tum

    single_threaded_libraries()
    paths = middle_frames(parser, args.results, args.frames)
    trajectory = read_tum(args.results / "trajectory.tum")
    fusion = yaml.safe_load((args.results / "config.yaml").read_text())["fusion"]
    fuser = VoxelMapFuser(
        voxel_size_m=fusion["voxel_size_m"], tsdf_voxel_m=fusion["tsdf_voxel_m"],
        mesh=fusion["mesh"], max_depth_m=fusion.get("max_depth_m") or float("inf"),
    )
    prepare = fuser.preparer()
    rows = []
    for path in paths:
        read_ms, frame = _best_ms(lambda path=path: load_frame(path), args.repeat)
        T = trajectory.poses_world_sensor[int(np.argmin(np.abs(trajectory.timestamps_s - frame.timestamp)))]
        prepare_ms, _ = _best_ms(lambda frame=frame, T=T: prepare(frame, T), args.repeat)
        points = transform_points(T, frame.points)
        columns = np.column_stack([points, np.full((len(points), 3), 0.5), np.ones(len(points))])
        planes = np.ascontiguousarray(columns.T)
        keys = voxel_keys(points, fuser.voxel_size_m)
        ours_ms, ours = _best_ms(lambda keys=keys, planes=planes: _reduce(keys, planes), args.repeat)
        peer_ms, peer = _best_ms(lambda keys=keys, columns=columns: _peer_reduce(keys, columns), args.repeat)
        same = np.array_equal(ours[0], peer[0]) and np.array_equal(ours[1], peer[1].T)
        rows.append((read_ms, prepare_ms, ours_ms, peer_ms))
        print(f"frame {frame.id}: {len(points)} points; read {read_ms:.0f} ms, prepare {prepare_ms:.0f} ms; "
              f"voxel sums {ours_ms:.0f} ms vs peer {peer_ms:.0f} ms ({peer_ms / ours_ms:.2f}x), bitwise {'the same' if same else 'DIFFERENT'}")
    read_ms, prepare_ms, ours_ms, peer_ms = np.median(np.array(rows), axis=0)
    print(f"median of {len(rows)} frames: read {read_ms:.0f} ms, prepare {prepare_ms:.0f} ms; voxel sums {ours_ms:.0f} ms vs peer {peer_ms:.0f} ms ({peer_ms / ours_ms:.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
