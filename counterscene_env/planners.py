"""Reference ego planners for stress runs and tests.

A planner is an external policy for the ego: ``reset(scene, seed)`` once per episode, then
``act(state) -> [2]`` (acceleration m/s^2, steering rad) every step, from the
:class:`~counterscene_env.sim.state.WorldState` it is given. The closed loop feeds the action through
highway-env's bicycle model. A planner with ``replays_log = True`` instead gives the ego's next
state, ``next_state(state) -> [4]`` (x m, y m, yaw rad, speed m/s), written as is.

- :class:`IDMPlanner`: a reactive lane follower with highway-env's own ``IDMVehicle`` logic
  (IDM on the vehicle ahead in its lane, lane-keeping steering, no lane changes) on the scene's
  road, along the lanes of the logged ego's route (``sim.traffic.IDMLaneFollower``). ``idm_yield`` adds highway-env's
  intersection priority rule (``RegulatedRoad``): it gives way to crossing traffic.
- :class:`ConstantVelocityPlanner`: zero acceleration and steering.
- :class:`LogReplayPlanner`: the factual ego, non-reactive (the paper's protocol).
- :class:`SB3Policy`: any Stable-Baselines3 policy (``sb3:PATH.zip``), loaded without
  unpickling; it acts on highway-env observations, so it runs through ``CounterScene-v0``.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Protocol

import numpy as np

from counterscene_env.scene.core import Scene
from counterscene_env.sim.state import WorldState
from counterscene_env.sim.traffic import IDMLaneFollower


class Planner(Protocol):
    """What the stress harness needs of an ego policy (module docstring)."""

    name: str
    replays_log: bool

    def reset(self, scene: Scene, seed: int) -> None: ...

    def act(self, state: WorldState) -> np.ndarray: ...


class ConstantVelocityPlanner:
    """Keeps speed and heading: acceleration 0, steering 0."""

    name = "constant_velocity"
    replays_log = False

    def reset(self, scene: Scene, seed: int) -> None:
        pass

    def act(self, state: WorldState) -> np.ndarray:
        return np.zeros(2)


class LogReplayPlanner:
    """The factual ego: its logged state at the next step, whatever the traffic does."""

    name = "log"
    replays_log = True

    def reset(self, scene: Scene, seed: int) -> None:
        self.scene = scene

    def act(self, state: WorldState) -> np.ndarray:
        raise TypeError("LogReplayPlanner writes states: call next_state()")

    def next_state(self, state: WorldState) -> np.ndarray:
        s, e, t1 = self.scene, self.scene.ego_index, state.t + 1
        if not s.valid[e, t1]:  # the log lost the ego: hold its last state
            return np.array([*state.positions[e], state.yaws[e], state.speeds[e]])
        return np.array([*s.positions[e, t1], s.yaws[e, t1], s.speeds[e, t1]])


class IDMPlanner:
    """highway-env's IDM lane follower driving the ego (``sim.traffic.IDMLaneFollower``, the
    same follower the closed loop uses for background traffic).

    Args:
        target_speed: desired speed [m/s]; default: the fastest the ego drove in the 3 s
            before "now" (at least ``min_target_speed``).
        min_target_speed: floor of the default target speed [m/s].
        yield_to_traffic: also apply highway-env's intersection priority rule
            (``RegulatedRoad``): give way to crossing traffic (planner ``idm_yield``).
    """

    name = "idm"
    replays_log = False

    def __init__(
        self,
        target_speed: float | None = None,
        min_target_speed: float = 5.0,
        yield_to_traffic: bool = False,
    ) -> None:
        self.follower = IDMLaneFollower(target_speed, min_target_speed, yield_to_traffic)
        if yield_to_traffic:
            self.name = "idm_yield"

    def reset(self, scene: Scene, seed: int) -> None:
        """Drive the scene's ego from "now" along the lanes of its logged route."""
        self.follower.reset(scene, seed)

    def act(self, state: WorldState) -> np.ndarray:
        return self.follower.act(state)


def sb3_sidecar(path: str | os.PathLike) -> Path:
    """Where an SB3 policy ``PATH.zip`` keeps the env config it was trained with
    (``PATH.env.json``, written by the recipes in ``agents/``)."""
    path = Path(path)
    return path.with_name(path.name.removesuffix(".zip") + ".env.json")


