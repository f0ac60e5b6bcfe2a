"""Ego choices in real logs: which vehicles can take the ego's seat, and the runs that cycle
a few stored scenes seating another one on each pass (``--egos``)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene

from counterscene_env.scene.egos import ego_choices, with_ego
from counterscene_env.scene.shards import save_scenes
from counterscene_env.scene.sources import scenes_for
from counterscene_env.stress import StressConfig, chunks


def _street(T: int = 40):
    """Row 0 the recorded ego; 1 drives the whole log; 2 drives but leaves early; 3 parked;
    4 a pedestrian; 5 appears only after "now"; 6 overlaps row 7 at one step; 8 drives a
    shorter log than row 1 (ranked after it)."""
    t = np.arange(T) * 0.1
    n = 9
    xy = np.zeros((n, T, 2))
    speeds = np.zeros((n, T))
    valid = np.ones((n, T), bool)
    for row, (x0, y, v) in enumerate(
        [
            (0, 0, 10),
            (-30, 4, 9),
            (40, 8, 8),
            (20, 12, 0),
            (5, 16, 1.4),
            (60, 20, 7),
            (100, 24, 6),
            (100, 24, 0),
            (-60, 28, 5),
        ]
    ):
        xy[row] = np.stack([x0 + v * t, np.full(T, float(y))], -1)
        speeds[row] = v
    valid[7, :] = False
    valid[7, 25] = True  # row 7 sits on row 6's box at step 25 only
    xy[7, 25] = xy[6, 25]
    valid[5, :15] = False  # appears after "now" (step 12)
    valid[8, 35:] = False
    valid[2, 14:] = False  # present around now, then gone: fewer valid steps
    types = np.array(["vehicle"] * 4 + ["pedestrian"] + ["vehicle"] * 4)
    return make_scene(
        xy, speeds=speeds, valid=valid, agent_types=types, current_index=12, scenario_id="street"
    )


def test_ego_choices_are_moving_vehicles_present_now_that_overlap_no_one():
    scene = _street()
    # Recorded ego first; then most valid steps: 1 (40), 8 (35), 2 (14). Not: 3 parked,
    # 4 a pedestrian, 5 absent before now, 6 and 7 overlap at step 25 (7 is also parked).
    assert ego_choices(scene) == [0, 1, 8, 2]
    seated = with_ego(scene, 8)
    assert seated.ego_index == 8 and seated.scenario_id == "street/ego=a8"
    assert seated.metadata["ego"] == "a8" and scene.ego_index == 0  # the input is untouched
    assert with_ego(seated, 1).scenario_id == "street/ego=a1"


def test_a_run_cycling_few_scenes_seats_the_next_choice_on_each_pass(tmp_path):
    path = tmp_path / "street.npz"
    save_scenes([_street()], path)
    ids = [s.scenario_id for s in scenes_for(str(path), 6, 0, egos=3)]
    assert ids == ["street", "street/ego=a1", "street/ego=a8"] * 2
    assert [s.scenario_id for s in scenes_for(str(path), 3, 0)] == ["street"] * 3
    # More egos asked than the scene has: its choices repeat.
    ids = [s.scenario_id for s in scenes_for(str(path), 6, 0, egos=9)]
    assert ids[3:] == ["street/ego=a2", "street", "street/ego=a1"]
    # A stress run's batches (and so a resumed or parallel run) see the same scenes.
    config = StressConfig(str(path), episodes=4, batch=3, egos=2)
    got = [s.scenario_id for _, scenes in chunks(config, []) for s in scenes]
    assert got == ["street", "street/ego=a1"] * 2
    with pytest.raises(ValueError, match="egos must be >= 1"):
        StressConfig(str(path), episodes=4, egos=0)


def test_a_run_can_seat_only_scenes_with_enough_log_after_their_start(tmp_path):
    # "street" has 2.7 s after now (40 steps, now at 12); "stub" 0.2 s; min_future skips the
    # stub, and the ego choices still cycle over the scenes kept.
    stub = _street().time_slice(0, 15).replace(scenario_id="stub")
    path = tmp_path / "logs.npz"
    save_scenes([stub, _street()], path)
    ids = [s.scenario_id for s in scenes_for(str(path), 3, 0, egos=2)]
    assert ids == ["stub", "street", "stub/ego=a1"]
    ids = [s.scenario_id for s in scenes_for(str(path), 3, 0, egos=2, min_future=1.0)]
    assert ids == ["street", "street/ego=a1", "street"]
    config = StressConfig(str(path), episodes=2, batch=2, min_future=2.7)
    assert [s.scenario_id for _, scenes in chunks(config, []) for s in scenes] == ["street"] * 2
    with pytest.raises(ValueError, match="min_future = 3 s"):
        next(scenes_for(str(path), 1, 0, min_future=3.0))
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="min_future must be"):
            StressConfig(str(path), episodes=2, min_future=bad)
    # A generated road records a whole episode: the setting does not apply to it.
    assert StressConfig("merge", episodes=2, min_future=3.0).min_future == 0.0
