"""Checks of highway-env's observation and action configs, before the env applies them.

highway-env takes its ``config["observation"]`` and ``config["action"]`` dicts on trust: an
empty feature list, a count of 0, a one-axis grid or a reversed range is accepted and fails
at the first reset or step, or gives observations outside the declared space. Here each is
refused where it enters, with a message that names the key (docs/environment.md,
"Config"), and the types are then built on a scratch object.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from counterscene_env.config import check_bool, check_int, check_real, describe_value
from counterscene_env.envs.spaces import KINEMATIC_FEATURES

#: highway-env's observation types (``observation_factory``) that a CounterScene scene can fill.
OBSERVATION_TYPES = (
    "Kinematics",
    "OccupancyGrid",
    "TimeToCollision",
    "GrayscaleObservation",
    "MultiAgentObservation",
    "TupleObservation",
    "LidarObservation",
)
#: highway-env observation types made of what only their own env has (parking, exit,
#: lane-keeping): no CounterScene scene can fill them (they would fail at the first reset).
FOREIGN_OBSERVATIONS = {
    "KinematicsGoal": "a parking goal",
    "ExitObservation": "the exit env's exit lane",
    "AttributesObservation": "the lane-keeping env's state attributes",
}
#: highway-env's action types (``action_factory``).
ACTION_TYPES = ("ContinuousAction", "DiscreteAction", "DiscreteMetaAction", "MultiAgentAction")
#: ``Kinematics``' ``order`` values (highway-env's ``KinematicObservation``).
KINEMATICS_ORDERS = ("sorted", "shuffled")
#: Boolean keys of highway-env's observation configs.
_OBSERVATION_FLAGS = ("normalize", "clip", "absolute", "see_behind", "observe_intentions")


def check_types(config: Mapping[str, Any], egos: int, env: Any = None) -> None:
    """Check ``config``'s ``observation`` and ``action`` for ``egos`` controlled vehicles
    (more than one needs highway-env's multi-agent types), and build them on a scratch copy
    of ``env`` when it is given.

    Raises:
        TypeError, ValueError: naming the key (``observation.grid_step``, ...).
    """
    obs = check_observation_type("observation", config["observation"])
    act = check_type_dict("action", config["action"], ACTION_TYPES)
    multi = (obs["type"] == "MultiAgentObservation", act["type"] == "MultiAgentAction")
    if egos > 1 and not all(multi):
        raise ValueError(
            f"controlled_vehicles = {egos} needs highway-env's multi-agent types: observation "
            "{'type': 'MultiAgentObservation', 'observation_config': {...}} and action "
            "{'type': 'MultiAgentAction', 'action_config': {...}} (or use "
            "counterscene_env.parallel_env)"
        )
    obs_name = "observation"
    if multi[0]:
        obs_name = "observation.observation_config"
        obs = check_observation_type(obs_name, obs.get("observation_config"))
    if multi[1]:
        act = check_type_dict("action.action_config", act.get("action_config"), ACTION_TYPES)
    check_observation(obs, obs_name)
    _check_action(act, "action.action_config" if multi[1] else "action")
    if "TimeToCollision" in _leaf_types(obs) and act["type"] != "DiscreteMetaAction":
        raise ValueError(
            "the TimeToCollision observation needs the DiscreteMetaAction action type "
            "(its grid is over the ego's target speeds)"
        )
    if env is not None:
        _build_on_scratch(env, config)


def _leaf_types(obs: Mapping[str, Any]) -> list[str]:
    """The observation types of a checked config, a ``TupleObservation``'s parts in turn."""
    if obs["type"] != "TupleObservation":
        return [obs["type"]]
    return [t for part in obs["observation_configs"] for t in _leaf_types(part)]


def check_pair(key: str, value: Any) -> tuple[float, float]:
    """Two finite numbers (a list, tuple or 1-D array)."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        value = value.tolist()
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ValueError(f"{key} must be a list of two numbers, got {value!r}")
    return check_real(f"{key}[0]", value[0]), check_real(f"{key}[1]", value[1])


def check_range_pair(key: str, value: Any) -> None:
    """``[low, high]`` with low < high."""
    lo, hi = check_pair(key, value)
    if not hi > lo:
        raise ValueError(f"{key} must be [low, high] with low < high, got {list(value)}")


def check_type_dict(key: str, value: Any, types: tuple[str, ...]) -> Mapping[str, Any]:
    """A highway-env type config: a dict whose ``type`` is one of ``types``."""
    if not isinstance(value, Mapping):
        raise TypeError(
            f"{key} must be a dict with a 'type' (one of {list(types)}), {describe_value(value)}"
        )
    kind = value.get("type")
    if kind not in types:
        raise ValueError(f"{key} needs a 'type', one of {list(types)}; got {kind!r} in {value!r}")
    return value


def check_observation_type(key: str, value: Any) -> Mapping[str, Any]:
    """An observation config (:func:`check_type_dict`); highway-env's types that no scene
    here can fill are named with the reason."""
    kind = value.get("type") if isinstance(value, Mapping) else None
    if kind in FOREIGN_OBSERVATIONS:
        raise ValueError(
            f"{key}: highway-env's {kind} observation is built from "
            f"{FOREIGN_OBSERVATIONS[kind]}, which CounterScene's scenes do not have; "
            f"use one of {list(OBSERVATION_TYPES)}"
        )
    return check_type_dict(key, value, OBSERVATION_TYPES)


def check_observation(obs: Mapping[str, Any], name: str = "observation") -> None:
    """Counts, flags, features and grids of observation config ``name``; a
    ``TupleObservation``'s parts each in turn."""
    if obs["type"] == "TupleObservation":
        parts = obs.get("observation_configs")
        if not isinstance(parts, list | tuple) or not parts:
            raise ValueError(
                f"{name}.observation_configs must be a non-empty list of observation "
                f"configs, got {parts!r}"
            )
        for i, part in enumerate(parts):
            key = f"{name}.observation_configs[{i}]"
            check_observation(check_observation_type(key, part), key)
        return
    _check_scalars(obs, name)
    if obs["type"] == "Kinematics" and "features" in obs:
        _check_features(obs["features"], name)
    if obs.get("features_range") is not None:
        _check_features_range(obs["features_range"], name)
    if obs["type"] == "OccupancyGrid":
        _check_grid(obs, name)


def _check_scalars(obs: Mapping[str, Any], name: str) -> None:
    """Counts (>= 1), flags (bool), ``order`` and a Lidar's ``maximum_range`` (> 0 m)."""
    for key in ("vehicles_count", "cells", "horizon"):
        if key in obs:
            check_int(f"{name}.{key}", obs[key], ge=1)
    for key in _OBSERVATION_FLAGS:
        if key in obs:
            check_bool(f"{name}.{key}", obs[key])
    if obs.get("order", "sorted") not in KINEMATICS_ORDERS:
        raise ValueError(
            f"{name}.order must be one of {list(KINEMATICS_ORDERS)}, got {obs['order']!r}"
        )
    if "maximum_range" in obs:
        check_real(f"{name}.maximum_range", obs["maximum_range"], gt=0)


def _check_features(features: Any, name: str) -> None:
    """A non-empty list of ``Kinematics`` feature names."""
    if not isinstance(features, list | tuple) or not features:
        raise ValueError(
            f"{name}.features must be a non-empty list of {list(KINEMATIC_FEATURES)}, "
            f"got {features!r}"
        )
    unknown = [f for f in features if f not in KINEMATIC_FEATURES]
    if unknown:
        raise ValueError(
            f"{name}.features has unknown names {unknown}; valid: {list(KINEMATIC_FEATURES)}"
        )


def _check_features_range(ranges: Any, name: str) -> None:
    """feature -> [low, high], the normalisation's range."""
    if not isinstance(ranges, Mapping):
        raise TypeError(
            f"{name}.features_range must be a dict of feature -> [low, high], "
            f"{describe_value(ranges)}"
        )
    for feature, pair in ranges.items():
        check_range_pair(f"{name}.features_range.{feature}", pair)


def _check_grid(obs: Mapping[str, Any], name: str) -> None:
    """An ``OccupancyGrid``'s extent (``grid_size``: [[x_low, x_high], [y_low, y_high]] m)
    and cell size (``grid_step``: [dx, dy] m, each > 0)."""
    if "grid_size" in obs:
        size = obs["grid_size"]
        if isinstance(size, np.ndarray):
            size = size.tolist()
        if not isinstance(size, list | tuple) or len(size) != 2:
            raise ValueError(
                f"{name}.grid_size must be [[x_low, x_high], [y_low, y_high]] m, got {size!r}"
            )
        for axis, pair in zip("xy", size, strict=True):
            check_range_pair(f"{name}.grid_size ({axis})", pair)
    if "grid_step" in obs:
        dx, dy = check_pair(f"{name}.grid_step", obs["grid_step"])
        if not (dx > 0 and dy > 0):
            raise ValueError(f"{name}.grid_step must be [dx, dy] m, each > 0, got {[dx, dy]}")


def _check_action(act: Mapping[str, Any], name: str) -> None:
    """The ranges and speeds inside action config ``name``, which highway-env takes on trust
    (a reversed range flips the controls; an empty ``target_speeds`` fails at the first
    step)."""
    for key in ("acceleration_range", "steering_range", "speed_range"):
        if act.get(key) is not None:
            check_range_pair(f"{name}.{key}", act[key])
    if act.get("target_speeds") is not None:
        speeds = act["target_speeds"]
        if isinstance(speeds, np.ndarray) and speeds.ndim == 1:
            speeds = speeds.tolist()
        if not isinstance(speeds, list | tuple) or not speeds:
            raise ValueError(
                f"{name}.target_speeds must be a non-empty list of speeds in m/s, got {speeds!r}"
            )
        for i, v in enumerate(speeds):
            check_real(f"{name}.target_speeds[{i}]", v, ge=0)
    if "actions_per_axis" in act:
        check_int(f"{name}.actions_per_axis", act["actions_per_axis"], ge=1)


def _build_on_scratch(env: Any, config: Mapping[str, Any]) -> None:
    """Build the observation and action types and their spaces without keeping them: a config
    highway-env cannot build is refused before it is applied. (Keys a type does not know are
    ignored, as highway-env does: its own env configs carry some, e.g. ``flatten``.)"""
    from highway_env.envs.common.action import action_factory
    from highway_env.envs.common.observation import observation_factory

    for key, factory in (("observation", observation_factory), ("action", action_factory)):
        # The multi-agent types hold one config per ego: build that one.
        name, part = key, config[key]
        if f"{key}_config" in part:
            name, part = f"{key}.{key}_config", part[f"{key}_config"]
        try:
            built = factory(env, dict(part))
            built.space()
        except Exception as exc:  # highway-env's own message, with the key
            raise ValueError(f"{name} {part!r} cannot be built: {exc}") from None
