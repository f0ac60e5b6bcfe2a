"""The ScenarioNet importer: safe unpickling, malformed files, tracks, time base and map.

Every file here is written by the test into ``tmp_path``; nothing reads the shared data.
"""

from __future__ import annotations

import os
import pickle
import re
import subprocess
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import shapely

from counterscene_env.scene import Scene, SceneError
from counterscene_env.scene.core import NO_LANES, TOO_SHORT
from counterscene_env.scene.scenarionet import (
    DEFAULT_BOX,
    ScenarioNetError,
    UnsafePickleError,
    load_scenarionet,
    read_scenario_description,
)

T = 41  # 4 s at 10 Hz


# ---------------------------------------------------------------------- synthetic scenario
def _track(kind, xy, vel, heading, valid, length, width, n=T):
    """A ScenarioNet track with constant box; ``xy``/``vel`` are [n, 2], the rest broadcast."""
    pos = np.zeros((n, 3))
    pos[:, :2] = xy
    return {
        "type": kind,
        "state": {
            "position": pos,
            "heading": np.broadcast_to(np.asarray(heading, float), (n,)).copy(),
            "velocity": np.broadcast_to(np.asarray(vel, float), (n, 2)).copy(),
            "valid": np.broadcast_to(np.asarray(valid, float), (n,)).copy(),
            "length": np.full((n, 1), length),
            "width": np.full((n, 1), width),
            "height": np.full((n, 1), 1.5),
        },
        "metadata": {"type": kind},
    }


def _scenario(dt: float = 0.1, n: int = T, links: bool = True) -> dict:
    """Ego + 2 vehicles + a pedestrian + a cone (+ a never-valid vehicle) on three lanes."""
    t = np.arange(n) * dt
    ego_xy = np.stack([-5.0 + 10.0 * t, np.zeros(n)], -1)
    veh_xy = np.stack([3.0 * t, np.full(n, 3.5)], -1)
    few = np.arange(n) * dt < 1.0  # valid for the first second only
    ped_valid = (np.arange(n) * dt >= 1.0) & (np.arange(n) * dt <= 3.0)
    tracks = {
        "veh_a": _track("VEHICLE", veh_xy, (3.0, 4.0), 0.0, 1.0, 4.5, 1.9, n),
        "ego": _track("VEHICLE", ego_xy, (10.0, 0.0), 0.0, 1.0, 1.73, 4.08, n),
        "veh_b": _track("VEHICLE", np.tile([20.0, 0.0], (n, 1)), (0.0, 0.0), 0.1, few, 4.0, 1.8, n),
        "ghost": _track("VEHICLE", np.zeros((n, 2)), (0.0, 0.0), 0.0, 0.0, 4.0, 1.8, n),
        "ped": _track(
            "PEDESTRIAN", np.tile([10.0, 6.0], (n, 1)), (0.0, -1.2), -1.5, ped_valid, 0.7, 0.6, n
        ),
        "cone": _track(
            "TRAFFIC_CONE", np.tile([30.0, -2.0], (n, 1)), (0.0, 0.0), 0.0, 1.0, 0.4, 0.4, n
        ),
    }
    # Two straight lanes with polygons, one connector without (a left bend), one bike lane.
    lane1 = np.stack([np.linspace(-10, 50, 61), np.zeros(61), np.zeros(61)], -1)  # (P, 3)
    lane2 = np.stack([np.linspace(-10, 50, 61), np.full(61, 3.5)], -1)  # (P, 2)
    ang = np.linspace(-np.pi / 2, 0.0, 20)
    lane3 = np.stack([50 + 10 * np.cos(ang), 10 + 10 * np.sin(ang)], -1)  # (50,0) -> (60,10)
    features = {
        "l1": {
            "type": "LANE_SURFACE_STREET",
            "polyline": lane1,
            "polygon": np.array([[-10, -1.75], [50, -1.75], [50, 1.75], [-10, 1.75]], float),
        },
        "l2": {
            "type": "LANE_SURFACE_STREET",
            "polyline": lane2.tolist(),  # nuScenes files store plain lists
            "polygon": [[-10, 1.75], [50, 1.75], [50, 5.25], [-10, 5.25]],
            "width": np.full((61, 2), 1.6),  # Waymo style: left/right half widths
        },
        "l3": {"type": "LANE_SURFACE_STREET", "polyline": lane3},
        "bike": {"type": "LANE_BIKE_LANE", "polyline": np.array([[0.0, 40.0], [10.0, 40.0]])},
        "line": {"type": "ROAD_LINE_BROKEN_SINGLE_WHITE", "polyline": lane2[:, :2] - [0, 1.75]},
    }
    if links:
        features["l1"]["exit_lanes"] = ["l3"]
        features["l3"]["entry_lanes"] = ["l1"]
        features["l2"]["exit_lanes"] = []
    return {
        "id": "synthetic-1",
        "version": "test",
        "length": n,
        "metadata": {
            "dataset": "unit-test",
            "scenario_id": "synthetic-1",
            "sample_rate": dt,
            "ts": t,
            "sdc_id": "ego",
            "map": "none",
        },
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": features,
    }


