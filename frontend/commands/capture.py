"""``fpp-slam patterns | decode | calibrate | import``: real captures in, results out, no Python.

Registered as command plug-ins of ``fpp-slam`` (entry point group ``fpp_graph.cli``, see
``pyproject.toml``) because they need the FPP front-end, which the back-end must not import.
Each command is a thin wrapper over a library function; heavy modules are imported inside the
commands so that ``fpp-slam --help`` stays instant. User errors are FppErrors: one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from fpp_graph.cli.common import examples

if TYPE_CHECKING:
    from frontend.fpp.rig import RigCalibration

CalibrationOption = Annotated[Path, typer.Option("--calibration", help="Rig calibration: fpp-graph YAML, SLMaster caliInfo.yml, procam-calibration XML, SLStudio-style XML or a 40-number text file (detected by content).")]
PatternsOption = Annotated[Path, typer.Option("--patterns", help="Pattern file (YAML; `fpp-slam patterns` prints its schema) or a sequence.yaml.")]
ProjectorOption = Annotated[Optional[str], typer.Option("--projector", help="Projector WxH in pixels, for calibration files that do not store it (SLMaster: 1920x1080, procam-calibration: 1024x768 by default).")]  # noqa: UP045
CameraOption = Annotated[Optional[str], typer.Option("--camera", help="Camera WxH in pixels, for calibration files that do not store it (a 40-number text file); default: the size of the captures' images.")]  # noqa: UP045
ConfigOption = Annotated[Optional[Path], typer.Option("--config", "-c", help="YAML overriding the packaged defaults (the decode section's thresholds).")]  # noqa: UP045

SEQUENCE_FORMAT_LINE = "fpp-graph sequence v1"


def read_calibration_option(
    path: Path,
    projector_size: tuple[int, int] | None = None,
    option: str = "--calibration",
    camera_size: tuple[int, int] | None = None,
    images_from: Path | None = None,
) -> RigCalibration:
    """The rig of ``--calibration``: a calibration file in any format the project reads, or a
    sequence (its folder or its ``sequence.yaml``), whose ``calibration`` section is the rig.

    ``camera_size`` (``--camera``) is for files that do not store it (a 40-number text); without
    it such a file takes the size of the first image under ``images_from`` (a capture folder, or
    a folder of frame folders: :func:`camera_size_of_images`).

    Raises
    ------
    CalibrationError
        As :func:`frontend.fpp.calibration_io.read_any_calibration`; for a sequence, a malformed
        calibration section, or a ``--projector`` or ``--camera`` size the sequence contradicts.
    """
    from fpp_graph.errors import CalibrationError
    from frontend.fpp.calibration_io import read_any_calibration, stores_camera_size

    sequence_yaml = path / "sequence.yaml" if path.is_dir() else path
    if path.is_dir() and not sequence_yaml.is_file():
        raise CalibrationError(f"{option} {path} is a folder without a sequence.yaml: give a calibration file, or a sequence folder")
    if not (sequence_yaml.is_file() and _is_sequence_file(sequence_yaml)):
        if camera_size is None and images_from is not None and not stores_camera_size(path):
            camera_size = camera_size_of_images(images_from)
        return read_any_calibration(path, projector_size=projector_size, camera_size=camera_size)
    rig = _sequence_calibration(sequence_yaml)
    for device, model, given, size_option in (("projector", rig.projector, projector_size, "--projector"), ("camera", rig.camera, camera_size, "--camera")):
        if given is not None and tuple(given) != (model.width, model.height):
            raise CalibrationError(
                f"{option} {path}: its {device} is {model.width}x{model.height}, not the "
                f"{given[0]}x{given[1]} given; drop {size_option} or pass the rig's calibration file"
            )
    return rig


def camera_size_of_images(folder: Path) -> tuple[int, int]:
    """(width, height) of the first image (natural name order) in ``folder``, or in its first
    sub-folder holding images (a folder of frame or pose folders).

    Raises
    ------
    InputDataError
        No image there, or an unreadable first image.
    """
    from fpp_graph.errors import InputDataError
    from frontend.fpp.capture import IMAGE_SUFFIXES, natural_key
    from frontend.fpp.images import image_size

    folder = Path(folder)
    candidates = [folder, *sorted((p for p in folder.iterdir() if p.is_dir()), key=natural_key)] if folder.is_dir() else []
    for candidate in candidates:
        images = sorted((p for p in candidate.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
        if images:
            return image_size(images[0])
    raise InputDataError(f"{folder}: no image to take the camera's size from; give it with --camera WxH")


def _is_sequence_file(path: Path) -> bool:
    from fpp_graph.outputs import translated_os_errors

    with translated_os_errors(path, reading=True), open(path, encoding="utf-8", errors="replace") as handle:
        return SEQUENCE_FORMAT_LINE in handle.read(4096)


def _sequence_calibration(path: Path) -> RigCalibration:
    from fpp_graph.errors import CalibrationError
    from fpp_graph.yaml_files import read_yaml_file
    from frontend.fpp.rig import RigCalibration

    meta = read_yaml_file(path, CalibrationError, "sequence")
    if not isinstance(meta, dict) or not isinstance(meta.get("calibration"), dict):
        raise CalibrationError(f"{path}: a sequence file without a calibration section; pass the rig's calibration file to --calibration")
    return RigCalibration.from_dict(meta["calibration"], where=f"{path}: calibration")


def read_paths(*given: Path | None) -> list[Path | None]:
    """The paths a command reads, with the folder of each sequence among them: a sequence given by
    its ``sequence.yaml`` is read as a whole, and nothing may be written into it."""
    paths: list[Path | None] = list(given)
    for path in given:
        if path is not None and path.is_file() and path.name == "sequence.yaml" and _is_sequence_file(path):
            paths.append(path.parent)
    return paths


def refuse_existing_outputs(out: Path, names: Any, overwrite: bool, inputs: list[Any], option: str = "--out") -> None:
    """Refuse an output folder before the work that fills it (claim_output_folder checks again,
    under the folder's lock, when the files are written): nothing is created here."""
    from fpp_graph.errors import OutputError
    from fpp_graph.outputs import refuse_existing_file, refuse_input_overlap

    refuse_input_overlap(out, inputs, option)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{option} {out} is a file, not a folder: choose another {option}")
    for name in names:
        refuse_existing_file(out / name, overwrite, option)


def parse_size(text: str | None, what: str) -> tuple[int, int] | None:
    """``"1920x1080"`` -> (1920, 1080); ConfigError naming the option otherwise."""
    from fpp_graph.errors import ConfigError

    if text is None:
        return None
    parts = text.lower().replace(" ", "").split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise ConfigError(f"{what} {text!r} is not WIDTHxHEIGHT in pixels (e.g. 1920x1080)")
    return int(parts[0]), int(parts[1])


def required_size(text: str, what: str) -> tuple[int, int]:
    size = parse_size(text, what)
    assert size is not None  # a required option
    return size


def parse_range(text: str, what: str) -> tuple[float, float]:
    from fpp_graph.errors import ConfigError

    try:
        near, far = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"{what} {text!r} is not NEAR,FAR in metres (e.g. 0.05,10)") from None
    if not 0 < near < far:
        raise ConfigError(f"{what} {text!r}: need 0 < near < far (metres)")
    return near, far


