"""CounterScene-v0, the Gymnasium env: registration, API checkers, spaces, determinism, episode
end, info and reward, bad input and collisions."""

from __future__ import annotations

import json
import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from conftest import crash_scene
from highway_env.road.road import RoadNetwork

import counterscene_env
from counterscene_env.envs.single_agent import CounterSceneEnv
from counterscene_env.world_model.checkpoint import CheckpointError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHORT = {"duration": 1.0}
INFO_KEYS = (
    "collision",
    "collided_with",
    "hard_braking",
    "ego_acceleration",
    "adversary",
    "conflict_type",
    "danger_score",
    "conflict_point",
    "arrival_steps",
    "adversary_distance",
    "min_ttc",
    "off_road",
    "fallback",
    "rewards",
)
REWARD_KEYS = ("collision_reward", "off_road_reward", "hard_braking_reward", "high_speed_reward")
ZERO = np.zeros(2, np.float32)


@pytest.fixture(scope="module")
def env():
    """One short merge env shared by the tests that only reset and step it."""
    env = gym.make("CounterScene-merge-v0", config=SHORT)
    yield env
    env.close()


def run_episode(env, seed, actions=None, options=None):
    """(reset result, list of step results) of a whole episode; ``actions`` cycles."""
    first = env.reset(seed=seed, options=options)
    steps = []
    while True:
        a = ZERO if actions is None else actions[len(steps) % len(actions)]
        steps.append(env.step(a))
        if steps[-1][2] or steps[-1][3]:
            return first, steps


def same(a, b) -> bool:
    """Deep equality of observations and infos; NaN equals NaN."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return type(a) is type(b) and len(a) == len(b) and all(map(same, a, b))
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b, True)
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


# ---------------------------------------------------------------------- registration
def test_registered_ids_make_working_envs():
    """The documented ids all make the env; the variants fix the scenario."""
    for env_id, scenario in (
        ("CounterScene-v0", "intersection"),
        ("counterscene_env:CounterScene-v0", "intersection"),
        ("CounterScene-merge-v0", "merge"),
    ):
        env = gym.make(env_id, config=SHORT)
        assert isinstance(env.unwrapped, CounterSceneEnv)
        assert env.unwrapped.config["scenario"] == scenario
        obs, info = env.reset(seed=0)
        assert obs.shape == (10, 7) and env.action_space.shape == (2,)
        assert info["scenario_id"].startswith(f"{scenario}/")
        env.close()
    for scenario in counterscene_env.SCENARIO_VARIANTS:
        assert gym.spec(f"CounterScene-{scenario}-v0").kwargs["scenario"] == scenario
    # config["scenario"] overrides a variant's default
    env = gym.make("CounterScene-merge-v0", config={**SHORT, "scenario": "roundabout"})
    assert env.unwrapped.config["scenario"] == "roundabout"
    env.close()


def test_registration_is_idempotent():
    """Re-registering (a re-import, a notebook reload) warns about nothing and changes nothing."""
    import pettingzoo

    before = gym.spec("CounterScene-v0")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        counterscene_env._register()
        counterscene_env._register()
    assert gym.spec("CounterScene-v0") is before
    assert "CounterScene-v0" in pettingzoo.parallel_registry


# ---------------------------------------------------------------------- API checkers
@pytest.mark.slow
@pytest.mark.parametrize("scenario", counterscene_env.SCENARIO_VARIANTS)
def test_gymnasium_and_sb3_env_checkers_pass(scenario, generated, tmp_path):
    """Both checkers pass on every scenario with the shipped model. The env draws from a shard
    holding one generated scene of the scenario: the checkers reset ~20 times with fresh seeds,
    and generating a fresh highway recording each time would take minutes."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    from counterscene_env.scene.shards import save_scenes

    shard = save_scenes([generated[scenario]], tmp_path / f"{scenario}.npz")
    env = gym.make("CounterScene-v0", config={**SHORT, "scenario": str(shard)})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
        sb3_check_env(env.unwrapped)
    messages = [f"{w.category.__name__}: {w.message}" for w in caught]
    # The only one allowed: SB3 on the 2-D Kinematics observation (highway-env's convention).
    assert len(messages) == 1, messages
    assert caught[0].category is UserWarning and "unconventional shape" in messages[0]
    env.close()


