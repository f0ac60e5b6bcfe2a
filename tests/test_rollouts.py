"""Candidate rollouts (``counterscene stress --rollouts K``): each episode run under K
closed-loop seeds, the run most severe for the ego kept, paired with plain runs by episode and
replayed as it ran."""

from __future__ import annotations

import json

import pytest

from counterscene_env.cli import main
from counterscene_env.planners import make_planner
from counterscene_env.report.replay import replay_batch
from counterscene_env.report.rundir import load_run
from counterscene_env.scene.shards import save_scenes
from counterscene_env.sim import SimConfig
from counterscene_env.stress import StressConfig, rollouts
from counterscene_env.stress.batch import run_batch
from counterscene_env.stress.episodes import BatchRunner
from counterscene_env.stress.rollouts import keep_most_severe, rollout_seed
from counterscene_env.world_model import load_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHORT = SimConfig(duration=2.0, num_samples=2)


@pytest.fixture(scope="module")
def shard(generated, tmp_path_factory):
    path = tmp_path_factory.mktemp("rollouts") / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"]], path)
    return str(path)


def record(seed: int, **values) -> dict:
    base = {"seed": seed, "cr": 0.0, "cr_ego_adversary": 0.0, "min_ttc": float("inf")}
    base.update(min_clearance_adversary=float("nan"), hbr_ego=0.0, seconds=1.0)
    return {**base, "replan_seconds": 0.5 + seed / 100, **values}


def test_the_kept_candidate_is_the_worst_for_the_ego():
    near_miss = record(10, min_ttc=0.4, min_clearance_adversary=0.8)
    hit_by_other = record(11, cr=1.0, min_ttc=0.0)
    hit_by_adversary = record(12, cr=1.0, cr_ego_adversary=1.0, min_ttc=0.0)
    calm = record(13, min_ttc=3.0)
    kept = keep_most_severe([[near_miss, calm], [hit_by_other, calm], [hit_by_adversary, calm]])
    assert kept[0]["cr_ego_adversary"] == 1.0
    assert (kept[0]["seed"], kept[0]["rollout"], kept[0]["rollout_seed"]) == (10, 2, 12)
    assert kept[0]["rollouts"] == 3
    # The episode cost all three runs; a replan's time stays the kept run's own.
    assert kept[0]["seconds"] == 3.0 and kept[0]["replan_seconds"] == pytest.approx(0.62)
    # Equally severe candidates: the lower one, here the episode's own seed.
    assert kept[1]["rollout"] == 0 and kept[1]["rollout_seed"] == 13
    assert keep_most_severe([[near_miss], [hit_by_other]])[0]["rollout"] == 1
    with pytest.raises(ValueError, match="at least one candidate"):
        keep_most_severe([])


def test_candidate_seeds_are_fixed_and_distinct():
    assert rollout_seed(100, 0) == 100  # candidate 0 is the plain episode
    seeds = [rollout_seed(s, k) for s in (100, 101) for k in range(8)]
    assert len(set(seeds)) == len(seeds)
    assert seeds == [rollout_seed(s, k) for s in (100, 101) for k in range(8)]
    assert all(0 <= s < 2**32 for s in seeds)


def test_a_run_with_rollouts_keeps_the_most_severe_of_its_candidates(shard, generated):
    """Each episode's record is one of its candidates' plain records, the most severe."""
    config = StressConfig(shard, episodes=2, seed=40, sim=SHORT, batch=2, rollouts=3)
    model = load_model("default")
    runner = BatchRunner(model, config)
    scenes = [generated["merge"], generated["intersection"]]
    kept = runner(0, scenes)
    candidates = [
        run_batch(
            runner.loop,
            scenes,
            [rollout_seed(40, k), rollout_seed(41, k)],
            [make_planner("idm") for _ in scenes],
        )
        for k in range(3)
    ]
    volatile = ("seed", "seconds", "replan_seconds", "rollout", "rollout_seed", "rollouts")
    for b, rec in enumerate(kept):
        own = [candidates[k][b] for k in range(3)]
        assert rec["seed"] == 40 + b and rec["rollouts"] == 3
        k = rec["rollout"]
        assert rec["rollout_seed"] == rollout_seed(40 + b, k) == own[k]["seed"]
        same = {key: v for key, v in rec.items() if key not in volatile}
        assert json.dumps(same, sort_keys=True) == json.dumps(
            {key: v for key, v in own[k].items() if key not in volatile}, sort_keys=True
        )
        assert keep_most_severe([[c] for c in own])[0]["rollout"] == k
    # One candidate is the plain run: rollouts=1 records it with no candidate fields.
    plain = BatchRunner(model, StressConfig(shard, episodes=2, seed=40, sim=SHORT, batch=2))
    first = plain(0, scenes)
    assert not {"rollout", "rollout_seed", "rollouts"} & set(first[0])
    assert first[0]["min_ttc"] == candidates[0][0]["min_ttc"]


