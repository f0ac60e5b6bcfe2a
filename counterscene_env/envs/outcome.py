"""What one policy step means for an ego: its info over the step's frames, its reward terms
and whether it ends the ego's episode (``CounterScene-v0``'s spec sheet, ``envs/single_agent.py``);
and the episode's metric summary for an ego, given at its end.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from highway_env import utils

from counterscene_env import metrics
from counterscene_env.scene.core import Scene

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


def episode_summary(sim: Scene, factual: Scene, ego: int, adversary: int | None) -> dict:
    """Ego row ``ego``'s metric summary (``metrics.evaluate_scene``) of the simulated episode
    ``sim`` so far, against the log ``factual`` over the same steps; ``adversary``: its row."""
    if ego != sim.ego_index:
        sim = sim.replace(ego_index=ego)
    factual = factual.time_slice(0, sim.num_steps).replace(ego_index=ego)
    return metrics.evaluate_scene(sim, factual, adversary=adversary)