def _write(tmp_path: Path, obj, name: str = "scene.pkl", protocol: int = 4) -> Path:
    path = tmp_path / name
    with path.open("wb") as f:
        pickle.dump(obj, f, protocol=protocol)
    return path


def _node_after(road, start_xy):
    """The end node of the lane starting at ``start_xy`` (and the lane's start node)."""
    for _from, to_dict in road.network.graph.items():
        for _to, lanes in to_dict.items():
            for lane in lanes:
                if np.allclose(lane.position(0.0, 0.0), start_xy, atol=1e-6):
                    return _from, _to
    raise AssertionError(f"no lane starts at {start_xy}")


# ---------------------------------------------------------------------- the happy path
def test_synthetic_scenario_loads_to_expected_scene(tmp_path):
    scene = load_scenarionet(_write(tmp_path, _scenario()))
    assert isinstance(scene, Scene)
    assert scene.scenario_id == "synthetic-1"
    assert scene.dt == pytest.approx(0.1)
    assert scene.current_index == 30
    # ghost (never valid) is dropped; ego first, the others in file order
    assert scene.agent_ids.tolist() == ["ego", "veh_a", "veh_b", "ped", "cone"]
    assert scene.agent_types.tolist() == ["vehicle", "vehicle", "vehicle", "pedestrian", "other"]
    assert scene.ego_index == 0
    assert scene.positions.shape == (5, T, 2)
    assert scene.yaws.shape == scene.speeds.shape == scene.valid.shape == (5, T)
    assert scene.extents.shape == (5, 2)
    # speeds: norm of the velocity; states at 10 Hz as written
    np.testing.assert_allclose(scene.speeds[0], 10.0)
    np.testing.assert_allclose(scene.speeds[1], 5.0)
    np.testing.assert_allclose(scene.positions[0, :, 0], -5.0 + np.arange(T))
    assert scene.valid[2].sum() == 10 and not scene.valid[2, 10:].any()
    assert scene.valid[3].sum() == 21
    np.testing.assert_allclose(scene.yaws[3][scene.valid[3]], -1.5)
    # the nuScenes ego box (1.73 x 4.08) is swapped back; other boxes untouched
    np.testing.assert_allclose(scene.extents[0], [4.08, 1.73])
    np.testing.assert_allclose(scene.extents[1], [4.5, 1.9])
    np.testing.assert_allclose(scene.extents[4], [0.4, 0.4])
    assert scene.metadata["repairs"] == {"ego": ["length and width swapped"]}
    assert scene.metadata["num_tracks"] == {"vehicle": 3, "pedestrian": 1, "cyclist": 0, "other": 1}
    assert list(scene.metadata["dropped_tracks"]) == ["ghost"]
    assert scene.metadata["dataset"] == "unit-test"
    assert scene.metadata["source_file"] == "scene.pkl"


def test_synthetic_map(tmp_path):
    road = load_scenarionet(_write(tmp_path, _scenario())).road
    assert len(road.lane_centerlines) == 3  # the bike lane and the road line are not lanes
    # widths: polygon area / length, the width field (1.6 + 1.6), the 3.5 m default
    np.testing.assert_allclose(road.lane_widths, [3.5, 3.2, 3.5])
    pts = np.concatenate(road.lane_centerlines)
    assert shapely.intersects_xy(road.drivable_area, pts[:, 0], pts[:, 1]).all()
    assert not shapely.intersects_xy(road.drivable_area, 5.0, 40.0)  # bike lane left out
    assert not shapely.intersects_xy(road.drivable_area, 20.0, -3.0)  # beyond the lane polygon
    # exit_lanes: lane 1 ends where the connector starts
    _, end1 = _node_after(road, [-10.0, 0.0])
    start3, _ = _node_after(road, [50.0, 0.0])
    assert end1 == start3
    _, end2 = _node_after(road, [-10.0, 3.5])
    assert end2 != start3


