"""``fpp-slam calibration-info``: what a rig calibration implies, to check a hand-written one.

A thin wrapper over :func:`frontend.fpp.rig_geometry.rig_figures`; ``--write-yaml`` saves the
calibration as read in the project's YAML (millimetres), which every command reads without size
options.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from fpp_graph.cli.common import examples


@examples(
    "fpp-slam calibration-info datasets/calibrations/example_40_numbers.txt --projector 1280x720 --camera 1280x1024",
    "fpp-slam calibration-info datasets/calibrations/example_40_numbers.txt --projector 1280x720 --camera 1280x1024 --write-yaml rig.yaml",
    "fpp-slam calibration-info rig.yaml --json",
)
def calibration_info(
    calibration: Annotated[Path, typer.Argument(help="A calibration file in any format `decode` reads (the project's YAML, SLMaster, procam-calibration, SLStudio, 40-number text) or a sequence.")],
    projector: Annotated[Optional[str], typer.Option("--projector", help="Projector WxH in pixels, for files that do not store it.")] = None,  # noqa: UP045
    camera: Annotated[Optional[str], typer.Option("--camera", help="Camera WxH in pixels, for files that do not store it (a 40-number text).")] = None,  # noqa: UP045
    as_json: Annotated[bool, typer.Option("--json", help="Print the figures as JSON (lengths mm, angles deg, pixels).")] = False,
    write_yaml: Annotated[Optional[Path], typer.Option("--write-yaml", help="Also save the calibration as read in the project's YAML (millimetres).")] = None,  # noqa: UP045
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --write-yaml file.")] = False,
) -> None:
    """Print a calibration's baseline, axes, fields of view, distortion, working range and depth per projector pixel, with warnings."""
    from fpp_graph.outputs import refuse_existing_file, refuse_input_overlap
    from frontend.commands.capture import parse_size
    from frontend.fpp.rig import save_calibration
    from frontend.fpp.rig_geometry import rig_figures

    if write_yaml is not None:
        refuse_input_overlap(write_yaml, [calibration], option="--write-yaml")
        refuse_existing_file(write_yaml, overwrite, option="--write-yaml")
    projector_size, camera_size = parse_size(projector, "--projector"), parse_size(camera, "--camera")
    source, rotation_error = _source(calibration)
    rig = _read(calibration, projector_size, camera_size, rotation_error)
    figures = rig_figures(rig, rotation_error=rotation_error)
    if write_yaml is not None:
        save_calibration(write_yaml, rig, unit="mm", replace=overwrite)
    if as_json:
        typer.echo(json.dumps({"calibration": str(calibration), **source, **figures.to_dict(), "written_yaml": None if write_yaml is None else str(write_yaml)}, indent=2))
        return
    for line in _text_lines(calibration, source, figures):
        typer.echo(line)
    if write_yaml is not None:
        typer.echo(f"written: {write_yaml} (fpp-graph rig calibration, mm)")


def _source(path: Path) -> tuple[dict[str, Any], float]:
    """The file's format and length unit as read, and the text format's rotation error (0 if R is one)."""
    import numpy as np

    from fpp_graph.errors import CalibrationError
    from fpp_graph.yaml_files import read_yaml_file
    from frontend.fpp.calibration_io import (
        KNOWN_FORMATS,
        calibration_format,
        parse_text_calibration,
    )

    if path.is_dir() or path.name == "sequence.yaml":
        return {"format": "fpp-graph sequence (its calibration section)", "length_unit": "as the sequence states"}, 0.0
    kind = calibration_format(path)
    rotation_error = 0.0
    unit = "mm"
    if kind == KNOWN_FORMATS[0][0]:
        data = read_yaml_file(path, CalibrationError, "calibration")
        unit = data.get("length_unit", "?") if isinstance(data, dict) else "?"
    elif kind == KNOWN_FORMATS[4][0]:
        numbers = parse_text_calibration(path)
        if not numbers.is_rotation:
            det = float(np.linalg.det(numbers.R_projector_camera))
            rotation_error = max(numbers.rotation_error, abs(det - 1.0))
    return {"format": kind, "length_unit": unit}, rotation_error


def _read(calibration: Path, projector_size, camera_size, rotation_error: float):
    from frontend.commands.capture import read_calibration_option
    from frontend.fpp.calibration_io import read_text_calibration

    if rotation_error > 0:
        # a broken R is shown with its nearest rotation and a warning, not refused: this command
        # is where a hand-written file is checked
        return read_text_calibration(calibration, projector_size=projector_size, camera_size=camera_size, orthonormalise=True)
    return read_calibration_option(calibration, projector_size=projector_size, option="CALIBRATION", camera_size=camera_size)


def _vector(values, fmt: str = "+.3f") -> str:
    return "(" + ", ".join(format(v, fmt) for v in values) + ")"


def _optional(value: float | None, fmt: str, unit: str, none: str) -> str:
    return none if value is None else f"{value:{fmt}} {unit}"


def _text_lines(calibration: Path, source: dict[str, Any], f) -> list[str]:
    c, p = f.camera, f.projector
    lines = [
        f"{calibration}: {source['format']}, lengths in {source['length_unit']} as read (shown in mm)",
        f"baseline               {f.baseline_mm:.2f} mm, direction {_vector(f.baseline_direction_camera)} in the camera frame "
        f"(projector centre at {_vector(f.projector_centre_camera_mm, '+.2f')} mm)",
        f"optical axes           {f.optical_axes_angle_deg:.2f} deg apart",
        f"{'':22s} {'camera':>24s} {'projector':>24s}",
    ]
    rows = (
        ("image size px", lambda d: f"{d.size_px[0]}x{d.size_px[1]}"),
        ("focal length px", lambda d: f"{d.focal_px[0]:.1f}, {d.focal_px[1]:.1f}"),
        ("principal pt offset px", lambda d: f"{d.principal_offset_px[0]:+.1f}, {d.principal_offset_px[1]:+.1f}"),
        ("field of view deg", lambda d: f"{d.fov_deg[0]:.2f} x {d.fov_deg[1]:.2f}"),
        ("corner distortion px", lambda d: f"{d.max_corner_distortion_px:.2f}"),
    )
    lines += [f"{name:22s} {cell(c):>24s} {cell(p):>24s}" for name, cell in rows]
    if f.near_mm is None:
        lines.append("working range          none: the projector lights half of the camera's image at no depth")
    else:
        far = f"{f.far_mm:.0f} mm" if f.far_mm is not None else "open (beyond 20 m)"
        lines.append(f"working range          {f.near_mm:.0f} mm to {far} (the projector lights at least half of the camera's image)")
        where = "middle of the range" if f.far_mm is not None else "twice the near limit"
        columns, rows_mm = (_optional(f.depth_per_projector_px_mm[a], ".4g", "mm/px", "no depth change") for a in ("columns", "rows"))
        lines.append(f"at {f.reference_depth_mm:.0f} mm ({where}): triangulation angle {f.triangulation_angle_deg:.2f} deg; "
                     f"depth per projector pixel: columns {columns}, rows {rows_mm}")
    lines += [f"warning: {w}" for w in f.warnings] or ["warnings: none"]
    return lines
