"""Yielding: how far traffic may advance along its path before it meets another car."""

from __future__ import annotations

import math

import numpy as np
import pytest

from counterscene_env import geometry
from counterscene_env.sim import yielding


def straight_path(length: float = 40.0, step: float = 0.5):
    xs = np.arange(0.0, length + 1e-9, step)
    points = np.stack([xs, np.zeros_like(xs)], -1)
    return points, np.zeros(len(xs)), geometry.arc_length(points)


def free_distance_to(centre, velocity=(0.0, 0.0)):
    """free_distance along a straight eastbound path for a 4 m car facing one 4 m car."""
    points, yaws, arc = straight_path()
    car = np.array([[4.0, 2.0]])
    return yielding.free_distance(
        points, yaws, arc, car[0], np.array([centre]), np.zeros(1), car, np.array([velocity])
    )


def test_a_car_stopped_ahead_limits_the_free_distance_to_its_rear_minus_the_margin():
    # A 4 m car parked with its centre 20 m ahead: its rear is at 18 m; our box, grown forward
    # by MARGIN[0] = 1 m, reaches 3 m ahead of our centre, so we may go to 15 m (a station).
    d, v_lead = free_distance_to([20.0, 0.0])
    assert d == pytest.approx(15.0) and v_lead == 0.0
    # The same car in the next lane (4 m to the side) is no obstacle.
    assert free_distance_to([20.0, 4.0])[0] == math.inf


def test_the_lead_cars_speed_counts_along_our_heading_only():
    points, yaws, arc = straight_path()
    ext = np.array([[4.0, 2.0], [4.0, 2.0]])
    ahead = np.array([[20.0, 0.0], [30.0, 0.0]])
    _, v = yielding.free_distance(
        points, yaws, arc, ext[0], ahead, np.zeros(2), ext, np.array([[8.0, 0.0], [0.0, 0.0]])
    )
    assert v == pytest.approx(8.0)  # the nearer car, driving away at 8 m/s
    # A car crossing our path (velocity across it) gives no credit, and one coming towards us
    # gives none either.
    for velocity in ([0.0, 8.0], [-8.0, 0.0]):
        assert free_distance_to([20.0, 0.0], velocity)[1] == 0.0


def test_a_car_within_the_margin_ahead_stops_us_and_one_behind_does_not():
    for x, expected in ((4.5, 0.0), (-4.5, math.inf)):  # 0.5 m gap ahead, then behind
        assert free_distance_to([x, 0.0])[0] == expected


def test_a_car_already_overlapping_is_ignored_rather_than_freezing_us():
    assert free_distance_to([1.0, 0.5])[0] == math.inf


def test_allowed_advance_follows_the_safe_distance_rule():
    dt = 0.1
    # A clear path: the plan's step stands.
    assert yielding.allowed_advance(math.inf, 0.0, 10.0, 1.0, dt, lagging=False) == 1.0
    # 3 m free behind a stopped car: v = sqrt(2 * BRAKE * 3) = 6 m/s, so 0.6 m this step.
    assert yielding.allowed_advance(3.0, 0.0, 10.0, 1.0, dt, False) == pytest.approx(0.6)
    # Behind a car driving away at 10 m/s the same gap allows the plan's 1 m.
    assert yielding.allowed_advance(3.0, 10.0, 10.0, 1.0, dt, False) == pytest.approx(1.0)
    # Bumper to bumper (no free distance) behind a car at 5 m/s: only as far as it goes.
    assert yielding.allowed_advance(0.0, 5.0, 10.0, 1.0, dt, False) == pytest.approx(0.5)
    # Never backwards.
    assert yielding.allowed_advance(0.0, 0.0, 10.0, 1.0, dt, False) == 0.0
    # Held back to a stop, it regains speed by at most ACCEL: 0.4 m/s after one step.
    step = yielding.allowed_advance(math.inf, 0.0, 0.0, 1.0, dt, lagging=True)
    assert step == pytest.approx(yielding.ACCEL * dt * dt)


def test_point_at_interpolates_position_and_yaw_and_survives_a_standstill():
    points = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    yaws = np.array([0.0, 0.0, 0.0, np.pi / 2])
    arc = geometry.arc_length(points)
    np.testing.assert_allclose(arc, [0, 0, 10, 20])
    xy, yaw = yielding.point_at(points, yaws, arc, 5.0)
    np.testing.assert_allclose(xy, [5.0, 0.0])
    assert yaw == pytest.approx(0.0)
    xy, yaw = yielding.point_at(points, yaws, arc, 15.0)
    np.testing.assert_allclose(xy, [10.0, 5.0])
    assert yaw == pytest.approx(np.pi / 4)
    xy, _ = yielding.point_at(points, yaws, arc, 0.0)
    np.testing.assert_allclose(xy, [0.0, 0.0])


def test_moves_into_catches_a_turn_on_the_spot_but_not_an_old_overlap():
    ext = np.array([4.0, 2.0])
    other = (np.array([[0.0, 2.6]]), np.zeros(1), np.array([[4.0, 2.0]]))  # 0.6 m beside us
    here = (np.zeros(2), 0.0)
    turned = (np.zeros(2), np.pi / 4)  # same centre, rotated: a corner sweeps into it
    assert yielding.moves_into(turned, here, ext, *other)
    assert not yielding.moves_into(here, here, ext, *other)
    # Already overlapping before the step: not this step's doing.
    inside = (np.array([[0.0, 1.0]]), np.zeros(1), np.array([[4.0, 2.0]]))
    assert not yielding.moves_into(turned, here, ext, *inside)