def test_connectivity_from_geometry_without_links(tmp_path):
    road = load_scenarionet(_write(tmp_path, _scenario(links=False))).road
    _, end1 = _node_after(road, [-10.0, 0.0])
    start3, _ = _node_after(road, [50.0, 0.0])
    assert end1 == start3


def _ring(x0, y0, x1, y1, w=3.5):
    """Four lanes (with polygons) around the box [x0, x1] x [y0, y1], leaving it a hole."""
    h = w / 2
    sides = [
        ([x0 - h, y0], [x1 + h, y0]),
        ([x1, y0 - h], [x1, y1 + h]),
        ([x1 + h, y1], [x0 - h, y1]),
        ([x0, y1 + h], [x0, y0 - h]),
    ]
    out = {}
    for k, (a, b) in enumerate(sides):
        line = np.array([a, b], float)
        poly = shapely.LineString(line).buffer(h, cap_style="flat")
        out[f"r{x0}_{k}"] = {
            "type": "LANE_SURFACE_STREET",
            "polyline": line,
            "polygon": shapely.get_coordinates(poly.exterior),
        }
    return out


def test_small_holes_filled_large_kept_and_driveways_added(tmp_path):
    sd = _scenario()
    sd["map_features"].update(_ring(100, 0, 106, 6))  # 2.5 x 2.5 m hole: filled
    sd["map_features"].update(_ring(200, 0, 230, 30))  # 26.5 x 26.5 m block: kept
    sd["map_features"]["dw"] = {
        "type": "DRIVEWAY",
        "polygon": np.array([[0, -20], [10, -20], [10, -10], [0, -10]], float),
    }
    area = load_scenarionet(_write(tmp_path, sd)).road.drivable_area
    assert shapely.intersects_xy(area, 103.0, 3.0)
    assert not shapely.intersects_xy(area, 215.0, 15.0)
    assert shapely.intersects_xy(area, 5.0, -15.0)


@pytest.mark.parametrize("protocol", [3, 4, 5])
def test_pickle_protocols(tmp_path, protocol):
    scene = load_scenarionet(_write(tmp_path, _scenario(), protocol=protocol))
    assert scene.num_agents == 5


def test_current_index_argument(tmp_path):
    path = _write(tmp_path, _scenario())
    assert load_scenarionet(path, current_index=10).current_index == 10
    with pytest.raises(ScenarioNetError, match="current_index"):
        load_scenarionet(path, current_index=T)


# ---------------------------------------------------------------------- time base
def test_20hz_is_subsampled_to_10hz(tmp_path):
    ref = load_scenarionet(_write(tmp_path, _scenario(), "ref.pkl"))
    fast = load_scenarionet(_write(tmp_path, _scenario(dt=0.05, n=2 * T - 1), "fast.pkl"))
    assert fast.dt == pytest.approx(0.1)
    assert fast.num_steps == T
    assert fast.metadata["source_dt"] == pytest.approx(0.05) and not fast.metadata["resampled"]
    np.testing.assert_allclose(fast.positions, ref.positions, atol=1e-9)
    np.testing.assert_array_equal(fast.valid, ref.valid)
    np.testing.assert_allclose(fast.speeds, ref.speeds)


def test_sample_rate_from_ts_and_bad_rates(tmp_path):
    sd = _scenario()
    del sd["metadata"]["sample_rate"]
    assert load_scenarionet(_write(tmp_path, sd, "ts.pkl")).num_steps == T
    sd = _scenario(dt=0.03)
    with pytest.raises(ScenarioNetError, match=r"metadata.ts gives a step of 0.03 s"):
        load_scenarionet(_write(tmp_path, sd, "odd.pkl"))
    sd = _scenario(dt=0.2)
    del sd["metadata"]["ts"]
    with pytest.raises(ScenarioNetError, match=r"sample_rate gives a step of 0\.2 s"):
        load_scenarionet(_write(tmp_path, sd, "slow.pkl"))


