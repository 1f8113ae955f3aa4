"""Readers of third-party projector-camera calibration files into :class:`RigCalibration`.

:func:`read_any_calibration` recognises the format by content (:func:`calibration_format`). The
third-party formats are OpenCV FileStorage files (YAML or XML) or 40 numbers in a text file, with
lengths in millimetres; the readers convert to metres. Every problem (unreadable file, missing node, wrong matrix shape, a rotation
that is not one) raises :class:`CalibrationError` naming the file and the node.

SLMaster (``caliInfo.yml``)
---------------------------
Practice3DVision/SLMaster writes ``M1``/``D1`` (camera intrinsics and distortion), ``M4``/``D4``
(projector), ``Rlp``/``Tlp`` (camera <-> projector) and ``S`` (camera image size, width then
height). Direction of ``Rlp``/``Tlp``: they map *camera*-frame points into the *projector* frame,
i.e. they are ``T_projector_camera``. Evidence, from SLMaster's source and from the data:

- SLMaster estimates them with ``cv::solvePnPRansac(camPoints, projectorPixelPoints, M4, D4,
  Rlp, Tlp)`` where ``camPoints`` are 3D points in the camera frame: the pose returned by PnP maps
  those points into the projector frame. Its reconstruction builds the projector's matrix as
  ``PR4 = M4 [Rlp | Tlp]`` next to ``PL1 = M1 [I | 0]``, which is exactly our ``A_projector``.
- Geometry of the shipped file under that reading: the projector centre sits at
  ``-Rlp^T Tlp = (+106.4, +4.2, +25.3) mm`` in the camera frame (106 mm to the side, the usual
  monocular FPP baseline) and its optical axis ``Rlp[2, :] = (-0.090, 0.005, 0.996)`` turns back
  towards the camera's axis, the two axes crossing about 1.2 m ahead, inside SLMaster's default
  0-1500 mm depth range: a toed-in rig looking at a common working volume.
  (The opposite reading is the mirror rig, projector 108 mm on the other side, also toed in, so
  the rig geometry alone cannot tell them apart.)
- The data: the shipped relief capture, decoded (``scripts/decode_real.py``) and triangulated
  under this reading, is an eye relief about 200 x 185 mm across at 694-777 mm (1st-99th
  percentile depths); under the opposite reading the same map becomes a 1.0 x 1.2 m surface
  spread over 2.7-5.7 m. ``scripts/calibrate_real.py`` prints both.

The projector image size is not in the file: SLMaster's monocular rig uses a DLP4710
(``"DLP Width": 1920``, ``"DLP Height": 1080`` in its camera config), the default here.

procam-calibration (``calibration_result.xml``)
-----------------------------------------------
kamino410/procam-calibration writes ``img_shape`` (camera *rows, cols*), ``rms`` (the stereo RMS
reprojection error, px, from ``cv2.stereoCalibrate`` with fixed intrinsics), ``cam_int``/
``cam_dist``, ``proj_int``/``proj_dist``, and ``roration`` [sic]/``translation``, the
``cv2.stereoCalibrate(objpoints, camera_corners, projector_corners, ...)`` output, which "translate
points from camera coord to projector coord" (its own printout): ``T_projector_camera``. Lengths
are in the unit of the chessboard square size given to ``calibrate.py``; its help text says "mm or
cm or m". The shipped sample used 75 (a 75 mm square, 10x8 squares = a 750 x 600 mm board; read as
centimetres the baseline would be 6.4 m), so millimetres is the default ``length_unit``. The
projector size is not stored either: the sample is a 1024 x 768 projector.

SLStudio-style XML (``Kc kc Kp kp Rp Tp``)
-----------------------------------------
jakobwilm/slstudio's ``CalibrationData::saveXML`` (and tools derived from it) writes ``Kc``/``kc``
(camera intrinsics, 5 distortion terms), ``Kp``/``kp`` (projector), ``Rp``/``Tp``, the RMS errors
``cam_error``/``proj_error``/``stereo_error`` (px), ``frameWidth``/``frameHeight`` (camera) and
``screenResX``/``screenResY`` (projector). ``Rp``/``Tp`` come from ``cv::stereoCalibrate`` with
the camera first: they map camera-frame points into the projector frame (``T_projector_camera``),
in the unit of the calibration board, millimetres. Matrices are float32: the rotation is
re-orthonormalised on reading.

Forty numbers in a text file (commercial FPP cameras)
-----------------------------------------------------
Some rigs hand out their calibration as 40 numbers: camera ``K`` (9, row-major), camera
distortion (5: ``k1 k2 p1 p2 k3``, OpenCV's order), projector ``K`` (9) and distortion (5),
``R`` (9, row-major) and ``T`` (3), which map camera-frame points into the projector frame
(``T_projector_camera``), millimetres. Any whitespace, commas or semicolons separate them, ``#``
starts a comment. :func:`read_text_calibration` reads them (:data:`TEXT_CALIBRATION_LAYOUT` names
each number); the image sizes are not in the file, so the camera's and the projector's are
given (``camera_size``, ``projector_size``; ``--camera WxH`` and ``--projector WxH`` on the
command line, or the camera's from the captures' images).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import CalibrationError
from fpp_graph.geometry import make_pose
from fpp_graph.outputs import translated_os_errors
from frontend.fpp.rig import PinholeModel, RigCalibration, load_calibration

_UNIT_TO_M = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
# A rotation read from a file may carry rounding; beyond this it is not a rotation at all.
_ROTATION_TOL = 1e-4


class _Storage:
    """An OpenCV FileStorage opened for reading, with errors that name the file and the node."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise CalibrationError(f"calibration file {self.path} does not exist (or is not a file)")
        try:
            self.fs = cv2.FileStorage(str(self.path), cv2.FILE_STORAGE_READ)
        except Exception as exc:  # cv2.error, or SystemError wrapping it
            cause = exc.__cause__ or exc
            raise CalibrationError(f"{self.path}: not a readable OpenCV FileStorage (YAML/XML) file: {str(cause).strip().splitlines()[-1]}") from None
        if not self.fs.isOpened():
            raise CalibrationError(f"{self.path}: OpenCV cannot open it as a FileStorage (YAML/XML) file")

    def has(self, name: str) -> bool:
        return not self.fs.getNode(name).empty()

    def matrix(self, name: str, shapes: tuple[tuple[int, ...], ...]) -> NDArray[np.float64]:
        node = self.fs.getNode(name)
        if node.empty():
            raise CalibrationError(f"{self.path}: missing node {name!r}; is this the right kind of calibration file?")
        mat = node.mat() if node.isMap() else None
        if mat is None:
            raise CalibrationError(f"{self.path}: node {name!r} is not an OpenCV matrix")
        mat = np.asarray(mat, dtype=np.float64)
        for shape in shapes:
            if mat.size == int(np.prod(shape)) and (mat.shape == shape or mat.ndim <= 2 and 1 in mat.shape and len(shape) == 1):
                mat = mat.reshape(shape)
                break
        else:
            raise CalibrationError(f"{self.path}: node {name!r} has shape {mat.shape}, expected one of {list(shapes)}")
        if not np.all(np.isfinite(mat)):
            raise CalibrationError(f"{self.path}: node {name!r} holds non-finite values")
        return mat

    def real(self, name: str) -> float:
        node = self.fs.getNode(name)
        if node.empty() or not node.isReal() and not node.isInt():
            raise CalibrationError(f"{self.path}: missing or non-numeric node {name!r}")
        return float(node.real())

    def release(self) -> None:
        self.fs.release()


