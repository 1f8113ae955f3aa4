"""Locate a camera image in a map that ``fpp-slam run`` built (the paper's live localisation).

A results folder holds the decoded map frames (``frames/frame_<id>.npz``: texture, organised
points, keypoints and descriptors) and their optimised poses (``trajectory.tum``). A query texture
image (no fringes needed) is located in three steps, each a public function:

1. :func:`candidate_frames`: the query's keypoints (the run's detector) matched against every
   map frame's descriptors; the frames with the most matches that lift to 3D come first.
2. :func:`frontend.localization.localize_dlt` on those lifted world points (DLT in RANSAC, LM).
3. :func:`frontend.localization.localize_photometric` against the two best map frames, with the
   FPP shading model when the rig's projector lit the query texture.

The verdict (:func:`verdict`) is ``good`` when the photometric step converged close to the DLT
pose on enough pixels, ``approximate`` when only the DLT holds; a view the map does not contain
(too few consistent matches) is refused with :class:`~fpp_graph.errors.LocalizationError`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import load_config
from fpp_graph.errors import InputDataError, RegistrationError
from fpp_graph.slam.frame_store import FrameStore
from fpp_graph.trajectory import read_tum
from fpp_graph.types import Frame
from frontend.features.detect import make_detector, match_descriptors, stretch_contrast
from frontend.localization.dlt import LocalizationResult, localize_dlt
from frontend.localization.photometric import (
    DenseReference,
    PhotometricLocalizationResult,
    PhotometricQuery,
    localize_photometric,
)
from frontend.organised_surface import lift_keypoints

log = logging.getLogger(__name__)

MIN_DLT_INLIERS = 20
"""Fewer consistent 2D-3D matches and the view is refused: a random 6-point DLT reaches ~10 inliers
among a few hundred wrong matches at a 2 px threshold, a true view of the map hundreds."""
MAX_PHOTOMETRIC_SHIFT_M = 0.005
"""The photometric pose may move the DLT centre by a few millimetres (the DLT's own error from
sub-pixel keypoints at 0.3-0.6 m is 1-3 mm); more means it converged elsewhere."""
MIN_PHOTOMETRIC_PIXELS = 5000
"""Fewer textured pixels and the photometric refinement is not trusted over the DLT pose: with
grey-level noise of ~1 level against gradients of tens, a 6-dof fit needs thousands of residuals
(hundreds per degree of freedom) before its pose error falls below the DLT's millimetres."""


class LocalizationError(RegistrationError):
    """The query image cannot be located in the map (it shows a place the map does not contain)."""


@dataclass(frozen=True, eq=False)
class MapView:
    """A map frame's keypoints and optimised pose ``T_world_frame``; the whole frame (organised
    points, texture) is read from ``store`` when needed, so a long map does not fill the memory."""

    frame_id: int
    T_world_frame: NDArray[np.float64]
    keypoints_uv: NDArray[np.float64]
    descriptors: NDArray
    texture_shape: tuple[int, int]
    store: FrameStore

    def frame(self) -> Frame:
        return self.store.get(self.frame_id)