# ---------------------------------------------------------------------- hostile pickles
class _Exploit:
    def __init__(self, func, args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def test_os_system_payload_is_refused_and_never_runs(tmp_path):
    marker = tmp_path / "pwned"
    path = _write(tmp_path, _Exploit(os.system, (f"touch {marker}",)), "evil.pkl")
    with pytest.raises(UnsafePickleError, match="system") as info:
        load_scenarionet(path)
    assert isinstance(info.value, SceneError)
    assert "evil.pkl" in str(info.value)
    assert not marker.exists()


def test_payload_hidden_inside_a_valid_scenario_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    sd = _scenario()
    sd["metadata"]["extra"] = _Exploit(os.system, (f"touch {marker}",))
    with pytest.raises(UnsafePickleError):
        load_scenarionet(_write(tmp_path, sd, "evil.pkl"))
    assert not marker.exists()


@pytest.mark.parametrize(
    ("func", "args", "name"),
    [
        (eval, ("1 + 1",), "builtins.eval"),
        (subprocess.Popen, (["true"],), "subprocess.Popen"),
        (__import__, ("os",), "builtins.__import__"),
    ],
)
def test_other_dangerous_globals_are_refused(tmp_path, func, args, name):
    path = _write(tmp_path, {"metadata": _Exploit(func, args)}, "evil.pkl")
    with pytest.raises(UnsafePickleError, match=name.replace(".", r"\.")):
        read_scenario_description(path)


def test_persistent_ids_are_refused(tmp_path):
    import io

    class _P(pickle.Pickler):
        def persistent_id(self, obj):
            return "ref-1" if obj == "secret" else None

    buf = io.BytesIO()
    _P(buf, protocol=4).dump({"metadata": "secret"})
    path = tmp_path / "pid.pkl"
    path.write_bytes(buf.getvalue())
    with pytest.raises(UnsafePickleError, match="persistent"):
        load_scenarionet(path)


def test_build_cannot_alter_an_allowed_helper(tmp_path):
    from numpy._core import numeric

    before = numeric._frombuffer.__defaults__
    # numpy._core.numeric._frombuffer, then BUILD with slot state {"__defaults__": (1,)}
    payload = (
        b"\x80\x04"
        + b"\x8c\x13numpy._core.numeric\x8c\x0b_frombuffer\x93"
        + b"N}\x8c\x0c__defaults__K\x01\x85s\x86b."
    )
    path = tmp_path / "build.pkl"
    path.write_bytes(payload)
    with pytest.raises(SceneError):
        load_scenarionet(path)
    assert numeric._frombuffer.__defaults__ == before


# ---------------------------------------------------------------------- malformed files
def test_truncated_file(tmp_path):
    path = _write(tmp_path, _scenario())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ScenarioNetError, match=r"scene\.pkl.*not a readable pickle"):
        load_scenarionet(path)


def test_not_a_pickle(tmp_path):
    path = tmp_path / "notes.pkl"
    path.write_text("just some text\n")
    with pytest.raises(ScenarioNetError, match=r"notes\.pkl.*not a readable pickle"):
        load_scenarionet(path)


def test_scenarionets_index_files_are_read_as_its_readers_read_them(tmp_path):
    """ScenarioNet writes ``dataset_summary.pkl`` and ``dataset_mapping.pkl`` into every
    dataset directory: they are not scenarios. A merged dataset holds only them, and its
    mapping points at the scenarios in the datasets it merged."""
    from counterscene_env.scene.reading import iter_scenes
    from counterscene_env.scene.scenarionet import scenarionet_files

    data = tmp_path / "data"
    data.mkdir()
    _write(data, _scenario(), "sd_a.pkl")
    _write(data, _scenario(), "sd_b.pkl")
    _write(data, {"sd_a.pkl": {"id": "a"}, "sd_b.pkl": {"id": "b"}}, "dataset_summary.pkl")
    _write(data, {"sd_a.pkl": "", "sd_b.pkl": ""}, "dataset_mapping.pkl")
    assert [f.name for f in scenarionet_files(data)] == ["sd_a.pkl", "sd_b.pkl"]
    assert len(list(iter_scenes(data))) == 2
    (data / "dataset_mapping.pkl").unlink()  # no mapping: every .pkl but the index files
    assert [f.name for f in scenarionet_files(data)] == ["sd_a.pkl", "sd_b.pkl"]
    merged = tmp_path / "merged"
    merged.mkdir()
    _write(merged, {"sd_b.pkl": "../data"}, "dataset_mapping.pkl")
    assert scenarionet_files(merged) == [merged / "../data" / "sd_b.pkl"]
    _write(merged, {"sd_c.pkl": "../data"}, "dataset_mapping.pkl")
    with pytest.raises(FileNotFoundError, match="not there"):
        scenarionet_files(merged)


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioNetError, match="cannot read"):
        load_scenarionet(tmp_path / "absent.pkl")


