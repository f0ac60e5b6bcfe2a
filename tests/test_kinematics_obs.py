"""The pandas-free Kinematics observation (``envs/kinematics.py``) against highway-env's own
``KinematicObservation.observe``, bit for bit, on the states of short episodes of every
scenario, for the default config and many option combinations."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from highway_env.envs.common.observation import KinematicObservation
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Obstacle

import counterscene_env  # noqa: F401  (registers the envs)
from counterscene_env.envs.kinematics import SOURCES, observe_kinematics
from counterscene_env.envs.spaces import RowCappedKinematics

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: highway-env's pandas method, kept before any test replaces it.
PANDAS_OBSERVE = KinematicObservation.observe
ALL = list(SOURCES)  # every feature of Vehicle.to_dict
STEPS = 8
#: Options set on the observation instance between steps (highway-env reads them at every
#: observe). features_range None: highway-env's lazy default, computed by each path afresh.
VARIANTS = [
    {},  # as the scenario configures it
    {"absolute": True, "order": "shuffled", "normalize": False, "clip": False},
    {"features": ALL[::-1], "vehicles_count": 30, "order": "shuffled", "observe_intentions": True},
    {"vehicles_count": 1, "order": "shuffled", "see_behind": False},
    {"vehicles_count": 1, "features": ["presence", "vx", "x"]},
    {
        "features": ["heading", "vx", "presence", "long_off", "cos_d", "sin_d", "y", "lat_off"],
        "features_range": {
            "heading": [-3.14, 3.14],
            "presence": [0, 2],
            "long_off": [-50.5, 100],
            "vx": [-7, 7.5],
            "y": [-30.0, 30],
            "unused": [0, 1],
        },
        "clip": True,
        "include_obstacles": False,
        "observe_intentions": False,
        "see_behind": False,
    },
    {"vehicles_count": 3, "order": "neither", "features_range": {"x": [-20.0, 20.0]}},
]
#: One env per scenario: every feature, so highway-env keeps each vehicle's lane up to date.
FULL = {"type": "Kinematics", "features": ALL, "vehicles_count": 5, "see_behind": True}
SCENARIOS = {
    "merge": {"observation": {**FULL, "absolute": True, "order": "shuffled", "normalize": False}},
    "roundabout": {"observation": FULL},
    "highway": {"observation": FULL},
    # Two MDPVehicle egos: the second observer is not env.vehicle, and both follow routes
    # (destination directions that are not zero).
    "intersection": {
        "controlled_vehicles": 2,
        "action": {"type": "MultiAgentAction", "action_config": {"type": "DiscreteMetaAction"}},
        "observation": {"type": "MultiAgentObservation", "observation_config": FULL},
    },
}


class OwnRecord(Vehicle):
    """A vehicle class with its own ``to_dict``: its record must be used as is."""

    def to_dict(self, origin_vehicle=None, observe_intentions=True):
        d = super().to_dict(origin_vehicle, observe_intentions)
        d["x"] += 0.25
        del d["heading"]  # pandas: NaN
        return d


@pytest.fixture
def no_pandas(monkeypatch):
    """highway-env's pandas method fails if the env's observations call it: they must take the
    fast path (highway-env's own envs, which record the highway scenes, still use it)."""

    def refuse(self):
        if isinstance(self, RowCappedKinematics):
            raise AssertionError("CounterScene-v0 called highway-env's pandas observe")
        return PANDAS_OBSERVE(self)

    monkeypatch.setattr(KinematicObservation, "observe", refuse)


@pytest.fixture
def float64_rows(monkeypatch):
    """Both paths return their float64 rows uncast (a float64 space instead of float32), so
    that a difference in the last bit of the float64 arithmetic is not hidden by the cast."""

    def space(self):
        shape = (self.vehicles_count, len(self.features))
        return spaces.Box(-np.inf, np.inf, shape, np.float64)

    monkeypatch.setattr(KinematicObservation, "space", space)


def observation_types(env) -> list:
    u = env.unwrapped
    return list(getattr(u.observation_type, "agents_observation_types", [u.observation_type]))


def assert_same(env, obs_type) -> np.ndarray:
    """``obs_type.observe()`` (fast path) equals highway-env's method on the same state, with
    the same random draws and the same lazily set features_range; highway-env's full result."""
    u = env.unwrapped
    lazy = obs_type.features_range is None
    before = u.np_random.bit_generator.state
    fast = obs_type.observe()
    after, fast_range = u.np_random.bit_generator.state, obs_type.features_range
    u.np_random.bit_generator.state = before
    if lazy:
        obs_type.features_range = None
    full = PANDAS_OBSERVE(obs_type)
    slow = full[: obs_type.vehicles_count]
    assert u.np_random.bit_generator.state == after
    assert obs_type.features_range == fast_range
    assert fast.dtype == slow.dtype
    np.testing.assert_array_equal(fast, slow)  # NaN where highway-env has NaN
    bits = np.uint32 if fast.dtype == np.float32 else np.uint64
    np.testing.assert_array_equal(fast.view(bits), slow.view(bits))  # -0.0, NaN payloads
    return full


def run(env, check, seed: int) -> int:
    """Up to STEPS random steps (actions seeded by ``seed``) from the current state, until the
    episode ends; ``check()`` before each step and after the last. The number of checks."""
    env.action_space.seed(seed)
    for n in range(STEPS):
        check()
        if any(env.step(env.action_space.sample())[2:4]):
            return n + 1
    check()
    return STEPS + 1


def add_obstacle_and_own_record(env) -> None:
    """An obstacle 15 m ahead of the ego (NaN heading and lane offsets in pandas) and one
    traffic vehicle whose class has its own to_dict."""
    road, ego = env.unwrapped.road, env.unwrapped.vehicle
    road.objects.append(Obstacle(road, ego.position + 15.0 * ego.direction, ego.heading))
    others = [v for v in road.vehicles if v not in env.unwrapped.controlled_vehicles]
    others[0].__class__ = OwnRecord


@pytest.mark.usefixtures("no_pandas")
def test_default_config_matches_highway_env():
    env = gym.make("CounterScene-v0", config={"duration": 1.0})
    env.reset(seed=3)
    (obs_type,) = observation_types(env)  # reset builds the observation types
    checked = run(env, lambda: assert_same(env, obs_type), seed=3)
    assert obs_type.observe().dtype == np.float32
    assert checked >= 5
    env.close()


@pytest.mark.slow
@pytest.mark.usefixtures("no_pandas", "float64_rows")
# Options changed mid-episode give observations outside the space the env declared.
@pytest.mark.filterwarnings("ignore:.*not within the observation space")
@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_option_combinations_match_highway_env(scenario):
    env = gym.make("CounterScene-v0", config={"scenario": scenario, **SCENARIOS[scenario]})
    env.reset(seed=0)
    add_obstacle_and_own_record(env)
    types = observation_types(env)
    base = {k: getattr(types[0], k) for k in set().union(*VARIANTS)}
    seen = {"padded": 0, "all rows": 0, "nan": 0}

    def check():
        for variant in VARIANTS:
            for obs_type in types:
                for key, value in {**base, "features_range": None, **variant}.items():
                    setattr(obs_type, key, value)
                full = assert_same(env, obs_type)
                seen["padded"] += obs_type.vehicles_count == 30 and not full[-1].any()
                seen["all rows"] += obs_type.vehicles_count == 1 and len(full) > 1
                seen["nan"] += bool(np.isnan(full).any())

    checked = run(env, check, seed=1)
    assert checked >= 4
    # The cases meant to be covered were: zero rows, every vehicle at vehicles_count = 1,
    # the NaN of records without a feature.
    assert seen["padded"] and seen["all rows"] and seen["nan"], seen
    env.close()


def test_unsupported_options_fall_back_to_highway_env(monkeypatch):
    env = gym.make("CounterScene-v0", config={"duration": 1.0})
    env.reset(seed=5)
    (obs_type,) = observation_types(env)
    calls = []
    monkeypatch.setattr(
        KinematicObservation, "observe", lambda self: calls.append(1) or PANDAS_OBSERVE(self)
    )
    # float32 bounds: lmap's high - low is then a float32 subtraction, which is not reproduced.
    obs_type.features_range = {"x": [np.float32(-100.1), np.float32(100.1)]}
    assert observe_kinematics(obs_type) is None
    np.testing.assert_array_equal(obs_type.observe(), PANDAS_OBSERVE(obs_type))
    assert len(calls) == 1
    obs_type.features = ["presence", "speed"]  # not a to_dict key: highway-env's KeyError
    with pytest.raises(KeyError):
        obs_type.observe()
    env.close()
