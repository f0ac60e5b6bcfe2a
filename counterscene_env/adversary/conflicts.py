"""Causal conflict mining: where and when each candidate meets the ego, and how dangerous it is.

This module's one job is to mine each candidate's conflict with the ego: where and when they
meet, how, and how dangerous it is (paper appendix "Conflict Detection and Scoring",
Algorithm 1 "Offline Causal Conflict Mining and Target Identification"; docs/design.md,
"Causal adversary selection"). ``adversary/selection.py`` chooses among the conflicts. It
reads only future tracks, so it works the same on the factual log (the paper's offline
mining) and on the world model's own unguided prediction (re-mined at every replan). Plain
numpy.

Inputs, shared by every function:

- ``positions [N, T, 2] m``: the FUTURE tracks to mine (e.g. log steps ``now + 1 ..``), any
  frame; ``valid [N, T] bool``. Positions at invalid steps are ignored (NaN is fine there); a
  non-finite position at a valid step is a ``ValueError``.
- ``ego``: the ego's row. It is never a candidate.
- ``dt`` s per step; ``start_step``: the absolute episode step of index 0, so that the arrival
  steps in a :class:`Conflict` are absolute (the guidance converts them to its window).

Causal mining (``method="causal"``), faithful to the paper:

1. Candidates: every eligible non-ego row with at least ``min_joint_steps`` (5) steps ``V`` at
   which it and the ego are both valid.
2. Closest spatio-temporal encounter over all pairs of jointly valid steps,
   ``(tau_e, tau_a) = argmin_{t_e, t_a in V} ||p_e(t_e) - p_a(t_a)||`` (first minimum in
   row-major order); conflict point ``c`` the midpoint, ``d_min`` the distance, arrival gap
   ``|tau_e - tau_a| dt`` and ``v_rel`` the norm of the finite-difference velocity difference at
   the encounter.
3. Type from the coarse travel directions (last minus first valid position): cosine > 0.8 is
   ``following`` (``rear_approach`` if the candidate starts behind the ego along the ego's
   direction, ``lead_braking`` if ahead), otherwise ``intersection``.
4. Score ``v_rel / (gap + 0.5)`` for intersections, ``v_rel / (d_min + 1)`` for following.
5. Tiers 1 (intersection, gap < 5 s), 2 (rear approach, d_min < 10 m), 3 (lead braking,
   d_min < 12 m), each also needing score >= 0.05; the adversary is the first by
   ``(tier, -score)``, ties to the lower row. Guidance weight ``-80 - 40 min(s, 1)``
   (intersection) or ``-60 - 30 min(s, 1)`` (following); ``FALLBACK_WEIGHT`` (-50) for callers
   with no conflict.

What the paper lacks and we add (docs/design.md, "Strict selection gates"): optional
*strict* gates (on by default in :func:`select_adversary`, off in the paper preset) that
withdraw the tier of a conflict that the guidance cannot realistically turn into a near miss:
``d_min >= 15 m``, an encounter on the last jointly valid step (truncated by the horizon, so
not a real closest approach) or, for both, on the first (the two are closest *now* and drift apart: no conflict
lies ahead for the guidance to sharpen; side-by-side cars at a junction are the common case),
or a candidate that does not move (mean speed <= 1 m/s).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from counterscene_env.adversary.tracks import (
    Tracks,
    check_eligible,
    check_index,
    check_start_step,
    check_tracks,
    mean_speed,
    travel_direction,
)

INTERSECTION, FOLLOWING = "intersection", "following"
REAR_APPROACH, LEAD_BRAKING = "rear_approach", "lead_braking"
# ---------------------------------------------------------------- paper constants (appendix)
#: A candidate needs this many steps at which it and the ego are both valid (Algorithm 1, l. 5).
MIN_JOINT_STEPS = 5
#: Direction cosine above which an interaction is ``following`` (appendix, type classification).
FOLLOWING_COS = 0.8
#: A coarse travel direction shorter than this (m) has no direction: cosine 0, ``intersection``.
DIRECTION_EPS = 1e-6
#: s_conflict = v_rel / (gap + 0.5 s) for intersections: co-arrival matters.
INTERSECTION_GAP_OFFSET = 0.5
#: s_conflict = v_rel / (d_min + 1.0 m) for following: closing distance matters.
FOLLOWING_DISTANCE_OFFSET = 1.0
#: Tier 1: intersection with arrival gap below this, s.
TIER1_MAX_GAP = 5.0
#: Tier 2: rear approach with d_min below this, m.
TIER2_MAX_DISTANCE = 10.0
#: Tier 3: lead braking with d_min below this, m.
TIER3_MAX_DISTANCE = 12.0
#: Every tier needs s_conflict at least this.
MIN_SCORE = 0.05
#: w_guide = base + slope min(s, 1), by type (appendix, guidance weight).
INTERSECTION_WEIGHT = (-80.0, -40.0)
FOLLOWING_WEIGHT = (-60.0, -30.0)
#: w_guide when no conflict was mined (used by callers that guide without a target).
FALLBACK_WEIGHT = -50.0

# ---------------------------------------------------------------- strict gates (ours)
#: Two agents that never come within this (m) of each other are no conflict worth guiding:
#: the paper's tier 1 has no distance limit at all, so a car on a far parallel road qualifies.
STRICT_MAX_DISTANCE = 15.0
# No arrival-gap gate beyond tier 1's 5 s: a 1.5 s gate for crossing conflicts stood here
# until 26 Nov 2026. With the guidance's arrival-time compression active at every replan
# (its progress measured in denoising steps, the paper's main text) the crossings it let
# through are hit as often as the ones it kept (docs/history/closed_loop.md, "What changed on
# 26 Nov 2026").
#: Mean speed (m/s) over its valid steps that a candidate must exceed: guidance acts on the
#: adversary's actions, and a parked car's "encounter" is only the ego driving past it.
STRICT_MIN_SPEED = 1.0


@dataclass(frozen=True)
class Conflict:
    """The closest encounter of one candidate with the ego, typed, scored and tiered.

    Attributes:
        agent: row of the candidate in the arrays given.
        conflict_point: ``[2] m``, midpoint of the closest encounter, same frame as the inputs
            (read-only array).
        ego_step: ``tau_e``, absolute step (``start_step`` + index into the arrays) at which the
            ego is at its end of the closest encounter.
        adversary_step: ``tau_a``, absolute step, the candidate's end.
        min_distance: ``d_min``, m.
        arrival_gap: ``|tau_e - tau_a| dt``, s.
        relative_speed: ``v_rel``, m/s, finite difference at the encounter.
        type: ``INTERSECTION`` or ``FOLLOWING``.
        subtype: ``INTERSECTION`` for intersections, else ``REAR_APPROACH`` / ``LEAD_BRAKING``.
        score: ``s_conflict`` (m/s^2 for intersections, 1/s for following).
        tier: 1, 2 or 3, or None when the tier rule (or a strict gate) rejects the conflict.
        weight: ``w_guide``, the guidance weight for this type and score.
    """

    agent: int
    conflict_point: np.ndarray
    ego_step: int
    adversary_step: int
    min_distance: float
    arrival_gap: float
    relative_speed: float
    type: str
    subtype: str
    score: float
    tier: int | None
    weight: float


# ---------------------------------------------------------------- mining


def _tier(subtype: str, gap: float, d_min: float, score: float) -> int | None:
    """The paper's TierAssign: 1, 2, 3, or None (no conflict worth guiding)."""
    if score < MIN_SCORE:
        return None
    if subtype == INTERSECTION:
        return 1 if gap < TIER1_MAX_GAP else None
    if subtype == REAR_APPROACH:
        return 2 if d_min < TIER2_MAX_DISTANCE else None
    return 3 if d_min < TIER3_MAX_DISTANCE else None


