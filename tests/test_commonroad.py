"""The CommonRoad importer on tiny scenarios written here (format 2018b, like the NGSIM files).

Map: lanelet 1 (x 0..50) continues into lanelet 2 (x 50..100), lanelet 3 (x 0..100) runs
beside both in the same direction; each is 3.5 m wide. Traffic (0.1 s steps):

- 10: car, lane 1, 10 m/s, steps 0-39: the longest-present moving car that overlaps nobody.
- 11: car behind it, 8 m/s, steps 0-35: the second ego choice.
- 12: car on lane 3, 8 m/s, steps 0-44 (longest present) but it drives through 13.
- 13: car stopped on lane 3 (never an ego: not moving; overlapped by 12).
- 14: pedestrian (a circle of radius 0.3 m) without velocities: walks 1.2 m/s along +x.
- 15: a static parked vehicle.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

pytest.importorskip("commonroad")

from counterscene_env.geometry import points_in_area
from counterscene_env.scene.commonroad import (
    CommonRoadError,
    commonroad_egos,
    iter_commonroad,
    load_commonroad,
)


def _points(tag: str, pts) -> str:
    inner = "".join(f"<point><x>{x:.4f}</x><y>{y:.4f}</y></point>" for x, y in pts)
    return f"<{tag}>{inner}</{tag}>"


def _lanelet(lid: int, x0: float, x1: float, y0: float, links: str) -> str:
    xs = np.linspace(x0, x1, 6)
    left = _points("leftBound", [(x, y0 + 3.5) for x in xs])
    right = _points("rightBound", [(x, y0) for x in xs])
    return f'<lanelet id="{lid}">{left}{right}{links}</lanelet>'


def _state(tag: str, t: int, x: float, y: float, v: float | None) -> str:
    vel = "" if v is None else f"<velocity><exact>{v}</exact></velocity>"
    return (
        f"<{tag}><position><point><x>{x:.4f}</x><y>{y:.4f}</y></point></position>"
        f"<orientation><exact>0.0</exact></orientation><time><exact>{t}</exact></time>"
        f"{vel}<acceleration><exact>0.0</exact></acceleration></{tag}>"
    )


def _obstacle(oid: int, kind: str, shape: str, x0: float, y: float, v: float, steps: int, vel=True):
    states = [_state("state", t, x0 + v * 0.1 * t, y, v if vel else None) for t in range(steps)]
    return (
        f'<obstacle id="{oid}"><role>dynamic</role><type>{kind}</type><shape>{shape}</shape>'
        f"{_state('initialState', 0, x0, y, v if vel else None)}"
        f"<trajectory>{''.join(states[1:])}</trajectory></obstacle>"
    )


CAR = "<rectangle><length>4.5</length><width>1.8</width></rectangle>"


def _scenario(steps: int = 45, goal_x: float = 90.0, name: str = "DEU_Toy-1_1_T-1") -> str:
    """A CommonRoad 2018b file; ``steps`` caps every track, ``goal_x`` moves the planning
    problem (files differing only in it share their traffic)."""
    lanelets = (
        _lanelet(1, 0, 50, 0, '<successor ref="2"/><adjacentLeft ref="3" drivingDir="same"/>')
        + _lanelet(2, 50, 100, 0, '<predecessor ref="1"/>')
        + _lanelet(3, 0, 100, 3.5, '<adjacentRight ref="1" drivingDir="same"/>')
    )
    obstacles = (
        _obstacle(10, "car", CAR, 20, 1.75, 10.0, min(steps, 40))
        + _obstacle(11, "car", CAR, 0, 1.75, 8.0, min(steps, 36))
        + _obstacle(12, "car", CAR, 30, 5.25, 8.0, steps)
        + _obstacle(13, "car", CAR, 40, 5.25, 0.0, steps)
        + _obstacle(
            14, "pedestrian", "<circle><radius>0.3</radius></circle>", 60, -2, 1.2, steps, False
        )
        + '<obstacle id="15"><role>static</role><type>parkedVehicle</type>'
        f"<shape>{CAR}</shape>{_state('initialState', 0, 80, -3, 0.0)}</obstacle>"
    )
    problem = (
        '<planningProblem id="99">'
        + _state("initialState", 0, 0.0, 0.0, 5.0).replace(
            "</initialState>",
            "<yawRate><exact>0</exact></yawRate><slipAngle><exact>0</exact></slipAngle>"
            "</initialState>",
        )
        + f"<goalState><position><rectangle><length>4</length><width>2</width>"
        f"<orientation>0</orientation><center><x>{goal_x}</x><y>1.75</y></center></rectangle>"
        "</position><time><intervalStart>30</intervalStart><intervalEnd>40</intervalEnd></time>"
        "</goalState></planningProblem>"
    )
    return (
        '<?xml version="1.0" encoding="utf-8"?>\n'
        f'<commonRoad commonRoadVersion="2018b" benchmarkID="{name}" timeStepSize="0.1" '
        'date="2024-01-01" author="test" affiliation="test" source="test" '
        'tags="highway multi_lane">'
        f"{lanelets}{obstacles}{problem}</commonRoad>\n"
    )


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    path = tmp_path_factory.mktemp("cr") / "DEU_Toy-1_1_T-1.xml"
    path.write_text(_scenario())
    return path


@pytest.fixture(scope="module")
def scene(toy):
    return load_commonroad(toy)


def test_lanes_successors_and_drivable_area(scene):
    road = scene.road
    assert len(road.lane_centerlines) == 3
    np.testing.assert_allclose(road.lane_widths, 3.5)
    lanes = {}  # start point -> (from node, to node)
    for a, ends in road.network.graph.items():
        for b, lane_list in ends.items():
            lanes[tuple(np.round(lane_list[0].position(0.0, 0.0), 2))] = (a, b)
    assert lanes[(0.0, 1.75)][1] == lanes[(50.0, 1.75)][0]  # lanelet 1 -> 2
    assert lanes[(0.0, 5.25)][1] != lanes[(50.0, 1.75)][0]
    centres = np.concatenate(road.lane_centerlines)
    assert points_in_area(road.drivable_area, centres).all()
    # The seams between neighbouring lanelets are drivable, the world beyond is not.
    seams = np.array([[25.0, 3.5], [50.0, 1.75], [75.0, 3.5]])
    assert points_in_area(road.drivable_area, seams).all()
    assert not points_in_area(road.drivable_area, np.array([[50.0, 9.0]])).any()
    assert scene.metadata["num_lanelets"] == 3
    assert scene.metadata["lanelets_without_successor"] == 2


def test_default_ego_rows_types_and_extents(scene, toy):
    assert commonroad_egos(toy) == ["10", "11"]  # 12 overlaps 13, 13 stands, 14 walks
    assert scene.agent_ids.tolist() == ["10", "11", "12", "13", "14", "15"]
    assert scene.ego_index == 0 and scene.scenario_id == "DEU_Toy-1_1_T-1/ego=10"
    assert scene.agent_types.tolist() == ["vehicle"] * 4 + ["pedestrian", "other"]
    np.testing.assert_allclose(scene.extents[0], [4.5, 1.8])
    np.testing.assert_allclose(scene.extents[4], [0.6, 0.6])  # circle: its bounding box
    assert scene.valid[0, :40].all() and not scene.valid[0, 40:].any()
    assert scene.valid[5].all() and (scene.speeds[5] == 0).all()  # static: there throughout
    np.testing.assert_allclose(scene.positions[0, 10], [30.0, 1.75])
    np.testing.assert_allclose(scene.speeds[0][scene.valid[0]], 10.0)
    np.testing.assert_allclose(scene.speeds[4], 1.2, atol=1e-6)  # derived from positions
    meta = scene.metadata
    assert meta["repairs"] == {"14": ["speed derived from positions (no velocity)"]}
    assert meta["dataset"] == "commonroad" and meta["ego"] == "10" and meta["ego_choices"] == 2
    assert meta["num_tracks"] == {"vehicle": 4, "pedestrian": 1, "cyclist": 0, "other": 1}
    assert (meta["history_steps"], meta["future_steps"]) == (31, 14)
    assert meta["benchmark_id"] == "DEU_Toy-1_1_T-1" and meta["source_file"] == toy.name


def test_explicit_ego_and_refusals(toy):
    scene = load_commonroad(toy, ego=11)
    assert scene.agent_ids[0] == "11" and scene.scenario_id.endswith("/ego=11")
    assert scene.agent_ids[1:].tolist() == ["10", "12", "13", "14", "15"]
    with pytest.raises(CommonRoadError, match=r"DEU_Toy-1_1_T-1\.xml.*obstacle 12.*overlaps"):
        load_commonroad(toy, ego="12")
    with pytest.raises(CommonRoadError, match="mean speed"):
        load_commonroad(toy, ego=13)
    with pytest.raises(CommonRoadError, match="no usable obstacle with id '77'"):
        load_commonroad(toy, ego=77)


def test_all_egos_and_duplicate_traffic(tmp_path):
    (tmp_path / "a.xml").write_text(_scenario(goal_x=90.0))
    (tmp_path / "b.xml").write_text(_scenario(goal_x=70.0))  # another planning problem only
    report: dict = {}
    scenes = list(iter_commonroad(tmp_path, all_egos=True, report=report))
    assert [s.scenario_id for s in scenes] == ["DEU_Toy-1_1_T-1/ego=10", "DEU_Toy-1_1_T-1/ego=11"]
    assert all(s.metadata["source_file"] == "a.xml" for s in scenes)
    assert report["duplicates"] == {"b.xml": "a.xml"} and report["skipped"] == {}
    assert report["files"] == 2 and report["scenes"] == 2
    kept = list(iter_commonroad(tmp_path, skip_duplicates=False))
    assert [s.metadata["duplicate_of"] for s in kept] == [None, "a.xml"]


def test_short_recordings(tmp_path):
    short = tmp_path / "short.xml"
    short.write_text(_scenario(steps=16))  # 1.5 s: "now" moves back to step 14
    scene = load_commonroad(short)
    assert scene.current_index == 14 and scene.num_steps == 16
    assert (scene.metadata["history_steps"], scene.metadata["future_steps"]) == (15, 1)
    too_short = tmp_path / "too_short.xml"
    too_short.write_text(_scenario(steps=11))  # 1.0 s: no 1 s of history before a future step
    with pytest.raises(CommonRoadError, match=r"too_short\.xml: recording too short"):
        load_commonroad(too_short)
    report: dict = {}
    assert len(list(iter_commonroad(tmp_path, report=report))) == 1
    assert list(report["skipped"]) == ["too_short.xml"]


def test_malformed_file_names_it(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<commonRoad><lanelet")
    with pytest.raises(CommonRoadError, match=r"broken\.xml: not a readable CommonRoad file"):
        load_commonroad(bad)


def test_missing_commonroad_io_is_actionable(toy, monkeypatch):
    monkeypatch.setitem(sys.modules, "commonroad.common.file_reader", None)
    with pytest.raises(ImportError, match=r'pip install "counterscene-env\[commonroad\]"'):
        load_commonroad(toy)


def test_commonroad_spec_and_generate(tmp_path):
    """``commonroad:DIR`` is a scenario source, and ``generate --from-commonroad`` converts a
    folder (one scene per distinct recording; a too-short one counted, not fatal)."""
    from counterscene_env.cli import main
    from counterscene_env.scene.manifest import read_manifest
    from counterscene_env.scene.reading import iter_scenes
    from counterscene_env.scene.sources import SKIPPED, SceneSource, stored_scenes

    src = tmp_path / "src"
    src.mkdir()
    (src / "a.xml").write_text(_scenario(goal_x=90.0))
    (src / "b.xml").write_text(_scenario(goal_x=70.0))
    (src / "short.xml").write_text(_scenario(steps=11, name="DEU_Short-1_1_T-1"))
    spec = f"commonroad:{src}"
    assert [s.scenario_id for s in stored_scenes(spec)] == ["DEU_Toy-1_1_T-1/ego=10"]
    assert SKIPPED[spec] == {"too short for an episode": 1}
    drawn = SceneSource(spec).draw(np.random.default_rng(0))
    assert drawn.metadata["dataset"] == "commonroad"
    out = tmp_path / "ds"
    assert main(["generate", "--from-commonroad", str(src), "--out", str(out), "--quiet"]) == 0
    manifest = read_manifest(out)
    assert manifest["duplicates"] == {"b.xml": "a.xml"}
    assert manifest["scenes"] == 1 and manifest["rejected"] == 1
    every = tmp_path / "every"
    main(["generate", "--from-commonroad", str(src), "--out", str(every), "--all-egos", "--quiet"])
    ids = [s.scenario_id for s, _ in iter_scenes(every)]
    assert ids == ["DEU_Toy-1_1_T-1/ego=10", "DEU_Toy-1_1_T-1/ego=11"]


def test_sources_share_one_read_until_the_files_change(tmp_path):
    """Envs drawing from one stored folder share its scenes (a vector env of N envs holds
    one copy, read once), and a folder whose files change is read again."""
    from counterscene_env.scene.sources import SceneSource

    src = tmp_path / "src"
    src.mkdir()
    (src / "a.xml").write_text(_scenario(goal_x=90.0))
    spec = f"commonroad:{src}"
    rng = np.random.default_rng(0)
    first, second = SceneSource(spec).draw(rng), SceneSource(spec).draw(rng)
    assert first is second
    (src / "c.xml").write_text(_scenario(steps=40, name="DEU_Other-1_1_T-1"))
    drawn = {SceneSource(spec).draw(np.random.default_rng(s)).scenario_id for s in range(8)}
    assert drawn == {"DEU_Toy-1_1_T-1/ego=10", "DEU_Other-1_1_T-1/ego=10"}