def _rotation(storage: _Storage, name: str) -> NDArray[np.float64]:
    R = storage.matrix(name, ((3, 3), (3,)))
    if R.shape == (3,):  # a Rodrigues vector
        R = cv2.Rodrigues(R)[0]
    if np.abs(R.T @ R - np.eye(3)).max() > _ROTATION_TOL or np.linalg.det(R) <= 0:
        raise CalibrationError(f"{storage.path}: node {name!r} is not a rotation matrix (R^T R != I or det <= 0)")
    # Remove the rounding of the text file so that the pose is rigid to machine precision.
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def _device(storage: _Storage, K_name: str, dist_name: str, width: int, height: int) -> PinholeModel:
    K = storage.matrix(K_name, ((3, 3),))
    dist = storage.matrix(dist_name, ((4,), (5,), (8,), (12,), (14,))) if storage.has(dist_name) else np.zeros(0)
    try:
        return PinholeModel(width, height, K, dist)
    except CalibrationError as exc:
        raise CalibrationError(f"{storage.path}: nodes {K_name!r}/{dist_name!r}: {exc}") from None


def read_slmaster_calibration(
    path: str | os.PathLike[str],
    projector_size: tuple[int, int] = (1920, 1080),
    camera_size: tuple[int, int] | None = None,
) -> RigCalibration:
    """Read an SLMaster ``caliInfo.yml`` (monocular camera + projector, millimetres).

    Parameters
    ----------
    path : path-like
        The OpenCV FileStorage file.
    projector_size : (width, height)
        Projector resolution in pixels (not stored in the file); DLP4710 by default.
    camera_size : (width, height), optional
        Camera resolution; default from the file's ``S`` node.

    Returns
    -------
    RigCalibration
        ``T_projector_camera`` from ``Rlp``/``Tlp`` (see the module docstring), in metres.
    """
    st = _Storage(path)
    try:
        if camera_size is None:
            if not st.has("S"):
                raise CalibrationError(f"{st.path}: node 'S' (camera image size) is missing; pass camera_size=(width, height)")
            size = st.matrix("S", ((2,),))
            camera_size = (int(round(size[0])), int(round(size[1])))
        camera = _device(st, "M1", "D1", *camera_size)
        projector = _device(st, "M4", "D4", *projector_size)
        R = _rotation(st, "Rlp")
        t_mm = st.matrix("Tlp", ((3,),))
    finally:
        st.release()
    return RigCalibration(camera, projector, make_pose(R, t_mm * _UNIT_TO_M["mm"]))