@examples(
    "fpp-slam patterns",
    "fpp-slam patterns datasets/patterns/slmaster_monocular.yaml",
    "fpp-slam patterns datasets/patterns/single_frequency_8step.yaml --projector 1920x1080 --render-to patterns_1920x1080",
)
def patterns(
    spec: Annotated[Optional[Path], typer.Argument(help="A pattern file to check; without it the file's schema is printed.")] = None,  # noqa: UP045
    projector: Annotated[Optional[str], typer.Option("--projector", help="Also render the patterns for a WxH projector ...")] = None,  # noqa: UP045
    render_to: Annotated[Optional[Path], typer.Option("--render-to", help="... into this folder as 000.png, 001.png, ...")] = None,  # noqa: UP045
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the images an earlier --render-to wrote there.")] = False,
) -> None:
    """Print the pattern-file schema, or check a pattern file and list its images in capture order."""
    from frontend.fpp.pattern_file import SCHEMA, load_pattern_spec

    if spec is None:
        typer.echo(SCHEMA)
        return
    pattern_spec = load_pattern_spec(spec)
    typer.echo(f"{spec}: valid, {pattern_spec.kind} on axis {pattern_spec.axis}, {pattern_spec.image_count()} images per capture")
    for i, image in enumerate(pattern_spec.layout()):
        typer.echo(f"  {i:3d}  {image.token()}")
    size = parse_size(projector, "--projector")
    if render_to is not None:
        from fpp_graph.errors import ConfigError
        from fpp_graph.outputs import claim_output_folder
        from frontend.fpp.capture import write_png
        from frontend.fpp.patterns import generate_patterns

        if size is None:
            raise ConfigError("--render-to needs --projector WxH (the projector's size in pixels)")
        names = [f"{i:03d}.png" for i in range(pattern_spec.image_count())]
        with claim_output_folder(render_to, names, overwrite, inputs=[spec], option="--render-to") as folder:
            for name, image in zip(names, generate_patterns(pattern_spec, *size), strict=True):
                write_png(folder / name, image, replace=overwrite)
        typer.echo(f"rendered {pattern_spec.image_count()} {size[0]}x{size[1]} images into {render_to}")


