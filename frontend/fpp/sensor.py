"""The FPP sensor as the back-end sees it: one frame's pattern images -> a :class:`fpp_graph.types.Frame`.

decode (phase retrieval + unwrapping, :mod:`frontend.fpp.phase`) -> triangulate
(:mod:`frontend.fpp.triangulation`) -> Frame. Real recordings and simulated ones take exactly this
path. The decoder tables and the per-pixel triangulation constants are built once per sensor.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import finite_box, in_row_bands, masked_pixels
from fpp_graph.types import Frame, grey_colors
from frontend.config import DecodeConfig
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import DecodeResult, make_decoder
from frontend.fpp.rig import RigCalibration
from frontend.fpp.triangulation import Triangulator

log = logging.getLogger(__name__)


class FppSensor:
    """Turns the pattern images of one capture into a 3D frame.

    Parameters
    ----------
    calibration : RigCalibration
        Camera + projector calibration (sensor frame = camera frame).
    spec : PatternSpec
        The projected pattern set (capture order of the images).
    decode_config : DecodeConfig, optional
        Validity thresholds of the decoder.
    depth_range_m : (float, float)
        Accepted depths along the camera axis, metres.
    edge_max_angle_deg : float
        Depth-discontinuity / mixed-pixel filter (:func:`edge_filter_mask`): a pixel is dropped
        when its surface is seen at more than this angle from the viewing ray, or when the depth
        range of its 3x3 neighbourhood exceeds what such a surface could span. ``None`` or
        ``>= 90`` turns the filter off.
    edge_noise_floor_m : float
        Depth noise allowance added to the neighbourhood range bound, metres.
    camera_rays : (H, W, 3) float64, optional
        The camera's pixel rays, if already known (:class:`~frontend.fpp.triangulation.Triangulator`).
    cache_projector_fit : bool
        Keep the projector's inverse distortion in the user's cache (:class:`~frontend.fpp.triangulation.Triangulator`).
    """

    def __init__(
        self,
        calibration: RigCalibration,
        spec: PatternSpec,
        decode_config: DecodeConfig | None = None,
        depth_range_m: tuple[float, float] = (0.05, 10.0),
        edge_max_angle_deg: float | None = 75.0,
        edge_noise_floor_m: float = 0.0005,
        camera_rays: NDArray[np.float64] | None = None,
        cache_projector_fit: bool = False,
    ) -> None:
        self.calibration = calibration
        self.spec = spec
        proj = calibration.projector
        self.decoder = make_decoder(spec, proj.width, proj.height, decode_config)
        self.triangulator = Triangulator(calibration, axis=spec.coded_axis, depth_range_m=depth_range_m, camera_rays=camera_rays,
                                        cache_projector_fit=cache_projector_fit)
        self.edge_max_angle_deg = edge_max_angle_deg
        self.edge_noise_floor_m = float(edge_noise_floor_m)
        K = calibration.camera.K
        self._focal_px = float(np.sqrt(K[0, 0] * K[1, 1]))

    def decode(self, images: NDArray | Sequence[NDArray], where: str = "frame") -> DecodeResult:
        """Decode one capture (M, H, W); checks the image count and size first."""
        stack = images if isinstance(images, np.ndarray) else np.stack([np.asarray(im) for im in images])
        if stack.ndim != 3:
            raise InputDataError(f"{where}: expected a stack of 2D images (M, H, W), got shape {stack.shape}")
        if stack.shape[0] != self.spec.image_count():
            raise InputDataError(
                f"{where}: {stack.shape[0]} images but the {self.spec.kind} pattern set has {self.spec.image_count()}; "
                "check the sequence's pattern section"
            )
        self.calibration.check_image_size(stack.shape[2], stack.shape[1], where)
        return self.decoder.decode(stack)

    def points_from_decoding(self, result: DecodeResult) -> tuple[NDArray[np.float64], int]:
        """Triangulate a decoded capture and apply the mixed-pixel / discontinuity filter.

        Returns
        -------
        xyz_map : (H, W, 3) float64
            Metres, camera (sensor) frame, NaN where invalid.
        edge_rejected : int
            Decoded pixels the edge filter removed.
        """
        xyz = self.triangulator.triangulate(result.u_projector_px, result.mask)
        edge_rejected = 0
        if self.edge_max_angle_deg is not None and self.edge_max_angle_deg < 90:
            decoded = np.isfinite(xyz[..., 2])
            keep = edge_filter_mask(xyz, self._focal_px, self.edge_max_angle_deg, self.edge_noise_floor_m)
            drop = decoded & ~keep
            edge_rejected = int(np.count_nonzero(drop))
            xyz[drop] = np.nan
        return xyz, edge_rejected

    def frame_from_images(
        self,
        frame_id: int,
        timestamp: float,
        images: NDArray | Sequence[NDArray],
        T_world_sensor_guess: NDArray | None = None,
    ) -> Frame:
        """Decode and triangulate one capture.

        Returns
        -------
        Frame
            ``points`` (N, 3) metres in the sensor frame (valid pixels, row-major order),
            ``colors`` the texture grey in [0, 1] (N, 3), ``xyz_map`` (H, W, 3) NaN where
            invalid, ``texture`` (H, W) uint8; metadata holds the valid fraction, the
            decoder's invalid-pixel counts and (``edge_filter``) the pixels the
            mixed-pixel / discontinuity filter removed.
        """
        where = f"frame {frame_id}"
        result = self.decode(images, where)
        xyz, edge_rejected = self.points_from_decoding(result)
        valid = np.isfinite(xyz[..., 2])
        points = masked_pixels(xyz, valid)
        grey = result.texture[valid].astype(np.float64) / 255.0
        log.debug("%s: %d valid points (%.1f%%)", where, points.shape[0], 100.0 * points.shape[0] / valid.size)
        return Frame(
            id=int(frame_id),
            timestamp=float(timestamp),
            points=points,
            colors=grey_colors(grey),
            xyz_map=xyz,
            texture=result.texture,
            T_world_sensor_guess=T_world_sensor_guess,
            metadata={
                "valid_fraction": float(np.count_nonzero(valid)) / valid.size,
                "invalid_counts": {**dict(result.invalid_counts), "edge_filter": edge_rejected},
            },
        )


_KERNEL_3x3 = np.ones((3, 3), np.uint8)


def edge_filter_mask(
    xyz_map: NDArray[np.float64], focal_px: float, max_angle_deg: float = 75.0, noise_floor_m: float = 0.0005
) -> NDArray[np.bool_]:
    """Pixels of an organised point map that are not mixed pixels, silhouette or grazing surface.

    At a depth discontinuity (an object's silhouette in front of a farther surface, or the edge of
    a shadow) a camera pixel integrates light from both sides; its decoded phase, hence its point,
    lies somewhere between them, off every real surface. Such pixels are recognised locally:

    1. shadow/hole edges: a pixel any of whose 8 neighbours is invalid is dropped (the mask is
       eroded by one pixel where decoding failed);
    2. discontinuities: a surface seen at angle ``theta`` from the ray changes depth by about
       ``z tan(theta) / f`` per pixel, so over the 3x3 neighbourhood (diagonal 2 sqrt 2 px) its
       depth range stays below ``2 sqrt(2) z tan(max_angle) / f + noise_floor_m``; more is a jump;
    3. grazing angle: the normal from the neighbours' central differences makes more than
       ``max_angle_deg`` with the viewing ray (such points are also the least accurate ones).

    Parameters
    ----------
    xyz_map : (H, W, 3)
        Points in the camera frame, metres, NaN where invalid.
    focal_px : float
        Camera focal length in pixels (sets the angular size of a pixel).

    Returns
    -------
    (H, W) bool
        True where the pixel is valid and kept.
    """
    xyz = np.asarray(xyz_map)
    h, w = xyz.shape[:2]
    if h < 3 or w < 3:
        return np.zeros((h, w), dtype=bool)
    # every test is local to a 3x3 neighbourhood: only the box around the decoded pixels (and a
    # ring of one undecoded pixel, or the image border) is computed; a scanned object often
    # fills a fraction of the frame, and outside the box nothing is kept anyway
    rows, cols = finite_box(xyz)
    out = np.zeros((h, w), dtype=bool)
    # in bands of rows: a band's ~15 float32 planes stay in the core's cache, where the whole
    # box's went out to memory (~45 % faster on 1920x1200 frames)
    in_row_bands(lambda band: _edge_filter_box(band, focal_px, max_angle_deg, noise_floor_m), xyz[rows, cols], out[rows, cols], EDGE_FILTER_BAND_ROWS)
    return out


EDGE_FILTER_BAND_ROWS = 32
"""Rows per band of :func:`edge_filter_mask`: 32 rows of a 1920-pixel image are 0.25 MB per
float32 plane, so a band's planes fit a 4 MB L2 cache (16 rows was as fast, 64 and 128 10 % slower)."""