def read_procam_calibration(
    path: str | os.PathLike[str],
    projector_size: tuple[int, int] = (1024, 768),
    length_unit: str = "mm",
) -> RigCalibration:
    """Read a kamino410/procam-calibration ``calibration_result.xml``.

    Parameters
    ----------
    path : path-like
        The OpenCV FileStorage file.
    projector_size : (width, height)
        Projector resolution in pixels (not stored in the file); 1024 x 768 for the sample data.
    length_unit : {"mm", "cm", "m"}
        Unit of the chessboard square size the tool was run with (and so of ``translation``).

    Returns
    -------
    RigCalibration
        With ``reprojection_rms_px["stereo"]`` from the file's ``rms``.
    """
    if length_unit not in _UNIT_TO_M:
        raise CalibrationError(f"length_unit must be one of {sorted(_UNIT_TO_M)}, got {length_unit!r}")
    st = _Storage(path)
    try:
        rows, cols = (int(round(v)) for v in st.matrix("img_shape", ((2,),)))
        camera = _device(st, "cam_int", "cam_dist", cols, rows)
        projector = _device(st, "proj_int", "proj_dist", *projector_size)
        R = _rotation(st, "roration" if st.has("roration") else "rotation")
        t = st.matrix("translation", ((3,),))
        rms = {"stereo": st.real("rms")} if st.has("rms") else {}
    finally:
        st.release()
    return RigCalibration(camera, projector, make_pose(R, t * _UNIT_TO_M[length_unit]), reprojection_rms_px=rms)


