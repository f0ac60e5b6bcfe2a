"""What one policy step means for an ego: its info over the step's frames, its reward terms
and whether it ends the ego's episode (``CounterScene-v0``'s spec sheet, ``envs/single_agent.py``);
and the episode's metric summary for an ego, given at its end.

The functions compute these from plain values; :class:`EgoOutcomes` answers them per ego as
methods of the env (the PettingZoo env's per-agent results, highway-env's hooks for ego 0).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from highway_env import utils
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env import metrics
from counterscene_env.scene.core import Scene
from counterscene_env.sim import ClosedLoop
from counterscene_env.sim.state import Episode

#: Info flags that count if they happen at any frame of the policy step.
ANY_FRAME = ("collision", "hard_braking", "off_road")


def step_info(frames: Sequence[dict], scenario_id: str) -> dict:
    """An ego's info over a policy step from its per-frame closed-loop infos (``frames``,
    oldest first): the last frame's values, except the flags of ``ANY_FRAME`` (any frame),
    ``collided_with`` (the first hit) and ``min_ttc`` [s] (the smallest)."""
    info = dict(frames[-1])
    for key in ANY_FRAME:
        info[key] = any(f[key] for f in frames)
    hits = [f["collided_with"] for f in frames if f["collided_with"] is not None]
    info["collided_with"] = hits[0] if hits else None
    info["min_ttc"] = min(f["min_ttc"] for f in frames)
    info["scenario_id"] = scenario_id
    return info


def reward_terms(info: Mapping, speed_range: Sequence[float]) -> dict[str, float]:
    """The named reward terms of a step (weights apart): collision, off road and hard braking
    as 0/1, speed [m/s] mapped from ``speed_range`` to [0, 1] (clipped)."""
    speed = utils.lmap(info["ego_speed"], speed_range, [0, 1])
    return {
        "collision_reward": float(info["collision"]),
        "off_road_reward": float(info["off_road"]),
        "hard_braking_reward": float(info["hard_braking"]),
        "high_speed_reward": float(np.clip(speed, 0.0, 1.0)),
    }


def weighted_reward(terms: Mapping[str, float], config: Mapping) -> float:
    """The reward: each term times its config weight (``config[name]``), summed."""
    return float(sum(config[name] * r for name, r in terms.items()))


def ends_episode(info: Mapping, config: Mapping) -> bool:
    """The step ends the ego's episode: a collision or leaving the road, as configured
    (``terminate_on_collision``, ``terminate_on_off_road``)."""
    return bool(
        (config["terminate_on_collision"] and info["collision"])
        or (config["terminate_on_off_road"] and info["off_road"])
    )


def episode_summary(
    sim: Scene,
    factual: Scene,
    ego: int,
    adversary: Sequence[str | None],
    terminated: bool = False,
) -> dict:
    """Ego row ``ego``'s metric summary (``metrics.evaluate_scene``) of the simulated episode
    ``sim`` so far, against the log ``factual`` over the same steps; ``adversary``: its
    adversary's id at each rollout step (``Episode.adversary_ids``); ``terminated``: the
    ego's episode was cut short by its termination (a collision or leaving the road, as
    configured), so its collision, if any, holds at every later horizon."""
    if ego != sim.ego_index:
        sim = sim.replace(ego_index=ego)
    factual = factual.time_slice(0, sim.num_steps).replace(ego_index=ego)
    return metrics.evaluate_scene(sim, factual, adversary=adversary, terminated=terminated)


class EgoOutcomes:
    """The outcome of the last policy step for each ego, as methods of the env.

    Mixed into :class:`~counterscene_env.envs.single_agent.CounterSceneEnv`: the ``ego_*``
    methods answer for ego ``k`` (the PettingZoo env, ``envs/parallel.py``, calls them per
    agent), and highway-env's ``_reward``, ``_rewards``, ``_is_terminated``,
    ``_is_truncated`` and ``_info`` hooks answer for the env's single agent, ego 0. It reads
    the env's attributes below (set at reset and by ``envs/frames.py`` every frame) and
    highway-env's ``vehicle`` (ego 0's vehicle).
    """

    config: dict[str, Any]
    scene: Scene  # the episode's factual scene
    egos: list[int]  # the egos' scene rows
    frame_infos: list[list[dict]]  # [frame][ego]: the closed loop's infos of the policy step
    ended: list[bool]  # per ego: its episode has ended (terminated; it stops where it is)
    controlled_vehicles: list[Vehicle]  # the egos' highway-env vehicles
    loop: ClosedLoop
    slot: int  # this env's episode in ``loop``
    episode: Episode
    steps: int  # frames simulated in the episode (highway-env's counter)

    def ego_info(self, k: int = 0) -> dict:
        """Ego ``k``'s info over the last policy step (:func:`step_info`; the keys are in
        ``CounterSceneEnv``'s docstring)."""
        return step_info([f[k] for f in self.frame_infos], self.scene.scenario_id)

    def ego_step_info(self, k: int = 0) -> dict:
        """Ego ``k``'s info as the envs return it: :meth:`ego_info` with its reward terms
        (``rewards``), highway-env's ``speed`` [m/s] and ``crashed``."""
        info = self.ego_info(k)
        info["rewards"] = reward_terms(info, self.config["reward_speed_range"])
        vehicle = self.controlled_vehicles[k]
        info["speed"] = float(vehicle.speed)
        info["crashed"] = bool(vehicle.crashed or info["collision"])
        return info

    def ego_rewards(self, k: int = 0) -> dict[str, float]:
        return reward_terms(self.ego_info(k), self.config["reward_speed_range"])

    def ego_reward(self, k: int = 0) -> float:
        return weighted_reward(self.ego_rewards(k), self.config)

    def _ego_ended(self, k: int) -> bool:
        return ends_episode(self.ego_info(k), self.config)

    def ego_terminated(self, k: int = 0) -> bool:
        """Ego ``k`` collided or left the road (as configured) in the last policy step."""
        if self.ended[k]:
            return True
        ended = self._ego_ended(k)
        if ended:
            self.ended[k] = True
            self.controlled_vehicles[k].crashed = True  # it stops where it is
        return ended

    def ego_truncated(self, k: int = 0) -> bool:
        return self.episode.done and not self.ended[k] and not self._ego_ended(k)

    def episode_metrics(self, k: int = 0) -> dict:
        """Ego ``k``'s metric summary of the episode so far (metrics.evaluate_scene)."""
        return episode_summary(
            self.loop.scene(self.slot),
            self.scene,
            self.egos[k],
            self.episode.adversary_ids(k),
            terminated=self.ended[k],
        )

    def stop_ended_egos(self) -> None:
        """Mark crashed every ego whose episode the frames so far end: highway-env brakes a
        crashed vehicle to a stop where it is. (Called after every frame; the end itself is
        reported at the end of the policy step, by ``ego_terminated``.)"""
        for k, v in enumerate(self.controlled_vehicles):
            if not v.crashed and self._ego_ended(k):
                v.crashed = True

    def all_egos_ended(self) -> bool:
        """Every ego is done: the rest of the policy step would simulate no one's decision.
        (An ego that ends mid-step with others still driving brakes to a stop, crashed, and
        its end is reported at the end of the policy step.)"""
        return all(self.ended[k] or self._ego_ended(k) for k in range(len(self.egos)))

    # highway-env's hooks, for the env's single agent (ego 0)
    def _rewards(self, action: Any) -> dict[str, float]:
        return self.ego_rewards(0)

    def _reward(self, action: Any) -> float:
        return self.ego_reward(0)

    def _is_terminated(self) -> bool:
        return any([self.ego_terminated(k) for k in range(len(self.egos))])

    def _is_truncated(self) -> bool:
        return self.episode.done and not any(self.ended)

    def _info(self, obs: Any, action: Any = None) -> dict:
        info = self.ego_step_info(0)
        if self.steps and (any(self.ended) or self.episode.done):
            info["metrics"] = self.episode_metrics(0)
        return info
