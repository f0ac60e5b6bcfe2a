"""The recipes in agents/ run end to end (tiny budgets, as subprocesses), and SB3 policies,
including one trained on highway-env's own intersection-v2, are stress-tested here unchanged."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "SDL_VIDEODRIVER": "dummy"}


def run(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=timeout
    )


def counterscene(*args: str) -> subprocess.CompletedProcess:
    return run("-m", "counterscene_env.cli", *args)


@pytest.fixture(scope="module")
def highway_policy(tmp_path_factory) -> Path:
    """A DQN trained for a few steps on highway-env's intersection-v2, with its sidecar."""
    out = tmp_path_factory.mktemp("highway_intersection")
    done = run(
        "agents/highway_intersection.py",
        "--total-timesteps", "64", "--eval-episodes", "1", "--out", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    return out / "model.zip"


@pytest.mark.slow
def test_highway_intersection_recipe_writes_policy_sidecar_and_eval(highway_policy):
    out = highway_policy.parent
    sidecar = json.loads((out / "model.env.json").read_text())
    assert set(sidecar) == {"observation", "action", "policy_frequency"}
    assert sidecar["observation"]["vehicles_count"] == 15
    assert sidecar["action"]["type"] == "DiscreteMetaAction"
    evaluation = json.loads((out / "eval.json").read_text())
    assert evaluation["episodes"] == 1 and "idle_baseline" in evaluation


@pytest.mark.slow
def test_highway_env_policy_stress_tested_unchanged(highway_policy):
    """The policy trained on highway-env's intersection-v2 runs in CounterScene with no code
    change: the sidecar configures matching spaces (15 x 7 Kinematics, Discrete(3), 1 Hz)."""
    done = counterscene(
        "stress", "--scenario", "intersection", "--episodes", "1", "--duration", "2",
        "--planner", f"sb3:{highway_policy}", "--json", "--quiet",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout)
    assert summary["episodes"] == 1
    assert summary["config"]["planner"] == f"sb3:{highway_policy}"
    assert 0.0 <= summary["cr"] <= 1.0


@pytest.mark.slow
def test_sb3_batches_in_a_vector_env_give_the_one_at_a_time_records(
    highway_policy, generated, tmp_path, capsys
):
    """``--batch 3`` runs an sb3 policy's episodes 3 at a time in one vector env (one
    world-model call per replan); the records and the summary are those of ``--batch 1``,
    with episodes of different scenes (and so different lengths) in one batch."""
    from counterscene_env.cli import main
    from counterscene_env.scene.shards import save_scenes

    shard = tmp_path / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"], generated["highway"]], shard)
    args = ["stress", "--scenario", str(shard), "--episodes", "4", "--duration", "1.5"]
    args += ["--planner", f"sb3:{highway_policy}", "--samples", "2", "--quiet"]
    for batch in ("1", "3"):
        assert main([*args, "--batch", batch, "--out", str(tmp_path / batch)]) == 0
    capsys.readouterr()
    one, three = tmp_path / "1", tmp_path / "3"
    metrics = [json.loads((d / "metrics.json").read_text()) for d in (one, three)]
    assert [m["config"].pop("batch") for m in metrics] == [1, 3]
    assert metrics[0] == metrics[1]
    strip = ("seconds", "replan_seconds")
    records = [
        [{k: v for k, v in json.loads(line).items() if k not in strip} for line in lines]
        for lines in ((d / "episodes.jsonl").read_text().splitlines() for d in (one, three))
    ]
    assert records[0] == records[1] and len(records[0]) == 4


@pytest.mark.slow
def test_sb3_candidate_rollouts_keep_one_of_the_plain_runs(
    highway_policy, generated, tmp_path, capsys
):
    """``--rollouts 2`` with an sb3 policy: the kept record is the plain run of the candidate
    it names (its seed given as ``--seed``), under the episode's own seed."""
    from counterscene_env.cli import main
    from counterscene_env.metrics import severity
    from counterscene_env.scene.shards import save_scenes
    from counterscene_env.stress.rollouts import rollout_seed

    shard = tmp_path / "scenes.npz"
    save_scenes([generated["merge"]], shard)
    args = ["stress", "--scenario", str(shard), "--episodes", "1", "--duration", "1.5"]
    args += ["--planner", f"sb3:{highway_policy}", "--samples", "2", "--quiet", "--videos", "0"]
    assert main([*args, "--seed", "40", "--rollouts", "2", "--out", str(tmp_path / "k2")]) == 0
    for k in (0, 1):
        assert (
            main([*args, "--seed", str(rollout_seed(40, k)), "--out", str(tmp_path / f"c{k}")]) == 0
        )
    capsys.readouterr()

    def record(name: str) -> dict:
        return json.loads((tmp_path / name / "episodes.jsonl").read_text().splitlines()[0])

    kept, plain = record("k2"), [record("c0"), record("c1")]
    k = kept.pop("rollout")
    assert (kept.pop("seed"), kept.pop("rollouts")) == (40, 2)
    assert kept.pop("rollout_seed") == plain[k].pop("seed") == rollout_seed(40, k)
    assert kept == plain[k]
    assert severity(plain[k]) <= severity(plain[1 - k])


@pytest.mark.slow
def test_mismatched_policy_spaces_named_in_the_error(highway_policy):
    done = counterscene(
        "stress", "--scenario", "merge", "--episodes", "1", "--duration", "1",
        "--planner", f"sb3:{highway_policy}", "--env-config", '{"observation": {"type": "Kinematics"}}',
    )  # fmt: skip
    assert done.returncode != 0
    assert "(15, 7)" in done.stderr and "Discrete" in done.stderr


@pytest.mark.slow
def test_ppo_ego_recipe_trains_saves_and_evaluates(tmp_path):
    done = run(
        "agents/ppo_ego.py",
        "--scenario", "merge", "--total-timesteps", "16", "--n-steps", "8",
        "--batch-size", "8", "--n-epochs", "1", "--num-envs", "2", "--eval-episodes", "1",
        "--duration", "1", "--out", str(tmp_path),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "model.zip").is_file()
    sidecar = json.loads((tmp_path / "model.env.json").read_text())
    assert sidecar["policy_frequency"] == 2
    rows = json.loads((tmp_path / "eval.json").read_text())
    assert set(rows) == {"ppo none", "ppo full", "idm none", "idm full"}
    assert all(0.0 <= row["cr"] <= 1.0 for row in rows.values())


def test_ppo_ego_recipe_checks_its_evaluation_before_training(tmp_path):
    """A bad evaluation setting is refused at once, not after minutes of training."""
    done = run(
        "agents/ppo_ego.py", "--eval-episodes", "0", "--out", str(tmp_path / "out"),
    )  # fmt: skip
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert "--eval-" in done.stderr and "episodes must be >= 1" in done.stderr
    assert not (tmp_path / "out").exists()


def test_sb3_policy_loads_without_unpickling(tmp_path, monkeypatch):
    """Loading never calls pickle/cloudpickle (an SB3 zip can carry arbitrary pickles)."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    from counterscene_env.planners import SB3Policy

    env = gym.make("CartPole-v1")
    PPO("MlpPolicy", env, n_steps=16, batch_size=8, seed=0).save(tmp_path / "p.zip")

    def refuse(*args, **kwargs):
        raise AssertionError("unpickled")

    import pickle

    import cloudpickle

    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(cloudpickle, "loads", refuse)
    policy = SB3Policy(tmp_path / "p.zip")
    policy.bind(env.observation_space, env.action_space)
    action = policy.predict(np.zeros(4, np.float32))
    assert env.action_space.contains(int(action))


def test_sb3_policy_rejects_foreign_and_corrupt_files(tmp_path):
    from counterscene_env.planners import SB3Policy

    (tmp_path / "junk.zip").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a Stable-Baselines3 model zip"):
        SB3Policy(tmp_path / "junk.zip")
    spaces = {"observation_space": {}, "action_space": {}}
    for name, module, init in (
        ("foreign", "evil.module", "<function Evil.__init__ at 0>"),
        (
            "not_policies",
            "stable_baselines3.common.utils",
            "<function get_linear_fn.__init__ at 0>",
        ),
        ("not_a_policy", "stable_baselines3.common.policies", "<function BaseModel.__init__ at 0>"),
    ):
        with zipfile.ZipFile(tmp_path / f"{name}.zip", "w") as z:
            policy_class = {"__module__": module, "__init__": init}
            z.writestr("data", json.dumps({"policy_class": policy_class, **spaces}))
            z.writestr("policy.pth", b"")
        with pytest.raises(ValueError, match=r"not one of Stable-Baselines3.s|not an SB3 policy"):
            SB3Policy(tmp_path / f"{name}.zip")
    with zipfile.ZipFile(tmp_path / "no_spaces.zip", "w") as z:
        z.writestr("data", json.dumps({"policy_class": {}}))
        z.writestr("policy.pth", b"")
    with pytest.raises(ValueError, match="no \\['action_space', 'observation_space'\\]"):
        SB3Policy(tmp_path / "no_spaces.zip")
    with pytest.raises(FileNotFoundError):
        SB3Policy(tmp_path / "missing.zip")
