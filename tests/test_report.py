"""Stress reports and comparisons: the files a user opens, the order of the worst episodes,
the intervals and paired tests, the rerun command, videos, and refusals of bad input."""

from __future__ import annotations

import copy
import json
import re
import shlex
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from conftest import crash_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from counterscene_env import metrics
from counterscene_env.cli import _parser, main
from counterscene_env.cli.flags import parsed_fields
from counterscene_env.report import compare_runs, load_run, write_report
from counterscene_env.report.compare import to_json
from counterscene_env.report.document import interval
from counterscene_env.report.ranking import worst_episodes
from counterscene_env.report.stats import group_mean, mcnemar_exact, mean, paired_rate
from counterscene_env.report.tables import horizon_table
from counterscene_env.sim import SimConfig
from counterscene_env.stress import EpisodeLog, StressConfig, run_identity, summarize

# ---------------------------------------------------------------------- synthetic runs


@pytest.fixture(scope="module")
def template() -> dict:
    """One real episode record (metrics of a scene with a collision), to vary."""
    scene = crash_scene()
    rec = metrics.evaluate_scene(scene, scene, adversary=1)
    rec.update(
        adversary_type="following",
        adversary_tier=1,
        danger_score=1.0,
        fallback=None,
        replans=4,
        replan_seconds=0.4,
        seconds=1.0,
    )
    return rec


def episode(template: dict, i: int, **values) -> dict:
    """Episode i of a synthetic run (seed 100 + i, scene 1000 + i); ``values`` override
    fields; ``cr`` and ``ade`` also set the per-second CR and ADE."""
    rec = copy.deepcopy(template)
    rec.update(
        episode=i, seed=100 + i, scene_seed=1000 + i, scenario_id=f"intersection/seed={1000 + i}"
    )
    ade = values.pop("ade", None)
    for row in rec["per_second"].values():
        row["CR"] = values.get("cr", rec["cr"])
        if ade is not None:
            row["ADE"] = ade
    rec.update(values)
    return rec


def write_run(
    directory: Path,
    records: list[dict],
    planner: str = "idm",
    guidance: str = "full",
    scenario: str = "intersection",
    **run,
) -> Path:
    """A run directory written by the stress writers themselves (run.json,
    episodes.jsonl, metrics.json); ``run``: further ``StressConfig`` fields."""
    config = StressConfig(
        scenario,
        episodes=len(records),
        seed=100,
        planner=planner,
        sim=SimConfig(guidance=guidance),
        batch=2,
        **run,
    )
    log = EpisodeLog(
        directory, run_identity(config, "default"), summarize=lambda r: summarize(r, config)
    )
    log.append(records)
    return directory


def mixed(template: dict) -> list[dict]:
    """Eight episodes of known severity (see test_worst_episodes_are_ranked_by_severity)."""
    return [
        episode(template, 0, cr=0.0, cr_ego_adversary=0.0, min_ttc=2.0, min_clearance_adversary=3.0),
        episode(template, 1, cr=1.0, cr_ego_adversary=0.0, min_ttc=0.0, min_clearance_adversary=4.0),
        episode(template, 2, cr=0.0, cr_ego_adversary=0.0, min_ttc=float("inf"), min_clearance_adversary=9.0),
        episode(template, 3, cr=1.0, cr_ego_adversary=1.0, min_ttc=0.0, min_clearance_adversary=0.0),
        episode(template, 4, cr=0.0, cr_ego_adversary=0.0, min_ttc=0.5, min_clearance_adversary=1.0),
        episode(template, 5, cr=0.0, cr_ego_adversary=0.0, min_ttc=0.5, min_clearance_adversary=0.2),
        episode(
            template, 6, cr=0.0, cr_ego_adversary=float("nan"), min_ttc=1.0,
            min_clearance_adversary=float("nan"), adversary_id=None, adversary_type=None,
            fallback="no candidate",
        ),
        episode(template, 7, cr=0.0, cr_ego_adversary=0.0, min_ttc=2.0, min_clearance_adversary=3.0),
    ]  # fmt: skip


# ---------------------------------------------------------------------- the report


