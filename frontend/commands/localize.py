"""``fpp-slam localize RESULTS_DIR --image TEXTURE.png``: locate a camera image in a built map.

A thin wrapper over :func:`frontend.localization.in_map.locate_in_map`: prints ``T_world_camera``,
the camera centre, the inlier counts and a quality verdict, or refuses in one line (exit 2) when
the image shows a place the map does not contain.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from fpp_graph.cli.common import examples


def camera_model(calibration: Path | None, views: list[Any]) -> tuple[Any, Any, Any]:
    """``(K, dist, projector_centre_m)`` of the map's camera.

    From ``calibration`` (a calibration file in any format the project reads, or a sequence:
    its folder or its ``sequence.yaml``), else from what the run kept with each decoded frame.

    Raises
    ------
    CalibrationError
        Neither is available.
    """
    import numpy as np

    from fpp_graph.errors import CalibrationError

    if calibration is not None:
        from frontend.commands.capture import read_calibration_option

        rig = read_calibration_option(calibration)
        T = rig.T_projector_camera
        return rig.camera.K, rig.camera.dist, -T[:3, :3].T @ T[:3, 3]
    meta = views[0].frame().metadata
    if "K" not in meta or "dist" not in meta:
        raise CalibrationError("the map's frames do not record the camera's lens distortion (a run of an older version); pass --calibration SEQUENCE_DIR or a calibration file")
    centre = meta.get("projector_centre_m")
    return np.asarray(meta["K"], dtype=float), np.asarray(meta["dist"], dtype=float), None if centre is None else np.asarray(centre, dtype=float)


def read_grey_image(path: Path) -> Any:
    """An 8-bit grey image (colour is converted); InputDataError when unreadable."""
    import cv2

    from fpp_graph.errors import InputDataError

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputDataError(f"--image {path}: cannot read it as an image; give a PNG or JPEG of the map's camera")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != "uint8":
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype("uint8")
    return image


@examples(
    "fpp-slam localize results/turntable --image decoded/view/texture.png --calibration datasets/generated/turntable",
    "fpp-slam localize results/demo/results --image photo.png --no-projector --json",
)
def localize(
    results: Annotated[Path, typer.Argument(help="Results folder of 'fpp-slam run' (frames/ and trajectory.tum).")],
    image: Annotated[Path, typer.Option("--image", help="Texture image of the map's camera (no fringes needed).")],
    calibration: Annotated[Optional[Path], typer.Option("--calibration", help="Calibration file or sequence folder (default: what the run kept with its frames).")] = None,  # noqa: UP045
    no_projector: Annotated[bool, typer.Option("--no-projector", help="The image was not lit by the rig's projector (fixed light).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Locate a camera image in a map: DLT on keypoints, then photometric refinement."""
    import numpy as np

    from fpp_graph.cli import setup_logging
    from frontend.localization.in_map import load_map, locate_in_map

    setup_logging("WARNING")
    texture = read_grey_image(image)
    views, config = load_map(results)
    K, dist, projector_centre = camera_model(calibration, views)
    located = locate_in_map(views, config, texture, K, dist, None if no_projector else projector_centre)
    if as_json:
        typer.echo(json.dumps(located.to_dict(), default=float))
        return
    with np.printoptions(precision=9, suppress=True):
        typer.echo(f"T_world_camera =\n{located.T_world_camera}")
    c = located.camera_centre_world_m
    photometric = located.photometric.pixels_used if located.photometric is not None else 0
    typer.echo(f"camera centre (world, m): {c[0]:.6f} {c[1]:.6f} {c[2]:.6f}")
    typer.echo(
        f"inliers: {located.dlt.num_inliers} keypoints (DLT, {located.dlt.reprojection_rms_px:.2f} px RMS), {photometric} pixels (photometric) "
        f"against map frames {located.reference_ids}; verdict: {located.verdict}"
    )
