"""The research tools whose output other figures rest on (``tools/``)."""

from __future__ import annotations

import runpy
from pathlib import Path

import numpy as np
import pytest
from conftest import make_scene

ROOT = Path(__file__).resolve().parents[1]


def _run_tool(name: str, argv: list[str], monkeypatch) -> None:
    monkeypatch.setattr("sys.argv", [f"tools/{name}.py", *argv])
    runpy.run_path(str(ROOT / "tools" / f"{name}.py"), run_name="__main__")


def test_ngsim_split_holds_out_whole_map_sections_and_copies_nothing(tmp_path, monkeypatch):
    """The held-out NGSIM figures are honest only if no map section (whose files share
    vehicles) has files on both sides, and the split links the files rather than copying
    shared data."""
    src = tmp_path / "src"
    src.mkdir()
    names = [
        "USA_US101-5_1_T-1.xml",  # a held-out US-101 section ...
        "USA_US101-5_2_T-1.xml",  # ... with every one of its files
        "USA_US101-50_1_T-1.xml",  # 50 is not 5: a training section
        "USA_US101-1_1_S-1.xml",
        "USA_Peach-3_1_T-1.xml",
        "USA_Lanker-2_4_T-1.xml",
    ]
    for n in names:
        (src / n).write_text("<commonRoad/>")
    out = tmp_path / "split"
    _run_tool("ngsim_split", [str(src), str(out)], monkeypatch)
    heldout = {p.name for p in (out / "heldout").iterdir()}
    train = {p.name for p in (out / "train").iterdir()}
    assert heldout == {"USA_US101-5_1_T-1.xml", "USA_US101-5_2_T-1.xml", "USA_Peach-3_1_T-1.xml"}
    assert train == set(names) - heldout
    assert all(p.is_symlink() for p in out.rglob("*.xml"))
    # Rerunning is harmless (the links exist already).
    _run_tool("ngsim_split", [str(src), str(out)], monkeypatch)
    assert {p.name for p in (out / "heldout").iterdir()} == heldout


def test_ngsim_split_refuses_a_name_it_cannot_place_and_writes_nothing(tmp_path, monkeypatch):
    (tmp_path / "USA_US101-5_1_T-1.xml").write_text("<commonRoad/>")  # sorted first, placeable
    (tmp_path / "scenario.xml").write_text("<commonRoad/>")
    with pytest.raises(SystemExit, match=r"scenario\.xml"):
        _run_tool("ngsim_split", [str(tmp_path), str(tmp_path / "out")], monkeypatch)
    assert not (tmp_path / "out").exists()


def _selection_row(folder: Path, hits: list[int], tiers: list[int | None]) -> None:
    """A paper-tables row of episodes that hit their adversary (1) or not (0) at every second;
    ``None`` tiers are episodes with no adversary."""
    import json

    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps({"scenario": "intersection", "seed": 0}))
    lines = []
    for i, (hit, tier) in enumerate(zip(hits, tiers, strict=True)):
        per = {str(s): {"ADE": 1.0, "CR_adv": float(hit) if tier else None} for s in range(1, 11)}
        record = {"per_second": per, "adversary_tier": tier, "cr_ego_adversary": hit}
        record |= {"episode": i, "seed": i, "scenario_id": f"s{i}", "cr": hit, "hbr_ego": 0}
        record |= {"orr": 0, "min_ttc": 1.0, "min_clearance_adversary": 1.0}
        lines.append(json.dumps({**record, "adversary_id": "a" if tier else None}))
    (folder / "episodes.jsonl").write_text("\n".join(lines) + "\n")