def test_report_files_and_a_self_contained_page(template, tmp_path):
    run = write_run(tmp_path / "run", mixed(template))
    page = write_report(run, videos=0, progress=False)
    assert page == run / "report.html"
    for name in ("report.md", "command.txt"):
        assert (run / name).is_file()
    for png in (
        "cr_hbr_by_second",
        "ade_fde_by_second",
        "hist_min_ttc",
        "hist_min_clearance",
        "hist_ego_deceleration",
    ):
        assert (run / "plots" / f"{png}.png").stat().st_size > 1000
    text = page.read_text()
    # Opens offline: no remote address, no script, every image inline.
    assert not re.search(r"https?://|//cdn|<script|<link", text, re.IGNORECASE)
    images = re.findall(r'<img src="([^"]*)"', text)
    assert len(images) == 5 and all(s.startswith("data:image/png;base64,") for s in images)
    md = (run / "report.md").read_text()
    assert "| horizon | ADE [m] | FDE [m] | ORR [%] | HBR [%] | CR [%] |" in md
    for group in ("1-4s", "5-7s", "8-10s"):
        assert f"| {group} |" in md
    assert "Wilson" in md and "bootstrap" in md
    assert "No videos were asked for" in md


def test_records_without_a_plotted_field_get_a_report_that_names_it(template, tmp_path):
    older = [{k: v for k, v in r.items() if k != "ego_peak_deceleration"} for r in mixed(template)]
    run = write_run(tmp_path / "run", older)
    (run / "plots").mkdir()
    (run / "plots" / "hist_ego_deceleration.png").write_bytes(b"an earlier report's")
    write_report(run, videos=0, progress=False)
    assert not (run / "plots" / "hist_ego_deceleration.png").exists()
    assert "'ego_peak_deceleration'" in (run / "report.md").read_text()


def test_the_table_matches_metrics_json_and_rates_carry_wilson_intervals(template, tmp_path):
    run = load_run(write_run(tmp_path / "run", mixed(template)))
    # Each episode's timings, kept apart on disk, come back with its record.
    assert all(r["seconds"] == 1.0 and r["replan_seconds"] == 0.4 for r in run.records)
    table = horizon_table(run.records)
    for group, row in run.summary["horizons"].items():
        for key, value in row.items():
            est = table[group][key]
            if value is None:  # NaN in JSON: nothing measured (FDE past a 3.9 s rollout)
                assert np.isnan(est.value)
                continue
            assert est.value == pytest.approx(value)
            assert est.low <= est.value <= est.high
    md = write_report(run.directory, videos=0, progress=False).with_name("report.md").read_text()
    lo, hi = metrics.wilson_interval(2, 8)  # 2 collisions in 8 episodes
    assert f"| 25 [{100 * lo:.3g}, {100 * hi:.3g}] | 8 |" in md


def test_worst_episodes_are_ranked_by_severity(template, tmp_path):
    records = mixed(template)
    # Collision with the adversary, other collision, then by min TTC, then by clearance to
    # the adversary (the 0.2 m near miss before the 1 m one), no adversary after a
    # clearance, no projected conflict last.
    order = [3, 1, 5, 4, 6, 0, 7, 2]
    assert [r["episode"] for r in worst_episodes(records)] == order
    assert [r["episode"] for r in worst_episodes(records, 3)] == order[:3]
    run = write_run(tmp_path / "run", records)
    md = (write_report(run, videos=0, progress=False)).with_name("report.md").read_text()
    section = md[md.index("## Worst episodes") :]
    ranked = [int(m) for m in re.findall(r"^\| \d+ \| (\d+) \|", section, re.MULTILINE)]
    assert ranked == order
    assert "collision with the adversary" in section


def test_command_txt_reruns_the_same_run(template, tmp_path):
    run = write_run(tmp_path / "run", mixed(template), guidance="no_jerk")
    write_report(run, videos=0, progress=False)
    line = (run / "command.txt").read_text().splitlines()[-1]
    argv = shlex.split(line)
    assert argv[:2] == ["counterscene", "stress"]
    args = _parser().parse_args(argv[1:])
    ident = json.loads((run / "run.json").read_text())
    assert (args.scenario, args.seed, args.planner, args.batch, args.model) == (
        ident["scenario"], ident["seed"], ident["planner"], ident["batch"], ident["model"]
    )  # fmt: skip
    assert args.episodes == 8 and args.out == str(run) and args.resume
    assert asdict(SimConfig(**parsed_fields(args, SimConfig))) == ident["sim"]


