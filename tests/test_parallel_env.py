"""The PettingZoo ParallelEnv: API and seed tests, agents and spaces, one distinct adversary
per ego, bad input, and terminated agents leaving."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pettingzoo
import pytest
from conftest import crash_scene
from pettingzoo.test import parallel_api_test, parallel_seed_test

import counterscene_env
from counterscene_env.envs.parallel import CounterSceneParallelEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHORT = {"duration": 1.0, "scenario": "merge"}
ZERO = np.zeros(2, np.float32)


@pytest.fixture(scope="module")
def env():
    """One short two-ego merge env shared by the tests that only reset and step it."""
    env = counterscene_env.parallel_env(num_egos=2, config=SHORT)
    yield env
    env.close()


def ego_ids(env) -> list[str]:
    """The scene's agent id of each ego (ego_0 first)."""
    core = env.core
    return [str(core.scene.agent_ids[e]) for e in core.egos]


@pytest.mark.slow
# PettingZoo's test resets with options={"options": 1}, which the env names in a warning.
@pytest.mark.filterwarnings("ignore:reset ignores the unknown options")
def test_pettingzoo_parallel_api_test_passes():
    """PettingZoo's own API test, over more cycles than an episode has (agents finish)."""
    env = counterscene_env.parallel_env(num_egos=2, config=SHORT)
    parallel_api_test(env, num_cycles=15)
    env.close()


def test_pettingzoo_parallel_seed_test_passes():
    parallel_seed_test(
        lambda: counterscene_env.parallel_env(num_egos=2, config=SHORT), num_cycles=10
    )


def test_pettingzoo_make_builds_the_env():
    """The registry entry: pettingzoo.make("parallel", "CounterScene-v0", ...)."""
    env = pettingzoo.make("parallel", "CounterScene-v0", num_egos=2, config=SHORT)
    assert isinstance(env, CounterSceneParallelEnv)
    assert env.possible_agents == ["ego_0", "ego_1"]
    assert env.config["scenario"] == "merge" and env.config["controlled_vehicles"] == 2
    env.close()


def test_agents_and_spaces(env):
    """Agents are ego_0 .. ego_{n-1}; each agent's spaces are one fixed object (as PettingZoo
    asks) and every observation lies in its agent's space."""
    assert env.possible_agents == ["ego_0", "ego_1"]
    assert env.agents == []  # before the first reset
    spaces = {a: (env.observation_space(a), env.action_space(a)) for a in env.possible_agents}
    obs, infos = env.reset(seed=0)
    assert env.agents == env.possible_agents
    assert set(obs) == set(infos) == set(env.agents)
    for a in env.agents:
        assert env.observation_space(a) is spaces[a][0] is env.observation_space(a)
        assert env.action_space(a) is spaces[a][1]
        assert env.observation_space(a).shape == (10, 7) and env.action_space(a).shape == (2,)
        assert obs[a].dtype == np.float32 and env.observation_space(a).contains(obs[a])
    assert len(set(ego_ids(env))) == 2
    obs, rewards, terms, truncs, infos = env.step({a: ZERO for a in env.agents})
    for a in env.possible_agents:
        assert env.observation_space(a).contains(obs[a])
        assert type(rewards[a]) is float and type(terms[a]) is bool and type(truncs[a]) is bool
        assert "rewards" in infos[a] and "adversary" in infos[a]
    # The single-agent env's info keys, per ego, at reset and at every step.
    single = gym.make("CounterScene-merge-v0", config={"duration": 1.0})
    _, single_info = single.reset(seed=0)
    single.close()
    _, reset_infos = env.reset(seed=0)
    for info in [*infos.values(), *reset_infos.values()]:
        assert set(info) == set(single_info)
    assert env.state().shape == (2, 10, 7) and env.state_space.contains(env.state())


def test_each_ego_has_its_own_adversary_never_another_ego():
    """Merge seed 4 selects an adversary for both egos: they differ and neither is an ego."""
    env = counterscene_env.parallel_env(num_egos=2, config={"duration": 5.0, "scenario": "merge"})
    _, infos = env.reset(seed=4)
    adversaries = [infos[a]["adversary"] for a in env.possible_agents]
    assert None not in adversaries, [infos[a]["fallback"] for a in env.possible_agents]
    assert len(set(adversaries)) == 2
    assert not set(adversaries) & set(ego_ids(env))
    env.close()


