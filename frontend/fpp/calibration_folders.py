"""Rig calibration from board-capture folders described by a pattern file (``fpp-slam calibrate``).

A root folder holds one sub-folder per board pose, each with that pose's pattern images in the
order the pattern file states. The pattern set must give both projector coordinates: Gray code
with ``axis: both`` (OpenCV's Gray code with inverses, as procam-calibration captures it), or
any spec whose decoder returns ``axis == "both"`` (phase fringe sets on both axes, as SLStudio's
calibration sequence: 3-step phase at 16 periods and at one period along the columns, then the
same along the rows, 12 images without a white one). A spec that codes one axis is refused: a
board point's projector position needs its column and its row. Each pose is decoded with
:func:`frontend.fpp.phase.make_decoder`, the board (chessboard or circle grid) is found in the
set's white image (the decoded texture when the set has none), and :func:`calibrate_rig` does
the rest. :func:`calibrate_from_captures` and :func:`calibrate_from_stacks` do the same for
in-memory captures (the simulator's board captures): one decoder for real and simulated boards.

procam-calibration's validity rules map onto the decoder's thresholds: a pixel is valid when
``white - black > 40`` (``decode.min_modulation = 20.25``, half the contrast, as integers) and
every bit differs from its inverse by at least 5 grey levels (``decode.min_code_contrast = 5``);
:data:`PROCAM_DECODE` holds them.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import CalibrationError, ConfigError, InputDataError
from frontend.config import DecodeConfig
from frontend.fpp.calibration_board import CalibrationBoard
from frontend.fpp.capture import capture_image_paths, natural_key
from frontend.fpp.images import load_image_stack
from frontend.fpp.patterns import PatternSpec, opencv_gray_code_spec
from frontend.fpp.phase import Decoder, DecodeResult, make_decoder
from frontend.fpp.rig_calibration import (
    PoseObservation,
    RigCalibrationReport,
    calibrate_rig,
    observe_pose,
)

log = logging.getLogger(__name__)

PROCAM_DECODE = DecodeConfig(min_modulation=20.25, min_background=0.0, min_code_contrast=5.0)


def pose_folders(root: str | os.PathLike[str], pattern: str = "*") -> list[Path]:
    """The sub-folders of ``root`` matching ``pattern`` (one per board pose), in natural name order."""
    root = Path(root)
    if not root.is_dir():
        raise InputDataError(f"board-capture folder {root} does not exist (or is not a folder)")
    folders = sorted((p for p in root.glob(pattern) if p.is_dir()), key=natural_key)
    if not folders:
        raise InputDataError(f"{root} has no sub-folders matching {pattern!r}; put each board pose's images in a sub-folder of its own")
    return folders


def observe_pose_folders(
    folders: Sequence[str | os.PathLike[str]],
    spec: PatternSpec,
    board: CalibrationBoard,
    projector_size: tuple[int, int],
    decode_config: DecodeConfig = PROCAM_DECODE,
    *,
    images: str | None = None,
    skip_missing_board: bool = False,
    progress=None,
    corner_model: bool = True,
) -> tuple[list[PoseObservation], tuple[int, int]]:
    """Decode each pose folder and find the board's points in the camera and the projector.

    ``spec`` is a :class:`PatternSpec` or any spec :func:`~frontend.fpp.phase.make_decoder` takes.

    Raises
    ------
    ConfigError
        The pattern set does not give both projector coordinates.
    InputDataError
        A folder's image count differs from the spec, or image sizes differ between poses.
    CalibrationError
        The board is not found in a pose (unless ``skip_missing_board``: then it is skipped
        with a warning).
    """
    refuse_one_axis(spec)
    decoder = make_decoder(spec, *projector_size, decode_config)
    observations: list[PoseObservation] = []
    camera_size = None
    for k, folder in enumerate(folders):
        paths = capture_image_paths(folder, spec, images)
        stack = load_image_stack(paths)
        size = (stack.shape[2], stack.shape[1])
        if camera_size is not None and size != camera_size:
            raise InputDataError(f"{folder}: images are {size[0]}x{size[1]}, earlier poses {camera_size[0]}x{camera_size[1]}; one camera, one size")
        camera_size = size
        try:
            observations.append(observe_pose_stack(str(folder), stack, decoder, board, corner_model=corner_model, spec=spec))
        except CalibrationError:
            white_index = _white_index(spec)
            where = paths[white_index] if white_index is not None else Path(folder)
            message = (
                f"{where}: no {board.describe()} found; check --board and --grid (a chessboard's inner corners, not squares; "
                "a circle grid's circles per row and rows) and that the whole board is in view, or remove this pose"
            )
            if not skip_missing_board:
                raise CalibrationError(message + " (or pass --skip-missing-board)") from None
            log.warning("%s; pose skipped", message)
        if progress is not None:
            progress("poses", k + 1, len(folders))
    if camera_size is None:
        raise InputDataError("no pose folders given")
    return observations, camera_size


def calibrate_pose_folders(
    folders: Sequence[str | os.PathLike[str]],
    spec: PatternSpec,
    board: CalibrationBoard,
    projector_size: tuple[int, int],
    decode_config: DecodeConfig = PROCAM_DECODE,
    *,
    images: str | None = None,
    skip_missing_board: bool = False,
    progress=None,
    release_board: bool = False,
    corner_model: bool = True,
) -> RigCalibrationReport:
    """:func:`observe_pose_folders` then :func:`calibrate_rig` (intrinsics fixed in the stereo step
    unless ``release_board``)."""
    observations, camera_size = observe_pose_folders(
        folders, spec, board, projector_size, decode_config, images=images, skip_missing_board=skip_missing_board, progress=progress,
        corner_model=corner_model,
    )
    if len(observations) < 3:
        raise CalibrationError(f"only {len(observations)} of {len(folders)} poses show the board; calibration needs at least 3: check --board (inner corners) or capture more poses with the whole board in view")
    report = calibrate_rig(observations, board, camera_size, projector_size, release_board=release_board)
    finite = [np.isfinite(o.projector_px).all(axis=1).sum() for o in observations]
    log.info("calibrated from %d poses (%d projector corners)", len(observations), int(sum(finite)))
    return report


def refuse_one_axis(spec) -> None:
    """ConfigError for a spec that codes one projector axis (``axis`` "columns" or "rows").

    A spec that states no axis is checked on its first decoded pose (:func:`observe_pose_stack`).
    """
    axis = getattr(spec, "axis", None)
    if axis in ("columns", "rows"):
        raise ConfigError(_one_axis_message(f"the pattern set ({getattr(spec, 'kind', type(spec).__name__)}) codes only the projector {axis}"))


def _one_axis_message(what: str) -> str:
    return (
        f"calibration needs both projector coordinates, and {what}: a board point's position in the projector is its column "
        "and its row. Capture the boards with a set that codes both axes: Gray code with axis: both "
        "(datasets/patterns/procam_graycode_1024x768.yaml) or phase fringe sets along the columns and the rows"
    )


def _white_index(spec) -> int | None:
    """The index of the set's white image, None without one (roles as PatternImage or tokens)."""
    layout = spec.layout() if hasattr(spec, "layout") else ()
    return next((i for i, im in enumerate(layout) if getattr(im, "role", im) == "white"), None)