def read_sidecar(sidecar: Path) -> dict:
    """The env config in an SB3 policy's sidecar (``{}`` without one).

    Raises:
        ValueError: not a JSON object (the message names the file)."""
    if not sidecar.is_file():
        return {}
    try:
        config = json.loads(sidecar.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{sidecar}: not valid JSON ({exc})") from None
    if not isinstance(config, dict):
        raise ValueError(f"{sidecar}: must hold a JSON object of env-config keys, got {config!r}")
    return config


class SB3Policy:
    """A Stable-Baselines3 policy from its ``.zip``, for prediction, loaded without unpickling.

    SB3's own ``load`` unpickles (cloudpickle) the spaces, schedules and policy class stored in
    the zip. Here the policy class is imported by name (only from ``stable_baselines3``), its
    keyword arguments are read from the zip's JSON, and the weights with
    ``torch.load(weights_only=True)``. The spaces are the env's, after checking that they
    match the ones recorded in the zip (type, shape, dtype, number of actions).

    Unlike the planners above it acts on highway-env observations, so ``counterscene stress
    --planner sb3:PATH.zip`` runs it through ``CounterScene-v0``. The observation and action
    config it needs come from ``PATH.env.json`` next to the zip when there is one (the recipes
    in ``agents/`` write it), or, for a policy trained on a highway-env env, from that env's
    config (``--like ENV_ID``, ``envs.like``), else from the env's defaults.

    Args:
        path: the ``.zip`` written by ``model.save``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not an SB3 zip, a policy class outside ``stable_baselines3``, or policy
            keyword arguments that are Python objects (they would need unpickling).
    """

    name = "sb3"
    replays_log = False

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such SB3 policy file")
        try:
            with zipfile.ZipFile(self.path) as z:
                self.data = json.loads(z.read("data"))
                self._weights = z.read("policy.pth")
        except (zipfile.BadZipFile, KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{self.path}: not a Stable-Baselines3 model zip ({exc})") from None
        missing = sorted({"observation_space", "action_space"} - set(self.data))
        if missing:
            raise ValueError(f"{self.path}: not a Stable-Baselines3 model zip (no {missing})")
        self.policy_class = _sb3_policy_class(self.data, self.path)
        kwargs = self.data.get("policy_kwargs", {})
        if not isinstance(kwargs, dict) or ":serialized:" in kwargs:
            raise ValueError(
                f"{self.path}: its policy_kwargs hold Python objects, which cannot be loaded "
                "without unpickling; retrain with plain policy_kwargs (net_arch lists, numbers)"
            )
        self.policy_kwargs = kwargs
        self.env_config = read_sidecar(sb3_sidecar(self.path))
        self.policy = None

    def describe_spaces(self) -> tuple[str, str]:
        """The observation and action spaces recorded in the zip, as text."""
        return _describe(self.data["observation_space"]), _describe(self.data["action_space"])

    def bind(self, observation_space, action_space) -> None:
        """Build the policy on the env's spaces and load its weights.

        Raises:
            ValueError: the spaces differ from the ones the policy was trained on (the
                message names both), or the weights do not fit.
        """
        import inspect
        import io

        import torch

        mine = (
            _space_signature(self.data["observation_space"]),
            _space_signature(self.data["action_space"]),
        )
        theirs = (_env_signature(observation_space), _env_signature(action_space))
        if mine != theirs:
            obs, act = self.describe_spaces()
            raise ValueError(
                f"{self.path.name} was trained on observations {obs} and actions {act}, but "
                f"the env gives {observation_space} and {action_space}: configure the env's "
                "observation and action like the policy's training env (a PATH.env.json "
                "sidecar, --like ENV_ID for a highway-env env, or --env-config)"
            )
        kwargs = dict(self.policy_kwargs)
        if (
            self.data.get("use_sde")
            and "use_sde" in inspect.signature(self.policy_class).parameters
        ):
            kwargs["use_sde"] = True
        policy = self.policy_class(observation_space, action_space, lambda _: 0.0, **kwargs)
        state = torch.load(io.BytesIO(self._weights), map_location="cpu", weights_only=True)
        try:
            policy.load_state_dict(state)
        except RuntimeError as exc:
            raise ValueError(
                f"{self.path.name}: the weights do not fit the policy: {exc}"
            ) from None
        policy.set_training_mode(False)
        self.policy = policy

    def predict(self, observation: np.ndarray):
        """The deterministic action for one observation."""
        if self.policy is None:
            raise RuntimeError("call bind(observation_space, action_space) first")
        action, _ = self.policy.predict(observation, deterministic=True)
        return action


def _sb3_policy_class(data: dict, path: Path):
    import importlib
    import re

    cls = data.get("policy_class", {})
    module = cls.get("__module__", "") if isinstance(cls, dict) else ""
    init = cls.get("__init__", "") if isinstance(cls, dict) else ""
    match = re.match(r"<function (\w+)\.__init__", init)
    if not (module.startswith("stable_baselines3.") and module.endswith(".policies")) or (
        match is None
    ):
        raise ValueError(
            f"{path}: policy class {module or '?'} is not one of Stable-Baselines3's; only "
            "those are loaded (by name, without unpickling)"
        )
    from stable_baselines3.common.policies import BasePolicy

    try:
        cls = getattr(importlib.import_module(module), match.group(1))
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"{path}: cannot find policy class {module}.{match.group(1)}") from exc
    if not (isinstance(cls, type) and issubclass(cls, BasePolicy)):
        raise ValueError(f"{path}: {module}.{match.group(1)} is not an SB3 policy class")
    return cls


def _space_signature(entry: dict) -> tuple:
    kind = str(entry.get(":type:", "")).rsplit(".", 1)[-1].rstrip("'>")
    shape = entry.get("_shape", [])
    shape = tuple(json.loads(shape) if isinstance(shape, str) else shape)
    n = int(entry["n"]) if "n" in entry else None
    return kind, shape, str(entry.get("dtype")), n


def _env_signature(space) -> tuple:
    n = int(space.n) if hasattr(space, "n") else None
    return type(space).__name__, tuple(space.shape or ()), str(space.dtype), n


def _describe(entry: dict) -> str:
    kind, shape, dtype, n = _space_signature(entry)
    return f"{kind}(n={n})" if n is not None else f"{kind}{shape} {dtype}"


PLANNERS = {
    "idm": IDMPlanner,
    "idm_yield": lambda: IDMPlanner(yield_to_traffic=True),
    "constant_velocity": ConstantVelocityPlanner,
    "log": LogReplayPlanner,
}


def make_planner(name: str) -> Planner:
    """A planner by name (:data:`PLANNERS`; ``cv`` and ``replay`` are aliases)."""
    name = {"cv": "constant_velocity", "replay": "log"}.get(name, name)
    if name not in PLANNERS:
        raise ValueError(f"unknown planner {name!r}; valid: {sorted(PLANNERS)}")
    return PLANNERS[name]()
