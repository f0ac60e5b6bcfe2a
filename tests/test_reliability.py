"""Nothing breaks, nothing is lost: every bad config, reset or action is refused with a message
that names the key, and a refused call leaves the env exactly as it was."""

from __future__ import annotations

import copy
import hashlib
import json
import math

import gymnasium as gym
import numpy as np
import pytest

import counterscene_env
from counterscene_env.envs.single_agent import CounterSceneEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHORT = {"duration": 1.0, "num_samples": 2}


def snapshot(env) -> str:
    """Everything a refused call must leave alone, as one digest: the config, the clock, the
    generator's state, the episode records and the egos' vehicles."""
    env = env.unwrapped
    h = hashlib.sha256()
    h.update(json.dumps(env.config, sort_keys=True, default=repr).encode())
    h.update(repr((env.time, env.steps, env.np_random.bit_generator.state)).encode())
    h.update(repr((env.observation_space, env.action_space)).encode())
    if env.loop is not None:
        for ep in env.loop.episodes:
            for array in (ep.positions, ep.yaws, ep.speeds, ep.valid, ep.source, ep.plan_positions):
                h.update(np.ascontiguousarray(array).tobytes())
            h.update(repr((ep.t, ep.replans, len(ep.records))).encode())
            h.update(repr(ep.rng.bit_generator.state).encode())
            h.update(repr(ep.generator.get_state().tolist()).encode())
    for v in env.controlled_vehicles or []:
        h.update(repr((v.position.tolist(), v.heading, v.speed, v.crashed)).encode())
    return h.hexdigest()


@pytest.fixture(scope="module")
def shard(generated, tmp_path_factory):
    from counterscene_env.scene.shards import save_scenes

    path = tmp_path_factory.mktemp("reliability") / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"]], path)
    return str(path)


@pytest.fixture
def env(shard):
    env = gym.make("CounterScene-v0", config={"scenario": shard, **SHORT})
    env.reset(seed=3)
    env.step(np.zeros(2, np.float32))
    yield env
    env.close()


OBS = CounterSceneEnv.default_config()["observation"]

