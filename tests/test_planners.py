"""Reference ego planners: highway-env's IDM lane follower, constant velocity, log replay."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene

from counterscene_env.planners import (
    ConstantVelocityPlanner,
    IDMPlanner,
    LogReplayPlanner,
    make_planner,
)
from counterscene_env.sim import WorldState


def lane_scene(lead_gap: float | None, lead_speed: float = 0.0, ego_y: float = 0.0, T: int = 40):
    """Ego at x = 50 on lane y = 0 at 10 m/s (history 3 s at 10 m/s); optionally a car
    ``lead_gap`` m ahead in the same lane."""
    t = np.arange(T) * 0.1
    ego = np.stack([20 + 10 * t, np.full(T, ego_y)], -1)
    rows, speeds = [ego], [np.full(T, 10.0)]
    if lead_gap is not None:
        rows.append(np.stack([50 + lead_gap + lead_speed * (t - 3.0), np.zeros(T)], -1))
        speeds.append(np.full(T, lead_speed))
    return make_scene(np.stack(rows), speeds=np.stack(speeds), current_index=30)


def state_of(scene, t=None) -> WorldState:
    t = scene.current_index if t is None else t
    return WorldState(
        t=t,
        positions=scene.positions[:, t],
        yaws=scene.yaws[:, t],
        speeds=scene.speeds[:, t],
        valid=scene.valid[:, t],
        extents=scene.extents,
        ego_index=scene.ego_index,
        scene=scene,
    )


def test_idm_brakes_for_a_stopped_car_ahead_and_not_on_a_free_road():
    brake = IDMPlanner()
    scene = lane_scene(lead_gap=12.0)
    brake.reset(scene, 0)
    acc, steer = brake.act(state_of(scene))
    assert acc < -3.0  # 12 m from a stopped car at 10 m/s: hard braking
    assert abs(steer) < 1e-3  # on the lane centre, heading along it

    free = IDMPlanner(target_speed=15.0)
    scene = lane_scene(lead_gap=None)
    free.reset(scene, 0)
    acc, _ = free.act(state_of(scene))
    assert acc > 0.5  # below its target speed, nobody ahead


def test_idm_steers_back_to_its_lane():
    planner = IDMPlanner()
    scene = lane_scene(lead_gap=None, ego_y=1.0)  # 1 m left of the lane centre
    planner.reset(scene, 0)
    _, steer = planner.act(state_of(scene))
    assert steer < -0.01  # to the right (clockwise)


def test_idm_never_asks_a_stopped_ego_to_reverse():
    planner = IDMPlanner()
    scene = lane_scene(lead_gap=4.0)
    planner.reset(scene, 0)
    state = state_of(scene)
    speeds = state.speeds.copy()
    speeds[0] = 0.2
    acc, _ = planner.act(
        WorldState(
            state.t, state.positions, state.yaws, speeds, state.valid, state.extents, 0, scene
        )
    )
    assert acc >= -0.2 / 0.1 - 1e-9


def test_constant_velocity_and_log_replay():
    scene = lane_scene(lead_gap=30.0, lead_speed=8.0)
    cv = ConstantVelocityPlanner()
    cv.reset(scene, 0)
    assert cv.act(state_of(scene)).tolist() == [0.0, 0.0]
    log = LogReplayPlanner()
    log.reset(scene, 0)
    assert log.replays_log and not cv.replays_log
    nxt = log.next_state(state_of(scene))
    assert nxt.tolist() == [*scene.positions[0, 31], 0.0, 10.0]


def test_make_planner_names_and_aliases():
    assert isinstance(make_planner("idm"), IDMPlanner)
    assert isinstance(make_planner("cv"), ConstantVelocityPlanner)
    assert isinstance(make_planner("replay"), LogReplayPlanner)
    with pytest.raises(ValueError, match=r"unknown planner 'mpc'.*idm"):
        make_planner("mpc")


def test_idm_yield_gives_way_to_a_crossing_car_plain_idm_does_not():
    # Ego at x = 50 east at 10 m/s; a car 5 m south of the lane at x = 60 drives north at
    # 5 m/s: both reach (60, 0) in about 1 s. The ego is farther from the crossing, so
    # highway-env's priority rule makes it give way.
    T = 40
    t = np.arange(T) * 0.1
    ego = np.stack([20 + 10 * t, np.zeros(T)], -1)
    cross = np.stack([np.full(T, 60.0), -5 + 5 * (t - 3.0)], -1)
    scene = make_scene(
        np.stack([ego, cross]),
        yaws=np.stack([np.zeros(T), np.full(T, np.pi / 2)]),
        speeds=np.stack([np.full(T, 10.0), np.full(T, 5.0)]),
        current_index=30,
    )
    plain, polite = make_planner("idm"), make_planner("idm_yield")
    for p in (plain, polite):
        p.reset(scene, 0)
    assert plain.act(state_of(scene))[0] > -1.0  # nothing in its lane
    assert polite.act(state_of(scene))[0] < -3.0  # yields
    free, eager = lane_scene(lead_gap=None), IDMPlanner(target_speed=15.0, yield_to_traffic=True)
    eager.reset(free, 0)
    assert eager.act(state_of(free))[0] > 0.5  # nothing to yield to


def test_idm_reset_searches_lanes_for_itself_only_whatever_the_traffic(monkeypatch):
    """A lane follower reads the other agents' positions only: building them must not search
    the map's lanes for each (on real maps, hundreds of lanes per search, N agents per
    follower), and it still brakes for them."""
    from highway_env.road.road import RoadNetwork

    calls = []
    search = RoadNetwork.get_closest_lane_index
    monkeypatch.setattr(
        RoadNetwork,
        "get_closest_lane_index",
        lambda self, *a, **k: calls.append(1) or search(self, *a, **k),
    )
    base = lane_scene(lead_gap=12.0)
    far = np.stack([np.stack([np.full(40, 500.0 + 10 * i), np.zeros(40)], -1) for i in range(20)])
    scene = make_scene(
        np.concatenate([base.positions, far]),
        speeds=np.concatenate([base.speeds, np.zeros((20, 40))]),
        current_index=30,
    )
    planner = IDMPlanner()
    planner.reset(scene, 0)
    assert len(calls) <= 2  # the ego's vehicle and its route's goal, not the 21 others
    acc, _ = planner.act(state_of(scene))
    assert acc < -3.0  # the stopped car 12 m ahead is still seen
