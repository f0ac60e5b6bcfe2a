"""The env's config: CounterScene's keys and defaults, and the checks a config must pass.

highway-env's base config (``AbstractEnv.default_config``) gives the observation, action,
frequencies and rendering keys; CounterScene adds the scene, model, reward and episode-end
keys, and every closed-loop setting: each ``SimConfig`` field is a key of the same name and
default (:data:`SIM_KEYS`; one source, docs/design.md, "Configuration").
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any

from counterscene_env.config import defaults
from counterscene_env.sim.config import SimConfig

#: Keys of highway-env's base config that mean nothing here (the traffic is the world model).
UNUSED_BASE_KEYS = ("other_vehicles_type",)
#: Config keys that are closed-loop settings: every ``SimConfig`` field, by the same name
#: and with the same default (add a field there and it is a key here).
SIM_KEYS = tuple(defaults(SimConfig))


def counterscene_defaults() -> dict[str, Any]:
    """CounterScene's keys on top of highway-env's base config (a fresh dict each call)."""
    return {
        # Scenes and traffic; then every closed-loop setting (SimConfig's fields)
        "scenario": "intersection",
        "model": "default",
        **defaults(SimConfig),
        # The ego: highway-env observation and action types
        "observation": {
            "type": "Kinematics",
            "vehicles_count": 10,
            "features": ["presence", "x", "y", "vx", "vy", "cos_h", "sin_h"],
            "features_range": {
                "x": [-100, 100],
                "y": [-100, 100],
                "vx": [-20, 20],
                "vy": [-20, 20],
            },
            "absolute": False,
            "see_behind": True,
        },
        "action": {"type": "ContinuousAction"},
        "controlled_vehicles": 1,
        "simulation_frequency": 10,  # [Hz], the scenes' 0.1 s step
        "policy_frequency": 10,  # [Hz]
        # Rewards and episode end
        "collision_reward": -5.0,
        "off_road_reward": -1.0,
        "hard_braking_reward": -0.5,
        "high_speed_reward": 1.0,
        "reward_speed_range": [5.0, 15.0],  # [m/s]
        "terminate_on_collision": True,
        "terminate_on_off_road": True,
        # Rendering
        "screen_width": 640,  # [px]
        "screen_height": 640,  # [px]
        "centering_position": [0.5, 0.5],
        "scaling": 5.5,  # [px/m]
        "show_adversary_plan": True,
    }


def sim_settings(config: Mapping[str, Any]) -> dict[str, Any]:
    """The closed-loop settings of an env config (``SimConfig`` keyword arguments)."""
    return {key: config[key] for key in SIM_KEYS}


def validate(config: Mapping[str, Any]) -> None:
    """Check a complete env config (every key present) beyond its keys: frequencies,
    frame size, egos and their observation / action types, rewards, closed-loop settings.

    Raises:
        ValueError: the first problem found, naming the key.
    """
    sim = 10
    if config["simulation_frequency"] != sim:
        raise ValueError(
            f"simulation_frequency must be {sim} Hz (the scenes' 0.1 s step), "
            f"got {config['simulation_frequency']}"
        )
    pf = config["policy_frequency"]
    if not isinstance(pf, numbers.Integral) or pf < 1 or sim % pf:
        raise ValueError(f"policy_frequency must divide {sim} Hz (1, 2, 5, 10), got {pf!r}")
    for key in ("screen_width", "screen_height"):
        if config[key] % 16:
            raise ValueError(f"{key} must be a multiple of 16 px (video codecs), got {config[key]}")
    n = config["controlled_vehicles"]
    if not isinstance(n, numbers.Integral) or n < 1:
        raise ValueError(f"controlled_vehicles must be an int >= 1, got {n!r}")
    obs, act = config["observation"], config["action"]
    multi = (obs.get("type") == "MultiAgentObservation", act.get("type") == "MultiAgentAction")
    if n > 1 and not all(multi):
        raise ValueError(
            f"controlled_vehicles = {n} needs highway-env's multi-agent types: observation "
            "{'type': 'MultiAgentObservation', 'observation_config': {...}} and action "
            "{'type': 'MultiAgentAction', 'action_config': {...}} (or use "
            "counterscene_env.parallel_env)"
        )
    obs = obs.get("observation_config", obs)
    act = act.get("action_config", act)
    if obs.get("type") == "TimeToCollision" and act.get("type") != "DiscreteMetaAction":
        raise ValueError(
            "the TimeToCollision observation needs the DiscreteMetaAction action type "
            "(its grid is over the ego's target speeds)"
        )
    lo, hi = config["reward_speed_range"]
    if not hi > lo:
        raise ValueError(f"reward_speed_range must be [low, high] m/s, got {[lo, hi]}")
    SimConfig.from_mapping(sim_settings(config))  # selector, guidance, ... (raises)