def _weight(kind: str, score: float) -> float:
    """w_guide = base + slope min(s, 1) by type (appendix, guidance weight)."""
    base, slope = INTERSECTION_WEIGHT if kind == INTERSECTION else FOLLOWING_WEIGHT
    return base + slope * min(score, 1.0)


def _encounter(
    tracks: Tracks, agent: int, start_step: int, min_joint_steps: int
) -> Conflict | None:
    """Algorithm 1, lines 4-19, for one candidate (no strict gates); None if too few steps."""
    ego, pos, valid, dt = tracks.ego, tracks.positions, tracks.valid, tracks.dt
    joint = np.flatnonzero(valid[ego] & valid[agent])  # V, indices into the arrays
    if joint.size < min_joint_steps:
        return None
    p_e, p_a = pos[ego, joint], pos[agent, joint]  # [V, 2] m
    diff = p_e[:, None, :] - p_a[None, :, :]  # [V, V, 2]: rows ego steps, columns agent steps
    dist = np.hypot(diff[..., 0], diff[..., 1])  # [V, V] m
    # argmin over the flattened matrix: the first minimum in row-major order, so ties go to
    # the earliest ego step, then the earliest agent step (deterministic).
    row, col = divmod(int(np.argmin(dist)), joint.size)
    tau_e, tau_a = int(joint[row]), int(joint[col])
    d_min = float(dist[row, col])
    point = 0.5 * (pos[ego, tau_e] + pos[agent, tau_a])
    point.setflags(write=False)
    gap = abs(tau_e - tau_a) * dt
    v_rel = float(np.linalg.norm(tracks.velocities[ego, tau_e] - tracks.velocities[agent, tau_a]))

    # ClassifyConflict: cosine of the coarse travel directions over the whole given future.
    d_e = travel_direction(pos[ego], valid[ego])
    d_a = travel_direction(pos[agent], valid[agent])
    norm_e, norm_a = float(np.linalg.norm(d_e)), float(np.linalg.norm(d_a))
    cos = float(d_e @ d_a) / (norm_e * norm_a) if min(norm_e, norm_a) >= DIRECTION_EPS else 0.0
    if cos > FOLLOWING_COS:
        kind = FOLLOWING
        # Order along the ego's direction at the first jointly valid step: behind -> the
        # candidate closes in from the rear; ahead -> the ego closes in on a (braking) leader.
        along = float((p_a[0] - p_e[0]) @ d_e)
        subtype = REAR_APPROACH if along < 0.0 else LEAD_BRAKING
        score = v_rel / (d_min + FOLLOWING_DISTANCE_OFFSET)
    else:
        kind = subtype = INTERSECTION
        score = v_rel / (gap + INTERSECTION_GAP_OFFSET)

    return Conflict(
        agent=int(agent),
        conflict_point=point,
        ego_step=start_step + tau_e,
        adversary_step=start_step + tau_a,
        min_distance=d_min,
        arrival_gap=gap,
        relative_speed=v_rel,
        type=kind,
        subtype=subtype,
        score=score,
        tier=_tier(subtype, gap, d_min, score),
        weight=_weight(kind, score),
    )


