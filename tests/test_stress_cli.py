"""`counterscene stress`: the paper's table row as JSON, per-episode records, timings apart,
errors, and runs that survive a kill (``--resume``)."""

from __future__ import annotations

import json

import pytest

from counterscene_env.cli import main
from counterscene_env.scene.shards import save_scenes

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def shard(generated, tmp_path_factory):
    path = tmp_path_factory.mktemp("stress") / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"]], path)
    return str(path)


def stress(capsys, *args):
    code = main(["stress", "--duration", "2", "--samples", "2", "--quiet", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_stress_json_summary_and_episode_records(shard, tmp_path, capsys):
    out_dir = tmp_path / "run"
    code, out, _ = stress(
        capsys, "--scenario", shard, "--episodes", "3", "--json", "--out", str(out_dir)
    )
    assert code == 0
    summary = json.loads(out)
    timings = summary.pop("timings")  # --json adds the run's timings to the summary
    assert summary["episodes"] == 3  # two scenes, cycled
    assert summary["complete"] and summary["episodes_requested"] == 3
    assert set(summary["horizons"]) == {"1-4s", "5-7s", "8-10s"}
    for row in summary["horizons"].values():
        assert set(row) == {"ADE", "FDE", "ORR", "HBR", "CR"}
    assert list(summary["per_second"]) == [str(s) for s in range(1, 11)]
    # The test scenes' logs end 2 s after their start: horizons 1-2 s have values, the later
    # ones none (no episode reached them; a record carries its values on, the table does not).
    crs = [summary["per_second"][str(s)]["CR"] for s in range(1, 3)]
    assert all(0.0 <= c <= 1.0 for c in crs)
    assert crs == sorted(crs)  # CR at h counts collisions at or before h
    assert all(summary["per_second"][str(s)]["CR"] is None for s in range(3, 11))
    assert (
        summary["horizons"]["1-4s"]["CR"] is not None and summary["horizons"]["8-10s"]["CR"] is None
    )
    for key in ("cr", "cr_ego_adversary", "mean_min_ttc", "fallbacks", "config"):
        assert key in summary
    assert summary["config"]["sim"]["guidance"] == "full"
    assert json.loads((out_dir / "metrics.json").read_text()) == summary
    # Wall-clock figures live apart: metrics.json has none, timings.json has them.
    assert not {"seconds_per_episode", "seconds_per_replan"} & set(summary)
    assert json.loads((out_dir / "timings.json").read_text()) == timings
    assert timings["episodes"] == timings["episodes_run"] == 3 and timings["workers"] == 1
    assert timings["seconds_per_episode"] > 0 and timings["wall_seconds"] > 0
    lines = (out_dir / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 3
    # Each episode's own timings live apart too, in episode_timings.jsonl.
    assert not any(k in json.loads(x) for x in lines for k in ("seconds", "replan_seconds"))
    rows = [json.loads(x) for x in (out_dir / "episode_timings.jsonl").read_text().splitlines()]
    assert [r["episode"] for r in rows] == [0, 1, 2]
    assert all(r["seconds"] > 0 and r["replan_seconds"] > 0 for r in rows)
    first = json.loads(lines[0])
    assert first["scenario_id"] == "merge/seed=1" and first["rollout_s"] == pytest.approx(2.0)
    # Episodes 0 and 2 run the same scene with different seeds (noise).
    assert json.loads(lines[2])["scenario_id"] == first["scenario_id"]
    assert json.loads(lines[2])["seed"] == first["seed"] + 2


def test_stress_text_table(shard, capsys):
    code, out, _ = stress(
        capsys, "--scenario", shard, "--episodes", "1", "--guidance", "none", "--planner", "log"
    )
    assert code == 0
    assert out.startswith(f"1 episode of {shard}, planner log, selector causal, guidance none")
    assert "1-4s" in out and "episode CR" in out and "s per replan" in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--scenario", "parking_lot"], "unknown scenario 'parking_lot'"),
        (["--scenario", "merge", "--planner", "mpc"], "unknown planner 'mpc'"),
        (["--scenario", "merge", "--episodes", "0"], "episodes must be >= 1"),
        (["--scenario", "merge", "--model", "/no/such/model"], "/no/such/model"),
        (["--scenario", "merge", "--workers", "0"], "--workers must be >= 1, got 0"),
        (["--scenario", "merge", "--resume"], "--resume needs --out DIR"),
        (["--scenario", "merge", "--like", "intersection-v1"], "--like applies to sb3"),
        (["--scenario", "merge", "--env-config", "{}"], "--env-config applies to sb3"),
        (["--scenario", "merge", "--min-future", "-2"], "min_future must be >= 0"),
        (["--scenario", "merge", "--duration", "0.05"], "duration must be >= 0.1, got 0.05"),
    ],
)
def test_stress_bad_input(args, message, capsys):
    code, _, err = stress(capsys, *args)
    assert code == 1
    assert message in err


def test_stress_exposes_every_sim_field_as_a_flag(capsys):
    import dataclasses

    from counterscene_env.sim import SimConfig

    with pytest.raises(SystemExit):
        main(["stress", "--help"])
    text = capsys.readouterr().out
    for f in dataclasses.fields(SimConfig):
        assert f"--{f.name.replace('_', '-')}" in text, f.name
    # The documented short spellings stay.
    for flag in ("--samples", "--source", "--paper-gates", "--no-yield", "--no-road-keeping"):
        assert flag in text


def test_stress_flags_reach_the_run(shard, capsys):
    code, out, _ = stress(
        capsys, "--scenario", shard, "--episodes", "1", "--duration", "0.5", "--json",
        "--source", "model", "--paper-gates", "--no-yield", "--no-road-keeping",
        "--sampling-steps", "3", "--eta", "0.5", "--realism-weight", "0", "--max-windows", "2",
    )  # fmt: skip
    assert code == 0
    sim = json.loads(out)["config"]["sim"]
    assert sim["num_samples"] == 2 and sim["selection_source"] == "model"
    assert (sim["strict_gates"], sim["traffic_yields"], sim["road_keeping"]) == (False,) * 3
    assert (sim["sampling_steps"], sim["eta"], sim["realism_weight"]) == (3, 0.5, 0.0)
    assert sim["max_windows"] == 2 and sim["sampler"] is None  # not given: the default


def test_the_summary_names_the_world_model_as_given_and_its_directory(shard, tmp_path, capsys):
    """--json, metrics.json and the text report name the world model the run used: as given
    (--model, as run.json has it) and the checkpoint directory it resolved to (neither
    --json nor metrics.json named it)."""
    from counterscene_env.world_model.checkpoint import DEFAULT_MODEL_DIR

    out_dir = tmp_path / "run"
    one = ["--scenario", shard, "--episodes", "1", "--duration", "0.5"]
    code, out, _ = stress(capsys, *one, "--json", "--out", str(out_dir), "--videos", "0")
    assert code == 0
    model = {"given": "default", "directory": str(DEFAULT_MODEL_DIR.resolve())}
    assert json.loads(out)["model"] == model
    assert json.loads((out_dir / "metrics.json").read_text())["model"] == model
    assert json.loads((out_dir / "run.json").read_text())["model"] == "default"
    code, out, _ = stress(capsys, *one, "--model", str(DEFAULT_MODEL_DIR))
    assert code == 0
    assert f"world model: {DEFAULT_MODEL_DIR} ({DEFAULT_MODEL_DIR.resolve()})" in out


def _files(directory) -> dict[str, bytes]:
    return {
        str(p.relative_to(directory)): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def test_a_stopped_run_resumes_without_repeating_an_episode(shard, tmp_path, capsys):
    """Killed in the middle of its first batch of two: the recorded episode is kept, the
    other comes from that batch run again whole, and the files end as a run never stopped."""
    args = ["--scenario", shard, "--episodes", "3", "--batch", "2", "--duration", "0.5", "--json"]
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert stress(capsys, *args, "--out", str(full))[0] == 0
    lines = (full / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["episode"] for x in lines] == [0, 1, 2]
    # A run killed while writing its second episode: one whole line and half of the next.
    cut.mkdir()
    (cut / "run.json").write_text((full / "run.json").read_text())
    (cut / "episodes.jsonl").write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])
    before = _files(cut)
    # Without --resume a directory holding episodes is refused, and left as it was.
    code, _, err = stress(capsys, *args, "--out", str(cut))
    assert code == 1
    assert f"{cut} already holds 1 finished episode of this run" in err
    assert "--resume" in err and "another --out" in err
    assert _files(cut) == before
    code, out, _ = stress(capsys, *args, "--out", str(cut), "--resume")
    assert code == 0
    resumed = (cut / "episodes.jsonl").read_text().splitlines()
    assert resumed == lines  # the first kept, not run again; the others as a whole run's
    summary = json.loads(out)
    assert summary["episodes"] == 3 and summary["complete"]
    assert (cut / "metrics.json").read_bytes() == (full / "metrics.json").read_bytes()
    # Resuming with fewer episodes than it holds would leave a summary of 2 beside a log
    # and report of 3: refused, and the directory left as it was.
    before = _files(cut)
    fewer = [a if a != "3" else "2" for a in args]
    code, _, err = stress(capsys, *fewer, "--out", str(cut), "--resume")
    assert code == 1 and "holds 3 finished episodes" in err and "--episodes 3 or more" in err
    assert _files(cut) == before