# ---------------------------------------------------------------------- action types
def test_discrete_meta_action_drives_an_episode():
    """DiscreteMetaAction: Discrete(5) lane-following meta-actions; an episode runs to its end;
    an index outside the space is refused."""
    env = gym.make(
        "CounterScene-merge-v0", config={**SHORT, "action": {"type": "DiscreteMetaAction"}}
    )
    assert env.action_space == gym.spaces.Discrete(5)
    _, steps = run_episode(env, 0, actions=[1, 3, np.int64(1)])  # IDLE, FASTER, numpy int
    assert len(steps) == 10 and steps[-1][3] and not steps[-1][2]
    env.reset(seed=0)
    for bad in (7, -1, 1.5, np.array([1, 2])):
        with pytest.raises(ValueError, match="not in the action space"):
            env.step(bad)
    env.close()


def test_intersection_v2_style_config():
    """highway-env's intersection-v2 ego setup: 15 absolute Kinematics rows, 3 longitudinal
    meta-actions at three target speeds, one decision per second."""
    config = {
        "duration": 2.0,
        "policy_frequency": 1,
        "observation": {
            "type": "Kinematics",
            "vehicles_count": 15,
            "features": ["presence", "x", "y", "vx", "vy", "cos_h", "sin_h"],
            "features_range": {
                "x": [-100, 100],
                "y": [-100, 100],
                "vx": [-20, 20],
                "vy": [-20, 20],
            },
            "absolute": True,
            "flatten": False,
            "observe_intentions": False,
        },
        "action": {
            "type": "DiscreteMetaAction",
            "longitudinal": True,
            "lateral": False,
            "target_speeds": [0, 4.5, 9],
        },
    }
    env = gym.make("CounterScene-intersection-v0", config=config)
    assert env.action_space == gym.spaces.Discrete(3)
    assert env.observation_space.shape == (15, 7)
    (obs, _), steps = run_episode(env, 0, actions=[2])
    assert obs.shape == (15, 7) and obs.dtype == np.float32
    assert len(steps) == 2, "2 s at one decision per second"
    assert [s[4]["step"] for s in steps] == [10, 20]  # 10 simulation steps per decision
    assert all(env.observation_space.contains(s[0]) for s in steps)
    env.close()


# ---------------------------------------------------------------------- determinism
def test_same_seed_and_actions_give_the_same_episode():
    """Two separately made envs, same seed and actions: every step's observation, reward,
    flags and info are identical. Another seed gives another episode."""
    actions = np.random.default_rng(0).uniform(-1, 1, (10, 2)).astype(np.float32) * [1, 0.1]
    a_env = gym.make("CounterScene-merge-v0", config=SHORT)
    b_env = gym.make("CounterScene-merge-v0", config=SHORT)
    a0, a = run_episode(a_env, 5, actions)
    b0, b = run_episode(b_env, 5, actions)
    assert same(a0[0], b0[0]) and same(a0[1], b0[1])
    assert len(a) == len(b) == 10
    for k, (sa, sb) in enumerate(zip(a, b, strict=True)):
        assert same(sa[0], sb[0]), f"observation of step {k}"
        assert sa[1:4] == sb[1:4], f"reward / flags of step {k}"
        for key in sa[4]:
            assert same(sa[4][key], sb[4][key]), f"info[{key!r}] of step {k}"
        assert sa[4].keys() == sb[4].keys()
    c0, c = run_episode(b_env, 6, actions)
    assert c0[1]["scenario_id"] != a0[1]["scenario_id"] or not same(c[-1][0], a[-1][0])
    a_env.close()
    b_env.close()


def test_an_action_space_seeded_once_samples_the_same_actions_after_every_reset():
    """Gymnasium users seed the action space once; highway-env builds new, unseeded spaces at
    every reset, and ours keeps an unchanged space with its generator. A reset that changes
    the action type gets the new space."""

    def samples(env: CounterSceneEnv) -> np.ndarray:
        env.action_space.seed(3)
        out = []
        for seed in (1, 2):
            env.reset(seed=seed, options={"scene": crash_scene()})
            out += [env.action_space.sample() for _ in range(3)]
        return np.stack(out)

    a, b = CounterSceneEnv(config=SHORT), CounterSceneEnv(config=SHORT)
    np.testing.assert_array_equal(samples(a), samples(b))
    space = a.action_space
    discrete = {"action": {"type": "DiscreteMetaAction"}}
    a.reset(options={"config": discrete, "scene": crash_scene()})
    assert a.action_space is not space and a.action_space == gym.spaces.Discrete(5)
    a.close()
    b.close()


