"""A small TUM RGB-D sequence rendered from the synthetic wall, for the pipeline's tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fpp_graph.trajectory import Trajectory

synthetic_frames = pytest.importorskip("frontend.testing.synthetic_frames")

# the sensor slides 0.5 m along a textured wall and comes back: a revisit at the end
XS = [-0.25, -0.15, -0.05, 0.05, 0.15, 0.05, -0.05, -0.15, -0.25]


def write_tum_rgbd_sequence(folder: Path, xs=XS, width=320, height=200) -> Path:
    """A TUM RGB-D layout folder (rgb.txt, depth.txt at 5000 per metre, groundtruth, intrinsics)
    rendered from the synthetic wall."""
    import cv2

    from fpp_graph.trajectory import write_tum

    scene = synthetic_frames.bumpy_wall_scene(seed=3, size_m=(1.2, 0.8))
    poses = [synthetic_frames.wall_pose(x, distance_m=0.45) for x in xs]
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for i, T in enumerate(poses):
        frame = synthetic_frames.render_frame(scene, T, width=width, height=height, frame_id=i, supersampling=1)
        depth = np.nan_to_num(frame.xyz_map[..., 2], nan=0.0) * 5000.0
        t = 1.0 + i / 30.0
        cv2.imwrite(str(folder / f"rgb/{t:.6f}.png"), frame.texture)
        cv2.imwrite(str(folder / f"depth/{t:.6f}.png"), np.round(depth).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    K = frame.metadata["K"]
    (folder / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("# timestamp filename\n" + "\n".join(depth_lines) + "\n")
    (folder / "intrinsics.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    write_tum(folder / "groundtruth.txt", Trajectory.from_poses([1.0 + i / 30.0 for i in range(len(poses))], poses))
    return folder