def read_slstudio_calibration(
    path: str | os.PathLike[str],
    projector_size: tuple[int, int] | None = None,
    camera_size: tuple[int, int] | None = None,
    length_unit: str = "mm",
) -> RigCalibration:
    """Read an SLStudio-style OpenCV FileStorage calibration (``Kc kc Kp kp Rp Tp``).

    Parameters
    ----------
    path : path-like
    projector_size, camera_size : (width, height), optional
        Override (or supply, when the file lacks them) ``screenResX/Y`` and ``frameWidth/Height``.
    length_unit : {"mm", "cm", "m"}
        Unit of ``Tp`` (SLStudio: millimetres).

    Returns
    -------
    RigCalibration
        ``T_projector_camera`` from ``Rp``/``Tp`` in metres, with the file's RMS errors.
    """
    if length_unit not in _UNIT_TO_M:
        raise CalibrationError(f"length_unit must be one of {sorted(_UNIT_TO_M)}, got {length_unit!r}")
    st = _Storage(path)
    try:
        camera_size = camera_size or _size_nodes(st, "frameWidth", "frameHeight", "camera", "the captures' size")
        projector_size = projector_size or _size_nodes(st, "screenResX", "screenResY", "projector", "--projector WxH")
        camera = _device(st, "Kc", "kc", *camera_size)
        projector = _device(st, "Kp", "kp", *projector_size)
        R = _rotation(st, "Rp")
        t = st.matrix("Tp", ((3,),))
        rms = {key: st.real(node) for key, node in (("camera", "cam_error"), ("projector", "proj_error"), ("stereo", "stereo_error")) if st.has(node)}
    finally:
        st.release()
    return RigCalibration(camera, projector, make_pose(R, t * _UNIT_TO_M[length_unit]), reprojection_rms_px=rms)


def _size_nodes(st: _Storage, w_name: str, h_name: str, device: str, how: str) -> tuple[int, int]:
    if not (st.has(w_name) and st.has(h_name)):
        raise CalibrationError(f"{st.path}: the {device} size ({w_name}/{h_name}) is missing; give it ({how})")
    size = (int(round(st.real(w_name))), int(round(st.real(h_name))))
    if min(size) <= 0:
        raise CalibrationError(f"{st.path}: the {device} size {w_name}/{h_name} is {size[0]}x{size[1]}; give the real one ({how})")
    return size


def _text_layout() -> tuple[tuple[str, int], ...]:
    """(block name, count) of the 40 numbers, in file order."""
    return (
        ("camera K", 9), ("camera distortion (k1 k2 p1 p2 k3)", 5),
        ("projector K", 9), ("projector distortion (k1 k2 p1 p2 k3)", 5),
        ("R (camera -> projector)", 9), ("T (camera -> projector)", 3),
    )


#: What each of the 40 numbers of a text calibration is: ``(1-based position, meaning)``.
TEXT_CALIBRATION_LAYOUT: tuple[tuple[int, str], ...] = tuple(
    (start + i + 1, f"{name} #{i + 1}")
    for (name, count), start in zip(_text_layout(), np.cumsum([0] + [c for _, c in _text_layout()])[:-1].tolist(), strict=True)
    for i in range(count)
)
TEXT_CALIBRATION_COUNT = len(TEXT_CALIBRATION_LAYOUT)
_TEXT_SEPARATORS = str.maketrans({",": " ", ";": " "})


def _number_meaning(position: int) -> str:
    return TEXT_CALIBRATION_LAYOUT[position - 1][1] if 1 <= position <= TEXT_CALIBRATION_COUNT else "beyond the 40"


def _text_tokens(text: str) -> list[tuple[str, int]]:
    """The file's tokens with their 1-based line numbers, comments (``#`` to the line's end) removed."""
    tokens = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        tokens += [(token, line_number) for token in line.split("#", 1)[0].translate(_TEXT_SEPARATORS).split()]
    return tokens


def looks_like_text_calibration(text: str) -> bool:
    """True when every token (comments removed) is a number: a 40-number text calibration, or a
    malformed one that :func:`parse_text_calibration` will explain."""
    tokens = _text_tokens(text)
    if not tokens:
        return False
    try:
        for token, _ in tokens:
            float(token)
    except ValueError:
        return False
    return True