def _edge_filter_box(xyz_map: NDArray[np.float64], focal_px: float, max_angle_deg: float, noise_floor_m: float) -> NDArray[np.bool_]:
    """:func:`edge_filter_mask` of a box of the map whose sides are the image's border or lie on
    undecoded pixels: the same answer inside as on the whole map (a pixel's 3x3 neighbourhood is
    inside the box, and the box's own border pixels are dropped either way)."""
    # the coordinates as contiguous float32 planes: differences and products on the strided
    # channels of an (H, W, 3) map ran 15 % slower (the same numbers, in the same order)
    if min(np.shape(xyz_map)[:2]) < 3:
        return np.zeros(np.shape(xyz_map)[:2], dtype=bool)
    x, y, z = cv2.split(np.ascontiguousarray(xyz_map, dtype=np.float32))
    valid = np.isfinite(z)
    z_hi = np.where(valid, z, np.float32(np.inf))
    z_lo = np.where(valid, z, np.float32(-np.inf))
    # an invalid neighbour makes the range infinite: hole and shadow edges go with the jumps
    # (3x3 max/min as OpenCV dilate/erode with replicated borders: ~10x faster than ndimage)
    z_range = cv2.dilate(z_hi, _KERNEL_3x3, borderType=cv2.BORDER_REPLICATE)
    z_range -= cv2.erode(z_lo, _KERNEL_3x3, borderType=cv2.BORDER_REPLICATE)
    tan_max = np.float32(np.tan(np.radians(max_angle_deg)))
    with np.errstate(invalid="ignore"):
        bound = np.float32(2.0 * np.sqrt(2.0) / focal_px) * tan_max * z + np.float32(noise_floor_m)
        keep = valid & (z_range <= bound)
    keep[0, :] = keep[-1, :] = keep[:, 0] = keep[:, -1] = False
    # normal from central differences (all 8 neighbours are valid where keep holds), per
    # component: |n . r| >= cos(max) |n| |r| compared squared, in place where a product's
    # operands are no longer needed
    dux, duy, duz = (p[1:-1, 2:] - p[1:-1, :-2] for p in (x, y, z))
    dvx, dvy, dvz = (p[2:, 1:-1] - p[:-2, 1:-1] for p in (x, y, z))
    nx = duy * dvz - duz * dvy
    ny = duz * dvx - dux * dvz
    nz = dux * dvy - duy * dvx
    rx, ry, rz = (p[1:-1, 1:-1] for p in (x, y, z))
    with np.errstate(invalid="ignore", over="ignore"):
        dot = nx * rx
        dot += ny * ry
        dot += nz * rz
        dot *= dot
        n2 = np.multiply(nx, nx, out=nx)
        n2 += np.multiply(ny, ny, out=ny)
        n2 += np.multiply(nz, nz, out=nz)
        r2 = rx * rx
        r2 += ry * ry
        r2 += rz * rz
        n2 *= np.float32(np.cos(np.radians(max_angle_deg)) ** 2)
        n2 *= r2
        keep[1:-1, 1:-1] &= dot >= n2
    return keep