#: The strict gates by name, in the order :func:`strict_gate_failures` reports them.
STRICT_GATES = ("far", "truncated", "drifting_apart", "parked")


def strict_gate_failures(tracks: Tracks, conflict: Conflict, start_step: int) -> list[str]:
    """The strict gates (module constants) a conflict fails, by name (:data:`STRICT_GATES`):
    ``far`` (d_min), ``truncated`` (closest on the last jointly valid step),
    ``drifting_apart`` (both closest on the first), ``parked`` (mean speed)."""
    joint = np.flatnonzero(tracks.valid[tracks.ego] & tracks.valid[conflict.agent])
    first, last = start_step + int(joint[0]), start_step + int(joint[-1])
    failed = {
        "far": conflict.min_distance >= STRICT_MAX_DISTANCE,
        "truncated": last in (conflict.ego_step, conflict.adversary_step),
        "drifting_apart": conflict.ego_step == conflict.adversary_step == first,
        "parked": mean_speed(tracks, conflict.agent) <= STRICT_MIN_SPEED,
    }
    return [gate for gate in STRICT_GATES if failed[gate]]


def mine(
    tracks: Tracks, eligible: np.ndarray, start_step: int, strict: bool, min_joint_steps: int
) -> list[Conflict]:
    """Every candidate's conflict, in row order; tier None where a strict gate fails."""
    out = []
    for agent in np.flatnonzero(eligible):
        if agent == tracks.ego:
            continue
        conflict = _encounter(tracks, int(agent), start_step, min_joint_steps)
        if conflict is None:
            continue
        if (
            strict
            and conflict.tier is not None
            and strict_gate_failures(tracks, conflict, start_step)
        ):
            conflict = replace(conflict, tier=None)
        out.append(conflict)
    return out


