"""Shared pieces of the metrics: thresholds and keys, the rollout and horizon steps, agent
lookup, the NaN-aware mean."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np

from counterscene_env.scene.core import Scene

#: Hard-braking threshold on the longitudinal acceleration, m/s^2 (paper: -3.0).
HARD_BRAKE_THRESHOLD = -3.0

#: m/s^2: how far below a threshold an acceleration must be to count as below it. A
#: planner that brakes at exactly 3 m/s^2 gives -2.9999999999 or -3.0000000001 out of
#: ``(9.7 - 10.0) / 0.1``; exactly the threshold is not below it, whichever way floats round.
BRAKE_TOLERANCE = 1e-6


def is_hard_braking(acc, threshold: float = HARD_BRAKE_THRESHOLD):
    """Whether longitudinal acceleration ``acc`` m/s^2 (a number or an array; NaN: False) is
    below ``threshold`` m/s^2 (:data:`BRAKE_TOLERANCE`)."""
    return np.asarray(acc) < threshold - BRAKE_TOLERANCE


def brakes_at_least(deceleration, amount: float):
    """Whether a deceleration ``deceleration`` m/s^2 (positive: braking; NaN: False) reaches
    ``amount`` m/s^2, within :data:`BRAKE_TOLERANCE`: a planner's full braking, exactly
    ``amount``, counts whichever way floats round it."""
    return np.asarray(deceleration) >= amount - BRAKE_TOLERANCE


#: The version of the metric definitions, bumped whenever one changes what it measures. A
#: stress run's identity carries it, so that a run is never resumed, or compared, across two
#: definitions unnoticed. 1 (no version recorded): until 2 Dec 2026. 2: 3 Dec 2026, HBR along
#: the path and from the first rollout step, ORR within a cropped map's extent, an episode the
#: ego's crash ended counted at later horizons, no adversary counted as no collision with one
#: in every table. 3: 3 Dec 2026, only an episode that its termination cut short counts at
#: later horizons (2 counted one whose log ended with the ego in a collision too; docs/metrics.md).
METRICS_VERSION = 3


#: Per-second keys of :func:`evaluate_scene` and :func:`aggregate`: the paper's table.
PER_SECOND_KEYS = ("ADE", "FDE", "ORR", "HBR", "CR")

#: Further per-second keys of :func:`evaluate_scene` (``counterscene paper-tables``): the
#: ego-adversary CR within h, the ego's strongest braking within h [m/s^2], and the log's own
#: ORR within h (the same vehicles' logged positions on the same map).
EXTRA_PER_SECOND_KEYS = ("CR_adv", "DEC", "ORR_log")


#: Whole-rollout keys of :func:`evaluate_scene` (numbers averaged by :func:`aggregate`).
SCENE_KEYS = (
    "cr",
    "cr_all_agents",
    "cr_non_ego",
    "cr_non_ego_new",
    "cr_ego_adversary",
    "hbr_ego",
    "hbr_all",
    "hbr_paper",
    "orr",
    "orr_parked",
    "orr_moving",
    "orr_log",
    "orr_moving_log",
    "min_ttc",
    "min_clearance_adversary",
    "ego_peak_deceleration",
)


#: The paper's horizon groups (main tables), in seconds.
GROUPS = {"1-4s": (1, 2, 3, 4), "5-7s": (5, 6, 7), "8-10s": (8, 9, 10)}


AccelerationSource = Literal["position", "speed"]


def rollout_steps(scene: Scene) -> int:
    """Number of rollout steps, ``T - current_index - 1``."""
    return scene.num_steps - scene.current_index - 1


def horizon_steps(scene: Scene, seconds: float | None) -> int:
    """Rollout steps in the first ``seconds`` s: ``round(seconds / dt)``; None: all of them."""
    if seconds is None:
        return rollout_steps(scene)
    return round(float(seconds) / scene.dt)


def rollout_slice(scene: Scene) -> slice:
    return slice(scene.current_index + 1, scene.num_steps)


def in_horizon(scene: Scene, seconds: float | None) -> np.ndarray:
    """``[T_roll]`` bool: the rollout steps within the first ``seconds`` s (None: all)."""
    return np.arange(rollout_steps(scene)) < horizon_steps(scene, seconds)


def agent_index(scene: Scene, agent: int | str) -> int:
    """Row of an agent given by row index or by id; raises ValueError if there is none."""
    if isinstance(agent, str):
        rows = np.flatnonzero(scene.agent_ids == agent)
        if rows.size == 0:
            raise ValueError(f"no agent with id {agent!r} in scene {scene.scenario_id!r}")
        return int(rows[0])
    idx = int(agent)
    if not 0 <= idx < scene.num_agents:
        raise ValueError(f"agent index {idx} out of range for {scene.num_agents} agents")
    return idx


def adversary_index(scene: Scene, adversary: int | str) -> int:
    idx = agent_index(scene, adversary)
    if idx == scene.ego_index:
        raise ValueError("the adversary cannot be the ego")
    return idx


def one_agent(adversary: object) -> bool:
    """Whether ``adversary`` names one agent (a row or an id), not one entry per step."""
    return isinstance(adversary, (str, int, np.integer))


def adversary_tenures(
    scene: Scene, adversary: int | str | Sequence[int | str | None]
) -> list[tuple[int, int]]:
    """``(row, first rollout step)`` of every agent that was the ego's adversary.

    ``adversary`` is one agent (row or id: the adversary for the whole rollout, from step 0)
    or one entry per rollout step (None: no adversary at that step), as a closed loop that
    re-selects at its replans records it (``selection_source="model"``). Each distinct agent
    is listed once, from the first step it held the role, in that order: once chosen, the
    guidance has moved it toward the ego, so a later contact with it still counts.
    """
    if one_agent(adversary):
        return [(adversary_index(scene, adversary), 0)]
    steps = list(adversary)
    if len(steps) != rollout_steps(scene):
        raise ValueError(
            f"adversary: one entry per rollout step, {rollout_steps(scene)}, got {len(steps)}"
        )
    named: dict[int | str, int] = {}  # each name's first step, in the order chosen
    for step, agent in enumerate(steps):
        if agent is not None and agent not in named:
            named[agent] = step
    first: dict[int, int] = {}  # a row named both by row and by id counts once
    for agent, step in named.items():
        first.setdefault(adversary_index(scene, agent), step)
    return list(first.items())


def nan_mean(values: np.ndarray) -> float:
    """Mean ignoring NaN; NaN (without a warning) when nothing is left."""
    values = np.asarray(values, dtype=np.float64)
    values = values[~np.isnan(values)]
    return float(values.mean()) if values.size else math.nan


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a rate ``k / n`` (95 % for ``z = 1.96``); NaNs if n = 0.

    Better than the normal approximation at rates near 0 or 1 and at small ``n``, where most of
    our rates live (a collision rate of 2 in 50).
    """
    if n <= 0:
        return math.nan, math.nan
    p = k / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # At k = 0 (k = n) the bound is exactly 0 (1); the subtraction leaves a rounding residue
    # (6.9e-18), which a table would print as a rate of 6.94e-16 %.
    low = 0.0 if k == 0 else max(0.0, centre - half)
    high = 1.0 if k == n else min(1.0, centre + half)
    return low, high
