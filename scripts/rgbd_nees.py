"""Pairwise registration of RGB-D frames against their reference poses: error and NEES.

    .venv/bin/python scripts/rgbd_nees.py [SEQUENCE_DIR] [--pairs 150:152 155:158 ...]   (NEES_CONFIG=file.yaml: a config override)

Registers frame pairs with the RGB-D source's registrar (:mod:`frontend.rgbd.source`: colour resampled
onto the depth grid, the Kinect noise model ``KINECT_V1_NOISE``) and prints, per pair, the
translation/rotation error against the sequence's poses, the 1-sigma the information claims and
the NEES ``e^T I e`` (6 degrees of freedom: 6 on average when the information is right). The
mean NEES / 6 over the pairs is the factor the information is still too confident by.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import numpy as np

DEFAULT_SEQ = Path(__file__).resolve().parents[2] / "shared/data/rgbd/7scenes_chess_150_199"
DEFAULT_PAIRS = ["150:152", "155:158", "160:165", "165:170", "170:180", "180:190", "150:170", "185:199"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequence", type=Path, nargs="?", default=DEFAULT_SEQ)
    parser.add_argument("--pairs", nargs="+", default=DEFAULT_PAIRS, help="target:source frame ids")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from scipy.spatial.transform import Rotation

    from fpp_graph.config import load_config
    from fpp_graph.geometry import invert
    from frontend.rgbd.source import RgbdSource

    source = RgbdSource(args.sequence, load_config(os.environ.get("NEES_CONFIG")))
    gt = {e.frame_id: e.T_world_sensor for e in source.entries}
    registrar = source.make_registrar()
    frames: dict = {}

    def frame(i: int):
        if i not in frames:
            frames[i] = source.load_frame(i)
        return frames[i]

    nees = []
    print(f"information correlation {source.config.registration.noise.information_correlation:g}")
    for pair in args.pairs:
        a, b = (int(x) for x in pair.split(":"))
        c = registrar.register(frame(a), frame(b))
        if not c.accepted:
            print(f"{a}<-{b}: rejected: {c.rejection_reason}")
            continue
        E = invert(invert(gt[a]) @ gt[b]) @ c.T_target_source
        e = np.concatenate([Rotation.from_matrix(E[:3, :3]).as_rotvec(), E[:3, 3]])
        sigma = np.sqrt(np.diag(np.linalg.inv(c.information)))
        n = float(e @ c.information @ e)
        nees.append(n)
        print(
            f"{a}<-{b}: error {1e3 * np.linalg.norm(e[3:]):.1f} mm {np.degrees(np.linalg.norm(e[:3])):.2f} deg; "
            f"sigma xyz {np.round(1e3 * sigma[3:], 2)} mm; NEES {n:.1f}; keypoint inliers {c.metadata['ransac_inliers']}"
        )
    if nees:
        print(f"mean NEES/6 {np.mean(nees) / 6:.2f}, median {np.median(nees) / 6:.2f} over {len(nees)} pairs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
