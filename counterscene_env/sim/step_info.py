"""What every closed-loop step records for an ego: its info dict (docs/closed_loop.md, "One
episode", **Every step records**).

The info is computed from the episode's record at its current step ``t``: the ego's oriented
box against every other valid agent's (collision), the smallest constant-velocity box TTC,
the ego's signed longitudinal acceleration and hard braking, off-road, and the ego's current
adversary selection. Plain Python values only, so that an env can hand it on as it is.
"""

from __future__ import annotations

import math

import numpy as np

from counterscene_env import geometry
from counterscene_env.metrics import is_hard_braking
from counterscene_env.sim.state import Episode
from counterscene_env.ttc import box_time_to_collision

#: Horizon of the per-step TTC, s.
TTC_HORIZON = 5.0


def ego_step_info(ep: Episode, k: int, replanned: bool) -> dict:
    """Ego ``k``'s info at episode ``ep``'s current step; ``replanned``: whether the world
    model re-planned at this step.

    Keys (units): ``step``, ``time`` [s], ``collision``, ``collided_with`` (the hit agent's
    id), ``hard_braking``, ``ego_acceleration`` [m/s^2], ``ego_speed`` [m/s], ``off_road``,
    ``min_ttc`` [s, up to :data:`TTC_HORIZON`], ``adversary``, ``conflict_type``,
    ``danger_score``, ``tier``, ``conflict_point`` [m, world frame], ``arrival_steps``
    (steps after the episode start), ``adversary_distance`` [m], ``fallback``,
    ``replanned``.
    """
    t, log = ep.t, ep.factual
    e = ep.egos[k]
    pos, yaw, ok = ep.positions[:, t], ep.yaws[:, t], ep.valid[:, t].copy()
    ok[e] = False
    ext = log.extents
    hits = geometry.boxes_overlap(pos[e], yaw[e], ext[e], pos, yaw, ext) & ok
    hit_rows = np.flatnonzero(hits)
    vel = ep.speeds[:, t, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
    ttc = box_time_to_collision(
        pos[e], vel[e], yaw[e], ext[e], pos, vel, yaw, ext, horizon=TTC_HORIZON
    )
    ttc = np.where(ok, ttc, np.inf)
    acc = (ep.speeds[e, t] - ep.speeds[e, t - 1]) / log.dt if t > ep.start else 0.0
    conflict = ep.selections[k].conflict
    adv = None if conflict is None else conflict.agent
    adv_dist = float(np.linalg.norm(pos[adv] - pos[e])) if adv is not None and ok[adv] else None
    return {
        "step": t - ep.start,
        # Rounded: 3 * 0.1 s is 0.30000000000000004 s in floats; a user compares it with 0.3.
        "time": round((t - ep.start) * log.dt, 9),
        "collision": bool(hits.any()),
        "collided_with": str(log.agent_ids[hit_rows[0]]) if hit_rows.size else None,
        "hard_braking": bool(is_hard_braking(acc)),
        "ego_acceleration": float(acc),
        "ego_speed": float(ep.speeds[e, t]),
        "off_road": bool(log.road.off_road(pos[e])),
        "min_ttc": float(ttc.min()) if ttc.size else math.inf,
        "adversary": None if adv is None else str(log.agent_ids[adv]),
        "conflict_type": None if conflict is None else conflict.subtype,
        "danger_score": None if conflict is None else float(conflict.score),
        "tier": None if conflict is None else conflict.tier,
        "conflict_point": None if conflict is None else [float(x) for x in conflict.conflict_point],
        "arrival_steps": None
        if conflict is None
        else [int(conflict.ego_step) - ep.start, int(conflict.adversary_step) - ep.start],
        "adversary_distance": adv_dist,
        "fallback": ep.selections[k].fallback,
        "replanned": replanned,
    }
