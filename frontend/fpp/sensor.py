"""The FPP sensor as the back-end sees it: one frame's pattern images -> a :class:`fpp_graph.types.Frame`.

decode (phase retrieval + unwrapping, :mod:`frontend.fpp.phase`) -> triangulate
(:mod:`frontend.fpp.triangulation`) -> mixed-pixel edge filter -> Frame. Real recordings and
simulated ones take exactly this path. The decoder tables and the per-pixel triangulation
constants are built once per sensor.

The edge filter's noise model
-----------------------------
:func:`edge_filter_mask` compares depth differences between neighbouring pixels with what a
surface could give, so it must know how noisy a depth is: a 12-step, 32-period capture has
~0.1 mm of depth noise, a 3-step single-period one some millimetres, and a fixed allowance that
suits the first drops the whole cloud of the second. :meth:`FppSensor.decode` therefore states
each pixel's projector-coordinate noise (``DecodeResult.u_noise_px``) when the decoder does not:
``sigma_u = lambda / (2 pi) sqrt(2 / N) sigma_I / b`` (:mod:`frontend.fpp.phase_noise`) with the
image noise ``sigma_I`` measured on the finest frequency's N phase-shift images, or the stripe
quantisation ``W / (S sqrt 12)`` for Gray code alone; the triangulation turns it into the depth
noise ``sigma_z`` (:meth:`~frontend.fpp.triangulation.Triangulator.depth_sigma_m`), and the
filter's two tests allow for it at a per-pixel false-drop probability
:data:`EDGE_FALSE_DROP_PROBABILITY` (see :func:`edge_filter_mask`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from fpp_graph.errors import InputDataError
from fpp_graph.geometry import finite_box, in_row_bands, masked_pixels
from fpp_graph.types import Frame, grey_colors
from frontend.config import DecodeConfig
from frontend.fpp.patterns import PatternSpec
from frontend.fpp.phase import DecodeResult, make_decoder
from frontend.fpp.phase_noise import estimate_image_noise_grey, projector_coordinate_sigma_px
from frontend.fpp.rig import RigCalibration
from frontend.fpp.triangulation import Triangulator
from frontend.fpp.two_axis_triangulation import TwoAxisTriangulator

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
        Smallest depth noise allowance of the neighbourhood range bound, metres: the allowance is
        the larger of this and :func:`neighbourhood_range_quantile` times the pixels' expected
        depth noise. The codec's noise model leaves out blur across texture and reflectance
        edges, the projector's response harmonics and calibration error, so where it predicts
        less than the fixed 0.5 mm allowance the filter used before, that allowance stays: the
        noise model never makes the filter stricter than it was.
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
        # a capture that codes both projector axes is triangulated from both coordinates: the
        # point nearest (in projector pixels, weighted by each coordinate's noise) to both planes
        self.two_axis = (
            TwoAxisTriangulator(calibration, depth_range_m=depth_range_m, camera_rays=self.triangulator.rays) if spec.axis == "both" else None
        )
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
        result = self.decoder.decode(stack)
        if result.u_noise_px is None and isinstance(self.spec, PatternSpec):
            result = with_coordinate_noise(result, stack, self.spec, self.calibration.projector.height)
        return result

    @property
    def edge_filter_enabled(self) -> bool:
        return self.edge_max_angle_deg is not None and self.edge_max_angle_deg < 90

    def depth_sigma_m(self, result: DecodeResult) -> NDArray[np.float32] | None:
        """Each pixel's expected depth noise (1 sigma, metres; NaN where undecoded), or None when
        the decoding does not state its coordinate noise (``result.u_noise_px``)."""
        if result.u_noise_px is None:
            return None
        return self.triangulator.depth_sigma_m(result.u_projector_px, result.u_noise_px)

    def _triangulate(self, result: DecodeResult) -> tuple[NDArray[np.float64], NDArray[np.float32] | None, NDArray[np.float32] | None]:
        """The xyz map, each pixel's expected depth noise (None when the decoding states no
        coordinate noise) and, from both projector coordinates, each pixel's reprojection
        residual in projector pixels (None from one coordinate)."""
        if self.two_axis is None or result.v_projector_px is None:
            xyz = self.triangulator.triangulate(result.u_projector_px, result.mask)
            return xyz, self.depth_sigma_m(result), None
        noise_stated = result.u_noise_px is not None and result.v_noise_px is not None
        points = self.two_axis.triangulate(
            result.u_projector_px, result.v_projector_px, result.mask,
            u_sigma_px=result.u_noise_px if noise_stated else None, v_sigma_px=result.v_noise_px if noise_stated else None,
        )
        return points.xyz_m, points.depth_sigma_m, points.residual_px

    def points_from_decoding(self, result: DecodeResult) -> tuple[NDArray[np.float64], int]:
        """Triangulate a decoded capture and apply the mixed-pixel / discontinuity filter.

        Returns
        -------
        xyz_map : (H, W, 3) float64
            Metres, camera (sensor) frame, NaN where invalid.
        edge_rejected : int
            Decoded pixels the edge filter removed.
        """
        xyz, stats = self.filtered_points(result)
        return xyz, stats.removed

    def filtered_points(self, result: DecodeResult) -> tuple[NDArray[np.float64], EdgeFilterStats]:
        """:meth:`points_from_decoding` with the edge filter's account (:class:`EdgeFilterStats`).

        The filter allows for each pixel's depth noise (:meth:`depth_sigma_m`) when the decoding
        states it, else for ``edge_noise_floor_m`` alone. One warning is logged when it removes
        more than half of the triangulated pixels: a capture whose noise the model misjudges, or
        a scene seen at grazing angles throughout.
        """
        xyz, sigma_z, residual_px = self._triangulate(result)
        triangulated = np.isfinite(xyz[..., 2])
        count = int(np.count_nonzero(triangulated))
        median_residual_px = float(np.median(residual_px[triangulated])) if residual_px is not None and count else None
        if not self.edge_filter_enabled:
            return xyz, EdgeFilterStats(enabled=False, triangulated=count, image_noise_grey=result.image_noise_grey, median_residual_px=median_residual_px)
        keep = edge_filter_mask(xyz, self._focal_px, self.edge_max_angle_deg, self.edge_noise_floor_m, depth_sigma_m=sigma_z)
        drop = triangulated & ~keep
        removed = int(np.count_nonzero(drop))
        xyz[drop] = np.nan
        stats = EdgeFilterStats(
            enabled=True, triangulated=count, removed=removed, max_angle_deg=float(self.edge_max_angle_deg),
            noise_floor_m=self.edge_noise_floor_m, image_noise_grey=result.image_noise_grey,
            median_depth_sigma_m=float(np.median(sigma_z[triangulated])) if sigma_z is not None and count else None,
            median_residual_px=median_residual_px,
        )
        if 2 * removed > count:
            allowed = (
                f"a median depth noise of {1e3 * stats.median_depth_sigma_m:.3g} mm" if stats.median_depth_sigma_m is not None
                else f"a fixed {1e3 * self.edge_noise_floor_m:.3g} mm (the decoding states no noise)"
            )
            log.warning(
                "the mixed-pixel edge filter removed %d of %d triangulated pixels (%.0f %%): the depth noise it allowed for (%s) "
                "or its %.0f-degree grazing limit does not fit this capture; keep them with --no-edge-filter (fpp-slam decode) "
                "or FppSensor(edge_max_angle_deg=None)",
                removed, count, 100.0 * removed / max(count, 1), allowed, self.edge_max_angle_deg,
            )
        return xyz, stats

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


@dataclass(frozen=True)
class EdgeFilterStats:
    """What the mixed-pixel edge filter did to one capture, and the noise it allowed for.

    Attributes
    ----------
    enabled : bool
    triangulated : int
        Pixels with a point before the filter.
    removed : int
        Of those, the pixels it removed.
    max_angle_deg, noise_floor_m : float
        Its grazing limit and its smallest depth noise allowance.
    image_noise_grey : float or None
        The camera's image noise measured on the capture (None: not measured, e.g. Gray code alone).
    median_depth_sigma_m : float or None
        Median expected depth noise of the triangulated pixels (None: the decoding states no noise).
    median_residual_px : float or None
        Captures coding both projector axes: the median distance, in projector pixels, between
        the decoded coordinates and the projection of the triangulated point (None from one axis).
    """

    enabled: bool
    triangulated: int
    removed: int = 0
    max_angle_deg: float | None = None
    noise_floor_m: float | None = None
    image_noise_grey: float | None = None
    median_depth_sigma_m: float | None = None
    median_residual_px: float | None = None

    def as_dict(self) -> dict:
        """The report's ``edge_filter`` section (``decode.json``)."""
        if not self.enabled:
            return {"enabled": False, **({"median_residual_px": self.median_residual_px} if self.median_residual_px is not None else {})}
        p = EDGE_FALSE_DROP_PROBABILITY
        return {
            "enabled": True,
            "max_angle_deg": self.max_angle_deg,
            "noise_floor_m": self.noise_floor_m,
            "image_noise_grey": self.image_noise_grey,
            "median_depth_sigma_m": self.median_depth_sigma_m,
            "false_drop_probability": p,
            "range_sigma_multiple": neighbourhood_range_quantile(p),
            "gradient_sigma_multiple": gradient_noise_quantile(p),
            "triangulated_pixels": self.triangulated,
            "removed_pixels": self.removed,
        }


