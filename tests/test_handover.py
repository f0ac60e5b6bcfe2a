"""Handing a moment to highway-env's traffic (scene/handover.py)."""

import numpy as np
import pytest

from counterscene_env.geometry import overlaps_over_time
from counterscene_env.scene.handover import drive_on
from counterscene_env.scene.highway_traffic import make_env
from counterscene_env.scene.idm_constants import pristine_idm_constants


def _at(lane_index, s):
    with pristine_idm_constants():
        env = make_env("intersection")
        env.reset(seed=0)
        lane = env.road.network.get_lane(lane_index)
    return lane.position(s, 0.0), float(lane.heading_at(s))


def test_a_tie_at_the_crossing_is_settled_by_the_right_of_way():
    """Two cars that would reach the junction together: the one on the vertical road (lane
    priority 1) gives way to the one on the horizontal road (3), which keeps its speed; the
    two never overlap, and each follows its route at 10 Hz."""
    (minor, minor_yaw), (major, major_yaw) = (
        _at(("o0", "ir0", 0), 80.0),
        _at(("o1", "ir1", 0), 80.0),
    )
    speed = 8.0
    state, valid = drive_on(
        np.array([minor, major]),
        np.array([minor_yaw, major_yaw]),
        np.array([speed, speed]),
        np.array([speed, speed]),
        ["o2", "o3"],  # both straight on
        60,
    )
    assert state.shape == (2, 60, 4) and valid.all()
    # 10 Hz: the first step moves each car about speed * 0.1 s from where it started.
    np.testing.assert_allclose(
        np.linalg.norm(state[:, 0, :2] - np.array([minor, major]), axis=-1), 0.8, atol=0.1
    )
    assert state[0, :, 3].min() < 2.0  # the minor road's car stops for the other
    assert state[1, :, 3].min() > 6.0  # the horizontal road's car keeps going
    extents = np.array([[5.0, 2.0], [5.0, 2.0]])
    assert not overlaps_over_time(state[..., :2], state[..., 2], extents, valid).any()


def test_only_the_intersection_and_aligned_arrays_are_taken():
    one = (np.zeros((1, 2)), np.zeros(1), np.zeros(1), np.ones(1), [None])
    with pytest.raises(ValueError, match="scenario: only 'intersection'"):
        drive_on(*one, 5, scenario="merge")
    with pytest.raises(ValueError, match="must align"):
        drive_on(np.zeros((2, 2)), *one[1:], 5)