@examples(
    "fpp-slam decode ../shared/data/real_fpp/slmaster_monocular --calibration ../shared/data/real_fpp/slmaster_monocular/caliInfo.yml"
    " --patterns datasets/patterns/slmaster_monocular.yaml --out decoded/slmaster",
    "fpp-slam decode ../shared/data/real_fpp/slmaster_heterodyne --calibration ../shared/data/real_fpp/slmaster_monocular/caliInfo.yml"
    " --patterns datasets/patterns/slmaster_heterodyne.yaml --no-edge-filter --out decoded/heterodyne",
)
def decode(
    capture: Annotated[Path, typer.Argument(help="Folder with one capture's images, in the order the pattern file states (natural name order).")],
    calibration: CalibrationOption,
    patterns: PatternsOption,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder: points.ply, xyz_map.npy, texture.png, depth.png, decode.json.")],
    images: Annotated[Optional[str], typer.Option("--images", help="Glob picking the capture's images (default: every image file).")] = None,  # noqa: UP045
    projector: ProjectorOption = None,
    camera: CameraOption = None,
    edge_filter: Annotated[bool, typer.Option("--edge-filter/--no-edge-filter", help="The pipeline's mixed-pixel / discontinuity filter.")] = True,
    depth_range: Annotated[str, typer.Option("--depth-range", help="Accepted depths NEAR,FAR along the camera axis, metres.")] = "0.05,10",
    config: ConfigOption = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the outputs an earlier decode wrote into --out (other files there are kept).")] = False,
) -> None:
    """One capture -> coloured point cloud (metres), xyz map, texture, 16-bit depth image and a report."""
    from fpp_graph.cli import RichProgress, setup_logging
    from fpp_graph.config import load_config
    from fpp_graph.outputs import claim_output_folder
    from frontend.fpp.capture import (
        OUTPUT_FILES,
        decode_capture,
        read_capture,
        write_capture_outputs,
    )
    from frontend.fpp.images import check_images_match_calibration
    from frontend.fpp.pattern_file import load_pattern_spec

    setup_logging("WARNING")
    inputs = read_paths(capture, calibration, patterns, config)
    refuse_existing_outputs(out, OUTPUT_FILES, overwrite, inputs)
    cfg = load_config(config)
    near_far = parse_range(depth_range, "--depth-range")
    spec = load_pattern_spec(patterns)
    rig = read_calibration_option(calibration, projector_size=parse_size(projector, "--projector"), camera_size=parse_size(camera, "--camera"), images_from=capture)
    with RichProgress() as progress:
        stack = read_capture(capture, spec, images)
        check_images_match_calibration(stack.shape, rig, f"{capture} (calibration {calibration})")
        progress("read", 1, 1)
        result = decode_capture(
            stack, rig, spec, cfg.decode, edge_filter=edge_filter, depth_range_m=near_far,
            where=f"{capture} (calibration {calibration})", progress=progress,
        )
        refuse_empty_cloud(result.report, capture, calibration, near_far)
        with claim_output_folder(out, OUTPUT_FILES, overwrite, inputs) as folder:
            write_capture_outputs(folder, result, overwrite=overwrite)
        progress("decode", 4, 4)
    r = result.report
    depth = r["depth_m"]
    span = f"depth {1e3 * depth['p01']:.1f}-{1e3 * depth['p99']:.1f} mm (p1-p99)" if depth.get("count") else "no depth"
    total_s = sum(r["seconds"].values())
    typer.echo(f"{r['valid_pixels']} valid points ({100 * r['valid_pixels'] / (r['image_size'][0] * r['image_size'][1]):.1f} % of pixels), {span}, {total_s:.2f} s -> {out}")