def finest_phase_images(spec: PatternSpec) -> list[int]:
    """Indices (capture order) of the N phase-shift images of the spec's finest frequency; [] for Gray code alone."""
    if spec.kind == "gray_code":
        return []
    finest = int(np.argmax(spec.periods))
    return [i for i, im in enumerate(spec.layout()) if im.role == "phase" and im.frequency == finest]


def with_coordinate_noise(result: DecodeResult, images: NDArray, spec: PatternSpec, projector_height: int | None = None) -> DecodeResult:
    """``result`` with ``u_noise_px`` (and ``image_noise_grey``) stated from the codec and the capture.

    Phase shifting: ``sigma_u = lambda / (2 pi) sqrt(2 / N) sigma_I / b`` per pixel
    (:func:`~frontend.fpp.phase_noise.projector_coordinate_sigma_px`, the finest frequency's
    pitch and modulation, as the unwrapped coordinate has that frequency's phase noise) with
    ``sigma_I`` measured on the finest frequency's N images over the valid pixels
    (:func:`~frontend.fpp.phase_noise.estimate_image_noise_grey`). Gray code alone: the
    stripe's quantisation ``W / (S sqrt 12)`` (``pitch_px`` is the stripe width; the rows of an ``axis="both"`` set
    ``H / S_rows`` with ``projector_height``), the same at
    every pixel. NaN where the pixel is invalid.
    """
    if spec.kind == "gray_code":
        sigma_u = np.full(result.mask.shape, result.pitch_px / math.sqrt(12.0), np.float32)
        image_noise = result.image_noise_grey
        if result.v_projector_px is not None and projector_height is not None:  # rows: their own stripe width
            row_stripe_px = projector_height / spec.periods[1]
            sigma_v = np.full(result.mask.shape, row_stripe_px / math.sqrt(12.0), np.float32)
            sigma_u[~result.mask] = np.nan
            sigma_v[~result.mask] = np.nan
            return dataclasses.replace(result, u_noise_px=sigma_u, v_noise_px=sigma_v, image_noise_grey=image_noise)
    else:
        image_noise = result.image_noise_grey
        if image_noise is None:
            image_noise = _measured_image_noise(np.asarray(images), result.mask, finest_phase_images(spec))
        sigma_u = projector_coordinate_sigma_px(result.modulation, spec.phase_steps, result.pitch_px, image_noise)
    sigma_u[~result.mask] = np.nan
    return dataclasses.replace(result, u_noise_px=sigma_u, image_noise_grey=image_noise)


