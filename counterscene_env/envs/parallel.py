"""The PettingZoo ``ParallelEnv``: several external egos, each with its own adversary.

Agents ``ego_0 .. ego_{n-1}`` are vehicles of the scene driven by your policies (``ego_0`` is
the scene's ego; the others are the vehicles nearest to it that stay longest in the log). Each
has its own causally selected adversary among the world-model agents (distinct, never another
ego) and its own model window, where that adversary is guided; everyone else is world-model
traffic. Under the hood it is :class:`~counterscene_env.envs.single_agent.CounterSceneEnv` with
``controlled_vehicles = n`` and highway-env's multi-agent observation and action types, so each
agent sees and acts exactly as the single-agent env's ego does (same config keys).

An ego that collides or leaves the road (as configured) is terminated and removed from
``agents``; it stays in the world as a crashed vehicle that brakes to a stop (an action
still given for it is ignored). At the time limit
every remaining ego is truncated. Observations are per agent, rewards are each ego's own
(the single-agent reward terms), infos are each ego's step info (+ ``metrics`` at its end).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from counterscene_env.config import check_int
from counterscene_env.envs.config import reset_options
from counterscene_env.envs.single_agent import CounterSceneEnv
from counterscene_env.envs.spaces import check_action


class CounterSceneParallelEnv(ParallelEnv):
    """``counterscene_env.parallel_env(num_egos=n, config={...}, render_mode=...)``.

    Args:
        num_egos: number of external egos (agents ``ego_0 ..``).
        config: the single-agent env's config keys (``docs/environment.md``);
            ``observation`` and ``action`` are each agent's, ``controlled_vehicles`` is set
            from ``num_egos``.
        render_mode: None, ``"rgb_array"`` or ``"human"`` (the view follows ``ego_0``).
    """

    metadata: ClassVar[dict] = {
        "name": "counterscene_v0",
        "render_modes": ["human", "rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self, num_egos: int = 1, config: dict | None = None, render_mode: str | None = None
    ) -> None:
        num_egos = check_int("num_egos", num_egos, ge=1)
        config = dict(config or {})
        if "controlled_vehicles" in config:
            raise ValueError("set the number of egos with num_egos, not controlled_vehicles")
        base = CounterSceneEnv.default_config()
        self.agent_config = {
            "observation": config.pop("observation", base["observation"]),
            "action": config.pop("action", base["action"]),
        }
        config.update(
            controlled_vehicles=num_egos,
            observation={
                "type": "MultiAgentObservation",
                "observation_config": self.agent_config["observation"],
            },
            action={"type": "MultiAgentAction", "action_config": self.agent_config["action"]},
        )
        self.num_egos = num_egos
        self.possible_agents = [f"ego_{k}" for k in range(num_egos)]
        self.agents: list[str] = []
        self.render_mode = render_mode
        self.core = CounterSceneEnv(config=config, render_mode=render_mode)
        self.metadata = {**type(self).metadata, "render_fps": self.core.metadata["render_fps"]}
        # Cached: the same space objects for the env's whole life.
        self.observation_spaces = dict(
            zip(self.possible_agents, self.core.observation_space.spaces, strict=True)
        )
        self.action_spaces = dict(
            zip(self.possible_agents, self.core.action_space.spaces, strict=True)
        )
        boxes = list(self.observation_spaces.values())
        self.state_space = (
            spaces.Box(
                np.stack([b.low for b in boxes]),
                np.stack([b.high for b in boxes]),
                dtype=boxes[0].dtype,
            )
            if all(isinstance(b, spaces.Box) for b in boxes)
            else None
        )

    def state(self) -> np.ndarray:
        """The global state: every ego's observation stacked, ``[n, *obs_shape]``
        (``state_space``); for Box observations only."""
        if self.state_space is None:
            raise NotImplementedError("state() needs Box observations")
        self.core.episode  # noqa: B018 -- raises before the first reset, naming it
        return np.stack(self.core.observation_type.observe())

    def observation_space(self, agent: str) -> spaces.Space:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self.action_spaces[agent]

    @property
    def config(self) -> dict:
        return self.core.config

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, Any], dict[str, dict]]:
        options = reset_options(options)
        update = options.get("config", {})
        if not isinstance(update, Mapping):
            raise TypeError(f"options['config'] must be a dict of config keys, got {update!r}")
        fixed = sorted({"observation", "action", "controlled_vehicles"} & set(update))
        if fixed:
            raise ValueError(
                f"reset cannot change {fixed} of a parallel env (its spaces are fixed): make a "
                "new env with counterscene_env.parallel_env(...)"
            )
        obs, _ = self.core.reset(seed=seed, options=options)
        self.metadata["render_fps"] = self.core.metadata["render_fps"]  # policy_frequency
        self.agents = list(self.possible_agents)
        observations = {a: obs[k] for k, a in enumerate(self.possible_agents)}
        infos = {a: self.core.ego_step_info(k) for k, a in enumerate(self.possible_agents)}
        return observations, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("every agent is done: call reset()")
        if not isinstance(actions, Mapping):
            raise TypeError(
                f"actions must be a dict of agent name -> action ({self.agents}), "
                f"got {type(actions).__name__}"
            )
        # An action for an agent that is done is ignored, as PettingZoo's own wrappers do (a
        # loop over the last observations still holds it); an unknown name is a mistake.
        missing = sorted(set(self.agents) - set(actions))
        extra = sorted(set(actions) - set(self.possible_agents), key=str)
        if missing or extra:
            raise ValueError(
                f"step needs one action per live agent {self.agents}; missing {missing}, "
                f"unknown {extra}"
            )
        core = self.core
        for a in self.agents:  # every action is checked before any is applied
            check_action(self.action_spaces[a], actions[a], f"{a}'s action")
        obs = core.step_egos({self.possible_agents.index(a): actions[a] for a in self.agents})
        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for a in self.agents:
            k = self.possible_agents.index(a)
            observations[a] = obs[k]
            rewards[a] = core.ego_reward(k)
            terminations[a] = core.ego_terminated(k)
            truncations[a] = core.ego_truncated(k)
            info = core.ego_step_info(k)
            if terminations[a] or truncations[a]:
                info["metrics"] = core.episode_metrics(k)
            infos[a] = info
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        return self.core.render()

    def close(self) -> None:
        self.core.close()
