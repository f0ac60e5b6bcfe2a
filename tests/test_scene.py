"""The scene contract: validation, slicing, nearest-K selection, the road map."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import shapely
from conftest import make_scene, straight_road

from counterscene_env.scene import SceneError
from counterscene_env.scene.road import RoadMap
from counterscene_env.scene.road_json import network_from_json, network_to_json


def _line_scene(n=4, t=50):
    # Agent i sits at x = 10 i on y = 0, moving +x at 1 m per step.
    pos = np.zeros((n, t, 2))
    pos[..., 0] = np.arange(n)[:, None] * 10.0 + np.arange(t)[None, :]
    return make_scene(pos, speeds=np.full((n, t), 10.0), current_index=30)


def test_validation_names_the_bad_field():
    with pytest.raises(SceneError, match="yaws"):
        make_scene(np.zeros((2, 5, 2)), yaws=np.zeros((2, 4)))
    with pytest.raises(SceneError, match="ego_index"):
        make_scene(np.zeros((2, 5, 2)), ego_index=2)
    with pytest.raises(SceneError, match="non-finite"):
        make_scene(np.full((2, 5, 2), np.nan))
    with pytest.raises(SceneError, match="extents"):
        make_scene(np.zeros((2, 5, 2)), extents=np.zeros((2, 2)))
    with pytest.raises(SceneError, match="agent types"):
        make_scene(np.zeros((2, 5, 2)), agent_types=np.array(["vehicle", "tank"]))
    with pytest.raises(SceneError, match="ego must be a vehicle"):
        make_scene(np.zeros((2, 5, 2)), agent_types=np.array(["pedestrian", "vehicle"]))
    # Values that would be silently converted: a row of 1.7, a dt of "0.1", a validity of 0.5.
    with pytest.raises(SceneError, match="ego_index must be an int"):
        make_scene(np.zeros((2, 5, 2)), ego_index=1.7)
    with pytest.raises(SceneError, match="current_index must be an int"):
        make_scene(np.zeros((2, 5, 2)), current_index=2.5)
    for dt in ("0.1", float("inf"), 0.0):
        with pytest.raises(SceneError, match="dt must be"):
            make_scene(np.zeros((2, 5, 2)), current_index=2, dt=dt)
    with pytest.raises(SceneError, match="valid must be bools"):
        make_scene(np.zeros((2, 5, 2)), valid=np.full((2, 5), 0.5))
    with pytest.raises(SceneError, match="speeds must be numbers"):
        make_scene(np.zeros((2, 5, 2)), speeds=np.full((2, 5), "fast"))


def test_scene_owns_its_arrays():
    pos = np.zeros((2, 5, 2))
    valid = np.ones((2, 5), bool)
    valid[1, 2] = False
    pos[1, 2] = np.nan
    scene = make_scene(pos, valid=valid)
    assert np.isnan(pos[1, 2]).all(), "the caller's array is not modified"
    pos[0, 0] = 99.0
    assert scene.positions[0, 0, 0] == 0.0, "later changes by the caller do not leak in"


def test_nan_at_invalid_steps_is_allowed_and_zeroed():
    pos = np.zeros((2, 5, 2))
    pos[1, 3:] = np.nan
    valid = np.ones((2, 5), bool)
    valid[1, 3:] = False
    scene = make_scene(pos, valid=valid)
    assert np.isfinite(scene.positions).all()


def test_history_and_future_windows():
    scene = _line_scene()
    hist = scene.history(31)
    assert hist.num_steps == 31 and hist.current_index == 30
    np.testing.assert_allclose(hist.positions[0, -1], scene.positions[0, 30])
    fut = scene.future(10)
    assert fut.num_steps == 10
    np.testing.assert_allclose(fut.positions[0, 0], scene.positions[0, 31])
    # A window that would start before the log is shorter, not padded with invented frames.
    assert scene.history(31, t=5).num_steps == 6
    with pytest.raises(SceneError):
        scene.future(t=scene.num_steps - 1)


def test_nearest_k_puts_ego_first_then_by_distance():
    scene = _line_scene(n=5).replace(ego_index=2)
    idx = scene.nearest_indices(3)
    assert idx[0] == 2 and sorted(idx[1:].tolist()) == [1, 3]
    sub = scene.nearest(3)
    assert sub.num_agents == 3 and sub.ego_index == 0
    assert sub.agent_ids[0] == scene.agent_ids[2]


def test_nearest_skips_invalid_and_other_types():
    valid = np.ones((4, 50), bool)
    valid[1, 30] = False
    scene = _line_scene().replace(
        valid=valid, agent_types=np.array(["vehicle", "vehicle", "pedestrian", "vehicle"])
    )
    assert scene.nearest_indices(4, types=("vehicle",)).tolist() == [0, 3]


def test_road_map_from_network_clips_and_covers_lanes():
    road = straight_road(lanes=2, length=1000.0)
    clipped = RoadMap.from_network(road.network, bounds=(0, -10, 100, 20))
    assert len(clipped.lane_centerlines) == 2
    assert clipped.lane_centerlines[0][:, 0].max() <= 100.0 + 1e-9
    # Lane centres are on the road, a point 10 m beside it is not.
    assert shapely.intersects_xy(clipped.drivable_area, 50.0, 4.0)
    assert not shapely.intersects_xy(clipped.drivable_area, 50.0, 14.0)


def test_road_map_from_centerlines_builds_a_connected_network():
    a = np.array([[0.0, 0.0], [50.0, 0.0]])
    b = np.array([[50.0, 0.0], [100.0, 20.0]])
    road = RoadMap.from_centerlines([a, b], [3.5, 3.5], successors=[[1], []])
    lanes = road.network.lanes_list()
    assert len(lanes) == 2
    (start_a, end_a, _), (start_b, _, _) = (
        road.network.get_closest_lane_index(p) for p in ([25.0, 0.0], [75.0, 10.0])
    )
    assert end_a == start_b  # lane a flows into lane b
    assert road.network.next_lane((start_a, end_a, 0), position=np.array([49.0, 0.0]))[0] == start_b
    assert shapely.intersects_xy(road.drivable_area, 25.0, 1.5)
    assert not shapely.intersects_xy(road.drivable_area, 25.0, 2.5)


def test_a_real_map_pickles_to_the_same_lanes():
    """Real maps' spline lanes hold closures that do not pickle; a map still travels to a
    stress worker and comes back lane for lane the same, its area still prepared."""
    curve = np.stack([np.linspace(0, 60, 13), 0.01 * np.linspace(0, 60, 13) ** 2], axis=1)
    road = RoadMap.from_centerlines([curve, curve[-3:] + np.array([0.0, 4.0])], [3.5, 3.0])
    back = pickle.loads(pickle.dumps(road))
    points = np.array([[10.0, 2.0], [45.0, 18.0], [58.0, 40.0]])
    for a, b in zip(road.network.lanes_list(), back.network.lanes_list(), strict=True):
        assert type(a) is type(b) and a.length == b.length
        for p in points:
            assert np.array_equal(a.local_coordinates(p), b.local_coordinates(p))
    for p in points:
        assert back.network.get_closest_lane_index(p) == road.network.get_closest_lane_index(p)
    assert np.array_equal(back.off_road(points), road.off_road(points))
    assert shapely.is_prepared(back.drivable_area)


def test_network_json_round_trip_and_refuses_foreign_classes(generated):
    net = generated["roundabout"].road.network
    back = network_from_json(network_to_json(net))
    assert len(back.lanes_list()) == len(net.lanes_list())
    for a, b in zip(net.lanes_list(), back.lanes_list(), strict=True):
        np.testing.assert_allclose(a.position(3.0, 1.0), b.position(3.0, 1.0))
    evil = '[{"from": "a", "to": "b", "class": "os.system", "config": {}}]'
    with pytest.raises(ValueError, match="unknown lane class"):
        network_from_json(evil)


def _moving_scene():
    xy = np.zeros((2, 12, 2))
    xy[:, :, 0] = np.arange(12)
    xy[1, :, 1] = 3.5
    return make_scene(xy)


def test_a_position_jump_no_road_user_makes_is_refused_with_the_reason():
    scene = _moving_scene()
    positions = scene.positions.copy()
    positions[1, 7, 0] += 1e12
    with pytest.raises(SceneError, match=r"agent 'a1' moves 1e\+12 m between steps 6 and 7"):
        scene.replace(positions=positions)


def test_impossible_jumps_cost_only_their_samples_or_the_shorter_piece():
    from counterscene_env.scene.core import drop_impossible_jumps

    T = 20
    positions = np.zeros((3, T, 2))
    positions[:, :, 0] = np.arange(T) * 1.0  # 10 m/s
    valid = np.ones((3, T), bool)
    positions[0, 5, 0] = 1e12  # a lone bad sample
    positions[1, 15:, 0] += 500.0  # a teleport: the last 5 steps are another car
    fixed, repaired = drop_impossible_jumps(positions, valid, 0.1)
    assert repaired == {0: 1, 1: 5}
    assert fixed[0].sum() == T - 1 and not fixed[0, 5]
    assert fixed[1, :15].all() and not fixed[1, 15:].any()
    assert fixed[2].all()  # a sound track is left alone


@pytest.mark.parametrize(
    ("key", "message"),
    [
        ("road_lines", "lane centre line 0 has non-finite coordinates"),
        ("road_widths", "lane width 0 must be finite and > 0"),
    ],
)
def test_a_shard_with_non_finite_map_geometry_is_refused_with_the_reason(tmp_path, key, message):
    from counterscene_env.scene.shards import load_scenes, save_scenes

    path = tmp_path / "scene.npz"
    save_scenes([_moving_scene()], path)
    arrays = dict(np.load(path, allow_pickle=False))
    arrays[f"0/{key}"] = arrays[f"0/{key}"].copy()
    arrays[f"0/{key}"].flat[0] = np.nan
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=message):
        load_scenes(path)


def test_the_intersection_map_carries_each_lanes_right_of_way(generated, tmp_path):
    """highway-env's intersection gives its horizontal road the right of way (lane priority 3
    straight, 2 turning left; the vertical road 1 and 0): every centre line carries its lane's,
    through a shard and from a shard written before the field existed. Imported maps carry
    none (0)."""
    from counterscene_env.scene.shards import load_scenes, save_scenes

    scene = generated["intersection"]
    road = scene.road
    by_lane = {float(lane.priority) for lane in road.network.lanes_list()}
    assert by_lane == {0.0, 1.0, 2.0, 3.0} and set(road.lane_priorities) == by_lane
    # Each centre line's priority is that of the network lane at its midpoint and heading.
    for line, priority in zip(road.lane_centerlines, road.lane_priorities, strict=True):
        mid = line[len(line) // 2]
        heading = np.arctan2(*(line[len(line) // 2 + 1] - mid)[::-1])
        lane = road.network.get_lane(road.network.get_closest_lane_index(mid, heading))
        assert lane.priority == priority
    path = tmp_path / "scene.npz"
    save_scenes([scene], path)
    assert np.array_equal(load_scenes(path)[0].road.lane_priorities, road.lane_priorities)
    arrays = dict(np.load(path, allow_pickle=False))
    del arrays["0/road_priorities"]  # a shard of an older version
    np.savez(path, **arrays)
    assert np.array_equal(load_scenes(path)[0].road.lane_priorities, road.lane_priorities)
    assert not generated["highway"].road.lane_priorities.any()
    a = np.array([[0.0, 0.0], [50.0, 0.0]])
    assert RoadMap.from_centerlines([a], [3.5]).lane_priorities.tolist() == [0.0]
    with pytest.raises(ValueError, match="1 centre lines but 2 lane priorities"):
        RoadMap(road.network, road.drivable_area, [a], [3.5], None, [1.0, 2.0])
