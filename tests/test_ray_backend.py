"""`counterscene stress --backend ray`: the serial run's batches as Ray tasks on a local Ray,
with the serial run's files; a stopped Ray run resumes to them; what a task needs (the model,
an sb3 zip and its sidecar) travels with it; bad input is one line."""

from __future__ import annotations

import json
import logging
import shutil
import sys

import pytest

from counterscene_env.cli import main
from counterscene_env.metrics import json_safe
from counterscene_env.scene.shards import save_scenes
from counterscene_env.sim import SimConfig
from counterscene_env.stress import EpisodeLog, StressConfig, run_policy_episodes
from counterscene_env.world_model import DEFAULT_MODEL_DIR

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: The short closed loop of these tests: 0.5 s episodes, 2 samples per replan.
SHORT = ["--duration", "0.5", "--samples", "2", "--quiet", "--videos", "0"]
INSTALL = 'pip install "counterscene-env[ray]"'


@pytest.fixture(scope="module")
def shard(generated, tmp_path_factory):
    path = tmp_path_factory.mktemp("ray") / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"]], path)
    return str(path)


@pytest.fixture(scope="module")
def ray_session():
    """One local Ray (2 CPUs) for the module: starting Ray takes several seconds. The runs
    use it as it is and leave it running."""
    ray = pytest.importorskip("ray")
    ray.init("local", num_cpus=2, include_dashboard=False, logging_level=logging.WARNING)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def serial(shard, tmp_path_factory):
    """The serial run the Ray runs must reproduce: 4 episodes in batches of 2."""
    args = ["stress", "--scenario", shard, "--episodes", "4", "--batch", "2", *SHORT]
    out = tmp_path_factory.mktemp("serial") / "run"
    assert main([*args, "--out", str(out)]) == 0
    return args, out


def _without_timings(record: dict) -> str:
    """A record but its wall-clock timings, as JSON text (NaN never equals NaN)."""
    kept = {k: v for k, v in record.items() if k not in ("seconds", "replan_seconds")}
    return json.dumps(json_safe(kept), sort_keys=True)