def test_selection_horizon_mined_keeps_the_causal_rows_valid_mining_cases(
    tmp_path, monkeypatch, capsys
):
    """``--mined``: every row on the episodes where the causal selection found a conflict; the
    baseline's hit where causal had no adversary leaves the comparison."""
    _selection_row(tmp_path / "counterscene", [1, 1, 0, 0], [1, 2, 1, None])
    _selection_row(tmp_path / "ttc", [1, 0, 0, 1], [1, 1, 1, 1])
    _run_tool("selection_horizon", [str(tmp_path)], monkeypatch)
    assert "causal / best baseline (ttc): 1.00x" in capsys.readouterr().out  # 2 hits each
    _run_tool("selection_horizon", [str(tmp_path), "--mined"], monkeypatch)
    out = capsys.readouterr().out
    assert "3 of 4 episodes are valid mining cases" in out
    assert "causal / best baseline (ttc): 2.00x" in out  # 2 hits against 1


def test_early_speed_track_alone_scores_the_continued_acceleration_against_the_log():
    """The track-alone baselines behind the hypotheses table's row on recent accelerations:
    on a car that keeps accelerating, continuing its recent acceleration beats constant
    velocity, and on a car that holds its speed both are exact."""
    tool = runpy.run_path(str(ROOT / "tools" / "early_speed.py"), run_name="early_speed")
    t = np.arange(80) * 0.1
    speeds = np.stack([np.full(80, 10.0), 5.0 + 1.0 * t])  # held, and +1 m/s^2 throughout
    x = np.stack([10.0 * t, 5.0 * t + 0.5 * t**2])
    scene = make_scene(np.stack([x, np.stack([np.zeros(80), np.full(80, 4.0)])], -1), speeds=speeds)
    rows = tool["track_alone"]([scene], [(0, 30), (0, 40)], [0.5, 1.0])
    assert len(rows["recent"]) == 4  # two cars, two windows each
    np.testing.assert_allclose(rows["recent"], [0.0, 1.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(rows["next"], rows["recent"], atol=1e-9)
    held, accelerating = slice(0, None, 2), slice(1, None, 2)
    for tau in (0.0, 0.5, 1.0, "positions"):
        assert rows[tau][held].max() < 0.02  # the held speed: every baseline on the log
    cv, continued = rows[0.0][accelerating].mean(), rows[1.0][accelerating].mean()
    assert continued < 0.7 * cv  # a continuation of 1 m/s^2 over 1 s closes much of the gap
    # A window without 3 s of logged future is not scored.
    assert len(tool["track_alone"]([scene], [(0, 60)], [0.5])["recent"]) == 0


def _tool(name: str) -> dict:
    """A tool's functions, without running its ``main``."""
    return runpy.run_path(str(ROOT / "tools" / f"{name}.py"), run_name=name)


def _stress_dir(folder: Path, wall: float, cr: float = 0.0) -> None:
    """What ``stress --out`` leaves: results, timings, the command, a report, plots, videos."""
    import json

    (folder / "plots").mkdir(parents=True)
    (folder / "videos").mkdir()
    (folder / "run.json").write_text(json.dumps({"scenario": "merge", "seed": 1}))
    (folder / "episodes.jsonl").write_text(json.dumps({"episode": 0, "cr": cr}) + "\n")
    (folder / "metrics.json").write_text(json.dumps({"cr": cr, "episodes": 1}))
    timing = {"episodes": 1, "seconds_per_episode": wall, "workers": 1}
    timing |= {"wall_seconds": wall + 0.4, "wall_seconds_per_episode": wall + 0.4}
    (folder / "timings.json").write_text(json.dumps(timing))
    (folder / "episode_timings.jsonl").write_text(json.dumps({"episode": 0, "seconds": wall}))
    (folder / "command.txt").write_text(f"# rerun\ncounterscene stress --out {folder}\n")
    (folder / "report.md").write_text(f"# run\n{wall} s per episode\n")
    (folder / "report.html").write_text(f"<p>{wall}</p>")
    (folder / "plots" / "ade.png").write_bytes(bytes([137, 80, 78, 71, int(wall * 10) % 256]))
    (folder / "videos" / "episode_0000.gif").write_bytes(b"GIF89a" + bytes([int(wall) % 256]))


def test_regression_compares_the_results_of_two_stress_dirs_not_their_reports(tmp_path, capsys):
    """Two recordings of the same code differ only in wall clock, the --out path and the
    rendered report: they compare as identical; a changed result still shows."""
    compare = _tool("regression")["compare"]
    _stress_dir(tmp_path / "a" / "stress-merge", wall=1.3)
    _stress_dir(tmp_path / "b" / "stress-merge", wall=2.7)
    assert compare(tmp_path / "a", tmp_path / "b") == 0
    out = capsys.readouterr().out
    assert out.strip().endswith("IDENTICAL (timings aside)")
    assert "stress-merge/timings.json: identical" in out
    assert "report" not in out.replace("reports,", "")  # no line per rendered file
    _stress_dir(tmp_path / "c" / "stress-merge", wall=1.3, cr=1.0)
    assert compare(tmp_path / "a", tmp_path / "c") == 1
    out = capsys.readouterr().out
    assert "stress-merge/metrics.json: 1 differences" in out
    assert ".cr: 0.0 != 1.0" in out
    assert out.strip().endswith("2 files differ")


def test_diagnose_world_model_lane_stats_reads_the_lane_segments(tmp_path):
    """The ``lanes`` figures: segment lengths and widths of the scene's lanes, and logged
    positions along a lane of the window are inside it."""
    import torch

    tool = runpy.run_path(str(ROOT / "tools" / "diagnose_world_model.py"), run_name="diag")
    t = np.arange(80) * 0.1
    xy = np.stack(
        [np.stack([10 + 10 * t, np.zeros(80)], -1), np.stack([20 + 8 * t, 4 + 0 * t], -1)]
    )
    scene = make_scene(xy, speeds=np.stack([np.full(80, 10.0), np.full(80, 8.0)]))
    future = torch.zeros(1, 1, 30, 4)
    future[..., 0] = torch.linspace(0, 29, 30)  # along the window's lane, on its centre line
    lane = torch.stack([torch.linspace(0, 30, 10), torch.zeros(10)], -1)
    batch = {
        "future": future,
        "future_valid": torch.ones(1, 1, 30, dtype=torch.bool),
        "map": lane[None, None],
        "map_valid": torch.ones(1, 1, dtype=torch.bool),
        "map_widths": torch.full((1, 1), 4.0),
    }
    stats = tool["lane_stats"]([scene], batch, torch.ones(1, 1, dtype=torch.bool))
    assert stats["segment_length_p10_p50_p90"] == [20.0, 20.0, 20.0]  # 300 m lanes, 20 m cuts
    assert stats["width_p10_p50_p90"] == [4.0, 4.0, 4.0]
    assert stats["segments_within_30m_p10_p50_p90"] is not None
    assert stats["logged_positions_outside_window_lanes"] == 0.0


def test_real_logs_off_road_shares_count_only_positions_the_map_judges():
    """A cropped map says nothing beyond its extent: positions there are neither on nor off
    the road, in the share's numerator and denominator alike."""
    import dataclasses

    import shapely
    from conftest import straight_road

    factual_fit = _tool("real_logs")["factual_fit"]
    road = dataclasses.replace(straight_road(), extent=shapely.box(0, -10, 100, 10))
    t = np.arange(20) * 0.1
    on = np.stack([50 + 10 * t, np.zeros(20)], -1)  # on its lane, inside the extent
    off = np.stack([52 + 50 * t, np.full(20, 8.0)], -1)  # off the road; x > 100 from t = 1 s
    scene = make_scene(
        np.stack([on, off]), speeds=np.stack([np.full(20, 10.0), np.full(20, 50.0)]), road=road
    )
    fit = factual_fit(scene)
    assert fit["vehicle_positions_beyond_map"] == 10  # x = 102 ... 147
    assert fit["judged_vehicle_positions"] == 20 + 10
    assert fit["vehicle_off"] == 10  # the off-road car while the map still covers it
    assert fit["judged_moving_positions"] == 30 and fit["moving_off"] == 10


def test_paired_ade_gives_a_one_scene_group_no_interval(capsys):
    group_line = _tool("paired_ade")["group_line"]
    rng = np.random.default_rng(0)
    one = group_line("Peach", np.array([[2.1, 2.0]]), rng, 100)
    assert one == "Peach: 1.050 [one scene: no interval] (1 scene)"
    two = group_line("US101", np.array([[2.0, 2.0], [1.0, 2.0]]), rng, 100)
    assert two.startswith("US101: 0.750 [") and two.endswith("(2 scenes)")


def test_paired_ade_refuses_a_model_named_twice(monkeypatch, capsys):
    """Results are per model name: a repeated one would be compared with itself silently."""
    with pytest.raises(SystemExit):
        _run_tool(
            "paired_ade", ["scenarionet:/nowhere", "default", "runs/a", "default"], monkeypatch
        )
    assert "model given more than once: default" in capsys.readouterr().err


def test_stress_custom_planner_counts_an_episode_without_adversary_as_no_collision():
    """Every episode a fallback: the example prints the summary's ego-adversary CR, 0 as
    ``counterscene stress`` does, not NaN."""
    import math

    from counterscene_env.stress import StressConfig, summarize

    example = runpy.run_path(str(ROOT / "examples" / "stress_custom_planner.py"), run_name="ex")
    record = {"per_second": {}, "cr": 0.0, "cr_ego_adversary": math.nan, "hbr_ego": 0.5}
    record |= {"orr": 0.0, "min_ttc": math.inf, "min_clearance_adversary": math.nan}
    record |= {"adversary_id": None, "fallback": "no conflict", "rollout_s": 10.0}
    config = StressConfig(scenario="intersection", episodes=2)
    records = [{**record, "episode": i, "seed": i, "scenario_id": f"s{i}"} for i in range(2)]
    line = example["summary_line"]("none", summarize(records, config))
    assert "ego-adversary CR 0.00" in line and "nan" not in line
    assert "no TTC conflict in any episode" in line
    assert "(no adversary found in 2 of 2 episodes)" in line


def test_selection_horizon_prints_no_difference_as_plus_zero(tmp_path, monkeypatch, capsys):
    _selection_row(tmp_path / "counterscene", [1, 0, 0, 0], [1, 1, 1, 1])
    _selection_row(tmp_path / "ttc", [1, 0, 0, 0], [1, 1, 1, 1])
    _run_tool("selection_horizon", [str(tmp_path), "--split"], monkeypatch)
    out = capsys.readouterr().out
    assert "causal minus it: CR +0.0 points [" in out
    assert "ADE +0.00 m [+0.00, +0.00]" in out
    assert "(+0.00 m of the gap)" in out
    assert "-0.0 " not in out and "-0.00 " not in out and "-0.00]" not in out


def test_soak_measures_growth_from_the_end_of_the_warm_up():
    """60 steps sampled every 20 with a warm-up of 6: the warm-up ends at the sample of step
    20, not at the start sample nearest to 6."""
    soak = runpy.run_path(str(ROOT / "tools" / "soak.py"), run_name="soak")["soak"]
    steps = []
    soak.__globals__["make"] = lambda kind, config: (
        lambda seed: None,
        lambda rng: steps.append(1) and False,
        lambda: None,
    )
    report = soak("single", 60, 20, 6, {})
    assert report["warmup_steps"] == 20 and len(steps) == 60
    assert [s for s, _ in report["samples"]] == [0, 20, 40, 60]
    assert report["warmup_steps"] == soak("single", 60, 20, 20, {})["warmup_steps"]
    assert soak("single", 60, 20, 100, {})["warmup_steps"] == 60  # longer than the run: the end


def test_after_contact_says_when_no_episode_hit_the_ego():
    line = _tool("after_contact")["contact_line"]
    rows = [{"hit_s": None}, {"hit_s": None}]
    assert line("causal", rows) == "causal: 2 episodes with an adversary, no episode hit the ego"
    rows = [{"hit_s": 1.0}, {"hit_s": 3.0}, {"hit_s": None}]
    assert "2 hit the ego (median first contact 2.0 s)" in line("distance", rows)
