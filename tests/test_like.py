"""`--like ENV_ID`: a plain SB3 policy trained on a highway-env env, stress-tested with the
observation, action and policy frequency of that env's config (``envs.like``)."""

from __future__ import annotations

import json
import warnings

import gymnasium as gym
import pytest

from counterscene_env.cli import main
from counterscene_env.envs.like import config_like, highway_env_ids
from counterscene_env.envs.type_checks import FOREIGN_OBSERVATIONS
from counterscene_env.scene.shards import save_scenes


def test_intersection_v1_gives_its_observation_action_and_frequency_and_warns():
    with pytest.warns(UserWarning, match=r"absolute coordinates \(absolute: True\)"):
        config = config_like("intersection-v1")  # deprecated, still registered
    assert set(config) == {"observation", "action", "policy_frequency"}
    obs = config["observation"]
    assert obs["type"] == "Kinematics" and obs["vehicles_count"] == 5
    assert obs["features"][-3:] == ["long_off", "lat_off", "ang_off"]
    assert config["action"]["type"] == "ContinuousAction"
    assert config["policy_frequency"] == 1


def test_relative_observations_borrow_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        config = config_like("highway-v0")
    assert config["observation"] == {"type": "Kinematics"}  # highway-env's class defaults
    assert config["action"] == {"type": "DiscreteMetaAction"}


def test_a_multi_agent_env_gives_one_egos_observation_and_action():
    with pytest.warns(UserWarning, match="absolute"):  # its ego observation is absolute
        config = config_like("intersection-multi-agent-v1")
    assert config["observation"]["type"] == "Kinematics"
    assert config["action"]["type"] == "DiscreteMetaAction"


def test_unknown_and_foreign_ids_are_refused_by_name():
    with pytest.raises(ValueError, match=r"'interseciton-v1' is not a registered highway-env"):
        config_like("interseciton-v1")
    with pytest.raises(ValueError, match=r"did you mean intersection-v1"):
        config_like("interseciton-v1")
    with pytest.raises(ValueError, match=r"registered: .*roundabout-v0"):
        config_like("CartPole-v1")  # a gymnasium id, not highway-env's
    with pytest.raises(ValueError, match="parking goal"):
        config_like("parking-v0")


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
def test_every_highway_env_id_is_borrowed_or_refused_with_a_reason(generated, tmp_path):
    """For each registered id, either a clear refusal, or CounterScene-v0 built on the
    borrowed keys gives that env's (per-ego) spaces and runs a step."""
    from counterscene_env.envs.single_agent import CounterSceneEnv

    shard = tmp_path / "scenes.npz"
    save_scenes([generated["intersection"]], shard)
    ids = highway_env_ids()
    assert {"intersection-v1", "highway-v0", "roundabout-v0"} <= set(ids)
    for env_id in ids:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                config = config_like(env_id)
            except ValueError as exc:
                assert any(why in str(exc) for why in FOREIGN_OBSERVATIONS.values()), env_id
                continue
            theirs = gym.make(env_id)
        ours = CounterSceneEnv(config={**config, "scenario": str(shard), "duration": 1.0})
        obs_space, act_space = theirs.observation_space, theirs.action_space
        if isinstance(obs_space, gym.spaces.Tuple):  # multi-agent: one ego's
            obs_space, act_space = obs_space.spaces[0], act_space.spaces[0]
        assert ours.observation_space.shape == obs_space.shape, env_id
        assert type(ours.action_space) is type(act_space), env_id
        assert ours.action_space.shape == act_space.shape, env_id
        ours.reset(seed=0)
        ours.step(ours.action_space.sample())
        ours.close()
        theirs.close()


@pytest.mark.slow
@pytest.mark.usefixtures("one_torch_thread")
@pytest.mark.filterwarnings("ignore:.*intersection-v1 is out of date")
def test_a_plain_ppo_from_intersection_v1_is_stress_tested_with_one_flag(
    generated, tmp_path, capsys
):
    """PPO on highway-env's intersection-v1 with its defaults, saved without a sidecar: the
    env's defaults do not fit it; --like intersection-v1 does, serial and with two workers
    alike, and the run records what it borrowed."""
    from stable_baselines3 import PPO

    train_env = gym.make("intersection-v1")
    model = PPO("MlpPolicy", train_env, n_steps=32, batch_size=32, n_epochs=1, seed=0)
    model.learn(64)
    model.save(tmp_path / "x.zip")
    train_env.close()
    assert not (tmp_path / "x.env.json").exists()
    shard = tmp_path / "scenes.npz"
    save_scenes([generated["intersection"]], shard)
    args = ["stress", "--scenario", str(shard), "--planner", f"sb3:{tmp_path / 'x.zip'}"]
    args += ["--episodes", "2", "--duration", "2", "--samples", "2", "--quiet"]

    assert main(args) == 1
    err = capsys.readouterr().err
    assert "--like ENV_ID" in err  # the mismatch names the way out
    assert "has no .env.json sidecar" in err  # and the defaults were not taken silently
    # The run's own settings are its flags: an env config that sets them is refused, not
    # silently overwritten (run.json would record a duration the episodes never had).
    assert main([*args, "--env-config", '{"duration": 1, "guidance": "none"}']) == 1
    assert "--env-config sets ['duration', 'guidance']" in capsys.readouterr().err
    sidecar = tmp_path / "x.env.json"
    for text, words in (("{bad", "not valid JSON"), ("[1, 2]", "must hold a JSON object")):
        sidecar.write_text(text)
        assert main(args) == 1
        err = capsys.readouterr().err
        assert str(sidecar) in err and words in err
    sidecar.unlink()

    like = [*args, "--like", "intersection-v1"]
    assert main([*like, "--json", "--out", str(tmp_path / "serial")]) == 0
    out = capsys.readouterr()
    assert "warning: --like: intersection-v1's observation" in out.err
    assert "sidecar" not in out.err
    assert "absolute" in out.err
    summary = json.loads(out.out)
    assert summary["episodes"] == 2 and 0.0 <= summary["cr"] <= 1.0
    borrowed = json.loads((tmp_path / "serial" / "run.json").read_text())["env_config"]
    assert borrowed["observation"]["vehicles_count"] == 5
    assert borrowed["action"]["type"] == "ContinuousAction"
    assert borrowed["policy_frequency"] == 1

    assert main([*like, "--workers", "2", "--out", str(tmp_path / "parallel")]) == 0
    capsys.readouterr()
    metrics = [(tmp_path / d / "metrics.json").read_bytes() for d in ("serial", "parallel")]
    assert metrics[0] == metrics[1]
