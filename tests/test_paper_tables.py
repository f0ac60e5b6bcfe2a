"""`counterscene paper-tables`: every row on the same episodes, horizons a log does not
reach left empty, intervals and paired tests, resumable runs, timings apart."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from counterscene_env.cli import main
from counterscene_env.report import paper_tables
from counterscene_env.scene.shards import save_scenes
from counterscene_env.stress import paper

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _record(cr: float, dec: float, rollout: float = 10.0, adversary: str | None = "a7"):
    per = {
        str(s): {
            "ADE": 0.1 * s,
            "FDE": 0.3 * s,
            "ORR": 0.0,
            "HBR": float(dec > 3),
            "CR": cr,
            "CR_adv": math.nan if adversary is None else cr,
            "DEC": dec,
        }
        for s in range(1, 11)
    }
    return {"per_second": per, "rollout_s": rollout, "adversary_id": adversary}


def test_horizons_past_the_log_are_empty_and_hbr_reads_the_braking_peak():
    records = [_record(1.0, 7.0, rollout=4.0), _record(0.0, 4.0, adversary=None)]
    at_7 = paper_tables.per_episode(records, "ADE", [3, 7])
    assert at_7[0, 0] == pytest.approx(0.3) and math.isnan(at_7[0, 1])  # log ends at 4 s
    assert paper_tables.per_episode(records, "HBR3", [3])[:, 0].tolist() == [1.0, 1.0]
    assert paper_tables.per_episode(records, "HBR6", [3])[:, 0].tolist() == [1.0, 0.0]
    # HBR -6 is the IDM's full braking: exactly 6 m/s^2 counts, whichever way floats round
    # it; HBR -3 is the paper's strict "harder than 3".
    at = [_record(0.0, dec) for dec in (6.0, 6.0 - 1e-9, 3.0 + 1e-9, 5.99)]
    assert paper_tables.per_episode(at, "HBR6", [3])[:, 0].tolist() == [1.0, 1.0, 0.0, 0.0]
    assert paper_tables.per_episode(at, "HBR3", [3])[:, 0].tolist() == [1.0, 1.0, 0.0, 1.0]
    # No adversary: no collision with one (0), not "nothing to measure".
    assert paper_tables.per_episode(records, "CR_adv", [3])[:, 0].tolist() == [1.0, 0.0]


def test_a_row_with_many_more_collisions_is_outside_the_noise_and_a_copy_is_not():
    reference = [_record(0.0, 2.0) for _ in range(40)]
    worse = [_record(1.0 if i < 20 else 0.0, 2.0) for i in range(40)]
    cells = paper_tables.table(
        "ablation", {"counterscene": reference, "minimal": worse, "no_jerk": list(reference)}
    )
    assert cells["counterscene"]["3s"]["CR"].paired is None
    assert cells["counterscene"]["3s"]["CR"].estimate.value == 0.0
    hit = cells["minimal"]["3s"]["CR"]
    assert hit.estimate.value == 0.5 and hit.estimate.low < 0.5 < hit.estimate.high
    assert hit.paired.significant and hit.paired.b_only == 20
    assert not cells["no_jerk"]["3s"]["CR"].paired.significant


def test_whole_episode_rates_pair_third_party_collisions_with_the_reference():
    """Under every table: the ego's whole-episode CRs and the third parties' collisions the
    log does not have, each row paired with CounterScene; a record from before the key
    existed counts as nothing measured, not as no collision."""

    def rec(cr: float, third: float | None, adversary: str | None = "a7") -> dict:
        r = {**_record(cr, 2.0, adversary=adversary), "cr": cr, "cr_ego_adversary": cr}
        return r if third is None else {**r, "cr_non_ego_new": third}

    reference = [rec(1.0, 0.0) for _ in range(30)]
    through_others = [rec(1.0, 1.0 if i < 15 else 0.0) for i in range(30)]
    old = [rec(0.0, None, adversary=None) for _ in range(30)]
    cells = paper_tables.table(
        "main", {"counterscene": reference, "ttc": through_others, "unguided": old}
    )
    third = cells["ttc"][paper_tables.EPISODE]["cr_non_ego_new"]
    assert third.estimate.value == 0.5 and third.paired.b_only == 15 and third.paired.significant
    assert cells["counterscene"][paper_tables.EPISODE]["cr"].paired is None
    unguided = cells["unguided"][paper_tables.EPISODE]
    assert unguided["cr_non_ego_new"].estimate.n == 0 and unguided["cr_non_ego_new"].paired.n == 0
    assert unguided["cr_ego_adversary"].estimate.value == 0.0  # no adversary: no such collision
    assert unguided["cr"].paired.a_only == 30


def test_rows_of_each_table_and_refused_settings(tmp_path):
    assert paper.rows_for("intersection")[0] == "counterscene"
    # Real scenes are seated with the log the real-logs table's first horizon needs.
    assert paper.REAL_MIN_FUTURE == min(min(h) for h in paper_tables.COLUMNS["real"].values())
    real = paper.row_config(f"scenarionet:{tmp_path}", paper.ROWS["random"], 1, 0, "idm", 1)
    assert real.min_future == paper.REAL_MIN_FUTURE
    assert paper.row_config("merge", paper.ROWS["random"], 1, 0, "idm", 1).min_future == 0
    assert set(paper.rows_for("intersection")) == set(paper.ROWS)
    assert paper.rows_for("scenarionet:/data/logs") == paper.TABLES["main"]
    assert paper.scenario_dir("scenarionet:/data/nuscenes_mini/") == "scenarionet-nuscenes_mini"
    with pytest.raises(ValueError, match="selector"):
        paper.row_config("merge", paper.ROWS["random"], 1, 0, "idm", 1, {"selector": "ttc"})
    with pytest.raises(ValueError, match="nope"):
        paper.row_config("merge", paper.ROWS["random"], 1, 0, "idm", 1, {"nope": 1})
    # --tables main: the main table's rows only, on generated roads; real logs keep theirs.
    assert paper.rows_for("merge", ["main"]) == paper.TABLES["main"]
    assert paper.rows_for("scenarionet:/data/logs", ["ablation"]) == paper.TABLES["main"]
    with pytest.raises(ValueError, match="tables must be some of"):
        paper.rows_for("merge", ["mian"])
    # A mixture of generated roads is generated: the full tables, no ego choices.
    assert paper.rows_for("intersection,merge") == paper.rows_for("intersection")
    assert (
        paper.row_config("intersection,merge", paper.ROWS["random"], 1, 0, "idm", 1, egos=3).egos
        == 1
    )


def test_two_log_folders_of_one_name_are_refused_before_anything_runs(tmp_path):
    for d in ("a/logs", "b/logs"):
        (tmp_path / d).mkdir(parents=True)
    specs = [f"scenarionet:{tmp_path / d}" for d in ("a/logs", "b/logs")]
    with pytest.raises(ValueError, match="scenarionet-logs"):
        paper.run_rows(tmp_path / "out", specs, 1, 0)
    assert not (tmp_path / "out").exists()


def _row_on_disk(out, name: str, episodes: int) -> None:
    """Row ``name`` of ``paper-tables --scenario merge --episodes 2`` with ``episodes``
    synthetic episodes in ``out/merge/name/``, as a stopped run leaves it."""
    from counterscene_env.stress import EpisodeLog, run_identity

    config = paper.row_config("merge", paper.ROWS[name], 2, 300000, "idm", 4)
    log = EpisodeLog(out / "merge" / name, run_identity(config, "default"))
    scalars = {"cr": 0.0, "cr_ego_adversary": 0.0, "hbr_ego": 0.0, "orr": 0.0}
    scalars |= {"min_ttc": None, "min_clearance_adversary": 5.0, "cr_non_ego_new": 0.0}
    log.append(
        [
            {**_record(0.0, 1.0), **scalars, "episode": i, "seed": 300000 + i,
             "scenario_id": f"merge/seed={i}"}
            for i in range(episodes)
        ]
    )  # fmt: skip


def test_tables_only_names_the_rows_never_run_and_how_to_run_them(tmp_path, capsys):
    """--tables-only before every row ran: the rows with no episode are named in tables.md,
    tables.json and on stderr with the command that runs them (they were left out in
    silence), and a missing reference row says what the others are paired with instead."""
    out = tmp_path / "tables"
    _row_on_disk(out, "unguided", 2)
    _row_on_disk(out, "ttc", 1)
    args = ["paper-tables", "--scenario", "merge", "--tables", "main", "--episodes", "2"]
    args += ["--out", str(out), "--quiet"]
    assert main([*args, "--tables-only"]) == 0
    captured = capsys.readouterr()
    run = "counterscene " + " ".join(args)
    md = (out / "tables.md").read_text()
    assert captured.out == md
    assert "**Rows not run yet**" in md
    assert (
        "- merge, main table: CounterScene (causal, full guidance) (`merge/counterscene/`), "
        "random selector (`merge/random/`), distance selector (`merge/distance/`); the "
        "table's reference row CounterScene (causal, full guidance) is among them, so its rows "
        "are paired with world model, unguided instead"
    ) in md
    assert f"Run them with: `{run}`" in md
    assert (
        "rows not run yet, left out of the tables: merge/counterscene, merge/distance, "
        f"merge/random; run them with: {run}"
    ) in captured.err
    doc = json.loads((out / "tables.json").read_text())
    assert doc["missing_rows"] == {"merge": {"main": ["counterscene", "random", "distance"]}}
    assert list(doc["tables"]["merge"]["main"]) == ["unguided", "ttc"]
    assert main([*args, "--tables-only", "--json"]) == 0
    assert "merge/counterscene" in capsys.readouterr().err  # --json hides nothing


@pytest.mark.slow
def test_paper_tables_on_stored_logs_resumes_and_writes_timings_apart(generated, tmp_path, capsys):
    logs = tmp_path / "logs.npz"
    save_scenes([generated["merge"], generated["intersection"]], logs)
    out = tmp_path / "tables"
    args = ["paper-tables", "--scenario", str(logs), "--out", str(out), "--quiet"]
    args += ["--set", "duration=3.2", "num_samples=2"]
    assert main([*args, "--episodes", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    real = doc["tables"]["logs.npz"]["real"]
    assert list(real) == list(paper.TABLES["main"])  # CounterScene first
    ade = real["counterscene"]["3s"]["ADE"]
    assert ade["n"] == 2 and np.isfinite(ade["value"]) and ade["low"] <= ade["value"]
    assert real["counterscene"]["5s"]["ADE"]["n"] == 0  # the 3.2 s rollouts never reach 5 s
    assert real["counterscene"]["3s"]["CR"]["paired"] is None
    assert real["unguided"]["3s"]["CR"]["paired"]["n"] == 2
    third = real["unguided"][paper_tables.EPISODE]["cr_non_ego_new"]
    assert third["n"] == 2 and third["paired"]["n"] == 2
    assert "seconds" not in json.dumps(doc)  # compute times are in timings.json only
    assert json.loads((out / "timings.json").read_text())["row_seconds"]["logs.npz"]
    lines = {r: (out / "logs.npz" / r / "episodes.jsonl").read_text() for r in real}
    first = (out / "tables.json").read_text()
    assert main([*args, "--episodes", "2"]) == 0
    again = {r: (out / "logs.npz" / r / "episodes.jsonl").read_text() for r in real}
    assert again == lines  # nothing ran twice
    assert json.loads((out / "tables.json").read_text())["tables"] == json.loads(first)["tables"]
    assert "Real logs at 3 s, 5 s and 7 s" in (out / "tables.md").read_text()
    assert "| CR third parties (%) |" in (out / "tables.md").read_text()
    assert (
        "real scenes with at least 3 s of log after their start" in (out / "tables.md").read_text()
    )
    # --tables-only runs nothing, even when more episodes are asked for.
    assert main([*args, "--episodes", "5", "--tables-only"]) == 0
    assert {r: (out / "logs.npz" / r / "episodes.jsonl").read_text() for r in real} == lines
    assert "the episodes run so far of 5 per row" in (out / "tables.md").read_text()
    # Fewer episodes than a row holds is refused: its summary would disagree with its file.
    summaries = {r: (out / "logs.npz" / r / "metrics.json").read_text() for r in real}
    capsys.readouterr()
    assert main([*args, "--episodes", "1"]) == 1
    assert "holds 2 finished episodes of this row, more than --episodes 1" in (
        capsys.readouterr().err
    )
    assert {r: (out / "logs.npz" / r / "metrics.json").read_text() for r in real} == summaries


def test_a_mean_difference_over_a_handful_of_episodes_is_never_called_outside_the_noise():
    """Two episodes that differ alike bootstrap to the one-point interval [d, d]: that is no
    evidence, and the verdict must not say otherwise (the rate's McNemar test agrees)."""
    from counterscene_env.report import stats

    few = stats.paired_mean([0.0, 0.0], [1.0, 1.0])
    assert few.low == few.high == 1.0 and not few.significant
    many = stats.paired_mean([0.0] * 10, [1.0] * 10)
    assert many.significant
    one = stats.paired_mean([0.0], [1.0])
    assert np.isnan(one.low) and not one.significant
