"""A highway-env env's ego interface as CounterScene-v0 config (``counterscene stress --like``).

A policy trained on a highway-env env (``model.save("x.zip")``, no ``x.env.json`` sidecar)
needs, to drive here, the observation it was trained on, the action type it outputs and the
frequency it decides at. :func:`config_like` reads them from that env's config, as
``gym.make(env_id)`` builds it (its defaults plus any registered keyword config), for any
registered highway-env id, deprecated versions included.
"""

from __future__ import annotations

import copy
import difflib
import warnings
from typing import Any

from counterscene_env.envs.config import SIMULATION_FREQUENCY
from counterscene_env.envs.type_checks import FOREIGN_OBSERVATIONS

#: The CounterScene-v0 keys borrowed: what a policy sees, what it outputs and how often.
BORROWED_KEYS = ("observation", "action", "policy_frequency")


def highway_env_ids() -> list[str]:
    """Every env id registered by highway-env (``highway_env.envs``), sorted."""
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers its envs)

    return sorted(
        env_id
        for env_id, spec in gym.registry.items()
        if str(spec.entry_point).startswith("highway_env.")
    )


def config_like(env_id: str) -> dict[str, Any]:
    """The observation, action and policy frequency of highway-env env ``env_id``, as
    CounterScene-v0 config keys (:data:`BORROWED_KEYS`).

    A multi-agent env gives one ego's observation and action (its ``observation_config``
    and ``action_config``). highway-env's simulation frequency is not borrowed (here it is the
    scenes' 10 Hz); the policy still decides every ``1 / policy_frequency`` s.

    Warns (``UserWarning``) when the observation uses absolute coordinates
    (``absolute: True``): they are positions on that env's road, and mean nothing on
    CounterScene's maps.

    Raises:
        ValueError: ``env_id`` is not a registered highway-env id (the message names it and
            the closest registered ones), its observation is made of what only its own env
            has (:data:`FOREIGN_OBSERVATIONS`), or its policy frequency does not divide 10 Hz.
    """
    import gymnasium as gym

    ids = highway_env_ids()
    if env_id not in ids:
        close = difflib.get_close_matches(env_id, ids, n=3)
        hint = f"did you mean {', '.join(close)}? " if close else ""
        raise ValueError(
            f"{env_id!r} is not a registered highway-env env id; {hint}registered: {', '.join(ids)}"
        )
    with warnings.catch_warnings():
        # The user names an old version on purpose (their policy was trained on it):
        # gymnasium's "out of date" notice would only be noise.
        warnings.simplefilter("ignore")
        env = gym.make(env_id)
    try:
        config = copy.deepcopy(env.unwrapped.config)
    finally:
        env.close()
    obs, act = config["observation"], config["action"]
    if obs.get("type") == "MultiAgentObservation":
        obs = obs["observation_config"]
    if act.get("type") == "MultiAgentAction":
        act = act["action_config"]
    if obs.get("type") in FOREIGN_OBSERVATIONS:
        raise ValueError(
            f"{env_id}'s observation ({obs['type']}) is built from "
            f"{FOREIGN_OBSERVATIONS[obs['type']]}, which CounterScene's scenes do not have"
        )
    frequency = config["policy_frequency"]
    if SIMULATION_FREQUENCY % frequency:
        raise ValueError(
            f"{env_id} decides at {frequency} Hz, which does not divide CounterScene's "
            f"{SIMULATION_FREQUENCY} Hz step"
        )
    if obs.get("absolute"):
        warnings.warn(
            f"{env_id}'s observation ({obs.get('type')}) uses absolute coordinates "
            "(absolute: True): positions on that env's own road, which mean nothing on "
            "CounterScene's maps",
            UserWarning,
            stacklevel=2,
        )
    return {"observation": obs, "action": act, "policy_frequency": frequency}
