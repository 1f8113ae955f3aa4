"""A camera's undistorted pixel rays and a rig's inverse projector distortion, computed once per
model and kept on disk.

Every decode process needs the ray of every camera pixel (:class:`frontend.fpp.triangulation.Triangulator`).
With lens distortion that is an iterative undistortion of each pixel: 1.3 s of one core at
1920x1200, paid by each worker of every run, while a rig's calibration changes rarely. The rays
depend on the camera model alone (size, K, distortion), so they are kept per model in the user's
cache (``$FPP_GRAPH_CACHE/rays`` or ``~/.cache/fpp-graph/rays``, 55 MB at 1920x1200, the
:data:`MAX_ENTRIES` most recently used kept): the first process computes them under a file
lock while the other workers of its run wait and then read them, later runs read them, and all
of them map the same file (one copy in memory for the whole run). A cache that cannot be
written or read only costs the computation; an entry of the wrong shape is recomputed.

A projector with lens distortion adds its inverse along each pixel's epipolar line
(:func:`frontend.fpp.projector_distortion.fit_inverse_distortion`: per-pixel polynomials, ~1 s
of one core at 1920x1200, before a worker can decode its first frame while the tracking process
waits for it). It depends on the whole calibration, the coded axis, the tolerance and the
number type, and is kept the same way per rig (:func:`cached_projector_fit`,
``$FPP_GRAPH_CACHE/projector_fits``, 55 MB at 1920x1200 with degree 5 in float32).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from fpp_graph.atomic import atomic_open
from fpp_graph.mapped_npz import mapped_npz
from frontend.fpp.projector_distortion import FIT_SAMPLES, InverseDistortionFit
from frontend.fpp.rig import PinholeModel, RigCalibration
from frontend.user_cache import user_cache_dir

log = logging.getLogger(__name__)

MAX_ENTRIES = 8
"""Camera models kept (by last use): a lab's few rigs, with room for simulated ones."""
CACHE_VERSION = 1
"""Bumped whenever the rays' computation changes, so old entries are never read."""


def default_ray_cache_dir() -> Path:
    """``$FPP_GRAPH_CACHE/rays`` or ``~/.cache/fpp-graph/rays``."""
    return user_cache_dir("rays")


def ray_cache_key(camera: PinholeModel) -> str:
    """A digest of everything the rays depend on: image size, K and distortion (exact bits)."""
    digest = hashlib.sha256(f"v{CACHE_VERSION} {camera.width}x{camera.height}".encode())
    for array in (camera.K, camera.dist):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()[:24]


def cached_camera_rays(
    camera: PinholeModel, compute: Callable[[PinholeModel], NDArray[np.float64]], cache_dir: str | os.PathLike[str] | None = None
) -> NDArray[np.float64]:
    """``compute(camera)`` (the (H, W, 3) rays), from the cache when it has them (read-only, mapped).

    Parameters
    ----------
    camera : PinholeModel
    compute : callable
        What makes the rays (:func:`frontend.fpp.triangulation.pixel_rays`).
    cache_dir : path, optional
        Default :func:`default_ray_cache_dir`.
    """
    folder = Path(cache_dir) if cache_dir is not None else default_ray_cache_dir()
    shape = (camera.height, camera.width, 3)
    return _kept(
        folder / f"{ray_cache_key(camera)}.npy", lambda path: _read(path, shape), lambda: compute(camera), np.save, "camera rays",
    )


def _kept(path: Path, read: Callable[[Path], Any], compute: Callable[[], Any], write: Callable[[IO[bytes], Any], None], what: str) -> Any:
    """``read(path)`` when the entry is there and sound, else ``compute()`` under the entry's lock,
    written with ``write`` (atomically) and read back mapped; a cache that cannot be written only
    costs the computation (``what`` names the entry in the warning)."""
    folder = path.parent
    if (value := read(path)) is not None:
        return value
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with _locked(folder / f"{path.stem}.lock"):
            if (value := read(path)) is not None:  # another process made it while this one waited
                return value
            value = compute()
            with atomic_open(path, "wb") as handle:
                write(handle, value)
        _evict(folder, keep=path)
    except OSError as exc:  # a read-only or full cache only costs the computation
        log.warning("cannot cache %s in %s: %s", what, folder, exc)
        return value if value is not None else compute()
    mapped = read(path)  # this process maps the file too: one copy in memory for all
    return mapped if mapped is not None else value


def _read(path: Path, shape: tuple[int, int, int]) -> NDArray[np.float64] | None:
    if not path.is_file():
        return None
    try:
        rays = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        log.warning("unreadable camera rays %s (%s): computing them again", path, exc)
        return None
    if rays.shape != shape or rays.dtype != np.float64:
        log.warning("camera rays %s have shape %s %s, not %s float64: computing them again", path, rays.shape, rays.dtype, shape)
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # last use, for the eviction
    return rays