def test_not_a_dict(tmp_path):
    path = _write(tmp_path, [1, 2, 3], "list.pkl")
    with pytest.raises(ScenarioNetError, match=r"list\.pkl.*dict.*list"):
        load_scenarionet(path)


@pytest.mark.parametrize("field", ["tracks", "metadata", "map_features"])
def test_missing_top_level_field(tmp_path, field):
    sd = _scenario()
    del sd[field]
    with pytest.raises(ScenarioNetError, match=f"scene.pkl.*{field}"):
        load_scenarionet(_write(tmp_path, sd))


def test_missing_sdc_id(tmp_path):
    sd = _scenario()
    del sd["metadata"]["sdc_id"]
    with pytest.raises(ScenarioNetError, match="sdc_id"):
        load_scenarionet(_write(tmp_path, sd))
    sd["metadata"]["sdc_id"] = "nobody"
    with pytest.raises(ScenarioNetError, match="'nobody'"):
        load_scenarionet(_write(tmp_path, sd))


def test_a_malformed_track_is_dropped_with_its_reason_and_the_scene_loads(tmp_path):
    for name, change, reason in [
        ("veh_a", lambda st: st.update(position=np.zeros((T, 4))), r"position.*\(T, 2\|3\)"),
        ("ped", lambda st: st.update(heading=np.zeros(T - 1)), "heading"),
        ("cone", lambda st: st.pop("velocity"), "velocity"),
    ]:
        sd = _scenario()
        change(sd["tracks"][name]["state"])
        scene = load_scenarionet(_write(tmp_path, sd))
        assert name not in scene.agent_ids.tolist()
        assert re.search(reason, scene.metadata["dropped_tracks"][name])
        assert scene.num_agents == 4
    sd = _scenario()
    sd["tracks"]["ego"]["state"]["position"] = np.zeros((T, 4))  # the ego cannot be dropped
    with pytest.raises(ScenarioNetError, match=r"ego.*position"):
        load_scenarionet(_write(tmp_path, sd))
    sd = _scenario()
    sd["map_features"]["l1"]["polyline"] = np.zeros((5, 4))
    with pytest.raises(ScenarioNetError, match=r"l1.*polyline"):
        load_scenarionet(_write(tmp_path, sd))


def test_tracks_of_different_lengths(tmp_path):
    sd = _scenario()
    sd["tracks"]["cone"] = _track(
        "TRAFFIC_CONE", np.zeros((T + 1, 2)), (0, 0), 0, 1, 0.4, 0.4, T + 1
    )
    scene = load_scenarionet(_write(tmp_path, sd))
    assert "steps" in scene.metadata["dropped_tracks"]["cone"]


# ---------------------------------------------------------------------- review fixes
def test_reversing_vehicle_gets_a_negative_speed(tmp_path):
    sd = _scenario()
    state = sd["tracks"]["veh_a"]["state"]
    state["velocity"] = -state["velocity"]  # velocity points backwards relative to the heading
    scene = load_scenarionet(_write(tmp_path, sd))
    row = scene.agent_ids.tolist().index("veh_a")
    np.testing.assert_allclose(scene.speeds[row][scene.valid[row]], -5.0)