def _count_numbers(text: str) -> int:
    count = 0
    for token, _ in _text_tokens(text):
        try:
            float(token)
            count += 1
        except ValueError:
            pass
    return count


@dataclass(frozen=True)
class TextCalibrationNumbers:
    """The 40 numbers of a text calibration, as written (lengths in the file's unit)."""

    K_camera: NDArray[np.float64]
    dist_camera: NDArray[np.float64]
    K_projector: NDArray[np.float64]
    dist_projector: NDArray[np.float64]
    R_projector_camera: NDArray[np.float64]
    t_projector_camera: NDArray[np.float64]

    @property
    def rotation_error(self) -> float:
        """Largest entry of ``|R^T R - I|`` (0 for a rotation; the file's rounding gives ~1e-6)."""
        R = self.R_projector_camera
        return float(np.abs(R.T @ R - np.eye(3)).max())

    @property
    def is_rotation(self) -> bool:
        """R is a rotation within the rounding a file may carry (:data:`_ROTATION_TOL`)."""
        return self.rotation_error <= _ROTATION_TOL and float(np.linalg.det(self.R_projector_camera)) > 0


def parse_text_calibration(path: str | os.PathLike[str]) -> TextCalibrationNumbers:
    """The 40 numbers of a text calibration file (see the module docstring), checked.

    Raises
    ------
    CalibrationError
        Missing file, a token that is not a number (its line and position named), a count other
        than 40 (the first missing or extra number named), non-finite numbers, an intrinsic
        matrix whose last row is not ``0 0 1`` or whose focal lengths are not positive.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist (or is not a file)")
    with translated_os_errors(path, reading=True):
        text = path.read_text(encoding="utf-8", errors="replace")
    values = []
    for position, (token, line) in enumerate(_text_tokens(text), start=1):
        try:
            values.append(float(token))
        except ValueError:
            raise CalibrationError(
                f"{path}:{line}: {token!r} is not a number (number {position}, {_number_meaning(position)}); "
                "a text calibration holds 40 numbers separated by spaces, commas or newlines, comments after #"
            ) from None
    n = len(values)
    if n < TEXT_CALIBRATION_COUNT:
        raise CalibrationError(
            f"{path}: {n} numbers, a text calibration has {TEXT_CALIBRATION_COUNT}; number {n + 1} ({_number_meaning(n + 1)}) "
            f"and after are missing{_shift_hint(values)}. Order: {_layout_summary()}"
        )
    if n > TEXT_CALIBRATION_COUNT:
        raise CalibrationError(
            f"{path}: {n} numbers, a text calibration has {TEXT_CALIBRATION_COUNT}; number 41 (value {values[40]:g}) and after are extra"
            f"{_shift_hint(values)}. Order: {_layout_summary()}"
        )
    v = np.asarray(values)
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise CalibrationError(f"{path}: number {bad[0] + 1} ({_number_meaning(int(bad[0]) + 1)}) is {v[bad[0]]}; every number must be finite")
    numbers = TextCalibrationNumbers(v[0:9].reshape(3, 3), v[9:14], v[14:23].reshape(3, 3), v[23:28], v[28:37].reshape(3, 3), v[37:40])
    for K, first in ((numbers.K_camera, 1), (numbers.K_projector, 15)):
        if not np.allclose(K[2], (0.0, 0.0, 1.0)) or K[1, 0] != 0.0:
            raise CalibrationError(
                f"{path}: numbers {first}-{first + 8} ({_number_meaning(first)[:-3]}, row-major) must end in 0 0 1 with a 0 as number {first + 3}, "
                f"got {K.ravel().tolist()}; is the order camera K, camera distortion, projector K, projector distortion, R, T?"
            )
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"{path}: the focal lengths (numbers {first} and {first + 4}) must be positive pixels, got {K[0, 0]:g} and {K[1, 1]:g}")
    return numbers


def _shift_hint(values: list[float]) -> str:
    """Where a lost or extra number is, from the intrinsic matrices' last rows ``0 0 1``, which
    a shifted file puts out of place (empty when they are where they belong)."""
    for name, first in (("camera", 1), ("projector", 15)):
        home = first + 6  # 1-based position of the last row's first number
        for shift in (0, -1, 1, -2, 2, -3, 3):
            start = home + shift
            if 1 <= start and start + 2 <= len(values) and values[start - 1:start + 2] == [0.0, 0.0, 1.0]:
                if shift:
                    where = f"a number is missing before number {home}" if shift < 0 else f"a number too many before number {start}"
                    return f"; the {name} K's last row 0 0 1 is at numbers {start}-{start + 2}, not {home}-{home + 2}: {where}"
                break
    return ""


def _layout_summary() -> str:
    start, parts = 1, []
    for name, count in _text_layout():
        parts.append(f"{start}-{start + count - 1} {name}")
        start += count
    return ", ".join(parts)


def read_text_calibration(
    path: str | os.PathLike[str],
    projector_size: tuple[int, int] | None = None,
    camera_size: tuple[int, int] | None = None,
    length_unit: str = "mm",
    orthonormalise: bool = False,
) -> RigCalibration:
    """Read a 40-number text calibration (see the module docstring).

    Parameters
    ----------
    path : path-like
    projector_size, camera_size : (width, height)
        Image sizes in pixels; the file does not hold them, so both are required.
    length_unit : {"mm", "cm", "m"}
        Unit of ``T`` (millimetres for the cameras that write this format).
    orthonormalise : bool
        False: a ``R`` that is not a rotation (beyond :data:`_ROTATION_TOL`, far above a printed
        number's rounding) raises. True: its nearest rotation is used (for inspecting a broken
        file; :func:`parse_text_calibration` gives the deviation).

    Raises
    ------
    CalibrationError
        As :func:`parse_text_calibration`; a missing size (the message names the option that
        gives it); ``R`` not a rotation.
    """
    if length_unit not in _UNIT_TO_M:
        raise CalibrationError(f"length_unit must be one of {sorted(_UNIT_TO_M)}, got {length_unit!r}")
    numbers = parse_text_calibration(path)
    if camera_size is None:
        raise CalibrationError(f"{path}: a 40-number text calibration does not store the camera's image size; give it (--camera WxH, or camera_size=(width, height))")
    if projector_size is None:
        raise CalibrationError(f"{path}: a 40-number text calibration does not store the projector's size; give it (--projector WxH, or projector_size=(width, height))")
    R = numbers.R_projector_camera
    det = float(np.linalg.det(R))
    if not orthonormalise and not numbers.is_rotation:
        raise CalibrationError(
            f"{path}: numbers 29-37 (R, row-major) are not a rotation: max |R^T R - I| = {numbers.rotation_error:.2g}, det R = {det:.4f} "
            "(a rotation has 0 and 1); check their order and that no number was lost or mistyped"
        )
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    try:
        camera = PinholeModel(*camera_size, numbers.K_camera, numbers.dist_camera)
        projector = PinholeModel(*projector_size, numbers.K_projector, numbers.dist_projector)
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    return RigCalibration(camera, projector, make_pose(R, numbers.t_projector_camera * _UNIT_TO_M[length_unit]))


#: The formats :func:`read_any_calibration` recognises, as (name, nodes that identify it).
KNOWN_FORMATS = (
    ("fpp-graph rig calibration YAML", "format: fpp-graph rig calibration v1"),
    ("SLMaster caliInfo.yml", "M1, D1, M4, D4, Rlp, Tlp"),
    ("procam-calibration calibration_result.xml", "cam_int, cam_dist, proj_int, proj_dist, roration, translation"),
    ("SLStudio-style XML", "Kc, kc, Kp, kp, Rp, Tp, screenResX, screenResY"),
    ("40-number text calibration", "camera K, distortion, projector K, distortion, R, T; needs --camera and --projector"),
)


def calibration_format(path: str | os.PathLike[str]) -> str:
    """The name (in :data:`KNOWN_FORMATS`) of a calibration file's format, recognised by content.

    Raises
    ------
    CalibrationError
        Missing or unreadable file, or an unknown format (the message lists the known ones).
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist (or is not a file)")
    with translated_os_errors(path, reading=True):
        head = path.read_text(encoding="utf-8", errors="replace")[:65536]
    if "fpp-graph rig calibration" in head[:4096]:
        return KNOWN_FORMATS[0][0]
    if looks_like_text_calibration(head) or path.suffix.lower() == ".txt" and _count_numbers(head) >= TEXT_CALIBRATION_COUNT // 2:
        # a .txt mostly of numbers is a text calibration with a typo: its reader names the bad token
        return KNOWN_FORMATS[4][0]
    known = "; ".join(f"{name} ({nodes})" for name, nodes in KNOWN_FORMATS)
    try:
        st = _Storage(path)
    except CalibrationError as exc:
        raise CalibrationError(f"{exc}; known calibration formats: {known}") from None
    try:
        if st.has("M1") and st.has("M4"):
            return KNOWN_FORMATS[1][0]
        if st.has("cam_int") and st.has("proj_int"):
            return KNOWN_FORMATS[2][0]
        if st.has("Kc") and st.has("Kp") and st.has("Rp"):
            return KNOWN_FORMATS[3][0]
    finally:
        st.release()
    raise CalibrationError(f"{path}: unknown calibration format; known formats: {known}")


