"""The batched vector env (``gymnasium.make_vec("CounterScene-v0", num_envs=N)``) and its SB3
adapter: the same episodes as N single envs, one world-model call per replan, Gymnasium's
autoreset modes and info format, bad input refused."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import crash_scene
from gymnasium.vector import AutoresetMode

import counterscene_env  # noqa: F401  (registers the envs)
from counterscene_env.envs.sb3_vec import SB3VecEnv, unbatch_info
from counterscene_env.envs.vector import CounterSceneVectorEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# Short episodes of mixed roads (different agent counts in one batch), one sample per replan.
CONFIG = {"duration": 1.5, "num_samples": 1, "scenario": ["merge", "intersection"]}


def single_env_steps(seed: int, actions: list, scene=None) -> list:
    """A single env's results for ``actions``, reset with ``seed`` and then, after each end,
    without one (Gymnasium's next-step autoreset, by hand): [(obs, reward, terminated,
    truncated, info)] with reward 0 and the reset's obs and info at each autoreset."""
    env = gym.make("CounterScene-v0", config=CONFIG)
    obs, info = env.reset(seed=seed, options=None if scene is None else {"scene": scene})
    out, ended = [(obs, 0.0, False, False, info)], False
    for action in actions:
        if ended:
            obs, info = env.reset()
            out.append((obs, 0.0, False, False, info))
            ended = False
        else:
            out.append(env.step(action))
            ended = out[-1][2] or out[-1][3]
    env.close()
    return out


@pytest.mark.slow
def test_each_env_of_the_vector_env_plays_the_single_envs_episode():
    """Env by env, the same seeds and actions give the same observations, rewards, ends and
    infos as separate single envs, across autoresets, with scenes of different sizes and
    lengths in one batch (env 0 crashes within a second, the others go on)."""
    N, steps = 3, 24
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, N, 2)).astype(np.float32)
    actions[:, 0] = [1.0, 0.0]  # env 0: full throttle into the parked car of the crash scene
    venv = gym.make_vec("CounterScene-v0", num_envs=N, config=CONFIG)
    assert isinstance(venv, CounterSceneVectorEnv)
    scenes = [crash_scene(), None, None]
    obs, info = venv.reset(seed=7, options={"scenes": scenes})
    got = [[(obs[i], 0.0, False, False, unbatch_info(info, i))] for i in range(N)]
    for t in range(steps):
        obs, rewards, terminated, truncated, info = venv.step(actions[t])
        for i in range(N):
            got[i].append((obs[i], rewards[i], terminated[i], truncated[i], unbatch_info(info, i)))
    venv.close()
    ends = []
    for i in range(N):
        want = single_env_steps(7 + i, list(actions[:, i]), scenes[i])
        for t, (g, w) in enumerate(zip(got[i], want, strict=True)):
            np.testing.assert_equal(g[0], w[0], err_msg=f"env {i} obs at step {t}")
            assert (float(g[1]), bool(g[2]), bool(g[3])) == (float(w[1]), w[2], w[3]), (i, t)
            np.testing.assert_equal(g[4], w[4], err_msg=f"env {i} info at step {t}")
        ends.append([t for t, w in enumerate(want) if w[2] or w[3]])
    assert got[0][ends[0][0]][2], "env 0 crashes (terminated)"
    assert ends[0][0] < ends[1][0], "env 0 ends while the others go on"
    assert sum(map(len, ends)) >= N + 1, "the run covers autoresets"


class CountingReplanner:
    """Wraps a closed loop's replanner and records the episodes of each call."""

    def __init__(self, inner):
        self.inner, self.calls = inner, []

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __call__(self, episodes):
        self.calls.append(len(episodes))
        return self.inner(episodes)


def test_a_replan_is_one_world_model_call_for_every_env():
    venv = CounterSceneVectorEnv(4, config={**CONFIG, "scenario": "merge", "duration": 1.0})
    venv.reset(seed=0)
    venv.loop.replanner = counting = CountingReplanner(venv.loop.replanner)
    venv.step(np.zeros((4, 2), np.float32))
    assert counting.calls == [4]  # the first frame: every env replans, in one call
    venv.close()


THROTTLE = np.array([[1.0, 0.0], [0.0, 0.0]], np.float32)  # env 0 into the parked car


def drive_until_env_0_ends(venv):
    """Step with THROTTLE until env 0 ends (within a second); the last step's results."""
    for _ in range(10):
        result = venv.step(THROTTLE)
        if result[2][0] or result[3][0]:
            return result
    raise AssertionError("env 0 did not crash")


def test_same_step_autoreset_reports_the_final_observation_and_info():
    venv = CounterSceneVectorEnv(2, config=CONFIG, autoreset_mode=AutoresetMode.SAME_STEP)
    venv.reset(seed=3, options={"scenes": [crash_scene(), None]})
    obs, _, terminated, truncated, info = drive_until_env_0_ends(venv)
    assert terminated[0] and not truncated[0] and not terminated[1]
    assert info["_final_obs"].tolist() == [True, False]
    final = unbatch_info(info["final_info"], 0)
    assert final["collision"] and "metrics" in final
    assert not np.array_equal(info["final_obs"][0], obs[0])  # obs[0] is the new episode's
    assert info["_collision"].all()  # every env reports its step (or reset) info
    venv.close()


