"""The FPP sensor as the back-end sees it: one frame's pattern images -> a :class:`fpp_graph.types.Frame`.

decode (phase retrieval + unwrapping, :mod:`frontend.phase`) -> triangulate
(:mod:`frontend.triangulation`) -> Frame. Real recordings and simulated ones take exactly this
path. The decoder tables and the per-pixel triangulation constants are built once per sensor.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import DecodeConfig
from fpp_graph.errors import InputDataError
from fpp_graph.types import Frame
from frontend.patterns import PatternSpec
from frontend.phase import Decoder, DecodeResult
from frontend.rig import RigCalibration
from frontend.triangulation import Triangulator

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
    """

    def __init__(
        self,
        calibration: RigCalibration,
        spec: PatternSpec,
        decode_config: DecodeConfig | None = None,
        depth_range_m: tuple[float, float] = (0.05, 10.0),
    ) -> None:
        self.calibration = calibration
        self.spec = spec
        proj = calibration.projector
        self.decoder = Decoder(spec, proj.width, proj.height, decode_config)
        self.triangulator = Triangulator(calibration, axis=spec.axis, depth_range_m=depth_range_m)

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
            invalid, ``texture`` (H, W) uint8; metadata holds the valid fraction and the
            decoder's invalid-pixel counts.
        """
        where = f"frame {frame_id}"
        result = self.decode(images, where)
        xyz = self.triangulator.triangulate(result.u_projector_px, result.mask)
        valid = np.isfinite(xyz[..., 2])
        points = xyz[valid]
        grey = result.texture[valid].astype(np.float64) / 255.0
        log.debug("%s: %d valid points (%.1f%%)", where, points.shape[0], 100.0 * points.shape[0] / valid.size)
        return Frame(
            id=int(frame_id),
            timestamp=float(timestamp),
            points=points,
            colors=np.repeat(grey[:, None], 3, axis=1),
            xyz_map=xyz,
            texture=result.texture,
            T_world_sensor_guess=T_world_sensor_guess,
            metadata={"valid_fraction": float(np.count_nonzero(valid)) / valid.size, "invalid_counts": dict(result.invalid_counts)},
        )
