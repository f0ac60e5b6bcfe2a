"""The env's config: CounterScene's keys and defaults, and the checks a config must pass.

highway-env's base config (``AbstractEnv.default_config``) gives the observation, action,
frequencies and rendering keys; CounterScene adds the scene, model, reward and episode-end
keys, and every closed-loop setting: each ``SimConfig`` field is a key of the same name and
default (:data:`SIM_KEYS`; one source, docs/design.md, "Configuration").
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Mapping
from typing import Any

from counterscene_env.config import (
    check_bool,
    check_int,
    check_real,
    check_seed,
    defaults,
)
from counterscene_env.envs.egos import pick_egos
from counterscene_env.envs.type_checks import check_pair, check_types
from counterscene_env.scene.core import Scene, unplayable_reason
from counterscene_env.scene.sources import SceneSource
from counterscene_env.sim.config import SimConfig
from counterscene_env.sim.memory import check_replan_memory
from counterscene_env.world_model.checkpoint import shared_model

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
        "prefetch_scenes": True,  # record the next generated scene in a background process
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


_BOOL_KEYS = (
    "prefetch_scenes",
    "terminate_on_collision",
    "terminate_on_off_road",
    "show_adversary_plan",
    "show_trajectories",
    "render_agent",
    "offscreen_rendering",
    "manual_control",
    "real_time_rendering",
    "neighbour_vehicles_connected_lanes",
)
_REWARD_KEYS = ("collision_reward", "off_road_reward", "hard_braking_reward", "high_speed_reward")
#: The scenes' step: the env simulates at exactly this frequency [Hz].
SIMULATION_FREQUENCY = 10


def prepare(
    current: Mapping[str, Any],
    update: Mapping | None,
    valid: Mapping[str, Any],
    source: SceneSource | None,
    env: Any = None,
) -> tuple[dict, SceneSource]:
    """The checked config that ``update`` would give on top of ``current`` (of an env whose
    config keys are ``valid``), and its scene source (``source`` while the scenario stays).
    Checks types and ranges (:func:`validate`, the observation and action types built on a
    scratch copy of ``env``), and that a replan fits in memory.

    Raises:
        TypeError, ValueError: naming the key; nothing is changed.
    """
    if update is None:
        update = {}
    if not isinstance(update, Mapping):
        raise TypeError(f"config must be a dict of config keys, got {update!r}")
    unknown = sorted(set(update) - set(valid), key=str)
    if unknown:
        raise ValueError(f"unknown CounterScene config keys {unknown}; valid keys: {sorted(valid)}")
    # A copy: later changes to the caller's (nested) dicts do not reach the env.
    candidate = {**current, **copy.deepcopy(dict(update))}
    if isinstance(candidate.get("observation"), Mapping):
        candidate["observation"] = json_shapes_as_tuples(candidate["observation"])
    validate(candidate, env)
    if source is None or candidate["scenario"] != current["scenario"]:
        source = SceneSource(candidate["scenario"])  # raises on an unknown scenario
    model = shared_model(candidate["model"])
    sim = SimConfig.from_mapping(sim_settings(candidate))
    sim.check_model(model.config.num_train_timesteps)
    windows = max(sim.max_windows, candidate["controlled_vehicles"])
    check_replan_memory(model.config, sim.num_samples, windows, sim.memory_limit_gb)
    return candidate, source


#: The keys of ``reset(options=...)`` (``CounterSceneEnv.reset``).
RESET_OPTIONS = ("config", "scene", "episode_seed", "selection_seed")

#: The reset options of one episode, and the list of one per env that a vector env takes for
#: each instead (``envs/vector.py``).
PER_ENV_OPTIONS = {
    "scene": "scenes",
    "episode_seed": "episode_seeds",
    "selection_seed": "selection_seeds",
}


#: The keys of a vector env's ``reset(options=...)`` (``envs/vector.py``): a config update
#: for every env, the envs to reset, and one value per env of each per-env option.
VECTOR_RESET_OPTIONS = ("config", "reset_mask", *PER_ENV_OPTIONS.values())


def reset_options(
    options: Any,
    known: tuple[str, ...] = RESET_OPTIONS,
    kept: tuple[str, ...] = (),
    stacklevel: int = 3,
) -> dict:
    """``reset``'s ``options`` as a new dict (None: empty) of its ``known`` keys and the
    ``kept`` ones (which the caller refuses with a message of its own); anything but a dict
    is refused, and other keys are named in a warning and dropped (a misspelt option would
    otherwise silently run another episode; PettingZoo's API test sends one)."""
    if options is not None and not isinstance(options, Mapping):
        raise TypeError(f"options must be a dict or None, got {options!r}")
    options = dict(options or {})
    unknown = sorted(set(options) - set(known) - set(kept), key=str)
    if unknown:
        warnings.warn(
            f"reset ignores the unknown options {unknown}; known: {list(known)}",
            stacklevel=stacklevel,
        )
    return {key: value for key, value in options.items() if key not in unknown}


def check_episode_inputs(
    seed: Any,
    scene: Any,
    episode_seed: Any,
    selection_seed: Any,
    egos: int,
    names: tuple[str, ...] = (
        "seed",
        "options['scene']",
        "options['episode_seed']",
        "options['selection_seed']",
    ),
) -> None:
    """Raise unless a reset's own inputs are sound: a seed (None or an int >= 0), an episode
    seed and a selection seed (each None or an int in [0, ``config.MAX_SEED``]: they seed
    the episode's torch generator) and a scene (None, or a :class:`Scene` with ``egos`` egos
    to pick, that can be played: ``scene.core.unplayable_reason``). ``names`` are theirs in
    the error messages."""
    if seed is not None:
        check_int(names[0], seed, ge=0)
    if episode_seed is not None:
        check_seed(names[2], episode_seed)
    if selection_seed is not None:
        check_seed(names[3], selection_seed)
    if scene is not None:
        if not isinstance(scene, Scene):
            raise TypeError(f"{names[1]} must be a Scene, got {type(scene).__name__}")
        reason = unplayable_reason(scene)
        if reason is not None:
            raise ValueError(f"{names[1]} {scene.scenario_id!r} cannot be played: {reason}")
        pick_egos(scene, egos)


def json_shapes_as_tuples(observation: Mapping[str, Any]) -> dict[str, Any]:
    """``observation`` with each ``observation_shape`` list made a tuple, in every part:
    highway-env's ``GrayscaleObservation`` needs a tuple, and a config read from JSON (an
    SB3 sidecar, ``--env-config``) has lists."""
    out = dict(observation)
    if isinstance(out.get("observation_shape"), list):
        out["observation_shape"] = tuple(out["observation_shape"])
    if isinstance(out.get("observation_config"), Mapping):
        out["observation_config"] = json_shapes_as_tuples(out["observation_config"])
    if isinstance(out.get("observation_configs"), list):
        out["observation_configs"] = [
            json_shapes_as_tuples(p) if isinstance(p, Mapping) else p
            for p in out["observation_configs"]
        ]
    return out


def validate(config: Mapping[str, Any], env: Any = None) -> None:
    """Check a complete env config (every key present) by type and range, before anything is
    applied: frequencies, frame size, rewards, flags, the egos and their observation and
    action types (built on a scratch object when ``env`` is given), the closed-loop settings.

    Raises:
        TypeError: a value of the wrong type; ValueError: a wrong value. The message names the
            key, the value and what is allowed.
    """
    _check_scalars(config)
    egos = check_int("controlled_vehicles", config["controlled_vehicles"], ge=1)
    check_types(config, egos, env)
    SimConfig.from_mapping(sim_settings(config))  # types, ranges and choices (raises)


def _check_scalars(config: Mapping[str, Any]) -> None:
    """The flat keys: frequencies, frame, rewards, flags, model."""
    sim = check_int("simulation_frequency", config["simulation_frequency"])
    if sim != SIMULATION_FREQUENCY:
        raise ValueError(
            f"simulation_frequency must be {SIMULATION_FREQUENCY} Hz (the scenes' 0.1 s "
            f"step), got {sim}"
        )
    pf = check_int("policy_frequency", config["policy_frequency"], ge=1)
    if sim % pf:
        raise ValueError(f"policy_frequency must divide {sim} Hz (1, 2, 5, 10), got {pf!r}")
    for key in ("screen_width", "screen_height"):
        size = check_int(key, config[key], ge=16)
        if size % 16:
            raise ValueError(f"{key} must be a multiple of 16 px (video codecs), got {size}")
    check_real("scaling", config["scaling"], gt=0)
    check_pair("centering_position", config["centering_position"])
    for key in _REWARD_KEYS:
        check_real(key, config[key])
    lo, hi = check_pair("reward_speed_range", config["reward_speed_range"])
    if not hi > lo:
        raise ValueError(f"reward_speed_range must be [low, high] m/s, got {[lo, hi]}")
    for key in _BOOL_KEYS:
        if not (key == "offscreen_rendering" and config[key] is None):  # None: by render mode
            check_bool(key, config[key])
    if not isinstance(config["model"], str) or not config["model"]:
        raise TypeError(f"model must be 'default' or a model directory, got {config['model']!r}")