def test_an_agent_that_becomes_an_ego_is_no_longer_an_adversary(generated):
    """On the generated merge scene the lone ego's adversary is veh6; with two egos veh6 is
    ego_1, and ego_0 gets no adversary rather than another policy's vehicle."""
    scene = generated["merge"]
    alone = counterscene_env.parallel_env(num_egos=1, config={"duration": 2.0})
    _, infos = alone.reset(seed=0, options={"scene": scene})
    lone_adversary = infos["ego_0"]["adversary"]
    assert lone_adversary is not None
    pair = counterscene_env.parallel_env(num_egos=2, config={"duration": 2.0})
    _, infos = pair.reset(seed=0, options={"scene": scene})
    egos = ego_ids(pair)
    assert egos[1] == lone_adversary
    for a in pair.possible_agents:
        assert infos[a]["adversary"] not in egos
    alone.close()
    pair.close()


def test_bad_input_is_refused(env):
    env.reset(seed=1)
    with pytest.raises(ValueError, match=r"missing \['ego_1'\]"):
        env.step({"ego_0": ZERO})
    with pytest.raises(ValueError, match=r"unknown \['ego_7'\]"):
        env.step({"ego_0": ZERO, "ego_1": ZERO, "ego_7": ZERO})
    with pytest.raises(ValueError, match="NaN"):
        env.step({"ego_0": ZERO, "ego_1": np.array([np.nan, 0.0], np.float32)})
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        env.step({"ego_0": ZERO, "ego_1": np.zeros(3, np.float32)})
    assert env.core.steps == 0, "refused actions do not advance the episode"
    with pytest.raises(ValueError, match="num_egos"):
        counterscene_env.parallel_env(num_egos=0)
    with pytest.raises(TypeError, match="num_egos"):
        counterscene_env.parallel_env(num_egos=2.0)
    with pytest.raises(TypeError, match="num_egos"):
        counterscene_env.parallel_env(num_egos=True)
    with pytest.raises(TypeError, match="options must be a dict or None"):
        env.reset(options="scene")
    with pytest.raises(ValueError, match="controlled_vehicles"):
        counterscene_env.parallel_env(num_egos=2, config={"controlled_vehicles": 2})


def test_a_terminated_agent_leaves_and_the_others_play_on():
    """ego_0 drives into a parked car: terminated and removed from agents, absent from every
    later output; ego_1 plays on to the time limit (truncated), then stepping raises."""
    env = counterscene_env.parallel_env(num_egos=2, config={"duration": 2.0})
    env.reset(seed=0, options={"scene": crash_scene()})
    assert ego_ids(env) == ["a0", "a1"]
    full = np.array([1.0, 0.0], np.float32)
    gone_at = None
    for k in range(20):
        actions = {a: full if a == "ego_0" else ZERO for a in env.agents}
        # An action still given for the ended ego (a loop over the last observations) is
        # ignored.
        outputs = env.step({"ego_0": full, **actions})
        for out in outputs:
            assert set(out) == set(actions), f"step {k}: only the live agents' entries"
        _, rewards, terms, truncs, infos = outputs
        if gone_at is None and terms.get("ego_0"):
            gone_at = k
            assert infos["ego_0"]["collision"] and infos["ego_0"]["collided_with"] == "a2"
            assert rewards["ego_0"] < -4.0 and "metrics" in infos["ego_0"]
            assert not truncs["ego_0"] and env.agents == ["ego_1"]
        if not env.agents:
            break
    assert gone_at is not None and gone_at < 19
    assert k == 19 and truncs == {"ego_1": True} and terms == {"ego_1": False}
    assert "metrics" in infos["ego_1"]
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})
    env.close()


def test_an_ego_ending_mid_decision_does_not_cut_the_others_decision_short():
    """At 2 Hz every decision of the surviving ego lasts 5 closed-loop steps, also the one in
    which the other ego crashes."""
    env = counterscene_env.parallel_env(num_egos=2, config={"duration": 3.0, "policy_frequency": 2})
    env.reset(seed=0, options={"scene": crash_scene()})
    full = np.array([1.0, 0.0], np.float32)
    steps = []
    while env.agents:
        actions = {a: full if a == "ego_0" else ZERO for a in env.agents}
        _, _, terms, _, infos = env.step(actions)
        steps.append(infos["ego_1"]["step"])
        if "ego_0" in terms:
            ended = terms["ego_0"]
    assert ended
    assert steps == [5, 10, 15, 20, 25, 30]
    env.close()


def test_reset_cannot_change_the_spaces():
    env = counterscene_env.parallel_env(num_egos=1, config={"duration": 1.0, "scenario": "merge"})
    with pytest.raises(ValueError, match="spaces are fixed"):
        env.reset(seed=0, options={"config": {"action": {"type": "DiscreteMetaAction"}}})
    env.close()
