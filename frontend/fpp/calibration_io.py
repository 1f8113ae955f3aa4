"""Readers of third-party projector-camera calibration files into :class:`RigCalibration`.

:func:`read_any_calibration` recognises the format by content. All third-party formats are OpenCV FileStorage files (YAML or XML) with lengths in millimetres; the readers
convert to metres. Every problem (unreadable file, missing node, wrong matrix shape, a rotation
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
"""

from __future__ import annotations

import os
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


#: The formats :func:`read_any_calibration` recognises, as (name, nodes that identify it).
KNOWN_FORMATS = (
    ("fpp-graph rig calibration YAML", "format: fpp-graph rig calibration v1"),
    ("SLMaster caliInfo.yml", "M1, D1, M4, D4, Rlp, Tlp"),
    ("procam-calibration calibration_result.xml", "cam_int, cam_dist, proj_int, proj_dist, roration, translation"),
    ("SLStudio-style XML", "Kc, kc, Kp, kp, Rp, Tp, screenResX, screenResY"),
)


def read_any_calibration(path: str | os.PathLike[str], projector_size: tuple[int, int] | None = None, **kwargs) -> RigCalibration:
    """Read a calibration in any supported format (:data:`KNOWN_FORMATS`), recognised by content.

    ``projector_size`` (width, height) is for formats that do not store it (SLMaster,
    procam-calibration) or overrides it (SLStudio); for the project's YAML it must agree with
    the file. Other keyword arguments go to the matching reader.

    Raises
    ------
    CalibrationError
        Missing or unreadable file, an unknown format (the message lists the known ones), a
        malformed node, or a projector size that contradicts the file.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist (or is not a file)")
    with translated_os_errors(path, reading=True):
        head = path.read_text(encoding="utf-8", errors="replace")[:4096]
    size_kw = {"projector_size": tuple(projector_size)} if projector_size is not None else {}
    if "fpp-graph rig calibration" in head:
        cal = load_calibration(path)
        if projector_size is not None and tuple(projector_size) != (cal.projector.width, cal.projector.height):
            raise CalibrationError(f"{path}: its projector is {cal.projector.width}x{cal.projector.height}, not the {projector_size[0]}x{projector_size[1]} given; drop --projector or fix the file")
        return cal
    known = "; ".join(f"{name} ({nodes})" for name, nodes in KNOWN_FORMATS)
    try:
        st = _Storage(path)
    except CalibrationError as exc:
        raise CalibrationError(f"{exc}; known calibration formats: {known}") from None
    try:
        is_slmaster = st.has("M1") and st.has("M4")
        is_procam = st.has("cam_int") and st.has("proj_int")
        is_slstudio = st.has("Kc") and st.has("Kp") and st.has("Rp")
    finally:
        st.release()
    if is_slmaster:
        return read_slmaster_calibration(path, **size_kw, **kwargs)
    if is_procam:
        return read_procam_calibration(path, **size_kw, **kwargs)
    if is_slstudio:
        return read_slstudio_calibration(path, **size_kw, **kwargs)
    raise CalibrationError(f"{path}: unknown calibration format; known formats: {known}")