@contextlib.contextmanager
def _locked(lock_path: Path) -> Iterator[None]:
    """An exclusive lock on ``lock_path`` (POSIX ``flock``; without it, none: both compute)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with open(lock_path, "a+b") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _evict(folder: Path, keep: Path) -> None:
    """Delete all but the :data:`MAX_ENTRIES` most recently used entries (never ``keep``)."""
    entries = sorted(folder.glob(f"*{keep.suffix}"), key=lambda p: p.stat().st_mtime, reverse=True)
    for old in [p for p in entries if p != keep][MAX_ENTRIES - 1 :]:
        with contextlib.suppress(OSError):
            old.unlink()
            old.with_suffix(".lock").unlink(missing_ok=True)


FIT_CACHE_VERSION = 1
"""Bumped whenever the projector fit's computation changes, so old entries are never read."""


def default_projector_fit_cache_dir() -> Path:
    """``$FPP_GRAPH_CACHE/projector_fits`` or ``~/.cache/fpp-graph/projector_fits``."""
    return user_cache_dir("projector_fits")


def projector_fit_cache_key(calibration: RigCalibration, row: int, tolerance_px: float, dtype: np.dtype) -> str:
    """A digest of everything the fit depends on: both models, the rig's pose, the axis, the
    tolerance and the number type (exact bits)."""
    digest = hashlib.sha256(f"v{FIT_CACHE_VERSION} row {int(row)} tolerance {float(tolerance_px)!r} {np.dtype(dtype).str}".encode())
    for model in (calibration.camera, calibration.projector):
        digest.update(f" {model.width}x{model.height}".encode())
        for array in (model.K, model.dist):
            digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(calibration.T_projector_camera, dtype=np.float64).tobytes())
    return digest.hexdigest()[:24]


def cached_projector_fit(
    calibration: RigCalibration, row: int, tolerance_px: float, dtype: np.dtype, compute: Callable[[], InverseDistortionFit],
    cache_dir: str | os.PathLike[str] | None = None,
) -> InverseDistortionFit:
    """``compute()`` (the fit of :func:`~frontend.fpp.projector_distortion.fit_inverse_distortion`
    for ``calibration``, axis ``row``, ``tolerance_px`` and ``dtype``), from the cache when it has
    it (its coefficients read-only views of the mapped file), else computed under the folder's
    lock and stored; as :func:`cached_camera_rays`. Default folder :func:`default_projector_fit_cache_dir`."""
    folder = Path(cache_dir) if cache_dir is not None else default_projector_fit_cache_dir()
    shape = (calibration.camera.height, calibration.camera.width)
    return _kept(
        folder / f"{projector_fit_cache_key(calibration, row, tolerance_px, dtype)}.npz", lambda path: _read_fit(path, shape, dtype),
        compute, _write_fit, "the projector's inverse distortion",
    )


def _write_fit(handle: IO[bytes], fit: InverseDistortionFit) -> None:
    np.savez(
        handle, center=np.float64(fit.center), degree=np.int64(fit.degree), table_error_px=np.float64(fit.table_error_px),
        coverage=np.float64(fit.coverage), nodes=np.asarray(fit.nodes, dtype=np.float64), coeffs=np.stack(fit.coeffs),
    )


def _read_fit(path: Path, shape: tuple[int, int], dtype: np.dtype) -> InverseDistortionFit | None:
    if not path.is_file():
        return None
    try:
        arrays = mapped_npz(path)
        degree = int(arrays["degree"])
        coeffs, nodes = arrays["coeffs"], arrays["nodes"]
        fit = InverseDistortionFit(
            float(arrays["center"]), list(coeffs), degree, float(arrays["table_error_px"]), nodes, float(arrays["coverage"]),
        )
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("unreadable projector fit %s (%s): computing it again", path, exc)
        return None
    if coeffs.shape != (degree + 1, *shape) or coeffs.dtype != np.dtype(dtype) or nodes.shape != (FIT_SAMPLES,):
        log.warning("projector fit %s has coefficients %s %s, not %s %s: computing it again", path, coeffs.shape, coeffs.dtype, (degree + 1, *shape), np.dtype(dtype))
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # last use, for the eviction
    return fit


__all__ = [
    "MAX_ENTRIES", "cached_camera_rays", "cached_projector_fit", "default_projector_fit_cache_dir", "default_ray_cache_dir",
    "projector_fit_cache_key", "ray_cache_key",
]