def refuse_empty_cloud(report: dict[str, Any], capture: Path, calibration: Path, depth_range_m: tuple[float, float]) -> None:
    """InputDataError when no pixel gave a point: an empty cloud is not a result.

    Pixels that decode but none of which triangulates into the depth range mean a calibration of
    another rig (its baseline or lenses do not fit the images); none decoding, a pattern file
    that does not describe the capture.
    """
    from fpp_graph.errors import InputDataError

    if report["valid_pixels"] > 0:
        return
    decoded = report["decoded_pixels"]
    if decoded:
        raise InputDataError(
            f"{capture}: {decoded} pixels decode but none triangulates to a depth in {depth_range_m[0]:g}-{depth_range_m[1]:g} m with the calibration "
            f"{calibration}: it is probably another rig's; pass this rig's calibration (or widen --depth-range)"
        )
    raise InputDataError(f"{capture}: no pixel decodes; check that --patterns describes these images, in their order, and --images picks them")


@examples(
    "fpp-slam calibrate ../shared/data/real_fpp/procam_calibration --poses 'capture_*'"
    " --patterns datasets/patterns/procam_graycode_1024x768.yaml --board 9x7 --square-mm 75 --projector 1024x768 --out procam_calibration.yaml",
    "fpp-slam calibrate boards --patterns slstudio_calibration.yaml --grid asymmetric-circles --board 4x11 --square-mm 20"
    " --projector 1280x800 --out rig.yaml",
)
def calibrate(
    board_captures: Annotated[Path, typer.Argument(help="Folder with one sub-folder of pattern images per chessboard pose.")],
    patterns: PatternsOption,
    board: Annotated[str, typer.Option("--board", help="Board points COLSxROWS: a chessboard's inner corners (e.g. 9x7), a circle grid's circles per row x rows (e.g. 4x11).")],
    square_mm: Annotated[float, typer.Option("--square-mm", help="Chessboard square side; circle grid: spacing of neighbouring centres (asymmetric: OpenCV's unit, the row offset, half the spacing within a row), millimetres.")],
    projector: Annotated[str, typer.Option("--projector", help="Projector WxH in pixels.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Calibration YAML to write (fpp-graph format, millimetres).")],
    images: Annotated[Optional[str], typer.Option("--images", help="Glob picking each pose's images (default: every image file).")] = None,  # noqa: UP045
    poses: Annotated[str, typer.Option("--poses", help="Glob picking the pose sub-folders.")] = "*",
    black_threshold: Annotated[float, typer.Option("--black-threshold", help="Valid pixels have white - black above this (grey levels).")] = 40.0,
    white_threshold: Annotated[float, typer.Option("--white-threshold", help="... and every Gray bit differs from its inverse by at least this.")] = 5.0,
    skip_missing_board: Annotated[bool, typer.Option("--skip-missing-board", help="Skip poses whose board is not found instead of stopping.")] = False,
    release_board: Annotated[bool, typer.Option("--release-board", help="Estimate the board's corner positions too (a board that is not flat); needs many varied poses (15 in the simulator; 5 are too few), see the README.")] = False,
    corners: Annotated[str, typer.Option("--corners", help="Camera corner refinement: 'model' (cornerSubPix, then a blurred X-junction fit: 0.005 px on simulated boards) or 'subpix' (cornerSubPix alone, as procam-calibration).")] = "model",
    grid: Annotated[str, typer.Option("--grid", help="Board type: checker (chessboard), circles (symmetric circle grid) or asymmetric-circles (OpenCV's staggered grid); dark circles on a light board.")] = "checker",
    circle_mm: Annotated[float, typer.Option("--circle-mm", help="Circle diameter, millimetres (0: half the spacing of nearest centres); sets the window of decoded pixels around a circle.")] = 0.0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --out file.")] = False,
) -> None:
    """Camera + projector calibration from board captures under any pattern set coding both projector axes; prints per-view and overall reprojection RMS."""
    from fpp_graph.cli import RichProgress, setup_logging
    from fpp_graph.errors import ConfigError
    from fpp_graph.outputs import refuse_existing_file, refuse_input_overlap
    from frontend.config import DecodeConfig
    from frontend.fpp.calibration_board import Chessboard, CircleGrid
    from frontend.fpp.calibration_folders import calibrate_pose_folders, pose_folders
    from frontend.fpp.pattern_file import load_pattern_spec
    from frontend.fpp.rig import save_calibration

    setup_logging("WARNING")
    refuse_input_overlap(out, [board_captures, patterns])  # before the minutes of calibration
    refuse_existing_file(out, overwrite)
    inner_corners = required_size(board, "--board")
    size = required_size(projector, "--projector")
    if corners not in ("model", "subpix"):
        raise ConfigError(f"--corners must be 'model' or 'subpix', got {corners!r}")
    if not square_mm > 0:
        raise ConfigError(f"--square-mm must be positive, got {square_mm}")
    if grid not in ("checker", "circles", "asymmetric-circles"):
        raise ConfigError(f"--grid must be checker, circles or asymmetric-circles, got {grid!r}")
    if grid == "checker":
        target = Chessboard(inner_corners, square_mm * 1e-3)
    else:
        target = CircleGrid(inner_corners, square_mm * 1e-3, asymmetric=grid == "asymmetric-circles", diameter_m=circle_mm * 1e-3)
    spec = load_pattern_spec(patterns)
    # half the white - black contrast; +0.25 makes "above the threshold" strict on integer images
    decode_config = DecodeConfig(min_modulation=black_threshold / 2 + 0.25, min_background=0.0, min_code_contrast=white_threshold)
    folders = pose_folders(board_captures, poses)
    with RichProgress() as progress:
        report = calibrate_pose_folders(
            folders, spec, target, size, decode_config, images=images, skip_missing_board=skip_missing_board,
            progress=progress, release_board=release_board, corner_model=corners == "model",
        )
    save_calibration(out, report.calibration, replace=overwrite)
    rms = report.calibration.reprojection_rms_px
    typer.echo(f"{'pose':<40s} {'camera px':>10s} {'projector px':>13s}")
    for name, errors in report.per_view_rms_px.items():
        typer.echo(f"{Path(name).name:<40s} {errors['camera']:10.3f} {errors['projector']:13.3f}")
    for name, why in report.skipped_poses.items():
        typer.echo(f"{Path(name).name:<40s} skipped: {why}")
    if report.board_deviation_m is not None:
        typer.echo(f"board estimated: corners up to {1e3 * float(abs(report.board_deviation_m).max()):.3f} mm from the nominal flat board")
    typer.echo(f"RMS reprojection: camera {rms['camera']:.3f} px, projector {rms['projector']:.3f} px, stereo {rms['stereo']:.3f} px; "
               f"baseline {1e3 * report.calibration.baseline_m:.1f} mm -> {out}")