def test_lane_stubs_shorter_than_a_metre_do_not_break_the_import(tmp_path):
    sd = _scenario()
    sd["map_features"]["stub"] = {
        "type": "LANE_SURFACE_STREET",
        "polyline": np.array([[0.0, 40.0], [0.5, 40.0]]),
    }
    scene = load_scenarionet(_write(tmp_path, sd))
    reference = load_scenarionet(_write(tmp_path, _scenario(), name="ref.pkl"))
    assert len(scene.road.lane_centerlines) == len(reference.road.lane_centerlines)
    assert scene.road.drivable_area.intersects(shapely.Point(0.25, 40.0)), "its surface is kept"


def test_a_corrupt_position_costs_its_samples_not_the_scene(tmp_path):
    sd = _scenario()
    track = sd["tracks"]["veh_a"]["state"]
    track["position"] = np.asarray(track["position"], float).copy()
    track["position"][35, 0] += 1e12
    scene = load_scenarionet(_write(tmp_path, sd))
    assert scene.metadata["repairs"]["veh_a"] == ["1 steps after an impossible jump made invalid"]
    row = list(scene.agent_ids).index("veh_a")
    assert not scene.valid[row, 35] and scene.valid[row, 34] and scene.valid[row, 36]
    assert np.abs(scene.positions).max() < 1e3


# ---------------------------------------------------------------------- files as converters write them
def test_float32_timestamps_are_resampled_onto_the_exact_grid(tmp_path):
    """Waymo files: float32 ``ts`` with steps of 0.09994-0.10006 s and no ``sample_rate``."""
    sd = _scenario()
    del sd["metadata"]["sample_rate"]
    jitter = np.random.default_rng(0).uniform(-6e-5, 6e-5, T)
    jitter[0] = 0.0
    ts = (np.arange(T) * 0.1 + jitter).astype(np.float32)
    sd["metadata"]["ts"] = ts
    # The ego moves at 10 m/s along x: its logged x is its true x at the jittered time.
    sd["tracks"]["ego"]["state"]["position"][:, 0] = -5.0 + 10.0 * ts.astype(float)
    scene = load_scenarionet(_write(tmp_path, sd))
    assert scene.num_steps == T and scene.dt == 0.1 and scene.metadata["resampled"]
    # Resampled at exactly k * 0.1 s: x = -5 + k (to float32 precision of the stamps).
    np.testing.assert_allclose(scene.positions[0, :, 0], -5.0 + np.arange(T), atol=1e-4)
    sd["metadata"]["ts"] = np.arange(T) * 0.13  # neither 0.1 s nor a fraction of it
    with pytest.raises(ScenarioNetError, match=r"metadata.ts gives a step of 0.13 s"):
        load_scenarionet(_write(tmp_path, sd))


def test_a_gap_in_the_timestamps_leaves_invalid_steps_not_invented_motion(tmp_path):
    """Frames missing from a log (its clock jumps 1.1 s after 3.9 s): the grid steps inside
    the hole are invalid for everyone; those on either side read their frames."""
    n = 61
    sd = _scenario(n=n)
    ts = np.arange(n) * 0.1
    ts[40:] += 1.0  # frame 40 is at 5.0 s: 4.0-4.9 s were never recorded
    sd["metadata"]["ts"] = ts
    del sd["metadata"]["sample_rate"]
    scene = load_scenarionet(_write(tmp_path, sd))
    assert scene.num_steps == n + 10
    ego = scene.ego_index
    assert scene.valid[ego, :40].all() and scene.valid[ego, 50:].all()
    assert not scene.valid[:, 40:50].any()


def test_flat_box_arrays_and_bad_boxes_are_repaired(tmp_path):
    sd = _scenario()
    ped = sd["tracks"]["ped"]["state"]
    ped["length"], ped["width"] = np.zeros(T), np.full(T, np.nan)  # (T,), zero and NaN
    veh = sd["tracks"]["veh_a"]["state"]
    veh["length"] = np.full(T, 4.5)
    veh["length"][:5] = 0.0  # a few zero sizes: the median of the good ones
    scene = load_scenarionet(_write(tmp_path, sd))
    rows = scene.agent_ids.tolist()
    np.testing.assert_allclose(scene.extents[rows.index("ped")], DEFAULT_BOX["pedestrian"])
    np.testing.assert_allclose(scene.extents[rows.index("veh_a")], [4.5, 1.9])
    assert len(scene.metadata["repairs"]["ped"]) == 2
    assert "veh_a" not in scene.metadata["repairs"]