def test_command_txt_keeps_the_runs_stored_scene_filter_and_candidate_rollouts(
    template, tmp_path, generated
):
    """A run on stored scenes with --min-future and --rollouts: the rebuilt command has both,
    so that it resumes the run rather than being refused as another one."""
    from counterscene_env.scene.shards import save_scenes

    shard = tmp_path / "scenes.npz"
    save_scenes([generated["merge"]], shard)
    run = write_run(
        tmp_path / "run", mixed(template), scenario=str(shard), min_future=1.5, rollouts=3
    )
    write_report(run, videos=0, progress=False)
    args = _parser().parse_args(shlex.split((run / "command.txt").read_text().splitlines()[-1])[1:])
    assert (args.min_future, args.rollouts) == (1.5, 3)
    ident = json.loads((run / "run.json").read_text())
    rebuilt = StressConfig(
        args.scenario, args.episodes, args.seed, args.planner,
        SimConfig(**parsed_fields(args, SimConfig)), args.batch, args.egos,
        args.min_future, args.rollouts,
    )  # fmt: skip
    assert run_identity(rebuilt, args.model) == ident


def test_a_stopped_run_gets_a_report_of_its_finished_episodes(template, tmp_path):
    run = write_run(tmp_path / "run", mixed(template)[:4])
    with open(run / "episodes.jsonl", "a") as f:
        f.write('{"scenario_id": "intersection/seed=1004", "rollout')  # killed mid-line
    summary = json.loads((run / "metrics.json").read_text())
    summary.update(complete=False, episodes_requested=8)
    (run / "metrics.json").write_text(json.dumps(summary))
    md = write_report(run, videos=0, progress=False).with_name("report.md").read_text()
    assert "unfinished: 4 of 8 episodes" in md
    assert "cut short by a kill" in md
    assert (run / "episodes.jsonl").read_text().endswith("rollout")  # the reader wrote nothing


def test_without_imageio_the_report_says_how_to_get_videos(template, tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "imageio" else real(name, *a)
    )
    run = write_run(tmp_path / "run", mixed(template))
    md = write_report(run, videos=2, progress=False).with_name("report.md").read_text()
    assert 'pip install "counterscene-env[video]"' in md
    assert not (run / "videos").exists()


def test_sb3_runs_are_reported_without_videos(template, tmp_path):
    policy = tmp_path / "policy.zip"
    policy.write_bytes(b"not read")
    run = write_run(tmp_path / "run", mixed(template), planner=f"sb3:{policy}")
    md = write_report(run, videos=2, progress=False).with_name("report.md").read_text()
    assert "not re-simulated for videos" in md


class _Brake:
    """A planner given from Python: always brakes hard."""

    name = "brake"
    replays_log = False

    def reset(self, scene, seed):
        pass

    def act(self, state):
        return np.array([-5.0, 0.0])


def test_a_python_planners_run_is_reported_as_its_own_not_the_configs(generated, tmp_path):
    """``run_episodes(planner_factory=...)`` with a log: the records name the planner, and
    the report shows it (not the config's ``idm``), makes no IDM videos of it and says that
    no command reruns it. A planner whose action is not two numbers is refused by name."""
    from counterscene_env.scene.shards import save_scenes
    from counterscene_env.stress import run_episodes
    from counterscene_env.world_model import load_model

    shard = save_scenes([generated["merge"]], tmp_path / "s.npz")
    config = StressConfig(str(shard), episodes=1, sim=SimConfig(duration=0.5, num_samples=2))
    log = EpisodeLog(
        tmp_path / "run", run_identity(config, "default"), summarize=lambda r: summarize(r, config)
    )
    model = load_model()
    run_episodes(model, config, planner_factory=_Brake, log=log, progress=False)
    md = write_report(tmp_path / "run", videos=1, progress=False).with_name("report.md")
    text = md.read_text()
    assert "ego planner: python:brake" in text and "given from Python" in text
    assert not (tmp_path / "run" / "videos").exists()
    assert "planner_factory" in (tmp_path / "run" / "command.txt").read_text()

    class Scalar(_Brake):
        def act(self, state):
            return -5.0  # would be read as -5 rad of steering too

    with pytest.raises(ValueError, match=r"planner 'brake': act\(\) must return .* shape \(2,\)"):
        run_episodes(model, config, planner_factory=Scalar, progress=False)