def stores_camera_size(path: str | os.PathLike[str]) -> bool:
    """Whether the calibration file holds the camera's image size (the 40-number text does not)."""
    return calibration_format(path) != KNOWN_FORMATS[4][0]


def read_any_calibration(
    path: str | os.PathLike[str],
    projector_size: tuple[int, int] | None = None,
    camera_size: tuple[int, int] | None = None,
    **kwargs,
) -> RigCalibration:
    """Read a calibration in any supported format (:data:`KNOWN_FORMATS`), recognised by content.

    ``projector_size`` and ``camera_size`` (width, height) are for formats that do not store them
    (SLMaster and procam-calibration the projector's, the 40-number text both) or override them
    (SLMaster's camera size, SLStudio's both); where the project's YAML or procam-calibration's
    file states one, a given size must agree with it. Other keyword arguments go to the matching
    reader.

    Raises
    ------
    CalibrationError
        Missing or unreadable file, an unknown format (the message lists the known ones), a
        malformed node, or a size that contradicts the file.
    """
    path = Path(path)
    kind = calibration_format(path)
    size_kw = {"projector_size": tuple(projector_size)} if projector_size is not None else {}
    if kind == KNOWN_FORMATS[0][0]:
        cal = load_calibration(path)
        _check_size(path, "projector", cal.projector, projector_size, "--projector")
    elif kind == KNOWN_FORMATS[1][0]:
        cal = read_slmaster_calibration(path, **size_kw, camera_size=camera_size, **kwargs)
    elif kind == KNOWN_FORMATS[2][0]:
        cal = read_procam_calibration(path, **size_kw, **kwargs)
    elif kind == KNOWN_FORMATS[3][0]:
        cal = read_slstudio_calibration(path, **size_kw, camera_size=camera_size, **kwargs)
    else:
        return read_text_calibration(path, projector_size=projector_size, camera_size=camera_size, **kwargs)
    _check_size(path, "camera", cal.camera, camera_size, "--camera")
    return cal


def _check_size(path: Path, device: str, model: PinholeModel, given: tuple[int, int] | None, option: str) -> None:
    if given is not None and tuple(given) != (model.width, model.height):
        raise CalibrationError(f"{path}: its {device} is {model.width}x{model.height}, not the {given[0]}x{given[1]} given; drop {option} or fix the file")