@dataclass(frozen=True, eq=False)
class MapLocalization:
    """Where a query image is in the map.

    ``T_world_camera`` maps camera points into the world; ``verdict`` is ``good`` or
    ``approximate`` (see :func:`verdict`).
    """

    T_world_camera: NDArray[np.float64]
    camera_centre_world_m: NDArray[np.float64]
    dlt: LocalizationResult
    photometric: PhotometricLocalizationResult | None
    reference_ids: list[int]
    verdict: str
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (metres)."""
        return {
            "T_world_camera": self.T_world_camera.tolist(),
            "camera_centre_world_m": self.camera_centre_world_m.tolist(),
            "dlt_inliers": self.dlt.num_inliers,
            "dlt_reprojection_rms_px": self.dlt.reprojection_rms_px,
            "photometric_pixels": self.photometric.pixels_used if self.photometric is not None else 0,
            "reference_frames": self.reference_ids,
            "verdict": self.verdict,
            **self.details,
        }


def load_map(results_dir: str | os.PathLike[str]) -> tuple[list[MapView], Any]:
    """The map frames of a results folder with their optimised poses, and the run's config.

    Raises
    ------
    InputDataError
        Not a results folder of ``fpp-slam run`` (no ``frames/`` or ``trajectory.tum``), or
        frames without keypoints or organised points.
    """
    results = Path(results_dir)
    for needed in ("frames", "trajectory.tum"):
        if not (results / needed).exists():
            raise InputDataError(f"{results} is not a results folder of 'fpp-slam run': {needed} is missing; give the --out folder of a finished run")
    config = load_config(results / "config.yaml" if (results / "config.yaml").is_file() else None)
    trajectory = read_tum(results / "trajectory.tum")
    store = FrameStore.open(results / "frames", max_in_memory=2)
    views = []
    for frame_id in store.ids:
        frame = store.get(frame_id)
        k = np.flatnonzero(np.abs(trajectory.timestamps_s - frame.timestamp) < 1e-6)
        if k.size == 0 or frame.xyz_map is None or frame.texture is None or frame.descriptors is None:
            continue
        views.append(MapView(frame_id, trajectory.poses_world_sensor[int(k[0])], frame.keypoints_uv, frame.descriptors, frame.texture.shape, store))
    if not views:
        raise InputDataError(f"{results}: no map frame has a pose, an organised point map, a texture and keypoints")
    return views, config


def candidate_frames(views: list[MapView], keypoints_uv: NDArray, descriptors: NDArray, ratio: float = 0.8) -> list[tuple[int, NDArray, NDArray]]:
    """Map frames ordered by the query keypoints that match into them with a 3D point.

    Returns
    -------
    list of (view index, world points (M, 3), query keypoints (M, 2)), most matches first.
    """
    out = []
    for i, view in enumerate(views):
        m = match_descriptors(view.descriptors, descriptors, ratio, True)
        if len(m) < 6:
            continue
        X, ok = lift_keypoints(view.frame().xyz_map, view.keypoints_uv[m[:, 0]])
        if ok.sum() == 0:
            continue
        T = view.T_world_frame
        out.append((i, X[ok] @ T[:3, :3].T + T[:3, 3], keypoints_uv[m[:, 1]][ok]))
    return sorted(out, key=lambda c: -len(c[1]))


def verdict(dlt: LocalizationResult, photometric: PhotometricLocalizationResult | None) -> str:
    """``good``: the photometric pose converged on enough pixels within a few mm of the DLT pose;
    ``approximate``: the DLT pose alone (keypoint accuracy, about a millimetre)."""
    if photometric is None or not photometric.success or photometric.pixels_used < MIN_PHOTOMETRIC_PIXELS:
        return "approximate"
    shift = float(np.linalg.norm(photometric.camera_centre_world_m - dlt.camera_centre_world_m))
    return "good" if shift <= MAX_PHOTOMETRIC_SHIFT_M else "approximate"


def locate_in_map(
    views: list[MapView],
    config: Any,
    texture: NDArray[np.uint8],
    K: NDArray,
    dist: NDArray | None,
    projector_centre_m: NDArray | None = None,
    max_candidates: int = 3,
) -> MapLocalization:
    """Locate a query texture image (H, W uint8, the map's camera) in the map.

    ``projector_centre_m`` (camera frame) turns on the FPP shading model: the query texture was
    lit by the rig's own projector, as an FPP texture is. Without it the photometric step fits a
    gain and offset only (a camera under fixed light).

    Raises
    ------
    LocalizationError
        Too few consistent 2D-3D matches: the view is not in the map.
    InputDataError
        An image of another size than the map frames.
    """
    texture = np.asarray(texture)
    shape = views[0].texture_shape
    if texture.ndim != 2 or texture.shape != shape:
        raise InputDataError(f"query image is {texture.shape}, the map's camera images are {shape}; give a grey image of the same camera")
    uv, desc = make_detector(config.registration)(np.ascontiguousarray(stretch_contrast(texture)))
    candidates = candidate_frames(views, uv, desc)
    best = None
    for i, X, q in candidates[:max_candidates]:  # a DLT per frame: pooled matches mix their errors
        if len(X) < 6:
            continue
        dlt = localize_dlt(X, q, K, dist)
        if dlt.success and (best is None or dlt.num_inliers > best[1].num_inliers):
            best = (i, dlt)
    if best is None or best[1].num_inliers < MIN_DLT_INLIERS:
        found = best[1].num_inliers if best else 0
        raise LocalizationError(
            f"the image does not match the map: best {found} consistent keypoint matches over {len(views)} map frames "
            f"(need {MIN_DLT_INLIERS}); is it a view of the mapped place, taken with the map's camera?"
        )
    i_best, dlt = best
    refs_idx = _nearest_views(views, dlt.camera_centre_world_m, i_best)
    frames = [views[j].frame() for j in refs_idx]
    refs = [DenseReference(f.xyz_map, f.texture, views[j].T_world_frame) for f, j in zip(frames, refs_idx, strict=True)]
    try:
        photometric = localize_photometric(refs, PhotometricQuery(texture, dlt.T_camera_world, K, dist, projector_centre_m))
    except (InputDataError, np.linalg.LinAlgError) as exc:
        log.info("photometric refinement not possible: %s", exc)
        photometric = None
    quality = verdict(dlt, photometric)
    T_camera_world = photometric.T_camera_world if quality == "good" else dlt.T_camera_world
    T_world_camera = np.linalg.inv(T_camera_world)
    details = {"dlt_centre_world_m": dlt.camera_centre_world_m.tolist(), "query_keypoints": len(uv)}
    ref_ids = [int(views[j].frame_id) for j in refs_idx]
    return MapLocalization(T_world_camera, T_world_camera[:3, 3].copy(), dlt, photometric, ref_ids, quality, details)


def _nearest_views(views: list[MapView], centre_world_m: NDArray, i_best: int, count: int = 2) -> list[int]:
    """The best-matching frame and the map frame nearest to the located centre that looks the same way."""
    axis_best = views[i_best].T_world_frame[:3, 2]
    ranked = sorted(
        (j for j in range(len(views)) if j != i_best and float(views[j].T_world_frame[:3, 2] @ axis_best) > 0.7),
        key=lambda j: float(np.linalg.norm(views[j].T_world_frame[:3, 3] - centre_world_m)),
    )
    return [i_best, *ranked[: count - 1]]