# ---------------------------------------------------------------------- spaces and returns
def test_observations_stay_in_the_space_and_returns_are_plain(env):
    """Every observation is a float32 member of observation_space (the [-1, 1] box);
    rewards are Python floats and the flags Python bools."""
    space = env.observation_space
    assert space == gym.spaces.Box(-1.0, 1.0, (10, 7), np.float32)
    (obs, info), steps = run_episode(env, 3)
    assert obs.dtype == np.float32 and space.contains(obs)
    assert isinstance(info, dict)
    for obs, reward, terminated, truncated, _ in steps:
        assert obs.dtype == np.float32 and space.contains(obs)
        assert type(reward) is float and math.isfinite(reward)
        assert type(terminated) is bool and type(truncated) is bool
        assert not (terminated and truncated)


def test_episode_is_truncated_at_the_time_limit_and_then_refuses_steps(env):
    """duration 1 s at 10 Hz: nine ordinary steps, truncated at the tenth (no collision here),
    and a step after the end raises."""
    _, steps = run_episode(env, 0)
    assert len(steps) == 10
    assert [s[3] for s in steps] == [False] * 9 + [True]
    assert not any(s[2] for s in steps)
    # Exactly the step's time, as a user compares it (not 0.30000000000000004 at step 3).
    assert [s[4]["time"] for s in steps] == [k / 10 for k in range(1, 11)]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(ZERO)
    env.reset(seed=0)
    env.step(ZERO)  # a reset makes it usable again


def test_step_before_reset_raises():
    """gym.make's order enforcing refuses a step before the first reset."""
    env = gym.make("CounterScene-merge-v0", config=SHORT)
    with pytest.raises(gym.error.ResetNeeded):
        env.step(ZERO)
    env.close()


# ---------------------------------------------------------------------- info and reward
def test_info_keys_reward_terms_and_end_metrics(env):
    """Every step's info has the documented keys; the reward is the config-weighted sum of
    info["rewards"]; the last step carries the episode's metrics."""
    config = env.unwrapped.config
    (_, info0), steps = run_episode(env, 1)
    for key in INFO_KEYS:
        if key != "rewards":
            assert key in info0, key
    assert "metrics" not in info0
    for k, (_, reward, _, _, info) in enumerate(steps):
        for key in INFO_KEYS:
            assert key in info, f"step {k} lacks {key!r}"
        assert set(info["rewards"]) == set(REWARD_KEYS)
        assert all(0.0 <= v <= 1.0 for v in info["rewards"].values())
        expected = sum(config[name] * term for name, term in info["rewards"].items())
        assert reward == pytest.approx(expected)
        assert ("metrics" in info) == (k == len(steps) - 1)
    metrics = steps[-1][4]["metrics"]
    for key in ("cr", "orr", "per_second", "scenario_id"):
        assert key in metrics
    assert metrics["cr"] == 0.0 and metrics["scenario_id"] == steps[-1][4]["scenario_id"]