def _files(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` with its bytes."""
    return {
        str(p.relative_to(directory)): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def test_a_report_stopped_while_filming_leaves_the_directory_as_it_was(
    template, tmp_path, monkeypatch
):
    """Ctrl-C (or a crash) while the worst episodes are re-simulated: no command.txt, plot
    or half a report appears; it used to leave command.txt and the plots behind."""
    run = write_run(tmp_path / "run", mixed(template))
    before = _files(run)

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("counterscene_env.report.replay.replay_batch", stopped)
    with pytest.raises(KeyboardInterrupt):
        write_report(run, videos=2, progress=False)
    assert _files(run) == before
    # An earlier report stays whole too: the rebuilt one never half-replaces it.
    write_report(run, videos=0, progress=False)
    # One more episode (a resumed run): the report of 9 episodes would differ from the last.
    identity = json.loads((run / "run.json").read_text())
    EpisodeLog(run, identity, resume=True).append([episode(template, 8, cr=1.0, min_ttc=0.0)])
    earlier = _files(run)
    with pytest.raises(KeyboardInterrupt):
        write_report(run, videos=2, progress=False)
    assert _files(run) == earlier


def test_metrics_json_keys_and_its_two_ttc_figures_are_documented(template, tmp_path):
    """Every key of metrics.json is described in docs/reports.md, "metrics.json"; the two TTC
    figures are what it says: the mean over the episodes with a projected conflict, and
    overall's median over every episode, no conflict (inf) included."""
    ttc = [1.0, 3.0, float("inf"), float("inf"), float("inf")]
    records = [episode(template, i, min_ttc=t) for i, t in enumerate(ttc)]
    summary = json.loads((write_run(tmp_path / "run", records) / "metrics.json").read_text())
    assert summary["mean_min_ttc"] == 2.0 and summary["episodes_without_ttc_conflict"] == 3
    assert summary["overall"]["min_ttc"] is None  # the median is inf: written as null
    records[2]["min_ttc"] = records[3]["min_ttc"] = 0.5
    summary = json.loads((write_run(tmp_path / "run2", records) / "metrics.json").read_text())
    assert summary["overall"]["min_ttc"] == 1.0 and summary["mean_min_ttc"] == 1.25
    docs = (Path(__file__).parents[1] / "docs" / "reports.md").read_text()
    section = docs[docs.index("## metrics.json") :]
    section = section[: section.index("\n## ", 1)]
    undocumented = [k for k in summary if f"`{k}`" not in section]
    undocumented += [k for k in summary["overall"] if k not in section]
    assert not undocumented, f"metrics.json keys missing from docs/reports.md: {undocumented}"
    mean_row = next(line for line in section.splitlines() if line.startswith("| `mean_min_ttc`"))
    assert "mean over the episodes with a projected conflict" in mean_row
    median_row = next(line for line in section.splitlines() if "`overall.min_ttc`" in line[:20])
    assert "median over every episode" in median_row and "inf included" in median_row


# ---------------------------------------------------------------------- compare


def paired_runs(template, tmp_path, flips_up: int, flips_down: int, ade_shift: float):
    """Two runs of the same 40 episodes: B flips ``flips_up`` of A's safe episodes to a
    collision and ``flips_down`` of its collisions to safe, and shifts ADE."""
    rng = np.random.default_rng(0)
    crash = np.zeros(40)
    crash[:10] = 1.0
    ade_a = rng.uniform(0.5, 1.5, 40)
    b_crash = crash.copy()
    b_crash[10 : 10 + flips_up] = 1.0
    b_crash[:flips_down] = 0.0
    ade_b = ade_a + ade_shift + rng.normal(0, 0.05, 40)
    a = [episode(template, i, cr=crash[i], ade=ade_a[i]) for i in range(40)]
    b = [episode(template, i, cr=b_crash[i], ade=ade_b[i]) for i in range(40)]
    return (
        write_run(tmp_path / "a", a, guidance="none"),
        write_run(tmp_path / "b", b, guidance="full"),
    )


def test_compare_finds_a_real_difference(template, tmp_path):
    a, b = paired_runs(template, tmp_path, flips_up=15, flips_down=0, ade_shift=0.5)
    c = compare_runs([a, b])
    assert c.labels == ["a (guidance=none)", "b (guidance=full)"]
    (p,) = c.paired
    assert p.shared == 40
    cr = p.metrics["cr"]
    assert cr.difference == pytest.approx(15 / 40)
    assert (cr.a_only, cr.b_only) == (0, 15) and cr.p_value == pytest.approx(2 * 0.5**15)
    assert cr.significant and p.metrics["ade"].significant
    assert p.metrics["ade"].low > 0.4
    out = to_json(c)["paired"][0]["metrics"]
    assert out["cr"]["verdict"].startswith("higher than a (guidance=none), outside the noise")


def test_compare_calls_a_null_difference_noise(template, tmp_path):
    a, b = paired_runs(template, tmp_path, flips_up=2, flips_down=2, ade_shift=0.0)
    c = compare_runs([a, b])
    (p,) = c.paired
    assert p.metrics["cr"].difference == 0.0 and p.metrics["cr"].p_value == 1.0
    assert not p.metrics["cr"].significant and not p.metrics["ade"].significant
    assert p.metrics["ade"].low < 0 < p.metrics["ade"].high
    verdicts = to_json(c)["paired"][0]["metrics"]
    assert all(v["verdict"].startswith("inside the noise") for v in verdicts.values())


@settings(max_examples=200, deadline=None)
@given(a_only=st.integers(0, 60), b_only=st.integers(0, 60), same=st.integers(0, 60))
def test_a_paired_rate_interval_excludes_0_exactly_when_the_test_passes(a_only, b_only, same):
    """A table prints "inside the noise" beside an interval: the two must agree. (The
    bootstrap interval of 5 of 20 against 0 of 20 was [-45, -10] points beside p = 0.0625.)"""
    a = [1.0] * a_only + [0.0] * b_only + [1.0] * same
    b = [0.0] * a_only + [1.0] * b_only + [1.0] * same
    if not a:
        return
    d = paired_rate(a, b)
    assert d.low <= d.difference <= d.high
    assert d.significant == (d.low > 0 or d.high < 0)
    assert d.significant == (mcnemar_exact(a_only, b_only) < 0.05)


def test_paired_rate_of_the_audit_case_and_of_many_pairs():
    d = paired_rate([1] * 5 + [0] * 15, [0] * 20)
    assert not d.significant and d.low < 0 < d.high and d.difference == -0.25
    assert paired_rate([1] * 6 + [0] * 14, [0] * 20).high < 0  # p = 0.031
    assert d.low < d.difference  # the chance in how many pairs disagree widens it too
    none, one = paired_rate([0] * 20, [0] * 20), paired_rate([1] + [0] * 19, [0] * 20)
    assert none.low < 0 < none.high and one.high - one.low >= none.high - none.low
    big = paired_rate([1.0] * 700 + [0.0] * 1300, [0.0] * 700 + [1.0] * 1300)  # overflowed
    assert big.significant and 0.25 < big.low < big.difference < big.high < 0.35


def test_mcnemar_exact():
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(3, 3) == 1.0
    assert mcnemar_exact(0, 6) == pytest.approx(2 / 64)
    assert mcnemar_exact(1, 9) == mcnemar_exact(9, 1) == pytest.approx(2 * 11 / 1024)


def test_a_mean_over_one_episode_has_no_interval_rather_than_a_zero_width_one():
    one = mean([6.73, float("nan")])
    assert one.value == 6.73 and one.n == 1 and np.isnan(one.low) and np.isnan(one.high)
    assert interval(one, "m") == "6.73 (no interval: 1 episode)"
    two = mean([1.0, 3.0])
    assert two.low < two.value < two.high and interval(two, "m") == "2 [1, 3]"
    grouped = group_mean(np.array([[1.0, 2.0], [np.nan, np.nan]]))
    assert grouped.value == 1.5 and grouped.n == 1 and np.isnan(grouped.low)


def test_compare_cli_table_json_and_plots(template, tmp_path, capsys):
    a, b = paired_runs(template, tmp_path, flips_up=15, flips_down=0, ade_shift=0.5)
    assert main(["compare", str(a), str(b), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [r["label"] for r in result["runs"]] == ["a (guidance=none)", "b (guidance=full)"]
    assert set(result["metrics"]) == {
        "cr",
        "cr_ego_adversary",
        "cr_non_ego_new",
        "hbr_ego",
        "orr",
        "ade",
    }
    out = tmp_path / "cmp"
    assert main(["compare", str(a), str(b), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| episode CR (ego collides) | % |" in text and "outside the noise" in text
    for key in result["metrics"]:
        assert (out / "plots" / f"compare_{key}.png").is_file()
    page = (out / "compare.html").read_text()
    assert "<script" not in page and "http" not in page
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("keep me")
    assert main(["compare", str(a), str(b), "--out", str(a_file)]) == 1
    assert "is a file, not a directory" in capsys.readouterr().err
    assert a_file.read_text() == "keep me"
    with pytest.raises(TypeError, match="a list of run directories"):
        compare_runs(str(a))
    with pytest.raises(ValueError, match="videos must be >= 0"):
        write_report(a, videos=-1)


def test_compare_runs_without_shared_episodes_say_so(template, tmp_path):
    a = write_run(tmp_path / "a", mixed(template))
    other = [dict(r, seed=r["seed"] + 500) for r in mixed(template)]
    b = write_run(tmp_path / "b", other)
    c = compare_runs([a, b])
    assert c.paired[0].shared == 0 and c.paired[0].metrics == {}
    from counterscene_env.report.compare import document
    from counterscene_env.report.markdown import render

    assert "b: no episode in common with a" in render(document(c))


def test_compare_says_a_run_is_unfinished_in_every_output(template, tmp_path, capsys):
    """A stopped run in a comparison is named at the top of the text, the markdown and the
    JSON, with how many of its episodes ran; it used to be compared in silence."""
    a = write_run(tmp_path / "a", mixed(template))
    b = write_run(tmp_path / "b", mixed(template)[:3], guidance="none")
    summary = json.loads((b / "metrics.json").read_text())
    summary.update(complete=False, episodes_requested=20)  # as a stopped run's summary says
    (b / "metrics.json").write_text(json.dumps(summary))
    warning = "run b (guidance=none) is unfinished: 3 of 20 episodes"
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    text = capsys.readouterr().out
    assert f"Warning: {warning}" in text.split("| metric |")[0]  # above the table
    assert "b (guidance=none): " in text and "3 of 20 episodes (unfinished)" in text
    assert warning in (tmp_path / "cmp" / "compare.md").read_text()
    assert warning in (tmp_path / "cmp" / "compare.html").read_text()
    assert main(["compare", str(a), str(b), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["warnings"] == [warning]
    assert [(r["complete"], r["episodes"], r["episodes_requested"]) for r in out["runs"]] == [
        (True, 8, 8),
        (False, 3, 20),
    ]
    # Finished runs get no warning; one without metrics.json cannot say, and says so.
    (b / "metrics.json").unlink()
    c = compare_runs([a, b])
    assert c.warnings == [
        "run b (guidance=none) has no metrics.json: whether its 3 episodes are the whole run "
        "is unknown"
    ]
    assert compare_runs([a, write_run(tmp_path / "c", mixed(template))]).warnings == []


def test_compare_labels_show_defaults_not_none(template, tmp_path):
    """run.json leaves rollouts, egos and min_future out at their defaults, and a
    closed-loop None means the model's own default: labels spell both out (they read
    ``rollouts=None``); a setting an older run.json lacks is its default, no difference."""
    a = write_run(tmp_path / "a", mixed(template))
    b = write_run(tmp_path / "b", mixed(template), rollouts=3)
    assert compare_runs([a, b]).labels == ["a (rollouts=1)", "b (rollouts=3)"]
    c = write_run(tmp_path / "c", mixed(template))
    ident = json.loads((c / "run.json").read_text())
    ident["sim"]["sampler"] = "ddim"
    del ident["sim"]["memory_limit_gb"]  # a run from before the setting existed
    (c / "run.json").write_text(json.dumps(ident))
    assert compare_runs([a, c]).labels == ["a (sampler=model default)", "c (sampler=ddim)"]
    # A run's own report shows them so too, never "None".
    from counterscene_env.report.run_report import what_was_run

    items = what_was_run(load_run(a), "cmd")[1].items
    settings = next(i for i in items if "other settings" in i)
    assert "None" not in settings and "sampler=model default" in settings
    assert "memory_limit_gb=half of memory" in settings
    labels = compare_runs([a, b, c]).labels
    assert not any("None" in label for label in labels)


# ---------------------------------------------------------------------- bad input


def test_bad_run_directories_are_refused_with_the_file_named(template, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match=r"episodes\.jsonl"):
        load_run(empty)
    run = write_run(tmp_path / "run", mixed(template))
    with pytest.raises(FileNotFoundError, match=r"is a file: give the run's directory"):
        load_run(run / "episodes.jsonl")
    lines = (run / "episodes.jsonl").read_text().splitlines()
    broken = json.loads(lines[1])
    del broken["min_ttc"]
    lines[1] = json.dumps(broken)
    (run / "episodes.jsonl").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"episodes.jsonl: line 2 has no field 'min_ttc'"):
        load_run(run)
    with pytest.raises(ValueError, match="at least two"):
        compare_runs([run])
    with pytest.raises(ValueError, match="more than once"):
        compare_runs([run, run / "."])
    assert main(["report", str(empty)]) == 1
    assert "episodes.jsonl" in capsys.readouterr().err
    assert main(["compare", str(empty), str(run)]) == 1
    assert "episodes.jsonl" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda r: r.update(cr="yes"), "line 3: field 'cr' is \"yes\", not a number or null"),
        (lambda r: r.update(min_ttc=True), "line 3: field 'min_ttc' is true, not a number"),
        (lambda r: r.update(seed="103"), "line 3: field 'seed' is \"103\", not a whole number"),
        (
            lambda r: r["per_second"]["2"].update(CR="x"),
            "line 3: field per_second['2']['CR'] is \"x\", not a number or null",
        ),
        (lambda r: r.update(per_second=[1]), "line 3: field 'per_second' is [1], not an object"),
    ],
)
def test_a_wrongly_typed_field_is_named_by_file_line_and_field(
    template, tmp_path, capsys, change, message
):
    """A record with a field of the wrong type is refused as the file is read, naming the
    file, the line and the field (it ended in numpy's "could not convert string to float"),
    by report, compare and a resumed stress run alike, and the report writes nothing."""
    run = write_run(tmp_path / "run", mixed(template))
    lines = (run / "episodes.jsonl").read_text().splitlines()
    bad = json.loads(lines[2])
    change(bad)
    lines[2] = json.dumps(bad)
    (run / "episodes.jsonl").write_text("\n".join(lines) + "\n")
    before = _files(run)
    expected = f"{run / 'episodes.jsonl'}: {message}"
    with pytest.raises(ValueError, match=re.escape(expected)):
        load_run(run)
    assert main(["report", str(run), "--videos", "0"]) == 1
    assert expected in capsys.readouterr().err
    assert _files(run) == before  # no command.txt, no plots
    good = write_run(tmp_path / "good", mixed(template))
    assert main(["compare", str(good), str(run)]) == 1
    assert expected in capsys.readouterr().err
    identity = json.loads((run / "run.json").read_text())
    with pytest.raises(ValueError, match=re.escape(expected)):
        EpisodeLog(run, identity, resume=True)


def test_a_run_json_of_the_wrong_shape_is_named(template, tmp_path, capsys):
    run = write_run(tmp_path / "run", mixed(template))
    ident = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**ident, "sim": ["full"]}))
    before = _files(run)
    assert main(["report", str(run)]) == 1
    assert f"{run / 'run.json'}: field 'sim' is ['full'], not an object" in capsys.readouterr().err
    (run / "metrics.json").write_text("[]")
    with pytest.raises(ValueError, match=re.escape(f"{run / 'metrics.json'}: list, not a JSON")):
        load_run(run)
    assert _files(run) == {**before, "metrics.json": b"[]"}


def test_a_wrongly_typed_timing_or_python_record_is_named(template, tmp_path):
    run = write_run(tmp_path / "run", mixed(template))
    path = run / "episode_timings.jsonl"
    lines = path.read_text().splitlines()
    lines[1] = json.dumps({"episode": 1, "seconds": "fast", "replan_seconds": 0.4})
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=re.escape(f"{path}: line 2: field 'seconds' is")):
        load_run(run)
    # Records handed over from Python (not read from a file) are named by episode.
    from counterscene_env.report.tables import EPISODE_METRICS

    records = [episode(template, 0), episode(template, 1, cr="yes")]
    with pytest.raises(ValueError, match="episode 1: field 'cr' is 'yes', not a number"):
        EPISODE_METRICS["cr"].estimate(records)


# ---------------------------------------------------------------------- videos of a real run


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_videos_of_the_worst_episodes_replay_the_recorded_run(generated, tmp_path, capsys):
    pytest.importorskip("imageio")
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v3 as iio

    from counterscene_env.scene.shards import save_scenes

    shard = tmp_path / "scenes.npz"
    save_scenes([generated["intersection"], generated["merge"]], shard)
    run = tmp_path / "run"
    code = main(
        ["stress", "--scenario", str(shard), "--episodes", "2", "--duration", "1",
         "--samples", "2", "--batch", "2", "--quiet", "--out", str(run)]
    )  # fmt: skip
    assert code == 0
    capsys.readouterr()
    assert main(["report", str(run), "--videos", "2", "--quiet"]) == 0
    for i in (0, 1):
        gif = run / "videos" / f"episode_{i:04d}.gif"
        assert (run / "videos" / f"episode_{i:04d}.mp4").stat().st_size > 0
        frames = iio.imread(gif, index=None)
        assert frames.shape[0] == 11  # "now" and ten 0.1 s steps
    md = (run / "report.md").read_text()
    assert "(videos/episode_0000.mp4)" in md and "(videos/episode_0001.gif)" in md
    assert "differs from the record" not in md  # the replays are the recorded episodes
    # Rebuilt with one video, and with a note of the user's in videos/: the other episode's
    # video goes (the report no longer links it), the note stays.
    (run / "videos" / "notes.txt").write_text("mine")
    assert main(["report", str(run), "--videos", "1", "--quiet"]) == 0
    assert sorted(p.name for p in (run / "videos").iterdir()) == [
        f"episode_{worst:04d}.{ext}"
        for worst in [int(re.search(r"videos/episode_(\d+)\.mp4", md).group(1))]
        for ext in ("gif", "mp4")
    ] + ["notes.txt"]


def test_a_run_scored_by_older_metric_definitions_is_not_resumed_or_compared_unnoticed(
    template, tmp_path
):
    """Metric definitions change (HBR read along the path since 3 Dec 2026): a run begun
    before, whose run.json has no ``metrics_version``, is refused on resume with the reason,
    and a comparison with it warns that the rates are not comparable."""
    old = write_run(tmp_path / "old", mixed(template))
    ident = json.loads((old / "run.json").read_text())
    assert ident.pop("metrics_version") == metrics.METRICS_VERSION
    (old / "run.json").write_text(json.dumps(ident))
    config = StressConfig("intersection", episodes=12, seed=100, planner="idm", batch=2)
    with pytest.raises(ValueError, match="another definition of the metrics"):
        EpisodeLog(old, run_identity(config, "default"), resume=True)
    new = write_run(tmp_path / "new", mixed(template))
    c = compare_runs([old, new])
    assert any("different definitions of the metrics" in w for w in c.warnings)
    assert c.labels == ["old", "new"]  # the version is a warning, not a label
    assert compare_runs([new, write_run(tmp_path / "new2", mixed(template))]).warnings == []
