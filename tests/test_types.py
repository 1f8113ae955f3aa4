from __future__ import annotations

import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.types import Constraint, ConstraintKind, Frame


def test_frame_validates_shapes_and_is_read_only():
    pts = np.zeros((5, 3))
    frame = Frame(id=0, timestamp=0.0, points=pts)
    assert frame.num_points == 5
    with pytest.raises(ValueError):
        frame.points[0, 0] = 1.0
    with pytest.raises(InputDataError, match="N x 3"):
        Frame(id=1, timestamp=0.0, points=np.zeros((5, 2)))
    with pytest.raises(InputDataError, match="texture shape"):
        Frame(id=2, timestamp=0.0, points=pts, xyz_map=np.zeros((4, 6, 3)), texture=np.zeros((5, 6), np.uint8))
    with pytest.raises(InputDataError, match="uint8"):
        Frame(id=3, timestamp=0.0, points=pts, texture=np.zeros((5, 6), np.float32))
    with pytest.raises(InputDataError, match="keypoints"):
        Frame(id=4, timestamp=0.0, points=pts, keypoints_uv=np.zeros((3, 2)), descriptors=np.zeros((2, 64)))
    with pytest.raises(InputDataError, match="rigid"):
        Frame(id=5, timestamp=0.0, points=pts, T_world_sensor_guess=2 * np.eye(4))


def test_constraint_validation_and_rejection():
    c = Constraint(source_id=1, target_id=0, T_target_source=np.eye(4), information=np.eye(6), kind="loop")
    assert c.accepted and c.kind is ConstraintKind.LOOP
    with pytest.raises(InputDataError, match="positive definite"):
        Constraint(source_id=1, target_id=0, T_target_source=np.eye(4), information=np.diag([1, 1, 1, 1, 1, 0.0]))
    with pytest.raises(InputDataError, match="symmetric"):
        info = np.eye(6)
        info[0, 1] = 0.5
        Constraint(source_id=1, target_id=0, T_target_source=np.eye(4), information=info)
    rejected = Constraint.rejected(3, 2, "too few inliers (4 < 15)", inlier_count=4)
    assert not rejected.accepted and "too few" in rejected.rejection_reason and rejected.inlier_count == 4