# ---------------------------------------------------------------------- bad input
def test_bad_actions_are_refused_and_out_of_range_values_clipped(env):
    """A wrong shape or a NaN raises ValueError; values outside [-1, 1] are clipped, so the
    ego's acceleration stays within ContinuousAction's [-5, 5] m/s^2."""
    env.reset(seed=2)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        env.step(np.zeros((1, 2), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(np.array([0.0, np.inf], np.float32))
    assert env.unwrapped.steps == 0, "refused actions do not advance the episode"
    _, _, _, _, info = env.step(np.array([5.0, -5.0], np.float32))
    assert 4.9 <= info["ego_acceleration"] <= 5.0 + 1e-6
    _, _, _, _, info = env.step(np.array([-50.0, 0.0], np.float32))
    assert -5.0 - 1e-6 <= info["ego_acceleration"] <= -4.9


def test_bad_config_is_refused_with_a_clear_error():
    """Config mistakes fail at gym.make with a message that says what is wrong."""
    with pytest.raises(ValueError, match="durration") as exc:
        gym.make("CounterScene-merge-v0", config={"durration": 1.0})
    assert "valid keys" in str(exc.value) and "'duration'" in str(exc.value)
    with pytest.raises(ValueError, match="unknown scenario 'parking'"):
        gym.make("CounterScene-v0", config={"scenario": "parking"})
    with pytest.raises(CheckpointError, match="/nonexistent/dir"):
        gym.make("CounterScene-merge-v0", config={**SHORT, "model": "/nonexistent/dir"})
    with pytest.raises(ValueError, match="screen_width must be a multiple of 16"):
        gym.make("CounterScene-merge-v0", config={"screen_width": 600})
    with pytest.raises(ValueError, match="policy_frequency"):
        gym.make("CounterScene-merge-v0", config={"policy_frequency": 3})
    with pytest.raises(ValueError, match="render_mode"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gym.make's own warning about the unknown mode
        gym.make("CounterScene-merge-v0", config=SHORT, render_mode="rgb")


# ---------------------------------------------------------------------- reset options and config
def test_reset_runs_a_given_scene(env, generated):
    """reset(options={"scene": scene}) runs that scene instead of drawing one."""
    scene = generated["merge"]
    _, info = env.reset(seed=0, options={"scene": scene})
    assert info["scenario_id"] == scene.scenario_id == "merge/seed=1"
    assert env.unwrapped.scene is scene
    _, info = env.reset(seed=0)  # the next plain reset draws again
    assert info["scenario_id"] != scene.scenario_id
    with pytest.raises(TypeError, match="Scene"):
        env.reset(seed=0, options={"scene": "merge/seed=1"})


def test_configure_and_reset_options_apply_new_config():
    """configure() then reset, or reset(options={"config": ...}), runs with the new config;
    an unknown key is refused there too."""
    env = gym.make("CounterScene-merge-v0", config=SHORT)
    env.unwrapped.configure({"duration": 0.5})
    _, steps = run_episode(env, 0)
    assert len(steps) == 5
    _, steps = run_episode(env, 0, options={"config": {"duration": 0.3, "policy_frequency": 5}})
    assert len(steps) == 2, "0.3 s at 5 Hz: the last decision is cut at the time limit"
    assert env.unwrapped.config["policy_frequency"] == 5
    with pytest.raises(ValueError, match="unknown CounterScene config keys"):
        env.unwrapped.configure({"speed_limit": 3})
    with pytest.raises(ValueError, match="policy_frequency"):
        env.reset(seed=0, options={"config": {"policy_frequency": 4}})
    env.close()


# ---------------------------------------------------------------------- collisions
def test_a_collision_terminates_with_the_collision_reward():
    """Full throttle into a parked car: terminated (not truncated) on the step it hits,
    info names the car, and the reward carries the (configured) collision weight."""
    config = {"duration": 2.0, "collision_reward": -7.0, "high_speed_reward": 0.5}
    env = gym.make("CounterScene-merge-v0", config=config)
    env.reset(seed=0, options={"scene": crash_scene()})
    for _ in range(20):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated and not truncated
    assert info["collision"] and info["collided_with"] == "a2" and info["crashed"]
    assert info["rewards"]["collision_reward"] == 1.0
    assert reward == pytest.approx(-7.0 + 0.5 * info["rewards"]["high_speed_reward"])
    assert info["metrics"]["cr"] == 1.0 and info["metrics"]["ends_in_ego_collision"]
    # The crash ends the episode before 2 s; the horizon tables count it as collided there.
    assert info["metrics"]["rollout_s"] < 2.0
    assert counterscene_env.metrics.horizon_values(info["metrics"], "2")["CR"] == 1.0
    with pytest.raises(RuntimeError):
        env.step(ZERO)
    env.close()


def test_without_terminate_on_collision_the_episode_goes_on():
    env = gym.make(
        "CounterScene-merge-v0", config={"duration": 2.0, "terminate_on_collision": False}
    )
    _, steps = run_episode(
        env, 0, actions=[np.array([1.0, 0.0], np.float32)], options={"scene": crash_scene()}
    )
    assert len(steps) == 20 and steps[-1][3]
    assert not any(s[2] for s in steps)
    hits = [s[4]["collision"] for s in steps]
    assert any(hits) and not hits[-1]
    # The ego stays under the policy's control after the hit (full throttle: it speeds up).
    first = hits.index(True)
    speeds = [s[4]["ego_speed"] for s in steps[first:]]
    assert speeds[-1] > speeds[0]
    env.close()


def test_bench_env_cli_reports_steps_per_second(capsys):
    from counterscene_env.cli import main

    assert main(["bench-env", "--scenario", "merge", "--steps", "3", "--policy", "hold",
                 "--set", "duration=1.0", "--json"]) == 0  # fmt: skip
    out = json.loads(capsys.readouterr().out)
    assert out["steps"] == 3 and out["steps_per_second"] > 0 and out["policy"] == "hold"
    assert 0.0 <= out["replan_share"] <= 1.0 and out["config"]["duration"] == 1.0


# ---------------------------------------------------------------------- refused calls, spaces
def test_a_refused_configure_or_reset_changes_nothing():
    env = gym.make("CounterScene-merge-v0", config=SHORT)
    u = env.unwrapped
    env.reset(seed=0)
    before = dict(u.config)
    with pytest.raises(ValueError, match="unknown scenario"):
        u.configure({"scenario": "nope"})
    assert u.config == before
    with pytest.raises(ValueError, match="multi-agent"):
        env.reset(seed=1, options={"config": {"controlled_vehicles": 2}})
    assert u.config == before
    with pytest.raises(TypeError, match="Scene"):
        env.reset(options={"scene": "x", "config": {"action": {"type": "DiscreteMetaAction"}}})
    assert u.config == before and env.action_space.shape == (2,)
    env.reset(seed=2)  # still works
    env.step(ZERO)
    env.close()


def test_partial_features_range_is_not_declared_bounded():
    """highway-env scales only the features of features_range: vx, vy here stay in m/s, so
    the space must not claim [-1, 1]; the observation is in its space at every step."""
    obs_config = {
        "type": "Kinematics",
        "features": ["presence", "x", "y", "vx", "vy"],
        "features_range": {"x": [-100, 100], "y": [-100, 100]},
    }
    env = gym.make("CounterScene-merge-v0", config={**SHORT, "observation": obs_config})
    assert np.isinf(env.observation_space.high).all()
    _, steps = run_episode(env, 0)
    assert all(env.observation_space.contains(s[0]) for s in steps)
    bounded = gym.make("CounterScene-merge-v0", config=SHORT)
    assert bounded.observation_space.high.max() == 1.0
    env.close()
    bounded.close()


def test_time_to_collision_observation_needs_discrete_meta_action():
    with pytest.raises(ValueError, match="DiscreteMetaAction"):
        gym.make(
            "CounterScene-merge-v0", config={**SHORT, "observation": {"type": "TimeToCollision"}}
        )
    env = gym.make(
        "CounterScene-merge-v0",
        config={**SHORT, "observation": {"type": "TimeToCollision"},
                "action": {"type": "DiscreteMetaAction"}},
    )  # fmt: skip
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(1)
    assert env.observation_space.contains(obs)
    env.close()


def test_configure_mid_episode_applies_from_the_next_reset():
    """The episode's clock and length stay as they were at reset; the next episode has the
    new ones (policy_frequency applied at once used to shorten the steps while the length
    stayed)."""
    env = gym.make("CounterScene-merge-v0", config=SHORT)
    env.reset(seed=0)
    env.step(ZERO)
    env.unwrapped.configure({"policy_frequency": 5, "duration": 0.4})
    times = [env.step(ZERO)[4]["time"] for _ in range(9)]
    assert times == [k / 10 for k in range(2, 11)]
    _, steps = run_episode(env, 0)
    assert [s[4]["time"] for s in steps] == [0.2, 0.4]
    env.close()


def test_the_parts_of_a_tuple_observation_keep_the_rules_of_a_whole_one():
    """Inside a ``TupleObservation`` too: ``Kinematics`` keeps to ``vehicles_count`` rows and
    its [-1, 1] bounds, and ``TimeToCollision`` needs ``DiscreteMetaAction``."""
    parts = [{"type": "Kinematics", "vehicles_count": 1}, {"type": "OccupancyGrid"}]
    tuple_obs = {"type": "TupleObservation", "observation_configs": parts}
    env = gym.make("CounterScene-merge-v0", config={**SHORT, "observation": tuple_obs})
    assert env.observation_space[0] == gym.spaces.Box(-1.0, 1.0, (1, 5), np.float32)
    _, steps = run_episode(env, 0)
    assert all(env.observation_space.contains(s[0]) for s in steps)
    env.close()
    parts[1] = {"type": "TimeToCollision"}
    with pytest.raises(ValueError, match="DiscreteMetaAction"):
        gym.make("CounterScene-merge-v0", config={**SHORT, "observation": tuple_obs})


def test_grayscale_frames_are_drawn_headless():
    """highway-env's viewer draws nothing under ``SDL_VIDEODRIVER=dummy`` (set for the
    tests); a ``GrayscaleObservation`` still gets the road and the vehicles. Its shape may
    be a list, as JSON has it (highway-env needs a tuple)."""
    gray = {"type": "GrayscaleObservation", "observation_shape": [64, 32], "stack_size": 2,
            "weights": [0.2989, 0.5870, 0.1140]}  # fmt: skip
    env = gym.make("CounterScene-merge-v0", config={**SHORT, "observation": gray})
    env.reset(seed=0)
    obs, *_ = env.step(ZERO)
    assert env.observation_space.contains(obs)
    assert len(np.unique(obs[-1])) > 3, "a blank frame"
    env.close()


def test_lane_features_see_the_current_lanes():
    """Lane-relative features are computed on each vehicle's current lane."""
    obs_config = {"type": "Kinematics", "features": ["presence", "x", "y", "lat_off"]}
    env = gym.make("CounterScene-merge-v0", config={"duration": 3.0, "observation": obs_config})
    env.reset(seed=0)
    for _ in range(20):
        env.step(ZERO)
    u = env.unwrapped
    net = u.road.network
    for v in u.road.vehicles[1:]:
        assert v.lane_index == net.get_closest_lane_index(v.position, v.heading)
    env.close()


def test_multi_ego_gym_env_refuses_steps_after_termination():
    """controlled_vehicles > 1 needs highway-env's multi-agent types; once an ego is done,
    the episode is over."""
    with pytest.raises(ValueError, match="MultiAgentObservation"):
        gym.make("CounterScene-merge-v0", config={**SHORT, "controlled_vehicles": 2})
    config = {
        "duration": 2.0,
        "controlled_vehicles": 2,
        "observation": {
            "type": "MultiAgentObservation",
            "observation_config": {"type": "Kinematics"},
        },
        "action": {"type": "MultiAgentAction", "action_config": {"type": "ContinuousAction"}},
    }
    env = gym.make("CounterScene-merge-v0", config=config)
    env.reset(seed=0, options={"scene": crash_scene()})
    full = np.array([1.0, 0.0], np.float32)
    for _ in range(20):
        _, _, terminated, truncated, _ = env.step([full, ZERO])  # a list works as a tuple
        if terminated or truncated:
            break
    assert terminated
    with pytest.raises(RuntimeError, match="reset"):
        env.unwrapped.step((ZERO, ZERO))
    env.close()


def test_a_scene_that_cannot_be_played_is_refused_with_the_reason(generated):
    """A reset's own scene without a lane, or with no step after "now", is named with why;
    the env is left as it was (it used to fail inside highway-env's lane search)."""
    from counterscene_env.scene.road import RoadMap

    env = gym.make("CounterScene-merge-v0", config=SHORT)
    first, _ = env.reset(seed=0)
    scene = generated["merge"]
    bare = scene.replace(road=RoadMap.from_network(RoadNetwork()))
    with pytest.raises(ValueError, match="cannot be played: its map has no lanes"):
        env.reset(seed=0, options={"scene": bare})
    with pytest.raises(ValueError, match="cannot be played: too short for an episode"):
        env.reset(seed=0, options={"scene": scene.replace(current_index=scene.num_steps - 1)})
    again, _ = env.reset(seed=0)
    np.testing.assert_array_equal(first, again)
    env.close()


def test_calls_that_need_an_episode_say_so_before_the_first_reset():
    """Past Gymnasium's order check (``env.unwrapped``), and in the PettingZoo env."""
    env = gym.make("CounterScene-merge-v0", config=SHORT, render_mode="rgb_array").unwrapped
    for call in (env.render, lambda: env.episode, lambda: env.step(ZERO)):
        with pytest.raises(RuntimeError, match=r"call reset\(\) first"):
            call()
    env.close()
    pair = counterscene_env.parallel_env(num_egos=2, config=SHORT, render_mode="rgb_array")
    for call in (pair.state, pair.render):
        with pytest.raises(RuntimeError, match=r"call reset\(\) first"):
            call()
    pair.close()


def test_render_fps_is_per_instance():
    a = gym.make("CounterScene-merge-v0", config={**SHORT, "policy_frequency": 2})
    b = gym.make("CounterScene-merge-v0", config=SHORT)
    a.reset(seed=0)
    b.reset(seed=0)
    assert a.unwrapped.metadata["render_fps"] == 2
    assert b.unwrapped.metadata["render_fps"] == 10
    a.close()
    b.close()
