"""Giving way by gap acceptance in recorded intersection traffic (``scene/gap_acceptance.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from counterscene_env.geometry import overlaps_over_time
from counterscene_env.scene.gap_acceptance import GapAcceptingVehicle, clearance
from counterscene_env.scene.highway import GeneratorConfig, generate, record
from counterscene_env.scene.idm_constants import pristine_idm_constants


def _crossing(minor_start: float, major_start: float, seconds: float = 12.0):
    """A car on the minor road (south, priority 1) and one on the major road (west, priority
    3), both going straight at 9 m/s towards the centre, simulated at 20 Hz on highway-env's
    intersection with the gap-acceptance road. Returns both cars' positions ``[T, 2, 2]`` m
    and speeds ``[T, 2]`` m/s."""
    from counterscene_env.scene.highway_traffic import make_env

    with pristine_idm_constants():
        env = make_env("intersection", "gap-acceptance")
        env.reset(seed=0)
        road = env.road
        road.vehicles.clear()
        cars = []
        for lane, start, goal in (("0", minor_start, "o2"), ("3", major_start, "o1")):
            car = GapAcceptingVehicle.make_on_lane(road, (f"o{lane}", f"ir{lane}", 0), start, 9.0)
            car.plan_route_to(goal)
            road.vehicles.append(car)
            cars.append(car)
        positions, speeds = [], []
        for _ in range(round(seconds * 20)):
            road.act()
            road.step(0.05)
            positions.append([c.position.copy() for c in cars])
            speeds.append([c.speed for c in cars])
    return np.array(positions), np.array(speeds), cars


def test_the_car_without_priority_stops_smoothly_before_the_crossing_and_then_goes():
    # Both would reach the centre together; the minor-road car gives way.
    positions, speeds, (minor, major) = _crossing(minor_start=60.0, major_start=60.0)
    gap = np.linalg.norm(positions[:, 0] - positions[:, 1], axis=-1)
    assert gap.min() > clearance(minor, major), "no collision, with room to spare"
    decel = -np.diff(speeds, axis=0) / 0.05
    assert decel[:, 1].max() < 0.5, "the car with the right of way does not brake"
    assert speeds[:, 0].min() < 5.0, "the other slows down for it"
    centre_time = np.linalg.norm(positions, axis=-1).argmin(axis=0)  # [2] steps
    assert centre_time[1] < centre_time[0], "and lets it through the centre first"
    assert decel[:, 0].max() < 4.0, "smoothly: highway-env's rule brakes at its 6 m/s^2 limit"
    assert speeds[-1, 0] > 5.0, "and goes once the crossing is clear"


def test_a_car_far_enough_ahead_keeps_going():
    # The major-road car is 6 s away when the minor one crosses: the gap is accepted.
    _, speeds, _ = _crossing(minor_start=70.0, major_start=20.0, seconds=6.0)
    assert speeds[:, 0].min() > 8.0


def test_a_gap_acceptance_recording_is_a_reproducible_safe_log():
    cfg = GeneratorConfig(yielding="gap-acceptance")
    scene = generate("intersection", seed=5, config=cfg)
    again = record("intersection", scene.metadata["seed"], cfg)
    np.testing.assert_array_equal(scene.positions, again.positions)
    assert not overlaps_over_time(scene.positions, scene.yaws, scene.extents, scene.valid).any()
    assert scene.metadata["yielding"] == "gap-acceptance"
    stock = record("intersection", scene.metadata["seed"])  # safe under both rules
    assert stock.metadata["yielding"] == "highway-env"
    assert stock.positions.shape != scene.positions.shape or not np.array_equal(
        stock.positions, scene.positions
    ), "the rule changes the traffic"


def test_the_rule_is_refused_where_no_traffic_crosses_and_a_bad_name_is_named():
    with pytest.raises(ValueError, match="intersection only"):
        record("merge", 0, GeneratorConfig(yielding="gap-acceptance"))
    with pytest.raises(ValueError, match="yielding"):
        GeneratorConfig(yielding="polite")