def encounter(
    positions: np.ndarray,
    valid: np.ndarray,
    ego: int,
    agent: int,
    *,
    dt: float = 0.1,
    start_step: int = 0,
    min_joint_steps: int = MIN_JOINT_STEPS,
) -> Conflict | None:
    """The closest spatio-temporal encounter of one agent with the ego (Algorithm 1, l. 4-19).

    Args:
        positions: ``[N, T, 2] m`` future tracks (NaN allowed at invalid steps).
        valid: ``[N, T] bool``.
        ego: the ego's row.
        agent: the candidate's row (not the ego).
        dt: s per step.
        start_step: absolute episode step of index 0.
        min_joint_steps: jointly valid steps needed.

    Returns:
        The :class:`Conflict` with the paper's tier rule applied (no strict gates: those need
        the candidate's speed, see :func:`mine_conflicts`), or None when the two share fewer
        than ``min_joint_steps`` jointly valid steps.

    Raises:
        ValueError: inconsistent shapes, a row out of range, ``agent == ego``, a non-finite
            position at a valid step.
    """
    tracks = check_tracks(
        positions, valid, ego, speeds=None, dt=dt, min_joint_steps=min_joint_steps
    )
    agent = check_index(agent, tracks.valid.shape[0], "agent")
    if agent == tracks.ego:
        raise ValueError(f"agent {agent} is the ego: the ego is never its own adversary")
    return _encounter(tracks, agent, check_start_step(start_step), min_joint_steps)


def mine_conflicts(
    positions: np.ndarray,
    valid: np.ndarray,
    ego: int,
    *,
    speeds: np.ndarray | None = None,
    eligible: np.ndarray | None = None,
    dt: float = 0.1,
    start_step: int = 0,
    strict: bool = False,
    min_joint_steps: int = MIN_JOINT_STEPS,
) -> list[Conflict]:
    """Every candidate's conflict with the ego (Algorithm 1's loop, keeping the untiered too).

    Args:
        positions: ``[N, T, 2] m`` future tracks (NaN allowed at invalid steps).
        valid: ``[N, T] bool``.
        ego: the ego's row; never a candidate.
        speeds: ``[N, T] m/s`` for the strict moving gate; None derives them from finite
            differences of ``positions``.
        eligible: ``[N] bool`` rows that may be candidates (e.g. vehicles only); None: all.
        dt: s per step.
        start_step: absolute episode step of index 0.
        strict: apply the strict gates (d_min, last or first step, moving): a conflict
            failing one gets ``tier=None``. False is the paper.
        min_joint_steps: jointly valid steps a candidate needs.

    Returns:
        One :class:`Conflict` per candidate, in row order; ``tier`` None for those the tier
        rule (or a strict gate) rejects.
    """
    tracks = check_tracks(
        positions, valid, ego, speeds=speeds, dt=dt, min_joint_steps=min_joint_steps
    )
    eligible = check_eligible(eligible, tracks.valid.shape[0])
    return mine(tracks, eligible, check_start_step(start_step), bool(strict), min_joint_steps)