NOISE_SAMPLE_PIXELS = 50_000
"""Valid pixels (about) whose sinusoid-fit residuals measure the image noise of N >= 4 steps: the
sample median of 5e4 chi-square variables with 1 degree of freedom (4 steps, the worst case) has
a standard error of 1 % of the median, 0.5 % in sigma; every k-th row of a 1920x1200 4-step
frame costs 0.02 s where all its residuals cost 0.12 s."""


def _measured_image_noise(images: NDArray, mask: NDArray, steps: list[int]) -> float:
    """:func:`~frontend.fpp.phase_noise.estimate_image_noise_grey` of the given phase-shift
    images, on every k-th row for N >= 4 (the residual is per pixel, so any rows will do; 3 steps
    need whole 3x3 neighbourhoods and their second differences are cheap)."""
    valid = int(np.count_nonzero(mask))
    row_step = max(1, -(-valid // NOISE_SAMPLE_PIXELS)) if len(steps) >= 4 else 1
    return estimate_image_noise_grey(images[steps, ::row_step], mask[::row_step])


EDGE_FALSE_DROP_PROBABILITY = 1e-3
"""Probability that noise alone makes the edge filter drop a pixel of a smooth surface, per test.

A thousandth of a cloud lost to noise is small against what the filter exists to remove: the
one-pixel rings around holes and depth jumps, 1.6 % of the triangulated pixels of SLMaster's real
12-step relief capture and 3.2 % of its 4-step heterodyne bust. The noise allowances of
:func:`edge_filter_mask` are this probability's quantiles."""


@functools.cache
def neighbourhood_range_quantile(false_drop_probability: float = EDGE_FALSE_DROP_PROBABILITY) -> float:
    """Upper ``1 - p`` quantile of the range (max - min) of 9 independent unit normal samples.

    The studentized range distribution with infinite degrees of freedom (the noise sigma is
    known): 5.90 at p = 1e-3. A 3x3 neighbourhood of a flat surface whose depths have noise
    sigma spans more than this many sigma with probability p. Neighbouring pixels' noise is
    positively correlated by the camera's blur, which only narrows the range: conservative.
    """
    from scipy import stats

    return float(stats.studentized_range.ppf(1.0 - false_drop_probability, 9, np.inf))


def gradient_noise_quantile(false_drop_probability: float = EDGE_FALSE_DROP_PROBABILITY) -> float:
    """Upper ``1 - p`` quantile of a Rayleigh variable, ``sqrt(-2 ln p)`` (3.72 at p = 1e-3): the
    length of the 2D noise vector of the two central depth differences, in units of its
    per-component sigma, is exceeded with probability p."""
    return math.sqrt(-2.0 * math.log(false_drop_probability))


_KERNEL_3x3 = np.ones((3, 3), np.uint8)


def edge_filter_mask(
    xyz_map: NDArray[np.float64],
    focal_px: float,
    max_angle_deg: float = 75.0,
    noise_floor_m: float = 0.0005,
    depth_sigma_m: NDArray | None = None,
) -> NDArray[np.bool_]:
    """Pixels of an organised point map that are not mixed pixels, silhouette or grazing surface.

    At a depth discontinuity (an object's silhouette in front of a farther surface, or the edge of
    a shadow) a camera pixel integrates light from both sides; its decoded phase, hence its point,
    lies somewhere between them, off every real surface. Such pixels are recognised locally:

    1. shadow/hole edges: a pixel any of whose 8 neighbours is invalid is dropped (the mask is
       eroded by one pixel where decoding failed);
    2. discontinuities: a surface seen at angle ``theta`` from the ray changes depth by about
       ``z tan(theta) / f`` per pixel, so over the 3x3 neighbourhood (diagonal 2 sqrt 2 px) its
       depth range stays below ``2 sqrt(2) z tan(max_angle) / f + allowance``; more is a jump.
       The noise allowance is ``max(noise_floor_m, q9 sigma_z)``, ``sigma_z`` the median
       expected depth noise of the 9 pixels (a mixed pixel's own is inflated: see below) and
       ``q9`` the :func:`neighbourhood_range_quantile` of 9 samples at
       :data:`EDGE_FALSE_DROP_PROBABILITY` (5.90);
    3. grazing angle: the normal from the neighbours' central differences makes more than
       ``max_angle_deg`` with the viewing ray (such points are also the least accurate ones).
       Each central difference spans 2 pixels, ``2 z / f`` across the ray, and its depth part
       carries noise of up to ``sqrt(2) sigma_z``, so the measured ``tan`` of the angle is off
       by ``|e| f / (2 z)`` with ``|e|`` the length of that 2D noise, at most the noise slope
       ``qR sqrt(2) sigma_z f / (2 z)`` with probability ``1 - p`` (``qR`` the
       :func:`gradient_noise_quantile`, 3.72). The accepted slope is ``tan(max_angle)`` and that
       noise slope added in quadrature, as independent tolerances are: where the depth noise
       exceeds the pixel's footprint nearly every angle passes (the test cannot tell them
       apart), while a quiet codec keeps the plain limit to within a few per cent (a grazing
       point is inaccurate beyond its noise: its footprint stretches along the slope and blur
       mixes the phases across it).
       (The footprint is the axial one; the obliquity of off-axis rays changes it by their
       ``1 + x_n^2``, under 15 % within 20 degrees of the axis.)

    Parameters
    ----------
    xyz_map : (H, W, 3)
        Points in the camera frame, metres, NaN where invalid.
    focal_px : float
        Camera focal length in pixels (sets the angular size of a pixel).
    depth_sigma_m : (H, W), optional
        Each pixel's expected depth noise, metres (:meth:`FppSensor.depth_sigma_m`); None: the
        noise floor alone, no noise allowance in the grazing test.

    Returns
    -------
    (H, W) bool
        True where the pixel is valid and kept.
    """
    xyz = np.asarray(xyz_map)
    h, w = xyz.shape[:2]
    if h < 3 or w < 3:
        return np.zeros((h, w), dtype=bool)
    if depth_sigma_m is not None and np.shape(depth_sigma_m) != (h, w):
        raise InputDataError(f"edge filter: the depth noise map is {np.shape(depth_sigma_m)} but the point map is {(h, w)}; pass one sigma per pixel")
    # every test is local to a 3x3 neighbourhood: only the box around the decoded pixels (and a
    # ring of one undecoded pixel, or the image border) is computed; a scanned object often
    # fills a fraction of the frame, and outside the box nothing is kept anyway
    rows, cols = finite_box(xyz)
    out = np.zeros((h, w), dtype=bool)
    if out[rows, cols].size == 0:  # no point at all: nothing to keep
        return out
    # in bands of rows: a band's ~15 float32 planes stay in the core's cache, where the whole
    # box's went out to memory (~45 % faster on 1920x1200 frames)
    if depth_sigma_m is None:
        in_row_bands(lambda band: _edge_filter_box(band, focal_px, max_angle_deg, noise_floor_m), xyz[rows, cols], out[rows, cols], EDGE_FILTER_BAND_ROWS)
    else:
        # the noise rides along as a fourth channel, so that the bands cut both maps alike
        packed = cv2.merge([np.ascontiguousarray(xyz[rows, cols], dtype=np.float32), np.asarray(depth_sigma_m, np.float32)[rows, cols]])
        in_row_bands(
            lambda band: _edge_filter_box(band[..., :3], focal_px, max_angle_deg, noise_floor_m, band[..., 3]),
            packed, out[rows, cols], EDGE_FILTER_BAND_ROWS,
        )
    return out


EDGE_FILTER_BAND_ROWS = 32
"""Rows per band of :func:`edge_filter_mask`: 32 rows of a 1920-pixel image are 0.25 MB per
float32 plane, so a band's planes fit a 4 MB L2 cache (16 rows was as fast, 64 and 128 10 % slower)."""


def _edge_filter_box(
    xyz_map: NDArray[np.float64], focal_px: float, max_angle_deg: float, noise_floor_m: float, depth_sigma_m: NDArray | None = None
) -> NDArray[np.bool_]:
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
    sigma_hood = None
    if depth_sigma_m is not None:
        # the neighbourhood's median noise, not its largest: a mixed pixel sums two fringe phases,
        # so its modulation drops and its predicted noise rises, and one or two of them must not
        # widen the allowance that is to find them (pixels next to holes go anyway)
        sigma = np.where(valid, np.asarray(depth_sigma_m, np.float32), np.float32(0.0))
        sigma_hood = cv2.medianBlur(np.nan_to_num(sigma, nan=0.0, posinf=0.0), 3)
    with np.errstate(invalid="ignore"):
        if sigma_hood is None:
            allowance = np.float32(noise_floor_m)
        else:
            allowance = np.maximum(np.float32(neighbourhood_range_quantile()) * sigma_hood, np.float32(noise_floor_m))
        bound = np.float32(2.0 * np.sqrt(2.0) / focal_px) * tan_max * z + allowance
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
        n2 *= _grazing_cos2(max_angle_deg, focal_px, rz, None if sigma_hood is None else sigma_hood[1:-1, 1:-1])
        n2 *= r2
        keep[1:-1, 1:-1] &= dot >= n2
    return keep


def _grazing_cos2(max_angle_deg: float, focal_px: float, z: NDArray[np.float32], sigma_hood: NDArray[np.float32] | None) -> NDArray[np.float32] | np.float32:
    """``cos^2`` of the largest accepted angle between normal and ray: the slope of
    ``max_angle_deg`` and the gradient's noise slope ``qR sqrt(2) sigma_z f / (2 z)`` added in
    quadrature (see :func:`edge_filter_mask`)."""
    tan_max = math.tan(math.radians(max_angle_deg))
    if sigma_hood is None:
        return np.float32(math.cos(math.radians(max_angle_deg)) ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        tan = sigma_hood * np.float32(gradient_noise_quantile() * math.sqrt(2.0) * focal_px / 2.0) / z
    tan *= tan
    tan += np.float32(tan_max * tan_max + 1.0)  # 1 + tan^2 = 1 / cos^2
    return np.reciprocal(tan, out=tan)