def test_two_runs_of_the_same_episodes_write_identical_results(shard, tmp_path, capsys):
    """Timings (which differ run to run) are in timings.json and episode_timings.jsonl, so
    metrics.json and episodes.jsonl are the same, byte for byte."""
    args = ["--scenario", shard, "--episodes", "2", "--duration", "0.5", "--quiet"]
    for name in ("a", "b"):
        assert stress(capsys, *args, "--out", str(tmp_path / name))[0] == 0
    for name in ("metrics.json", "episodes.jsonl"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    timings = [json.loads((tmp_path / n / "timings.json").read_text()) for n in ("a", "b")]
    assert timings[0]["wall_seconds"] != timings[1]["wall_seconds"]  # they do differ


def test_a_refused_run_writes_nothing(shard, tmp_path, capsys):
    out = tmp_path / "never"
    code, _, err = stress(capsys, "--scenario", shard, "--model", "/no/such", "--out", str(out))
    assert code == 1 and "/no/such" in err
    assert not out.exists()


def test_a_run_directory_refuses_other_settings(shard, tmp_path, capsys):
    args = ["--scenario", shard, "--episodes", "1", "--duration", "0.3", "--out", str(tmp_path)]
    assert stress(capsys, *args)[0] == 0
    code, _, err = stress(capsys, *args, "--guidance", "none")
    assert code == 1 and "another --out" in err
    assert "sim.guidance: 'full' there, 'none' now" in err  # the field, not only its group
    assert len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 1
    # A run.json edited by hand is named, not a bare JSON error.
    (tmp_path / "run.json").write_text("{cut")
    code, _, err = stress(capsys, *args, "--resume")
    assert code == 1 and f"{tmp_path / 'run.json'} is not JSON" in err


def test_resume_into_an_empty_directory_says_it_starts_the_run(shard, tmp_path, capsys):
    """``--resume`` is safe to pass every time; a DIR holding nothing (a typo?) is said."""
    out = tmp_path / "new"
    args = ["--scenario", shard, "--episodes", "1", "--duration", "0.3", "--quiet"]
    code, _, err = stress(capsys, *args, "--out", str(out), "--resume")
    assert code == 0 and f"--resume: {out} holds no episode of this run yet" in err
    code, _, err = stress(capsys, *args, "--out", str(out), "--resume")
    assert code == 0 and "--resume" not in err


@pytest.mark.slow
def test_a_killed_stress_process_loses_no_finished_episode(shard, tmp_path):
    """SIGKILL in the middle of a run: the episodes it finished are on disk, and the rerun
    completes the run as if it had never stopped."""
    import os
    import subprocess
    import sys
    import time

    cmd = [sys.executable, "-m", "counterscene_env.cli", "stress", "--scenario", shard]
    cmd += ["--episodes", "6", "--batch", "1", "--duration", "0.5", "--samples", "2", "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    log = tmp_path / "killed" / "episodes.jsonl"
    proc = subprocess.Popen([*cmd, "--out", str(tmp_path / "killed")], env=env)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if log.is_file() and len(log.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    kept = log.read_text().splitlines()
    assert len(kept) >= 2
    # The summary of the finished episodes is on disk too, even after SIGKILL.
    partial = json.loads((tmp_path / "killed" / "metrics.json").read_text())
    assert partial["complete"] is False and partial["episodes_requested"] == 6
    assert 1 <= partial["episodes"] <= len(kept)
    resume = [*cmd, "--out", str(tmp_path / "killed"), "--resume"]
    assert subprocess.run(resume, env=env).returncode == 0
    assert subprocess.run([*cmd, "--out", str(tmp_path / "whole")], env=env).returncode == 0
    resumed = log.read_text().splitlines()
    whole = (tmp_path / "whole" / "episodes.jsonl").read_text().splitlines()
    assert resumed[: len(kept) - 1] == kept[: len(kept) - 1]  # finished ones untouched
    assert resumed == whole
    metrics = [(tmp_path / d / "metrics.json").read_bytes() for d in ("killed", "whole")]
    assert metrics[0] == metrics[1]


def _record(episode: int, **values) -> dict:
    """An episode record with every field a reader requires (placeholder values)."""
    from counterscene_env.stress.log import REQUIRED_FIELDS

    return {**{k: 0 for k in REQUIRED_FIELDS}, "per_second": {}, "episode": episode, **values}


def test_a_log_whose_last_line_lost_its_newline_appends_on_a_new_line(tmp_path):
    from counterscene_env.stress import EpisodeLog

    (tmp_path / "run.json").write_text('{"scenario": "merge"}')
    text = f"{json.dumps(_record(0))}\n{json.dumps(_record(1))}"
    (tmp_path / "episodes.jsonl").write_text(text)
    with pytest.raises(ValueError, match="pass --resume"):
        EpisodeLog(tmp_path, {"scenario": "merge"})
    log = EpisodeLog(tmp_path, {"scenario": "merge"}, resume=True)
    assert [r["episode"] for r in log.records] == [0, 1]
    # Opening changes nothing; the repair comes with the first append.
    assert (tmp_path / "episodes.jsonl").read_text() == text
    log.append([_record(2)])
    lines = (tmp_path / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(x)["episode"] for x in lines] == [0, 1, 2]


def test_episode_timings_are_read_back_and_a_lost_one_is_left_out(tmp_path):
    """A record's timings go to episode_timings.jsonl and come back on reading; an episode
    whose timings a kill lost (they are written first, so only a cut line can be missing)
    counts in neither the results nor the timing means."""
    from counterscene_env.stress import EpisodeLog, timings

    identity = {"scenario": "merge"}
    log = EpisodeLog(tmp_path, identity)
    log.append([_record(0, replans=2, seconds=1.5, replan_seconds=1.0)])
    log.append([_record(1, replans=2, seconds=2.5, replan_seconds=2.0)])
    line = json.loads((tmp_path / "episodes.jsonl").read_text().splitlines()[1])
    assert line == _record(1, replans=2)  # no timing in the results' file
    again = EpisodeLog(tmp_path, identity, resume=True).records
    assert [(r["seconds"], r["replan_seconds"]) for r in again] == [(1.5, 1.0), (2.5, 2.0)]
    assert timings(again)["seconds_per_episode"] == 2.0
    path = tmp_path / "episode_timings.jsonl"
    path.write_text(path.read_text().splitlines()[0] + "\n" + '{"episode": 1, "sec')
    cut = EpisodeLog(tmp_path, identity, resume=True).records
    assert "seconds" not in cut[1] and cut[1]["replans"] == 2
    assert timings(cut)["seconds_per_episode"] == 1.5
    assert timings(cut)["seconds_per_replan"] == 0.5
    # The next append starts on a line of its own after the cut one, and is read back.
    resumed = EpisodeLog(tmp_path, identity, resume=True)
    resumed.append([_record(2, replans=1, seconds=0.5, replan_seconds=0.25)])
    read = EpisodeLog(tmp_path, identity, resume=True).records
    assert [r.get("seconds") for r in read] == [1.5, None, 0.5]
    # A run written before the split (timings inside episodes.jsonl) reads the same.
    old = tmp_path / "old"
    old.mkdir()
    (old / "run.json").write_text(json.dumps(identity))
    (old / "episodes.jsonl").write_text(json.dumps(log.records[0]) + "\n")
    assert EpisodeLog(old, identity, resume=True).records == again[:1]


def test_resume_checks_the_records_before_running_anything(tmp_path):
    """A record without a field the summary reads is named when the log is opened, before
    a resumed run adds an episode (it used to run one, then fail on a KeyError)."""
    from counterscene_env.stress import EpisodeLog

    (tmp_path / "run.json").write_text('{"scenario": "merge"}')
    broken = {k: v for k, v in _record(1).items() if k != "min_ttc"}
    text = f"{json.dumps(_record(0))}\n{json.dumps(broken)}\n"
    (tmp_path / "episodes.jsonl").write_text(text)
    with pytest.raises(ValueError, match=r"episodes.jsonl: line 2 has no field 'min_ttc'"):
        EpisodeLog(tmp_path, {"scenario": "merge"}, resume=True)
    assert (tmp_path / "episodes.jsonl").read_text() == text
