"""Source 1: highway-env traffic recorded as factual scenes."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from counterscene_env.geometry import overlaps_over_time
from counterscene_env.scene import SCENARIOS, generate
from counterscene_env.scene.highway import GeneratorConfig, RejectedScene, record


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_generated_scene_is_a_safe_13s_log(generated, scenario):
    scene = generated[scenario]
    assert scene.dt == 0.1
    assert scene.num_steps == 131 and scene.duration == pytest.approx(13.0)
    assert scene.current_index == 30  # 3 s of history, 10 s of future
    assert scene.num_agents >= 5
    assert scene.valid[scene.ego_index].all(), "the ego is present throughout"
    assert not overlaps_over_time(scene.positions, scene.yaws, scene.extents, scene.valid).any()
    assert (scene.speeds[scene.valid] >= 0).all(), "traffic never reverses"
    pts = scene.positions[scene.valid]
    on_road = shapely.intersects_xy(scene.road.drivable_area, pts[:, 0], pts[:, 1])
    assert on_road.mean() > 0.99
    assert scene.metadata["scenario"] == scenario


def test_same_seed_same_scene_whatever_ran_before(generated):
    # IntersectionEnv overwrites IDM class constants process-wide; generating an intersection
    # first must not change a later highway scene.
    again = generate("highway", seed=1)
    generate("intersection", seed=3)
    after = generate("highway", seed=1)
    first = generated["highway"]
    for scene in (again, after):
        np.testing.assert_array_equal(scene.positions, first.positions)
        np.testing.assert_array_equal(scene.valid, first.valid)
        assert scene.ego_index == first.ego_index
    assert not np.array_equal(generate("highway", seed=2).positions[:, :5], first.positions[:, :5])


def test_vehicles_appear_and_leave_with_validity(generated):
    scene = generated["intersection"]
    starts_late = ~scene.valid[:, 0] & scene.valid.any(axis=1)
    assert starts_late.any(), "the intersection spawns vehicles during the log"
    for i in np.flatnonzero(starts_late):
        first = np.argmax(scene.valid[i])
        assert not scene.valid[i, :first].any()


def test_a_seed_that_is_not_a_natural_number_is_refused_by_name():
    from counterscene_env.scene.highway import generate

    with pytest.raises(TypeError, match="seed must be an int"):
        generate("merge", 1.5)  # it recorded seed 1 and named the scene "merge/seed=1.5"
    with pytest.raises(ValueError, match="seed must be >= 0"):
        generate("merge", -1)


def test_unsafe_seed_is_rejected_and_the_next_seed_used():
    # Intersection seed 0 has two cars overlapping (highway-env's own IDM crash).
    with pytest.raises(RejectedScene, match="overlap"):
        record("intersection", 0)
    scene = generate("intersection", seed=0)
    assert scene.metadata["seed"] == 1 and scene.metadata["rejected_seeds"] == [0]


def test_a_doomed_recording_stops_at_its_first_overlap_and_keeps_the_same_scenes(monkeypatch):
    """Seed 0 of the intersection crashes about 8 s in: the recording stops there instead of
    simulating the whole 13 s, and the scenes kept (with the check or without it) are equal."""
    import counterscene_env.scene.highway as highway
    import counterscene_env.scene.highway_traffic as highway_traffic

    frames = []
    step = highway_traffic.Traffic.step
    monkeypatch.setattr(
        highway_traffic.Traffic, "step", lambda self, dt: frames.append(dt) or step(self, dt)
    )
    with pytest.raises(RejectedScene, match="overlap at step"):
        record("intersection", 0)
    full = (13.0 + highway.WARMUP["intersection"]) * GeneratorConfig().sim_frequency
    assert 0 < len(frames) < full  # the whole log: exactly `full` frames
    early = generate("intersection", seed=0)
    monkeypatch.setattr(highway, "_reject_early", lambda *args: None)
    late = generate("intersection", seed=0)
    assert early.metadata["rejected_seeds"] == late.metadata["rejected_seeds"] == [0]
    np.testing.assert_array_equal(early.positions, late.positions)


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown scenario"):
        generate("parking", seed=0)
    with pytest.raises(ValueError, match="at least 13"):
        GeneratorConfig(duration=10.0)
    with pytest.raises(ValueError, match="multiple of 10"):
        GeneratorConfig(sim_frequency=15)


def test_duration_comes_from_the_argument_or_the_config():
    assert generate("merge", seed=0, config=GeneratorConfig(duration=14.0)).num_steps == 141
    assert generate("merge", seed=0, duration=13.5).num_steps == 136


def test_a_mixed_spec_takes_its_roads_in_turn_each_from_the_seed():
    from counterscene_env.scene.sources import check_spec, scenes_for

    mixed = [s.scenario_id for s in scenes_for("merge,roundabout", 3, 10)]
    merge = [s.scenario_id for s in scenes_for("merge", 2, 10)]
    roundabout = [s.scenario_id for s in scenes_for("roundabout", 1, 10)]
    assert mixed == [merge[0], roundabout[0], merge[1]]
    with pytest.raises(ValueError, match="'nowhere'"):
        check_spec("merge,nowhere")


def test_a_users_intersection_env_changes_no_later_scene():
    # Building highway-env's intersection env sets IDM class constants process-wide.
    import gymnasium as gym
    import highway_env  # noqa: F401

    before = generate("merge", seed=4)
    gym.make("intersection-v2").close()
    after = generate("merge", seed=4)
    assert np.array_equal(before.positions, after.positions)


@pytest.mark.parametrize("scenario", ["intersection", "merge"])
def test_recording_with_the_pruned_searches_equals_highway_envs_own(monkeypatch, scenario):
    """The recorder's vehicle searches fewer lanes and reuses its predictions; the recorded
    traffic is bit for bit what highway-env's own searches give (merge has sine lanes,
    which are never pruned; intersection has arcs)."""
    from highway_env.vehicle.behavior import IDMVehicle
    from highway_env.vehicle.controller import ControlledVehicle

    from counterscene_env.scene.highway_vehicle import ForwardIDMVehicle

    fast = record(scenario, 2)
    monkeypatch.setattr(ForwardIDMVehicle, "on_state_update", IDMVehicle.on_state_update)
    monkeypatch.setattr(
        ForwardIDMVehicle,
        "predict_trajectory_constant_speed",
        ControlledVehicle.predict_trajectory_constant_speed,
    )
    plain = record(scenario, 2)
    for key in ("positions", "yaws", "speeds", "valid"):
        np.testing.assert_array_equal(getattr(fast, key), getattr(plain, key), err_msg=key)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_closest_lane_search_agrees_with_highway_env(scenario):
    """Random poses near each network, ties included (a pose at a lane's start, where the
    lanes leaving one node begin together): the pruned search returns highway-env's lane
    from any lane the vehicle was on before."""
    from counterscene_env.scene.highway_traffic import make_env
    from counterscene_env.scene.highway_vehicle import closest_lane_index

    env = make_env(scenario)
    env.reset(seed=0)
    network = env.road.network
    lanes = network.lanes_list()
    indexes = [
        (a, b, i)
        for a, tos in network.graph.items()
        for b, ls in tos.items()
        for i in range(len(ls))
    ]
    rng = np.random.default_rng(0)
    poses = []
    for _ in range(300):
        lane = lanes[rng.integers(len(lanes))]
        s = rng.uniform(-10, lane.length + 10)
        poses.append((lane.position(s, rng.normal(0, 3)), lane.heading_at(s) + rng.normal(0, 0.5)))
    poses += [(lane.position(0.0, 0.0), lane.heading_at(0.0)) for lane in lanes]
    for position, heading in poses:
        want = network.get_closest_lane_index(position, heading)
        for current in (want, indexes[rng.integers(len(indexes))], None):
            assert closest_lane_index(network, position, heading, current) == want
