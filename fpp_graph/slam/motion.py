"""Constant-velocity prediction of the next frame's pose relative to the last keyframe.

The keyframe manager records each processed frame's pose relative to the keyframe it was
registered to (a keyframe: relative to its odometry target). The prediction needs no world
poses, so loop corrections of the running estimate never disturb it: the motion between the
last two frames is found in a frame they share, scaled by the ratio of the time steps (a
dropped frame doubles the step) and applied to the last frame's pose in the current keyframe.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from fpp_graph.geometry import adjoint, invert, se3_exp, se3_log
from fpp_graph.types import Constraint, Frame, FrameTracker, PairRegistrar

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

MAX_STEP_RATIO = 3.0
"""Longest gap (in units of the last step) a velocity is extrapolated over: beyond it the
camera's acceleration dominates, and the last frame's pose (zero velocity) predicts as well."""


@dataclass(frozen=True)
class _Record:
    frame_id: int
    timestamp: float
    reference_id: int | None  # the keyframe the pose is relative to (None: a segment's first keyframe)
    T_reference_frame: Array


class ConstantVelocityPredictor:
    """Predicts ``T_keyframe_frame`` of the next frame from the last two (see module doc)."""

    def __init__(self) -> None:
        self._recent: deque[_Record] = deque(maxlen=2)

    def reset(self) -> None:
        """Forget the motion (a chain break: the next segment's poses are unrelated)."""
        self._recent.clear()

    def observe(self, frame_id: int, timestamp: float, reference_id: int | None, T_reference_frame: NDArray) -> None:
        """Record a processed frame's pose relative to keyframe ``reference_id``."""
        self._recent.append(_Record(frame_id, float(timestamp), reference_id, np.asarray(T_reference_frame, dtype=np.float64)))

    def predict(self, keyframe_id: int, timestamp: float) -> Array | None:
        """``T_keyframe_frame`` of a frame at ``timestamp``, or None when the last frame's pose
        relative to ``keyframe_id`` is unknown."""
        if not self._recent:
            return None
        last = self._recent[-1]
        if last.frame_id == keyframe_id:
            T_keyframe_last = np.eye(4)
        elif last.reference_id == keyframe_id:
            T_keyframe_last = last.T_reference_frame
        else:
            return None
        return T_keyframe_last @ self._step(timestamp)

    def _step(self, timestamp: float) -> Array:
        """The motion from the last frame to one at ``timestamp`` (identity when unknown)."""
        last_step = self._last_step()
        if last_step is None:
            return np.eye(4)
        T_before_last, dt_last = last_step
        dt_next = float(timestamp) - self._recent[-1].timestamp
        ratio = dt_next / dt_last if dt_last > 0 and math.isfinite(dt_next) else 1.0
        if not 0.0 <= ratio <= MAX_STEP_RATIO:
            return np.eye(4)
        return se3_exp(ratio * se3_log(T_before_last))

    def twist_per_s(self) -> Array | None:
        """The camera's twist ``[omega (rad/s), v (m/s)]`` over the last step (the last frame's
        body frame), or None when the last two frames' relative pose or time step is unknown."""
        last_step = self._last_step()
        if last_step is None or not last_step[1] > 0:
            return None
        T_before_last, dt_s = last_step
        return se3_log(T_before_last) / dt_s

    def _last_step(self) -> tuple[Array, float] | None:
        """``(T_before_last, dt_s)`` of the last two frames, or None when not known in a shared frame."""
        if len(self._recent) < 2:
            return None
        before, last = self._recent
        if last.reference_id is not None and last.reference_id == before.reference_id:
            T_before_last = invert(before.T_reference_frame) @ last.T_reference_frame
        elif last.reference_id is not None and last.reference_id == before.frame_id:
            T_before_last = last.T_reference_frame
        else:
            return None
        return T_before_last, last.timestamp - before.timestamp


def readout_motion(frame: Frame, twist_per_s: Array | None) -> Array | None:
    """The twist ``[rot, trans]`` the camera moves through while ``frame``'s rows are read out:
    ``twist_per_s`` times its camera's :attr:`~fpp_graph.types.CameraModel.readout_s` (a rolling
    shutter's readout time, checked when the camera model is made; 0 or no camera model: a global
    shutter or a still capture). None when either is unknown or zero."""
    readout_s = frame.camera.readout_s if frame.camera is not None else 0.0
    if twist_per_s is None or readout_s == 0 or not np.all(np.isfinite(twist_per_s)):
        return None
    return readout_s * np.asarray(twist_per_s, dtype=np.float64)


def with_readout_motion(constraint: Constraint, motion_source: Array | None, motion_target: Array | None) -> Constraint:
    """``constraint`` with its frames' motion during their rolling-shutter readout added to its covariance.

    A rolling shutter exposes a view's rows one after another over its readout time ``t_r``; a
    camera moving with twist ``xi`` meanwhile captures each row from a pose ``xi tau`` off the
    frame's, ``tau`` across ``[-t_r / 2, t_r / 2]``. A rigid pose fitted to such a view sits at the
    motion of whichever rows hold the structure that constrains it, which no pair knows in
    advance: the frame's pose is modelled as off by ``Exp(u s)`` with ``u = xi t_r``
    (:func:`readout_motion`) and ``s`` uniform over ``[-1/2, 1/2]``, a rank-one covariance
    ``u u^T / 12``. The source frame's term perturbs ``T_target_source`` on the right, the
    target's through ``Ad(T^-1)``; each is a rank-one update of the information
    (``I - I u u^T I c / (1 + c u^T I u)``, ``c = 1/12``, defined for a singular ``I`` too).
    Frames that do not move (``None``) add nothing; the constraint is returned as it is then.
    """
    motions = [] if motion_source is None else [np.asarray(motion_source, dtype=np.float64)]
    if motion_target is not None:
        motions.append(adjoint(invert(constraint.T_target_source)) @ np.asarray(motion_target, dtype=np.float64))
    if not motions or not constraint.accepted:
        return constraint
    information = np.asarray(constraint.information, dtype=np.float64)
    for u in motions:
        Iu = information @ u
        information = information - np.outer(Iu, Iu) * (UNIFORM_VARIANCE / (1.0 + UNIFORM_VARIANCE * float(u @ Iu)))
    return replace(constraint, information=0.5 * (information + information.T))


UNIFORM_VARIANCE = 1.0 / 12.0
"""Variance of a uniform distribution over an interval of length 1."""


class MotionTracking:
    """``keyframes.track_from_motion`` for the keyframe manager: the prediction, the registrar's
    ``track`` (when it is a :class:`~fpp_graph.types.FrameTracker`) and the count of what it did.

    Off (or with a registrar without ``track``), :meth:`predict` gives None and :meth:`track`
    never runs: the manager registers every frame in full, without a motion prior (an FPP
    capture's next view is placed by hand, not by a velocity).
    """

    def __init__(self, registrar: PairRegistrar, enabled: bool) -> None:
        self.tracker: FrameTracker | None = registrar if enabled and isinstance(registrar, FrameTracker) else None
        if enabled and self.tracker is None:
            log.warning("keyframes.track_from_motion is on but %s has no track(): every frame is registered in full", type(registrar).__name__)
        self.predictor = ConstantVelocityPredictor()
        self.tracked_frames = 0
        self.fallbacks: dict[str, int] = {}  # why track() handed frames to the full registration

    def predict(self, keyframe_id: int, timestamp: float) -> Array | None:
        """``T_keyframe_frame`` of the next frame; None when tracking is off or the motion unknown."""
        return self.predictor.predict(keyframe_id, timestamp) if self.tracker is not None else None

    def track(self, keyframe: Frame, frame: Frame, T_predicted: Array | None, last_try: bool = True) -> Constraint | None:
        """The frame's pose in ``keyframe`` by ``track()``; None (the reason counted) when tracking
        is off, there is no prediction, or ``track()`` hands the frame on. ``last_try`` False: the
        caller tracks the frame once more if this fails, which counts it then (each frame is
        counted once, tracked or handed on)."""
        if self.tracker is None or T_predicted is None:
            return None
        constraint = self.tracker.track(keyframe, frame, T_predicted)
        if constraint.accepted:
            self.tracked_frames += 1
            return constraint
        if not last_try:
            log.debug("frame %d: %s against keyframe %d; tracked again", frame.id, constraint.rejection_reason, keyframe.id)
            return None
        # the reason without its figures, so the counts group ("tracking: low overlap (0.05 < 0.1)")
        reason = (constraint.rejection_reason or "rejected").split(" (")[0]
        self.fallbacks[reason] = self.fallbacks.get(reason, 0) + 1
        log.debug("frame %d: %s; registered in full", frame.id, constraint.rejection_reason)
        return None

    def summary(self) -> dict:
        """``{"tracked_frames": n, "fallbacks": {reason: count}}``, or {} with tracking off."""
        return {"tracked_frames": self.tracked_frames, "fallbacks": dict(self.fallbacks)} if self.tracker is not None else {}


__all__ = ["MAX_STEP_RATIO", "ConstantVelocityPredictor", "MotionTracking", "readout_motion", "with_readout_motion"]