def test_nan_positions_at_valid_steps_are_made_invalid(tmp_path):
    sd = _scenario()
    sd["tracks"]["veh_a"]["state"]["position"][[3, 4], 0] = np.nan
    sd["tracks"]["cone"]["state"]["position"][:, 1] = np.nan  # nothing left: dropped
    scene = load_scenarionet(_write(tmp_path, sd))
    row = scene.agent_ids.tolist().index("veh_a")
    assert not scene.valid[row, 3:5].any() and scene.valid[row, 5]
    assert "2 steps" in scene.metadata["repairs"]["veh_a"][0]
    assert "no valid step" in scene.metadata["dropped_tracks"]["cone"]


def test_defaultdicts_with_builtin_factories_load_and_other_factories_are_refused(tmp_path):
    sd = _scenario()
    counts = defaultdict(int, {"VEHICLE": 3})
    sd["metadata"]["number_summary"] = {"num_moving_objects_each_type": counts}
    sd["metadata"]["lists"] = defaultdict(list, {"a": [1]})
    data = read_scenario_description(_write(tmp_path, sd))
    assert data["metadata"]["number_summary"]["num_moving_objects_each_type"]["VEHICLE"] == 3
    assert load_scenarionet(_write(tmp_path, sd)).num_agents == 5
    sd["metadata"]["bad"] = defaultdict(set)
    with pytest.raises(UnsafePickleError, match=r"builtins\.set"):
        read_scenario_description(_write(tmp_path, sd))