BAD_CONFIGS = [
    # (config update, exception type, words the message must contain)
    ({"strict_gates": "False"}, TypeError, ["strict_gates", "'False'", "bool"]),
    ({"terminate_on_collision": "no"}, TypeError, ["terminate_on_collision", "bool"]),
    ({"traffic_yields": None}, TypeError, ["traffic_yields", "None"]),
    ({"replan_every": 2.5}, TypeError, ["replan_every", "2.5", "int"]),
    ({"replan_every": True}, TypeError, ["replan_every", "True", "int"]),
    ({"replan_every": 0}, ValueError, ["replan_every", ">= 1"]),
    ({"collision_reward": math.nan}, ValueError, ["collision_reward", "nan", "finite"]),
    ({"collision_reward": "x"}, TypeError, ["collision_reward", "'x'"]),
    ({"num_samples": 1.5}, TypeError, ["num_samples", "1.5", "int"]),
    ({"num_samples": 10**6}, ValueError, ["num_samples", "GB", "memory_limit_gb"]),
    ({"duration": "5"}, TypeError, ["duration", "'5'"]),
    ({"duration": 0.05}, ValueError, ["duration", ">= 0.1", "0.05"]),  # rounds to no step
    ({"guidance": ["full"]}, ValueError, ["guidance", "['full']", "none"]),
    ({"scenario": None}, ValueError, ["scenario", "None"]),
    ({"scenario": "scenarionet:"}, ValueError, ["scenario", "names no path"]),
    ({"observation": "Kinematics"}, TypeError, ["observation", "'Kinematics'", "dict"]),
    ({"observation": {}}, ValueError, ["observation", "type"]),
    ({"observation": {**OBS, "features": []}}, ValueError, ["features", "[]"]),
    ({"observation": {**OBS, "features": ["bogus"]}}, ValueError, ["features", "'bogus'"]),
    ({"observation": {**OBS, "vehicles_count": 0}}, ValueError, ["vehicles_count", "0", ">= 1"]),
    ({"observation": {**OBS, "vehicles_count": -1}}, ValueError, ["vehicles_count", "-1"]),
    ({"observation": {"type": "Telepathy"}}, ValueError, ["observation", "'Telepathy'"]),
    ({"action": {"type": "Teleport"}}, ValueError, ["action", "'Teleport'"]),
    ({"action": ["ContinuousAction"]}, TypeError, ["action", "dict"]),
    ({"reward_speed_range": [5.0]}, ValueError, ["reward_speed_range"]),
    ({"policy_frequency": 3}, ValueError, ["policy_frequency", "3"]),
    ({"screen_width": 100}, ValueError, ["screen_width", "100"]),
    ({"memory_limit_gb": -1.0}, ValueError, ["memory_limit_gb", "-1.0"]),
    # Settings checked against the model or each other at make, not at the first step.
    ({"sampling_steps": 1000}, ValueError, ["sampling_steps", "<= 100", "1000"]),
    ({"eta": 5.0}, ValueError, ["eta", "<= 1"]),
    ({"warm_first_replan": True, "warm_start_steps": 0}, ValueError, ["warm_start_steps"]),
    # What lies inside highway-env's observation and action configs.
    (
        {"observation": {**OBS, "features_range": {"x": "abc"}}},
        ValueError,
        ["observation.features_range.x", "'abc'"],
    ),
    (
        {"observation": {**OBS, "features_range": {"x": [100, -100]}}},
        ValueError,
        ["features_range.x", "low < high"],
    ),
    (
        {"action": {"type": "DiscreteMetaAction", "target_speeds": []}},
        ValueError,
        ["action.target_speeds", "[]"],
    ),
    (
        {"action": {"type": "ContinuousAction", "steering_range": "x"}},
        ValueError,
        ["action.steering_range", "'x'"],
    ),
    (
        {"action": {"type": "ContinuousAction", "acceleration_range": [5, -5]}},
        ValueError,
        ["action.acceleration_range", "low < high"],
    ),
    # highway-env types that build, then fail at the first reset (no parking goal, ...).
    ({"observation": {"type": "KinematicsGoal"}}, ValueError, ["KinematicsGoal", "parking goal"]),
    ({"observation": {"type": "ExitObservation"}}, ValueError, ["ExitObservation", "exit lane"]),
    (
        {"observation": {"type": "AttributesObservation", "attributes": ["goal"]}},
        ValueError,
        ["AttributesObservation", "attributes"],
    ),
    (
        {"observation": {"type": "OccupancyGrid", "grid_size": [[-5, 5]]}},
        ValueError,
        ["observation.grid_size", "[[-5, 5]]"],
    ),
    (
        {"observation": {"type": "OccupancyGrid", "grid_step": [0, 5]}},
        ValueError,
        ["observation.grid_step", "> 0"],
    ),
    (
        {"observation": {"type": "TupleObservation", "observation_configs": []}},
        ValueError,
        ["observation.observation_configs", "non-empty"],
    ),
    (
        {"observation": {"type": "TupleObservation", "observation_configs": [{**OBS, "clip": 1}]}},
        TypeError,
        ["observation.observation_configs[0].clip", "bool"],
    ),
    ({"observation": {**OBS, "order": "bogus"}}, ValueError, ["observation.order", "'bogus'"]),
    ({"observation": {**OBS, "normalize": "yes"}}, TypeError, ["observation.normalize", "'yes'"]),
    (
        {"observation": {"type": "LidarObservation", "maximum_range": -5}},
        ValueError,
        ["observation.maximum_range", "-5"],
    ),
]


def _ids(case):
    return json.dumps(case[0], default=repr)[:60]


