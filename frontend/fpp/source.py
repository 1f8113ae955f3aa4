"""The FPP sequence as a :class:`fpp_graph.slam.sources.FrameSource` (registered as ``fpp``).

Reads a recorded sequence folder (``sequence.yaml`` + per-frame PNG stacks, the format the
simulator writes and a real sensor's recordings must fit), decodes each frame through
:class:`frontend.fpp.sensor.FppSensor` and computes its 2D keypoints once, so registration of
every pair reuses them.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from fpp_graph.config import Config, refuse_reference_time_offset
from fpp_graph.trajectory import Trajectory
from fpp_graph.types import CameraModel, Frame
from frontend.config import FPP_NOISE
from frontend.fpp.rig import RigCalibration
from frontend.fpp.sequence import SEQUENCE_FILE, read_sequence

log = logging.getLogger(__name__)

# The fusion voxels of a close-range rig where the configuration leaves them null: the point map's
# a few camera pixel footprints at half a metre, the TSDF's the registration's ICP voxel.
FPP_FUSION_VOXELS_M = {"voxel_size_m": 0.001, "tsdf_voxel_m": 0.002}


class FppSequenceSource:
    """Frames of a recorded FPP sequence, decoded lazily (pickles: heavy state is rebuilt per process)."""

    name = "fpp"

    def __init__(self, path: Path, config: Config) -> None:
        self.path = Path(path)
        self.config = self.resolve_config(config)
        refuse_reference_time_offset(self.config, f"the FPP sequence {self.path}")
        self.sequence = read_sequence(self.path)
        # a calibration of another camera fails every frame: refused here, in one line, rather
        # than every frame skipped one by one
        self.sequence.check_frames_match_calibration()
        self._index = {rec.id: i for i, rec in enumerate(self.sequence.frames)}
        self._sensor = None
        self._preparer = None

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_sensor"] = None  # decoder tables are rebuilt in each worker process
        state["_preparer"] = None
        return state

    @classmethod
    def detect(cls, path: Path) -> bool:
        # exists, not is_file: a sequence.yaml that is a folder, or that cannot be looked at, is
        # still this layout, and reading it says what is wrong with it
        try:
            return (Path(path) / SEQUENCE_FILE).exists()
        except PermissionError:
            return True

    @property
    def sensor(self):
        if self._sensor is None:
            from frontend.fpp.ray_cache import cached_camera_rays
            from frontend.fpp.sensor import FppSensor
            from frontend.fpp.triangulation import pixel_rays

            # the rays and the projector's inverse distortion are the costly part of the sensor's
            # start (1.3 + 1.0 s a worker at 1920x1200, while the tracking process waits for the
            # first frame) and depend on the calibration alone: made once per camera / rig, shared
            # by the run's workers and later runs
            calibration = self.sequence.calibration
            rays = cached_camera_rays(calibration.camera, pixel_rays)
            self._sensor = FppSensor(calibration, self.sequence.spec, self.config.decode, camera_rays=rays, cache_projector_fit=True)
        return self._sensor

    def frame_ids(self) -> list[int]:
        return [rec.id for rec in self.sequence.frames]

    def load_frame(self, frame_id: int) -> Frame:
        from frontend.features.detect import detect_and_describe

        i = self._index[frame_id]
        rec = self.sequence.frames[i]
        images = self.sequence.load_frame_images(i)
        frame = self.sensor.frame_from_images(rec.id, rec.timestamp, images)
        camera = self.sequence.calibration.camera
        frame = Frame(
            id=frame.id, timestamp=frame.timestamp, points=frame.points, colors=frame.colors,
            xyz_map=frame.xyz_map, texture=frame.texture,
            camera=CameraModel(camera.K, camera.width, camera.height),  # a still capture: no readout motion
            metadata={**frame.metadata, **camera_metadata(self.sequence.calibration)},
        )
        # the registrar's per-frame work that every pair of this frame needs, done here once
        # (on a decode worker) and stored with the frame
        if self._preparer is None:
            self._preparer = self.make_registrar()
        return self._preparer.prepare(detect_and_describe(frame, self.config.registration))

    def resolve_config(self, config: Config) -> Config:
        """``config`` with the rig's noise model (:data:`frontend.config.FPP_NOISE`) where
        ``registration.noise`` is left null, and the fusion voxels of :data:`FPP_FUSION_VOXELS_M`
        where ``fusion`` leaves them null (idempotent; a value the user set is kept)."""
        fusion = config.fusion
        fusion = fusion.model_copy(update={k: v for k, v in FPP_FUSION_VOXELS_M.items() if getattr(fusion, k) is None})
        return config.model_copy(update={"registration": config.registration.with_noise(FPP_NOISE), "fusion": fusion})

    def make_registrar(self):
        from frontend.registration import TextureCamera, TexturedSurfaceRegistrar

        # the rig's camera and projector: plane-like pairs (walls) get their in-plane directions from the texture
        return TexturedSurfaceRegistrar(self.config.registration, seed=self.config.run.seed, texture_camera=TextureCamera.from_rig(self.sequence.calibration))

    def ground_truth(self) -> Trajectory | None:
        return self.sequence.ground_truth

    def ground_truth_mesh(self) -> Path | None:
        return self.sequence.ground_truth_mesh_path

    def describe(self) -> dict[str, Any]:
        cam = self.sequence.calibration.camera
        scene_config = (self.sequence.source or {}).get("config") or {}
        turntable = scene_config.get("turntable") or {}
        out: dict[str, Any] = {
            "sensor": "fpp",
            "frames": len(self.sequence.frames),
            "image_size": [cam.width, cam.height],
            "patterns": self.sequence.spec.to_dict(),
        }
        if scene_config.get("scene") == "turntable" or turntable:
            out["views_per_turn"] = int(turntable.get("views_per_turn", 13))
        return out


def camera_metadata(calibration: RigCalibration) -> dict[str, Any]:
    """What locating a camera image in the map needs of the rig, kept with every decoded frame:
    the camera's ``K`` and OpenCV ``dist`` (pixels) and the projector centre in the camera frame
    (metres; it lights the texture)."""
    T = calibration.T_projector_camera
    return {
        "K": calibration.camera.K.tolist(),
        "dist": calibration.camera.dist.tolist(),
        "projector_centre_m": (-T[:3, :3].T @ T[:3, 3]).tolist(),
    }