def test_disabled_autoreset_needs_a_masked_reset_that_leaves_the_others_alone():
    venv = CounterSceneVectorEnv(2, config=CONFIG, autoreset_mode="Disabled")
    venv.reset(seed=3, options={"scenes": [crash_scene(), None]})
    _, _, terminated, _, _ = drive_until_env_0_ends(venv)
    assert terminated[0]
    with pytest.raises(RuntimeError, match="reset_mask"):
        venv.step(np.zeros((2, 2), np.float32))
    step_before = venv.envs[1].episode.t
    _, info = venv.reset(seed=[11, None], options={"reset_mask": np.array([True, False])})
    assert venv.envs[1].episode.t == step_before  # env 1 untouched
    assert info["_step"].tolist() == [True, False]
    venv.step(np.zeros((2, 2), np.float32))  # both run again
    venv.close()


def test_bad_input_is_refused_and_changes_nothing():
    venv = CounterSceneVectorEnv(2, config=CONFIG)
    with pytest.raises(RuntimeError, match="reset"):
        venv.step(np.zeros((2, 2), np.float32))
    venv.reset(seed=0)
    steps = [env.episode.t for env in venv.envs]
    bad = np.zeros((2, 2), np.float32)
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        venv.step(bad)
    assert [env.episode.t for env in venv.envs] == steps  # env 0 did not move either
    for options, match in [
        ({"config": {"observation": {"type": "OccupancyGrid"}}}, "observation"),
        ({"scene": crash_scene()}, "scenes"),
        ({"scenes": [crash_scene()]}, "list of 2"),
        ({"reset_mask": np.array([1, 0])}, "bool"),
        ({"config": {"duration": -1.0}}, "duration"),
        ({"scenes": [None, "merge"]}, r"scenes'\]\[1\]"),
        ({"episode_seeds": [1, -1]}, r"episode_seeds'\]\[1\]"),
        ({"episode_seeds": [1, 2**64]}, r"episode_seeds'\]\[1\]"),
        ({"selection_seeds": [-1, None]}, r"selection_seeds'\]\[0\]"),
        ({"selection_seed": 3}, "selection_seeds"),
        ("scenes", "options must be a dict or None"),
    ]:
        with pytest.raises((ValueError, TypeError), match=match):
            venv.reset(seed=0, options=options)
    # A misspelt option is named once, with the vector env's own keys, and ignored.
    with pytest.warns(
        UserWarning, match=r"\['episode_seedz'\]; known: \['config', 'reset_mask', 'scenes'"
    ) as caught:
        venv.reset(seed=0, options={"episode_seedz": [1, 2]})
    assert len([w for w in caught if "unknown options" in str(w.message)]) == 1
    steps = [env.episode.t for env in venv.envs]
    with pytest.raises(ValueError, match="one entry per env"):
        venv.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match=r"seed\[1\]"):
        venv.reset(seed=[1, -2])
    with pytest.raises(ValueError, match="num_envs"):
        CounterSceneVectorEnv(0)
    with pytest.raises(TypeError, match="num_envs"):  # a wrong type is a TypeError, as in configs
        CounterSceneVectorEnv("2")
    assert [env.episode.t for env in venv.envs] == steps
    venv.close()


def test_infos_of_mixed_types_widen_instead_of_truncating():
    venv = CounterSceneVectorEnv.__new__(CounterSceneVectorEnv)
    venv.num_envs = 3
    infos = {}
    for i, info in enumerate([{"tier": 1, "x": 1}, {"tier": None, "x": 2.5}, {"x": 3}]):
        infos = venv._add_info(infos, info, i)
    assert infos["tier"].tolist() == [1, None, None] and infos["_tier"].tolist() == [1, 1, 0]
    assert infos["x"].tolist() == [1.0, 2.5, 3.0]


@pytest.mark.slow
def test_sb3_ppo_trains_on_the_vector_env():
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    config = {**CONFIG, "scenario": "merge", "policy_frequency": 2, "duration": 2.0}
    venv = SB3VecEnv(2, config=config)
    venv.seed(5)
    obs = venv.reset()
    assert obs.shape == (2, *venv.observation_space.shape)
    seen_end = False
    for _ in range(6):
        venv.step_async(np.zeros((2, 2), np.float32))
        obs, rewards, dones, infos = venv.step_wait()
        assert rewards.dtype == np.float32 and len(infos) == 2
        for i in np.flatnonzero(dones):
            seen_end = True
            assert infos[i]["terminal_observation"].shape == obs[i].shape
            assert "metrics" in infos[i] and "TimeLimit.truncated" in infos[i]
    assert seen_end  # 2 s at 2 Hz: every env ends within 4 steps
    model = PPO("MlpPolicy", VecMonitor(venv), n_steps=8, batch_size=16, n_epochs=1, seed=0)
    model.learn(16)
    assert model.num_timesteps == 16
    venv.close()


def test_gymnasium_vector_conventions_and_wrappers():
    """Batched spaces, dtypes and shapes as Gymnasium's vector envs have them, and
    Gymnasium's vector wrappers work on it (episode statistics at each end)."""
    from gymnasium.wrappers.vector import RecordEpisodeStatistics

    venv = RecordEpisodeStatistics(
        gym.make_vec("CounterScene-merge-v0", num_envs=2, config={**CONFIG, "duration": 0.5})
    )
    assert venv.observation_space.shape == (2, *venv.single_observation_space.shape)
    assert venv.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
    obs, _ = venv.reset(seed=1)
    assert obs in venv.observation_space
    venv.action_space.seed(1)
    for _ in range(5):
        obs, rewards, terminated, truncated, infos = venv.step(venv.action_space.sample())
        assert obs in venv.observation_space
        assert rewards.dtype == np.float64 and terminated.dtype == truncated.dtype == np.bool_
        assert rewards.shape == terminated.shape == (2,)
    assert truncated.all() and infos["_episode"].all()  # 0.5 s: both end at step 5
    assert infos["episode"]["l"].tolist() == [5, 5]
    venv.close()