@pytest.mark.parametrize(("update", "kind", "words"), BAD_CONFIGS, ids=map(_ids, BAD_CONFIGS))
def test_a_bad_config_is_refused_at_make_with_the_key_named(shard, update, kind, words):
    with pytest.raises(kind) as info:
        gym.make("CounterScene-v0", config={"scenario": shard, **SHORT, **update})
    for word in words:
        assert word in str(info.value), (word, str(info.value))


@pytest.mark.parametrize(("update", "kind", "words"), BAD_CONFIGS, ids=map(_ids, BAD_CONFIGS))
def test_a_refused_reset_or_configure_changes_nothing(env, update, kind, words):
    before = snapshot(env)
    with pytest.raises(kind):
        env.reset(options={"config": update})
    assert snapshot(env) == before
    with pytest.raises(kind):
        env.unwrapped.configure(update)
    assert snapshot(env) == before
    # ... and the episode goes on.
    info = env.step(np.zeros(2, np.float32))[4]
    assert info["step"] == 2


@pytest.mark.parametrize("prefix", ["", "scenarionet:", "commonroad:"])
def test_a_folder_without_scenes_is_refused_before_anything_changes(env, tmp_path, prefix):
    """A path that exists but holds no playable scene is refused when the config is set
    (at make, by configure, by reset), naming the scenario: not at a later draw."""
    spec = prefix + str(tmp_path)
    with pytest.raises(ValueError, match="scenario"):
        gym.make("CounterScene-v0", config={"scenario": spec})
    before = snapshot(env)
    with pytest.raises(ValueError, match="scenario"):
        env.reset(options={"config": {"scenario": spec}})
    assert snapshot(env) == before
    assert env.step(np.zeros(2, np.float32))[4]["step"] == 2
    env.reset()  # and a plain reset still works


BAD_ACTIONS = [
    (["0.1", "0.2"], TypeError, "numbers"),
    ([10**400, 0], TypeError, "numbers"),
    ([math.nan, 0.0], ValueError, "NaN"),
    ([0.0, math.inf], ValueError, "inf"),
    ([0.0], ValueError, "shape"),
    (None, TypeError, "numbers"),
    ({"acceleration": 1}, TypeError, "numbers"),
]


@pytest.mark.parametrize(
    ("action", "kind", "words"), BAD_ACTIONS, ids=[repr(a)[:20] for a, *_ in BAD_ACTIONS]
)
def test_a_refused_step_changes_nothing(env, action, kind, words):
    before = snapshot(env)
    with pytest.raises(kind, match=words):
        env.step(action)
    assert snapshot(env) == before
    _, _, _, _, info = env.step(np.zeros(2, np.float32))
    assert info["step"] == 2 and env.unwrapped.time == pytest.approx(0.2)
    assert info["time"] == pytest.approx(0.2)


def test_a_bad_scene_option_changes_nothing(env):
    before = snapshot(env)
    for options, kind in (
        ({"scene": "merge"}, TypeError),
        ({"episode_seed": "7"}, TypeError),
        ({"episode_seed": -1}, ValueError),
        ({"selection_seed": 1.5}, TypeError),
        ({"selection_seed": -1}, ValueError),
        ({"episode_seed": 2**64}, ValueError),  # more than the torch generator's 64 bits
        ({"selection_seed": 2**64}, ValueError),
        ({"config": ["duration", 1.0]}, TypeError),
    ):
        with pytest.raises(kind, match=next(iter(options))):
            env.reset(options=options)
        assert snapshot(env) == before


def test_numpy_integer_seeds_are_seeds(env):
    """``np.int64`` seeds (what ``rng.integers`` gives) run the episode an ``int`` runs."""
    env.reset(seed=np.int64(5))
    a = env.step(np.full(2, 0.3, np.float32))[0]
    env.reset(seed=5)
    assert np.array_equal(env.step(np.full(2, 0.3, np.float32))[0], a)