@examples(
    "fpp-slam import ../shared/data/real_fpp/procam_calibration --frames 'capture_*'"
    " --patterns datasets/patterns/procam_graycode_1024x768.yaml"
    " --calibration ../shared/data/real_fpp/procam_calibration/calibration_result.xml --reference --out datasets/generated/procam_boards",
)
def import_captures(
    captures_root: Annotated[Path, typer.Argument(help="Folder with one sub-folder of pattern images per frame.")],
    patterns: PatternsOption,
    calibration: CalibrationOption,
    out: Annotated[Path, typer.Option("--out", "-o", help="Sequence folder to write (sequence.yaml + frames).")],
    copy: Annotated[bool, typer.Option("--copy/--reference", help="Copy the images into the sequence, or refer to them where they are.")] = True,
    images: Annotated[Optional[str], typer.Option("--images", help="Glob picking each frame's images (default: every image file).")] = None,  # noqa: UP045
    frames: Annotated[str, typer.Option("--frames", help="Glob picking the frame sub-folders.")] = "*",
    frame_period_s: Annotated[float, typer.Option("--frame-period", help="Seconds between frames (timestamps).")] = 1.0,
    projector: ProjectorOption = None,
    camera: CameraOption = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace a sequence an earlier import wrote into --out.")] = False,
) -> None:
    """Per-frame capture folders -> a sequence folder that `fpp-slam run` reads."""
    from fpp_graph.cli import RichProgress, setup_logging
    from frontend.fpp.capture import import_captures as import_folders
    from frontend.fpp.pattern_file import load_pattern_spec

    setup_logging("WARNING")
    spec = load_pattern_spec(patterns)
    rig = read_calibration_option(
        calibration, projector_size=parse_size(projector, "--projector"), camera_size=parse_size(camera, "--camera"), images_from=captures_root,
    )
    with RichProgress() as progress:
        path = import_folders(
            captures_root, spec, rig, out, images=images, frames=frames, copy=copy, frame_period_s=frame_period_s,
            overwrite=overwrite, inputs=read_paths(patterns, calibration), progress=progress,
        )
    from frontend.fpp.sequence import read_sequence

    sequence = read_sequence(path)
    typer.echo(f"{len(sequence)} frames of {spec.image_count()} images ({'copied' if copy else 'referenced'}) -> {path}; run it with `fpp-slam run {path}`")