def observe_pose_stack(name: str, stack: NDArray, decoder: Decoder, board: CalibrationBoard, corner_model: bool = True, spec=None) -> PoseObservation:
    """Decode one pose's image stack (capture order) and find the board in camera and projector.

    ``decoder`` is any decoder of :func:`~frontend.fpp.phase.make_decoder`; ``spec`` its pattern
    spec (default ``decoder.spec``). The board is found in the set's white image, or in the
    decoded texture when it has none. Raises ConfigError when the decoder gives one projector
    axis, CalibrationError when the board is not found.
    """
    spec = spec if spec is not None else getattr(decoder, "spec", None)
    result: DecodeResult = decoder.decode(stack)
    if result.v_projector_px is None or getattr(result, "axis", "both") != "both":
        raise ConfigError(_one_axis_message(f"{name} decodes only the projector {result.axis}"))
    white_index = _white_index(spec) if spec is not None else None
    white = stack[white_index] if white_index is not None else result.texture
    return observe_pose(name, white, result.u_projector_px, result.v_projector_px, board, result.mask, corner_model=corner_model)


def calibrate_from_captures(
    captures: Iterable[tuple[NDArray, NDArray, NDArray]],
    board: CalibrationBoard,
    projector_size: tuple[int, int],
    *,
    names: Sequence[str] | None = None,
    refine_intrinsics: bool = False,
    calibration_flags: int = 0,
    release_board: bool = False,
) -> tuple[RigCalibrationReport, list[PoseObservation]]:
    """Calibrate from in-memory Gray-code captures ``(patterns, white, black)`` of
    :func:`~frontend.fpp.patterns.opencv_gray_code_spec` (procam-calibration's set and rules).

    A pose whose board is not found is skipped with a warning; the report's ``poses`` are the ones used.
    """
    decoder = Decoder(opencv_gray_code_spec(*projector_size), *projector_size, PROCAM_DECODE)
    observations = []
    camera_size = None
    for i, (patterns, white, black) in enumerate(captures):
        name = names[i] if names is not None else f"pose {i}"
        camera_size = (white.shape[1], white.shape[0])
        stack = np.concatenate([patterns, white[None], black[None]])
        try:
            observations.append(observe_pose_stack(name, stack, decoder, board))
        except CalibrationError as exc:
            log.warning("%s; pose skipped", exc)
    if camera_size is None:
        raise CalibrationError("no captures given")
    report = calibrate_rig(
        observations, board, camera_size, projector_size, refine_intrinsics=refine_intrinsics, calibration_flags=calibration_flags, release_board=release_board
    )
    return report, observations


def calibrate_from_stacks(
    stacks: Iterable[NDArray],
    spec,
    board: CalibrationBoard,
    projector_size: tuple[int, int],
    decode_config: DecodeConfig = PROCAM_DECODE,
    *,
    names: Sequence[str] | None = None,
    release_board: bool = False,
    corner_model: bool = True,
) -> tuple[RigCalibrationReport, list[PoseObservation]]:
    """Calibrate from in-memory captures of any pattern spec whose decoder gives both projector
    coordinates: one (M, H, W) stack per pose, in the spec's capture order.

    A pose whose board is not found is skipped with a warning; the report's ``poses`` are the ones used.
    """
    refuse_one_axis(spec)
    decoder = make_decoder(spec, *projector_size, decode_config)
    observations = []
    camera_size = None
    for i, stack in enumerate(stacks):
        name = names[i] if names is not None else f"pose {i}"
        camera_size = (stack.shape[2], stack.shape[1])
        try:
            observations.append(observe_pose_stack(name, stack, decoder, board, corner_model=corner_model, spec=spec))
        except CalibrationError as exc:
            log.warning("%s; pose skipped", exc)
    if camera_size is None:
        raise CalibrationError("no captures given")
    return calibrate_rig(observations, board, camera_size, projector_size, release_board=release_board), observations