def test_unknown_reset_options_are_named_in_a_warning(env):
    with pytest.warns(UserWarning, match=r"unknown options \['confg'\].*'config'"):
        env.reset(seed=1, options={"confg": {"duration": 3.0}})
    with pytest.raises(TypeError, match="options must be a dict"):
        env.reset(options=[1])


def test_render_fps_is_the_policy_frequency_from_construction(shard):
    """Gymnasium's ``RecordVideo`` reads ``render_fps`` when it wraps the env, before any
    reset: one frame per policy step must be played at the policy frequency."""
    config = {"scenario": shard, **SHORT, "policy_frequency": 2}
    env = gym.make("CounterScene-v0", config=config)
    assert env.metadata["render_fps"] == 2
    env.unwrapped.configure({"policy_frequency": 5})
    assert env.unwrapped.metadata["render_fps"] == 5
    vec = gym.make_vec("CounterScene-v0", num_envs=2, config=config)
    par = counterscene_env.parallel_env(num_egos=2, config=config)
    assert vec.metadata["render_fps"] == par.metadata["render_fps"] == 2
    assert CounterSceneEnv.metadata["render_fps"] == 10  # the class default is untouched


def test_a_failure_inside_a_step_asks_for_a_reset(env, monkeypatch):
    """A bug (not bad input) mid-step: the env says it needs reset(), and reset() heals it."""
    core = env.unwrapped

    def broken(*args, **kwargs):
        raise ZeroDivisionError("simulated bug")

    monkeypatch.setattr(core.loop, "step", broken)
    with pytest.raises(RuntimeError, match=r"simulated bug.*reset\(\)"):
        env.step(np.zeros(2, np.float32))
    monkeypatch.undo()
    with pytest.raises(RuntimeError, match=r"reset\(\)"):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=4)
    env.step(np.zeros(2, np.float32))


def test_parallel_env_refuses_bad_configs_and_actions_without_changes(shard):
    env = counterscene_env.parallel_env(num_egos=2, config={"scenario": shard, **SHORT})
    env.reset(seed=0)
    before = snapshot(env.core)
    with pytest.raises(TypeError, match="num_samples"):
        env.reset(options={"config": {"num_samples": "4"}})
    with pytest.raises(TypeError, match="numbers"):
        env.step({"ego_0": ["a", "b"], "ego_1": [0.0, 0.0]})
    assert snapshot(env.core) == before
    for bad in ({"num_samples": -1}, {"observation": {"type": "Kinematics", "features": []}}):
        with pytest.raises(ValueError):
            counterscene_env.parallel_env(num_egos=2, config={"scenario": shard, **bad})
    env.close()


def test_kinematics_observation_stays_inside_its_space_with_one_vehicle(shard):
    obs_config = {**copy.deepcopy(OBS), "vehicles_count": 1}
    env = gym.make(
        "CounterScene-v0", config={"scenario": shard, **SHORT, "observation": obs_config}
    )
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    env.close()


EPISODE_SCRIPT = """
import hashlib, json, sys
import gymnasium as gym, numpy as np
import counterscene_env
env = gym.make("CounterScene-v0", config={"scenario": sys.argv[1], "duration": 2.0})
rng = np.random.default_rng(11)
out = []
obs, info = env.reset(seed=5)
for _ in range(25):
    obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
    out.append([hashlib.sha256(obs.tobytes()).hexdigest(), repr(reward), terminated, truncated,
                json.dumps(info, sort_keys=True, default=repr)])
    if terminated or truncated:
        obs, info = env.reset()
print(json.dumps(out))
"""


@pytest.mark.slow
def test_the_same_seed_and_actions_give_the_same_episode_in_two_processes(shard):
    import os
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "1", "SDL_VIDEODRIVER": "dummy"}
    runs = [
        subprocess.run(
            [sys.executable, "-c", EPISODE_SCRIPT, shard],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        for _ in range(2)
    ]
    assert json.loads(runs[0]) == json.loads(runs[1])
    assert len(json.loads(runs[0])) == 25
