"""Fuzzing with Hypothesis: random valid configs and actions keep every promise of the env;
random invalid configs and actions are refused with the key named and change nothing; random
mutations of scene files load or are refused with a clear error, never a traceback.

Two profiles: ``ci`` (the default, a short run inside the test command) and ``long``
(``COUNTERSCENE_FUZZ=long``; ``COUNTERSCENE_FUZZ_EXAMPLES`` sets its examples per test, a
twentieth of them for the test that plays whole episodes).
``COUNTERSCENE_FUZZ_REPORT=PATH`` writes what was tried (configs, env steps, actions, file
mutations, refusals) as JSON at the end.
"""

from __future__ import annotations

import io
import json
import math
import os
import pickle
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_reliability import snapshot

from counterscene_env.config import GuidancePreset, Sampler, SelectionSource, Selector
from counterscene_env.envs.single_agent import CounterSceneEnv
from counterscene_env.envs.spaces import KINEMATIC_FEATURES
from counterscene_env.envs.type_checks import FOREIGN_OBSERVATIONS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

LONG = os.environ.get("COUNTERSCENE_FUZZ") == "long"
settings.register_profile(
    "ci",
    max_examples=6,
    deadline=None,
    derandomize=True,  # the same examples every run: CI stays reproducible
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "long",
    max_examples=int(os.environ.get("COUNTERSCENE_FUZZ_EXAMPLES", 2000)),
    deadline=None,
    suppress_health_check=list(HealthCheck),
)
PROFILE = settings.get_profile("long" if LONG else "ci")
# Whole episodes cost seconds where the other examples cost milliseconds: a twentieth of them.
EPISODES = settings(PROFILE, max_examples=max(PROFILE.max_examples // 20, 1) if LONG else 6)
STEPS = 60 if LONG else 6  # env steps per valid-config example
STATS: Counter = Counter()
INFO_KEYS = {"collision", "hard_braking", "off_road", "min_ttc", "adversary", "fallback"}
INFO_KEYS |= {"rewards", "step", "time", "speed", "crashed", "scenario_id", "replanned"}


@pytest.fixture(scope="module", autouse=True)
def report():
    yield
    path = os.environ.get("COUNTERSCENE_FUZZ_REPORT")
    if path:
        Path(path).write_text(json.dumps(dict(STATS), indent=2) + "\n")


@pytest.fixture(scope="module")
def shard(generated, tmp_path_factory):
    from counterscene_env.scene.shards import save_scenes

    path = tmp_path_factory.mktemp("fuzz") / "scenes.npz"
    save_scenes([generated["merge"], generated["intersection"]], path)
    return str(path)


# ---------------------------------------------------------------------- valid configs
kinematics = st.fixed_dictionaries(
    {
        "type": st.just("Kinematics"),
        "vehicles_count": st.integers(1, 12),
        "features": st.lists(
            st.sampled_from(KINEMATIC_FEATURES), min_size=1, max_size=7, unique=True
        ),
    },
    optional={
        "normalize": st.booleans(),
        "absolute": st.booleans(),
        "see_behind": st.booleans(),
        "order": st.sampled_from(["sorted", "shuffled"]),
    },
)
lidar = st.builds(
    lambda cells, reach: {"type": "LidarObservation", "cells": cells, "maximum_range": reach},
    st.integers(1, 32),
    st.floats(1.0, 100.0),
)
time_to_collision = st.just({"type": "TimeToCollision", "horizon": 5})
observations = st.one_of(
    kinematics,
    st.just({"type": "OccupancyGrid", "grid_size": [[-20, 20], [-20, 20]], "grid_step": [5, 5]}),
    time_to_collision,
    lidar,
    st.builds(
        lambda parts: {"type": "TupleObservation", "observation_configs": parts},
        st.lists(st.one_of(kinematics, lidar, time_to_collision), min_size=1, max_size=2),
    ),
)
valid_updates = st.fixed_dictionaries(
    {"observation": observations},
    optional={
        "policy_frequency": st.sampled_from([1, 2, 5, 10]),
        "num_samples": st.integers(1, 3),
        "replan_every": st.integers(1, 10),
        "duration": st.floats(0.3, 2.0),
        "selector": st.sampled_from(Selector.values()),
        "guidance": st.sampled_from(GuidancePreset.values()),
        "selection_source": st.sampled_from(SelectionSource.values()),
        "strict_gates": st.booleans(),
        "traffic_yields": st.booleans(),
        "road_keeping": st.booleans(),
        "sampler": st.sampled_from(Sampler.values()) | st.none(),
        "sampling_steps": st.integers(1, 10) | st.none(),
        "eta": st.floats(0.0, 1.0) | st.none(),
        "realism_weight": st.floats(0.0, 5.0),
        "realism_horizon": st.floats(0.1, 6.0) | st.none(),
        "max_windows": st.integers(1, 3),
        "collision_reward": st.floats(-10, 10),
        "high_speed_reward": st.floats(-10, 10),
        "terminate_on_collision": st.booleans(),
        "terminate_on_off_road": st.booleans(),
        "action": st.sampled_from([{"type": "ContinuousAction"}, {"type": "DiscreteMetaAction"}]),
    },
)


@EPISODES
@given(update=valid_updates, seed=st.integers(0, 2**31 - 1))
def test_random_valid_configs_and_actions_keep_every_promise(shard, update, seed):
    if "TimeToCollision" in json.dumps(update["observation"]):  # its grid is over the
        update["action"] = {"type": "DiscreteMetaAction"}  # ego's target speeds
    env = gym.make("CounterScene-v0", config={"scenario": shard, **update})
    STATS["valid configs"] += 1
    env.action_space.seed(seed)
    obs, info = env.reset(seed=seed)
    assert env.observation_space.contains(obs)
    for _ in range(STEPS):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        STATS["env steps"] += 1
        assert env.observation_space.contains(obs)
        assert type(reward) is float and math.isfinite(reward)
        assert type(terminated) is bool and type(truncated) is bool
        assert not (terminated and truncated)
        assert INFO_KEYS <= set(info)
        assert isinstance(info["collision"], bool) and isinstance(info["off_road"], bool)
        if terminated or truncated:
            assert "metrics" in info
            obs, info = env.reset()
            STATS["resets"] += 1
    env.close()


# ---------------------------------------------------------------------- invalid configs
def _not(values):
    return lambda x: x not in values


anything_but_bool = st.one_of(
    st.text(max_size=5), st.integers(), st.none(), st.floats(), st.lists(st.booleans())
)
not_a_number = st.one_of(st.text(max_size=5), st.none(), st.booleans(), st.lists(st.floats()))
non_finite = st.sampled_from([math.nan, math.inf, -math.inf])
non_integral = st.floats().filter(lambda x: not (math.isfinite(x) and float(x).is_integer()))


def bad_count(low: int) -> st.SearchStrategy:
    return st.one_of(not_a_number, non_integral, st.integers(max_value=low - 1))


def bad_choice(values) -> st.SearchStrategy:
    return st.one_of(
        st.text(max_size=8).filter(_not(values)), st.integers(), st.none(), st.lists(st.text())
    )


OBS = CounterSceneEnv.default_config()["observation"]
bad_observations = st.one_of(
    st.text(max_size=8),
    st.none(),
    st.integers(),
    st.just({}),
    st.fixed_dictionaries({"type": st.text(max_size=8)}),
    st.builds(lambda f: {**OBS, "features": f}, st.lists(st.text(max_size=4), max_size=3)).filter(
        lambda o: not o["features"] or not set(o["features"]) <= set(KINEMATIC_FEATURES)
    ),
    st.builds(lambda n: {**OBS, "vehicles_count": n}, bad_count(1)),
    st.sampled_from([{"type": kind} for kind in FOREIGN_OBSERVATIONS]),
    st.just({"type": "TupleObservation", "observation_configs": []}),
    st.builds(lambda order: {**OBS, "order": order}, bad_choice(["sorted", "shuffled"])),
)
BAD_VALUES = {
    **{k: anything_but_bool for k in ("strict_gates", "traffic_yields", "road_keeping")},
    **{k: anything_but_bool for k in ("terminate_on_collision", "show_adversary_plan")},
    "num_samples": st.one_of(bad_count(1), st.integers(10**5, 10**12)),
    "replan_every": bad_count(1),
    "max_windows": bad_count(1),
    "sampling_steps": st.one_of(st.text(max_size=3), st.booleans(), non_integral),
    "duration": st.one_of(not_a_number, non_finite, st.floats(max_value=0.1, exclude_max=True)),
    "realism_weight": st.one_of(not_a_number, non_finite, st.floats(max_value=-1e-9)),
    "realism_horizon": st.one_of(  # None is a value: the whole plan
        not_a_number.filter(lambda x: x is not None), non_finite, st.floats(max_value=0)
    ),
    "memory_limit_gb": st.one_of(st.text(max_size=3), non_finite, st.floats(max_value=0)),
    "collision_reward": st.one_of(not_a_number, non_finite),
    "off_road_reward": st.one_of(not_a_number, non_finite),
    "selector": bad_choice(Selector.values()),
    "guidance": bad_choice(GuidancePreset.values()),
    "selection_source": bad_choice(SelectionSource.values()),
    "sampler": bad_choice(Sampler.values()).filter(lambda x: x is not None),
    "policy_frequency": st.one_of(
        not_a_number, st.integers().filter(lambda x: x < 1 or 10 % x), non_integral
    ),
    "screen_width": st.one_of(not_a_number, st.integers().filter(lambda x: x < 16 or x % 16)),
    "reward_speed_range": st.one_of(
        st.text(max_size=3), st.lists(st.floats(-10, 10), max_size=4).filter(lambda v: len(v) != 2)
    ),
    "scenario": st.one_of(
        st.none(),
        st.integers(),
        st.text(min_size=1, max_size=8).map(lambda s: f"no/such/{s}"),
    ),
    "model": st.one_of(st.none(), st.integers(), st.just("")),
    "observation": bad_observations,
    "action": st.one_of(
        st.text(max_size=8), st.none(), st.fixed_dictionaries({"type": st.text(max_size=8)})
    ),
}
bad_updates = st.sampled_from(sorted(BAD_VALUES)).flatmap(
    lambda key: st.tuples(st.just(key), BAD_VALUES[key])
)


@pytest.fixture(scope="module")
def running(shard):
    env = gym.make("CounterScene-v0", config={"scenario": shard, "duration": 1.0})
    env.reset(seed=0)
    env.step(np.zeros(2, np.float32))
    yield env
    env.close()


@PROFILE
@given(bad=bad_updates)
def test_random_invalid_configs_are_refused_and_change_nothing(running, bad):
    key, value = bad
    before = snapshot(running)
    for call in (
        lambda: running.unwrapped.configure({key: value}),
        lambda: running.reset(options={"config": {key: value}}),
    ):
        with pytest.raises((TypeError, ValueError)) as info:
            call()
        assert key.split("_")[0] in str(info.value), str(info.value)
        assert snapshot(running) == before
        STATS["refused configs"] += 1


bad_seeds = st.one_of(
    st.integers(max_value=-1),
    st.integers(min_value=2**64),  # more than the episode's torch generator takes
    st.floats(allow_nan=True),
    st.text(max_size=4),
    st.booleans(),
    st.lists(st.integers(0, 9), max_size=2),
)
bad_reset_options = st.one_of(
    st.tuples(st.sampled_from(["episode_seed", "selection_seed"]), bad_seeds),
    st.tuples(st.just("scene"), st.one_of(st.text(max_size=8), st.integers(), st.just({}))),
    st.tuples(st.just("config"), st.one_of(st.text(max_size=8), st.integers(), st.just([]))),
)


@PROFILE
@given(bad=bad_reset_options)
def test_random_invalid_reset_options_are_refused_and_change_nothing(running, bad):
    key, value = bad
    before = snapshot(running)
    with pytest.raises((TypeError, ValueError)) as info:
        running.reset(options={key: value})
    assert key in str(info.value), str(info.value)
    assert snapshot(running) == before
    STATS["refused reset options"] += 1


bad_actions = st.one_of(
    st.text(max_size=4),
    st.none(),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4).filter(
        lambda a: len(a) != 2 or not all(math.isfinite(x) for x in a)
    ),
    st.lists(st.text(max_size=3), min_size=2, max_size=2),
    st.lists(st.integers(min_value=2**64), min_size=2, max_size=2),
    st.lists(st.lists(st.floats(-1, 1), min_size=2, max_size=2), min_size=1, max_size=3),
)


@PROFILE
@given(action=bad_actions)
def test_random_invalid_actions_are_refused_and_change_nothing(running, action):
    before = snapshot(running)
    with pytest.raises((TypeError, ValueError)):
        running.step(action)
    assert snapshot(running) == before
    STATS["refused actions"] += 1


# ---------------------------------------------------------------------- scene files
@pytest.fixture(scope="module")
def shard_arrays(shard):
    with np.load(shard, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


replacement_arrays = st.one_of(
    st.sampled_from([np.nan, np.inf, -1e300, 0.0, 1e12]).map(np.array),
    st.integers(0, 3).map(lambda n: np.full((n, 2), np.nan)),
    st.integers(0, 5).map(lambda n: np.zeros(n)),
    st.text(max_size=20).map(np.array),
    st.just(np.array([True, False])),
)


@PROFILE
@given(data=st.data())
def test_random_mutations_of_a_shard_load_or_are_refused_clearly(
    shard, shard_arrays, tmp_path_factory, data
):
    from counterscene_env.scene.core import SceneError
    from counterscene_env.scene.shards import load_scenes

    path = tmp_path_factory.mktemp("mutated") / "scenes.npz"
    if data.draw(st.booleans(), label="byte level"):
        raw = bytearray(Path(shard).read_bytes())
        for _ in range(data.draw(st.integers(1, 8), label="flips")):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] = data.draw(st.integers(0, 255))
        cut = data.draw(st.integers(1, len(raw)), label="length")
        path.write_bytes(bytes(raw[:cut]))
    else:
        arrays = dict(shard_arrays)
        key = data.draw(st.sampled_from(sorted(arrays)), label="array")
        if data.draw(st.booleans(), label="delete"):
            del arrays[key]
        else:
            arrays[key] = data.draw(replacement_arrays, label="value")
        np.savez(path, **arrays)
    STATS["file mutations"] += 1
    try:
        scenes = load_scenes(path)
    except SceneError:
        STATS["mutations refused"] += 1
        return
    STATS["mutations loaded"] += 1
    assert all(s.num_agents >= 1 for s in scenes)


@PROFILE
@given(data=st.data())
def test_random_mutations_of_a_scenarionet_file_load_or_are_refused_clearly(tmp_path_factory, data):
    from test_scenarionet import _scenario

    from counterscene_env.scene.core import SceneError
    from counterscene_env.scene.scenarionet import load_scenarionet

    sd = _scenario()
    node, where = sd, []
    while isinstance(node, dict) and node and data.draw(st.booleans(), label="deeper"):
        key = data.draw(st.sampled_from(sorted(node, key=str)), label="key")
        where.append(key)
        parent, node = node, node[key]
    if where:
        parent[where[-1]] = data.draw(
            st.one_of(
                st.none(), st.text(max_size=5), st.integers(), replacement_arrays, st.just({})
            )
        )
    buffer = io.BytesIO()
    pickle.dump(sd, buffer, protocol=4)
    path = tmp_path_factory.mktemp("mutated_pkl") / "scene.pkl"
    path.write_bytes(buffer.getvalue())
    STATS["file mutations"] += 1
    try:
        load_scenarionet(path)
    except SceneError:
        STATS["mutations refused"] += 1
        return
    STATS["mutations loaded"] += 1