def _records(directory) -> list[dict]:
    lines = (directory / "episodes.jsonl").read_text().splitlines()
    return [_without_timings(json.loads(x)) for x in lines]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--address", "127.0.0.1:6379"], "--address applies to --backend ray only"),
        (["--backend", "ray", "--workers", "0"], "--workers must be >= 1, got 0"),
    ],
)
def test_bad_backend_flags_are_one_line_errors(args, message, capsys):
    assert main(["stress", "--scenario", "merge", *args]) == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_backend_ray_without_ray_says_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert main(["stress", "--scenario", "merge", "--backend", "ray"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("counterscene stress: error: --backend ray needs Ray")
    assert INSTALL in err and err.count("\n") == 1


def test_an_address_nothing_listens_on_is_refused_at_once(capsys):
    pytest.importorskip("ray")
    # Port 1 refuses at once; Ray itself would retry such an address for minutes.
    args = ["stress", "--scenario", "merge", "--backend", "ray", "--address", "127.0.0.1:1"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "cannot reach a Ray cluster at --address 127.0.0.1:1" in err
    assert err.count("\n") == 1


@pytest.mark.slow
def test_ray_gives_the_serial_runs_files(ray_session, serial, tmp_path, capsys):
    """Same metrics.json byte for byte, same records in the same order: each task runs one
    of the serial run's batches of 2 whole."""
    args, serial_dir = serial
    out = tmp_path / "ray"
    assert main([*args, "--backend", "ray", "--workers", "2", "--out", str(out)]) == 0
    capsys.readouterr()
    assert (out / "metrics.json").read_bytes() == (serial_dir / "metrics.json").read_bytes()
    assert _records(out) == _records(serial_dir)
    assert json.loads((out / "timings.json").read_text())["workers"] == 2


@pytest.mark.slow
def test_a_stopped_ray_run_resumes_to_the_serial_result(
    ray_session, serial, tmp_path, monkeypatch, capsys
):
    """Ctrl-C as the first batch is on disk: exit 130, the tasks still running cancelled, the
    finished episodes kept; --resume under Ray ends with the serial run's metrics.json."""
    args, serial_dir = serial
    out = tmp_path / "stopped"
    append = EpisodeLog.append

    def append_then_stop(self, records):
        append(self, records)
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(EpisodeLog, "append", append_then_stop)
        code = main([*args, "--backend", "ray", "--workers", "2", "--out", str(out)])
    assert code == 130
    assert "--resume" in capsys.readouterr().err
    kept = (out / "episodes.jsonl").read_text().splitlines()
    assert len(kept) == 2 and json.loads((out / "metrics.json").read_text())["complete"] is False

    resume = [*args, "--backend", "ray", "--workers", "2", "--out", str(out), "--resume"]
    assert main(resume) == 0
    capsys.readouterr()
    assert (out / "episodes.jsonl").read_text().splitlines()[:2] == kept  # nothing redone
    assert (out / "metrics.json").read_bytes() == (serial_dir / "metrics.json").read_bytes()


@pytest.fixture
def policy(tmp_path):
    """An untrained PPO policy on 3 x 5 Kinematics observations, with the sidecar that says
    so (without it, CounterScene-v0's default observation does not fit the policy)."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    observation = {"observation": {"type": "Kinematics", "vehicles_count": 3}}
    env = gym.make("CounterScene-v0", config={"scenario": "intersection", **observation})
    ppo = PPO("MlpPolicy", env, n_steps=8, batch_size=8, seed=0, policy_kwargs={"net_arch": [8]})
    path = tmp_path / "policy" / "p.zip"
    path.parent.mkdir()
    ppo.save(path)
    path.with_name("p.env.json").write_text(json.dumps(observation))
    env.close()
    return path


@pytest.mark.slow
def test_the_model_and_an_sb3_policy_travel_with_the_tasks(
    ray_session, shard, policy, tmp_path, monkeypatch
):
    """An sb3 run under Ray gives the serial run's records although the model directory,
    the zip and its sidecar are gone once the driver has read them: the tasks got bytes."""
    from counterscene_env.stress import ray_backend

    model = tmp_path / "model"
    shutil.copytree(DEFAULT_MODEL_DIR, model)
    sim = SimConfig(duration=0.5, num_samples=2)
    config = StressConfig(shard, episodes=2, seed=7, planner=f"sb3:{policy}", sim=sim)
    serial = run_policy_episodes(config, str(model), progress=False)

    read = ray_backend._payload

    def read_then_delete(*args):
        payload = read(*args)
        shutil.rmtree(model)
        shutil.rmtree(policy.parent)
        return payload

    monkeypatch.setattr(ray_backend, "_payload", read_then_delete)
    records = ray_backend.run_ray(config, workers=2, model=str(model), progress=False)
    assert not model.exists() and not policy.exists()
    assert [_without_timings(r) for r in records] == [_without_timings(r) for r in serial]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("error", "reported"),
    [(ValueError, "^the planner blew up$"), (RuntimeError, "stress task failed:")],
)
def test_a_failing_task_stops_the_run_with_its_error(ray_session, shard, error, reported):
    """Bad input comes back as the serial run raises it; anything else with the task's
    traceback. The planner is a local class: Ray carries it by value."""

    class Exploding:
        name = "exploding"
        replays_log = False

        def reset(self, scene, seed: int) -> None:
            raise error("the planner blew up")

        def act(self, state):
            raise AssertionError("never reached")

    from counterscene_env.stress import run_ray

    sim = SimConfig(duration=0.5, num_samples=2)
    config = StressConfig(shard, episodes=2, batch=1, sim=sim)
    with pytest.raises(error, match=reported) as caught:
        run_ray(config, workers=2, planner_factory=Exploding, progress=False)
    assert "the planner blew up" in str(caught.value)
