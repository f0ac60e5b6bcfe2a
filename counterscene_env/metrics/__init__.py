"""Scene metrics: collision, hard braking, off-road, displacement and safety-margin measures.

``safety.py`` (CR, HBR, TTC, clearance), ``realism.py`` (ORR, ADE/FDE), ``report.py`` (one
scene's record, the paper's averages, JSON output) and ``common.py`` (keys, horizons); every
name is importable from ``counterscene_env.metrics``.

This module's one job is to score a simulated :class:`~counterscene_env.scene.Scene` (against
its factual log where needed), per scene and per horizon second, and to average those scores
over scenes the way the paper's tables do (appendix "Metric Definitions";
docs/design.md, "Metric definitions").

What is scored: the rollout, steps ``current_index + 1 ..`` of the scene (the history is shared
with the log). Horizon ``h`` s means the first ``round(h / dt)`` rollout steps; steps a scene does
not have (a rollout cut short, e.g. by a terminating collision) are treated as invalid, so e.g.
CR at 8 s still counts a collision at 3 s and FDE at 8 s is NaN.

Conventions: rates are fractions in [0, 1] (per-scene flags are 0.0/1.0); a value with nothing
to average is NaN, never 0; ``min_ttc`` is ``inf`` when no conflict is projected. Results are
plain Python floats, so ``json.dumps`` writes them (as ``NaN``/``Infinity`` where they are).

Where we depart from the paper (docs/design.md, "Metric definitions" and
"Where we depart from the paper and its public code"):

- HBR uses the *signed* longitudinal acceleration. The paper's ``||a|| cos(world yaw)`` is kept
  as :func:`hbr_paper` for comparison only.
- Collision checks mask validity per agent (geometry layer).
"""

from counterscene_env.metrics.common import (
    BRAKE_TOLERANCE,
    EXTRA_PER_SECOND_KEYS,
    GROUPS,
    HARD_BRAKE_THRESHOLD,
    METRICS_VERSION,
    PER_SECOND_KEYS,
    SCENE_KEYS,
    AccelerationSource,
    agent_index,
    brakes_at_least,
    horizon_steps,
    is_hard_braking,
    rollout_steps,
    wilson_interval,
)
from counterscene_env.metrics.realism import (
    ade_fde,
    align_agents,
    displacement_steps,
    off_road_rate,
    off_road_steps,
    parked_agents,
    path_speeds,
)
from counterscene_env.metrics.report import (
    aggregate,
    evaluate_scene,
    horizon_values,
    json_safe,
    rate_value,
    severity,
)
from counterscene_env.metrics.safety import (
    agent_collision_steps,
    ego_adversary_collision_steps,
    ego_collided,
    ego_collision_steps,
    hbr_all,
    hbr_ego,
    hbr_paper,
    longitudinal_acceleration,
    min_clearance,
    min_ttc_ego,
)

__all__ = [
    "BRAKE_TOLERANCE",
    "EXTRA_PER_SECOND_KEYS",
    "GROUPS",
    "HARD_BRAKE_THRESHOLD",
    "METRICS_VERSION",
    "PER_SECOND_KEYS",
    "SCENE_KEYS",
    "AccelerationSource",
    "ade_fde",
    "agent_collision_steps",
    "agent_index",
    "aggregate",
    "align_agents",
    "brakes_at_least",
    "displacement_steps",
    "ego_adversary_collision_steps",
    "ego_collided",
    "ego_collision_steps",
    "evaluate_scene",
    "hbr_all",
    "hbr_ego",
    "hbr_paper",
    "horizon_steps",
    "horizon_values",
    "is_hard_braking",
    "json_safe",
    "longitudinal_acceleration",
    "min_clearance",
    "min_ttc_ego",
    "off_road_rate",
    "off_road_steps",
    "parked_agents",
    "path_speeds",
    "rate_value",
    "rollout_steps",
    "severity",
    "wilson_interval",
]