def test_every_candidate_of_an_episode_has_its_random_adversary(shard, generated):
    """The protocol varies the noise, not the choice: a ``random`` selector's vehicle is the
    episode's own in every candidate (not the best of K random vehicles), and a selection seed
    that is the episode's own leaves the episode as it was."""
    sim = SimConfig(duration=1.0, num_samples=2, selector="random")
    config = StressConfig(shard, episodes=2, seed=40, sim=sim, batch=2, rollouts=4)
    model = load_model("default")
    runner = BatchRunner(model, config)
    scenes = [generated["merge"], generated["intersection"]]
    plain = BatchRunner(model, StressConfig(shard, episodes=2, seed=40, sim=sim, batch=2))(
        0, scenes
    )
    chosen = [r["adversary_id"] for r in plain]
    assert all(a is not None for a in chosen)
    assert [r["adversary_id"] for r in runner(0, scenes)] == chosen

    def adversaries(k: int, shared: bool) -> list:
        seeds = [rollout_seed(40, k), rollout_seed(41, k)]
        planners = [make_planner("idm") for _ in scenes]
        records = run_batch(runner.loop, scenes, seeds, planners, 0, [40, 41] if shared else None)
        return [r["adversary_id"] for r in records]

    assert all(adversaries(k, shared=True) == chosen for k in range(1, 4))
    # Without the shared seed the candidates' own generators choose other vehicles.
    assert any(adversaries(k, shared=False) != chosen for k in range(1, 4))
    again = run_batch(
        runner.loop, scenes, [40, 41], [make_planner("idm") for _ in scenes], 0, [40, 41]
    )
    volatile = ("seconds", "replan_seconds")
    assert [{k: v for k, v in r.items() if k not in volatile} for r in again] == [
        {k: v for k, v in r.items() if k not in volatile} for r in plain
    ]
    with pytest.raises(ValueError, match="2 scenes but 1 selection seeds"):
        runner.loop.reset(scenes, [40, 41], selection_seeds=[40])


def test_a_kept_later_candidate_replays_as_it_ran(shard, tmp_path, monkeypatch, capsys):
    """A report's video replays the kept candidate's noise, in its batch as it ran."""
    seeds = {rollout_seed(40 + i, 1) for i in range(2)}
    # Keep candidate 1 of every episode, whatever happened: the replay must find its noise.
    monkeypatch.setattr(rollouts, "severity", lambda r: (0.0 if r["seed"] in seeds else 1.0,))
    out = tmp_path / "run"
    argv = ["stress", "--scenario", shard, "--episodes", "2", "--seed", "40", "--batch", "2"]
    argv += ["--duration", "2", "--samples", "2", "--rollouts", "2", "--quiet", "--json"]
    assert main([*argv, "--out", str(out), "--videos", "0"]) == 0
    capsys.readouterr()
    run = load_run(out)
    assert [r["rollout"] for r in run.records] == [1, 1]
    assert json.loads((out / "run.json").read_text())["rollouts"] == 2
    replays = replay_batch(load_model("default"), run, range(2), [0, 1])
    assert [r.mismatches for r in replays] == [(), ()]
    assert [r.record["episode"] for r in replays] == [0, 1]


def test_rollouts_are_part_of_a_runs_identity_and_refused_below_one(shard, tmp_path, capsys):
    with pytest.raises(ValueError, match="rollouts must be >= 1, got 0"):
        StressConfig(shard, rollouts=0)
    out = str(tmp_path / "run")
    argv = ["stress", "--scenario", shard, "--episodes", "1", "--duration", "0.5", "--quiet"]
    assert main([*argv, "--out", out, "--videos", "0"]) == 0
    # The same directory with candidate rollouts is another run: refused, nothing changed.
    before = (tmp_path / "run" / "episodes.jsonl").read_text()
    assert main([*argv, "--rollouts", "2", "--out", out, "--resume"]) == 1
    assert "rollouts" in capsys.readouterr().err
    assert (tmp_path / "run" / "episodes.jsonl").read_text() == before
    with pytest.raises(SystemExit):
        main([*argv, "--rollouts", "0"])
    assert "--rollouts: must be >= 1, got 0" in capsys.readouterr().err
