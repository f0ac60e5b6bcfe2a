"""``gymnasium.make_vec("CounterScene-v0", num_envs=N, workers=W)``: the envs in W processes,
the same episodes as in one, bad input refused by every shard before any acts, SB3 on it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import crash_scene
from gymnasium.vector import AutoresetMode

import counterscene_env  # noqa: F401  (registers the envs)
from counterscene_env.envs.sb3_vec import SB3VecEnv
from counterscene_env.envs.sharded import ShardedVectorEnv, vector_env
from counterscene_env.envs.vector import CounterSceneVectorEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CONFIG = {"duration": 1.5, "num_samples": 1, "scenario": ["merge", "intersection"]}


def play(venv, seed: int, scenes: list, actions: np.ndarray) -> list:
    """Every result of a reset and ``len(actions)`` steps."""
    out = [venv.reset(seed=seed, options={"scenes": scenes})]
    out += [venv.step(a) for a in actions]
    return out


@pytest.mark.slow
def test_the_envs_of_two_workers_play_the_episodes_of_one_process():
    """Observations, rewards, ends and infos (Gymnasium's vector format) are those of the
    one-process vector env, across autoresets, with a shard of two envs and one of one."""
    N, steps = 3, 16
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, (steps, N, 2)).astype(np.float32)
    actions[:, 0] = [1.0, 0.0]  # env 0 crashes into the parked car and is reset
    scenes = [crash_scene(), None, None]
    one = gym.make_vec("CounterScene-v0", num_envs=N, config=CONFIG)
    want = play(one, 4, scenes, actions)
    one.close()
    two = gym.make_vec("CounterScene-v0", num_envs=N, workers=2, config=CONFIG)
    assert isinstance(two, ShardedVectorEnv) and [s.stop - s.start for s in two.shards] == [2, 1]
    got = play(two, 4, scenes, actions)
    assert two.get_attr("slot") == (0, 1, 0)  # env 2 is env 0 of the second worker
    two.close()
    for t, (g, w) in enumerate(zip(got, want, strict=True)):
        for part, (x, y) in enumerate(zip(g, w, strict=True)):
            np.testing.assert_equal(x, y, err_msg=f"step {t}, result part {part}")
    assert any(result[2][0] for result in want[1:]), "env 0 crashes"


@pytest.mark.slow
def test_a_refused_call_changes_no_env_of_any_worker():
    venv = vector_env(3, workers=2, config=CONFIG, autoreset_mode=AutoresetMode.DISABLED)
    with pytest.raises(RuntimeError, match="reset"):
        venv.step(np.zeros((3, 2), np.float32))
    venv.reset(seed=0, options={"scenes": [None, None, crash_scene()]})
    steps = venv.get_attr("steps")
    bad = np.zeros((3, 2), np.float32)
    bad[2, 0] = np.nan  # only the second worker's env is bad: the first must not move
    with pytest.raises(ValueError, match="NaN"):
        venv.step(bad)
    with pytest.raises(ValueError, match=r"one row per env"):  # as with one process
        venv.step(np.zeros(2, np.float32))
    # An error names the env by its index in the whole vector env, not in its worker.
    with pytest.raises(ValueError, match=r"episode_seeds'\]\[2\]"):
        venv.reset(seed=0, options={"episode_seeds": [1, 2, -1]})
    with pytest.raises(ValueError, match="one entry per env"):
        venv.reset(seed=[1, 2])
    with pytest.raises(TypeError, match="options must be a dict or None"):
        venv.reset(options="scenes")
    with pytest.raises(ValueError, match="closed-loop settings"):
        venv.reset(options={"reset_mask": np.array([False, True, True]), "config": {"eta": 0.5}})
    assert venv.get_attr("steps") == steps
    for _ in range(10):  # env 2 crashes; autoreset disabled: it must be reset by hand
        _, _, terminated, _, _ = venv.step(np.array([[0, 0], [0, 0], [1, 0]], np.float32))
        if terminated[2]:
            break
    assert terminated[2]
    with pytest.raises(RuntimeError, match=r"envs \[2\] ended"):
        venv.step(np.zeros((3, 2), np.float32))
    _, info = venv.reset(seed=[None, None, 9], options={"reset_mask": np.array([0, 0, 1], bool)})
    assert info["_step"].tolist() == [False, False, True]
    venv.step(np.zeros((3, 2), np.float32))
    venv.close()
    with pytest.raises(ValueError, match="workers"):
        vector_env(2, workers=0)
    with pytest.raises(ValueError, match="cannot exceed"):
        ShardedVectorEnv(2, workers=3)
    assert isinstance(vector_env(1), CounterSceneVectorEnv)


@pytest.mark.slow
def test_sb3_steps_and_reaches_the_envs_of_every_worker():
    config = {**CONFIG, "scenario": "merge", "policy_frequency": 2, "duration": 1.0}
    venv = SB3VecEnv(3, config=config, workers=2)
    venv.seed(2)
    obs = venv.reset()
    assert obs.shape == (3, *venv.observation_space.shape)
    ends = 0
    for _ in range(3):
        venv.step_async(np.zeros((3, 2), np.float32))
        obs, _, dones, infos = venv.step_wait()
        for i in np.flatnonzero(dones):
            ends += 1
            assert infos[i]["terminal_observation"].shape == obs[i].shape
    assert ends >= 3  # 1 s at 2 Hz: every env ends by the second step
    assert venv.get_attr("slot", indices=[1, 2]) == [1, 0]
    assert venv.env_method("ego_truncated", indices=2) == [False]  # reset in the same step
    venv.set_attr("note", "hello", indices=[0, 2])
    assert venv.get_attr("note", indices=[0, 2]) == ["hello", "hello"]
    assert venv.venv.metadata["render_fps"] == 2  # the policy frequency, as each env's
    venv.close()