def test_single_point_polylines_are_not_lanes_and_do_not_fail(tmp_path):
    sd = _scenario()
    sd["map_features"]["dot"] = {"type": "LANE_SURFACE_STREET", "polyline": np.array([1.0, 2, 0])}
    sd["map_features"]["dot2"] = {"type": "ROAD_EDGE_BOUNDARY", "polyline": np.zeros((1, 3))}
    sd["map_features"]["dot3"] = {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": [[0, 0]]}
    scene = load_scenarionet(_write(tmp_path, sd))
    assert len(scene.road.lane_centerlines) == 3


# ---------------------------------------------------------------------- real maps
def test_drivable_area_outlines_fill_even_odd_and_pieces_are_merged(tmp_path):
    """nuScenes/nuPlan write the drivable area's rings as ``boundary_*`` solid white lines
    (AV2 in 20-point pieces): the road beyond the lanes, islands excluded."""
    sd = _scenario()
    outer = np.array([[60, -40], [120, -40], [120, 20], [60, 20], [60, -40]], float)
    island = np.array([[80, -20], [100, -20], [100, 0], [80, 0], [80, -20]], float)
    sd["map_features"]["boundary_0"] = {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": outer}
    sd["map_features"]["boundary_1"] = {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": island}
    # a second area in two open pieces
    sd["map_features"]["boundary_2"] = {
        "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
        "polyline": np.array([[-50, 60], [-30, 60], [-30, 80]], float),
    }
    sd["map_features"]["boundary_3"] = {
        "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
        "polyline": np.array([[-30, 80], [-50, 80], [-50, 60]], float),
    }
    sd["map_features"]["painted"] = {  # an ordinary painted line encloses nothing
        "type": "ROAD_LINE_SOLID_SINGLE_WHITE",
        "polyline": np.array([[0, -60], [20, -60], [20, -50], [0, -50], [0, -60]], float),
    }
    road = load_scenarionet(_write(tmp_path, sd)).road
    assert not road.off_road(np.array([70.0, -30.0]))
    assert road.off_road(np.array([90.0, -10.0]))  # the island
    assert not road.off_road(np.array([-40.0, 70.0]))
    assert road.off_road(np.array([10.0, -55.0]))


def test_road_edges_pave_the_kerbside_on_the_lanes_side_only(tmp_path):
    """Waymo: lanes are centre lines, the kerb a road edge 3 m beyond the lane's side."""
    sd = _scenario()
    # Lane l1 spans y in [-1.75, 1.75]; a kerb at y = -4.75, a crosswalk beyond it.
    sd["map_features"]["kerb"] = {
        "type": "ROAD_EDGE_BOUNDARY",
        "polyline": np.stack([np.linspace(50, -10, 30), np.full(30, -4.75)], -1),
    }
    sd["map_features"]["walk"] = {
        "type": "CROSSWALK",
        "polygon": np.array([[0, -12], [40, -12], [40, -10], [0, -10]], float),
    }
    road = load_scenarionet(_write(tmp_path, sd)).road
    assert not road.off_road(np.array([20.0, -4.0]))  # between lane and kerb: paved
    assert road.off_road(np.array([20.0, -6.0]))  # beyond the kerb
    del sd["map_features"]["kerb"]
    plain = load_scenarionet(_write(tmp_path, sd, "plain.pkl")).road
    assert plain.off_road(np.array([20.0, -4.0]))


def test_beyond_the_map_crop_is_not_off_road(tmp_path):
    road = load_scenarionet(_write(tmp_path, _scenario())).road
    assert road.extent is not None
    assert road.off_road(np.array([20.0, 20.0]))  # inside the crop, off the lanes
    assert not road.off_road(np.array([500.0, 0.0]))  # beyond every map feature: unknown


def test_short_logs_start_later_or_are_skipped_and_counted(tmp_path):
    """A log under 4 s starts early enough for 1 s of future, else at its last step but one
    (if 1 s of history remains); a shorter one is too short for any episode: stored specs
    skip it and count it."""
    from counterscene_env.scene.sources import SKIPPED, stored_scenes

    assert load_scenarionet(_write(tmp_path, _scenario(n=35), "mid.pkl")).current_index == 24
    n = 20
    scene = load_scenarionet(_write(tmp_path, _scenario(n=n), "short.pkl"))
    assert scene.current_index == n - 2
    (tmp_path / "mid.pkl").unlink()
    _write(tmp_path, _scenario(n=8), "tiny.pkl")
    with pytest.raises(SceneError, match=r"tiny\.pkl: recording too short: 8 steps"):
        load_scenarionet(tmp_path / "tiny.pkl")
    spec = f"scenarionet:{tmp_path}"
    assert [s.metadata["source_file"] for s in stored_scenes(spec)] == ["short.pkl"]
    assert SKIPPED[spec] == {TOO_SHORT: 1}


def test_a_scene_without_lanes_is_skipped_with_its_reason(tmp_path):
    """Its ego has no lane to follow: stress and the env skip it and say why, rather than
    failing inside highway-env's lane search."""
    from counterscene_env.scene.sources import SKIPPED, stored_scenes

    _write(tmp_path, _scenario(), "good.pkl")
    _write(tmp_path, {**_scenario(), "map_features": {}}, "nomap.pkl")
    spec = f"scenarionet:{tmp_path}"
    assert [s.metadata["source_file"] for s in stored_scenes(spec)] == ["good.pkl"]
    assert SKIPPED[spec] == {NO_LANES: 1}


def test_a_zero_velocity_ending_a_moving_track_is_filled(tmp_path):
    """ScenarioNet's nuScenes converter ends every track on a velocity of (0, 0): read as
    such, a car at 10 m/s would stop in one frame. A parked car's zero is kept."""
    sd = _scenario()
    ego = sd["tracks"]["ego"]["state"]
    ego["velocity"][-1] = 0.0  # moving at 10 m/s to the end
    veh = sd["tracks"]["veh_b"]["state"]  # parked: its zero stays
    scene = load_scenarionet(_write(tmp_path, sd))
    assert scene.speeds[0, -1] == pytest.approx(10.0)
    row = scene.agent_ids.tolist().index("veh_b")
    assert not veh["velocity"].any() and scene.speeds[row, scene.valid[row]].max() == 0.0
    assert "zero velocities" in scene.metadata["repairs"]["ego"][-1]
    assert "veh_b" not in scene.metadata["repairs"]


def test_a_car_that_really_stops_keeps_its_zero_velocity(tmp_path):
    sd = _scenario()
    ego = sd["tracks"]["ego"]["state"]
    ego["position"][-1] = ego["position"][-2]  # it did not move in its last step
    ego["velocity"][-1] = 0.0
    scene = load_scenarionet(_write(tmp_path, sd))
    assert scene.speeds[0, -1] == 0.0
    assert not any("zero velocities" in r for r in scene.metadata["repairs"].get("ego", []))
