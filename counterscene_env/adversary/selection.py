"""Adversary selection: choose the agent the counterfactual guidance pushes into the ego.

The causal selector (the paper's) takes the first mined conflict by ``(tier, -score)``
(``adversary/conflicts.py``, which also documents the inputs and the strict gates).

Baselines (paper Table 3), behind the same interface, differ only in the choice: ``random``
(uniform), ``distance`` (SafeSim: nearest at the first jointly valid step) and ``ttc`` (CCDiff:
smallest constant-velocity box time to collision at that step). Their pool is every candidate
(strict: every *moving* candidate); tiers and conflict gates do not filter them. The chosen
agent's :class:`Conflict` is still mined as above, so the guidance gets a target either way.

No adversary is a normal outcome: :func:`select_adversary` then returns a :class:`Selection`
with ``conflict=None`` and a human-readable ``fallback`` reason, and the caller runs the
unguided world model (docs/design.md, "Environment semantics").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from counterscene_env.adversary.conflicts import (
    DIRECTION_EPS,
    FALLBACK_WEIGHT,
    FOLLOWING,
    INTERSECTION,
    LEAD_BRAKING,
    MIN_JOINT_STEPS,
    REAR_APPROACH,
    STRICT_MIN_SPEED,
    Conflict,
    encounter,
    mine,
    mine_conflicts,
)
from counterscene_env.adversary.tracks import (
    Tracks,
    check_eligible,
    check_finite_where_valid,
    check_start_step,
    check_tracks,
    mean_speed,
    travel_direction,
)
from counterscene_env.config import Selector
from counterscene_env.geometry import arc_length
from counterscene_env.ttc import box_time_to_collision

__all__ = [
    "FALLBACK_WEIGHT",
    "FOLLOWING",
    "INTERSECTION",
    "LEAD_BRAKING",
    "MAX_REACH_ACCELERATION",
    "METHODS",
    "REAR_APPROACH",
    "Conflict",
    "Selection",
    "encounter",
    "mine_conflicts",
    "reachable",
    "required_acceleration",
    "select_adversary",
]

# ---------------------------------------------------------------- baselines
#: Constant-velocity look-ahead of the ``ttc`` selector, s (CCDiff-style).
TTC_HORIZON = 10.0
#: Box (length, width) m when ``extents`` is not given: a passenger car.
DEFAULT_EXTENT = (4.5, 2.0)
#: Below this speed (m/s) a finite-difference velocity gives no heading for the ``ttc`` boxes.
HEADING_MIN_SPEED = 0.1

#: The selection methods (:class:`~counterscene_env.config.Selector`).
METHODS = Selector.values()


@dataclass(frozen=True)
class Selection:
    """What a selector chose.

    Attributes:
        method: one of ``METHODS``.
        conflict: the adversary's conflict, or None: no adversary, fall back to unguided traffic.
        fallback: human-readable reason when ``conflict`` is None, else None.
        num_candidates: candidates (eligible non-ego rows with at least ``min_joint_steps``
            jointly valid steps), whatever the method and gates.
    """

    method: str
    conflict: Conflict | None
    fallback: str | None
    num_candidates: int


# ---------------------------------------------------------------- selectors


def passes_first(conflict: Conflict) -> bool:
    """Whether a crossing conflict's candidate reaches the conflict point before the ego.

    The paper's adversary is the agent whose behaviour keeps the scene safe: at a crossing,
    the one that arrives after the ego, leaving it the time to clear (its temporal guidance
    compresses exactly that margin). A candidate that passes first was not holding back for
    the ego; the ego held back for it. The paper's score ``v_rel / (gap + 0.5)`` does not
    tell the two apart (docs/history/closed_loop.md, "What changed on 26 Nov 2026").
    """
    return conflict.type == INTERSECTION and conflict.adversary_step < conflict.ego_step


#: Acceleration [m/s^2] up to which an adversary counts as able to reach its conflict point by
#: the ego's arrival (:func:`reachable`): a passenger car at full throttle (0-100 km/h in
#: about 7 s). A physical bound, not a value fitted to the runs (docs/history/closed_loop.md,
#: "Reachable conflicts first").
MAX_REACH_ACCELERATION = 4.0


def required_acceleration(tracks: Tracks, conflict: Conflict, start_step: int) -> float:
    """m/s^2: the constant acceleration that takes the candidate from its first valid step,
    at its speed there, along its own path to its end of the encounter by the ego's arrival.

    ``a = 2 (D - v T) / T^2`` with ``D`` m the candidate's path length to ``tau_a``, ``v``
    m/s its speed at its first valid step and ``T`` s the time from that step to ``tau_e``.
    Negative: at its present speed it would be there early. ``inf`` when the ego arrives
    before the candidate is valid at all (``T <= 0``).
    """
    agent = conflict.agent
    steps = np.flatnonzero(tracks.valid[agent])
    first = int(steps[0])
    T = (conflict.ego_step - start_step - first) * tracks.dt
    if T <= 0:
        return math.inf
    upto = steps[steps <= conflict.adversary_step - start_step]
    D = float(arc_length(tracks.positions[agent, upto])[-1])  # m, along its valid steps
    v = float(tracks.speeds[agent, first])
    return 2.0 * (D - v * T) / T**2


def reachable(tracks: Tracks, conflict: Conflict, start_step: int) -> bool:
    """Whether the guidance's arrival-time compression can act on a conflict: the candidate
    arrives after the ego (the compression moves the later agent's arrival, and the ego is
    not guided) and can make up the gap at no more than :data:`MAX_REACH_ACCELERATION`.
    A conflict whose point the ego occupies now (a follower's encounter on a shared path is
    often the ego's present place) would need the candidate there at once: it is not.
    """
    if conflict.adversary_step < conflict.ego_step:
        return False
    return required_acceleration(tracks, conflict, start_step) <= MAX_REACH_ACCELERATION


def _first_joint_steps(tracks: Tracks, agents: np.ndarray) -> np.ndarray:
    """``[P]`` int: each agent's earliest step jointly valid with the ego (they all have one)."""
    joint = tracks.valid[agents] & tracks.valid[tracks.ego][None]  # [P, T]
    return np.argmax(joint, axis=1)


def _headings(
    tracks: Tracks, agents: np.ndarray, steps: np.ndarray, yaws: np.ndarray | None
) -> np.ndarray:
    """``[P] rad`` box headings of ``agents`` at ``steps``.

    The given ``yaws`` if any; else the direction of the finite-difference velocity, or, for
    an agent slower than 0.1 m/s there (whose velocity direction is noise), its coarse travel
    direction; 0 when that is shorter than ``DIRECTION_EPS`` too.
    """
    if yaws is not None:
        return yaws[agents, steps]
    vel = tracks.velocities[agents, steps]  # [P, 2]
    out = np.arctan2(vel[:, 1], vel[:, 0])
    for k, (agent, v) in enumerate(zip(agents, vel, strict=True)):
        if np.hypot(*v) < HEADING_MIN_SPEED:
            d = travel_direction(tracks.positions[agent], tracks.valid[agent])
            out[k] = math.atan2(d[1], d[0]) if np.hypot(*d) >= DIRECTION_EPS else 0.0
    return out


def _start_distances(tracks: Tracks, agents: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """``[P] m`` centre distance to the ego at each agent's first jointly valid step."""
    delta = tracks.positions[agents, steps] - tracks.positions[tracks.ego, steps]
    return np.hypot(delta[:, 0], delta[:, 1])


def _check_extents(extents: np.ndarray | None, n: int) -> np.ndarray:
    """``[N, 2] m`` (length, width), finite and positive; ``DEFAULT_EXTENT`` when None."""
    if extents is None:
        return np.tile(np.asarray(DEFAULT_EXTENT, dtype=np.float64), (n, 1))
    extents = np.asarray(extents, dtype=np.float64)
    if extents.shape != (n, 2):
        raise ValueError(f"extents must be [N, 2] = ({n}, 2) (length, width), got {extents.shape}")
    if not (np.isfinite(extents).all() and (extents > 0).all()):
        raise ValueError("extents must be finite and positive (length, width) in m")
    return extents


def _check_yaws(yaws: np.ndarray | None, valid: np.ndarray) -> np.ndarray | None:
    """``[N, T] rad`` or None; finite at valid steps."""
    if yaws is None:
        return None
    yaws = np.asarray(yaws, dtype=np.float64)
    if yaws.shape != valid.shape:
        raise ValueError(f"yaws must be [N, T] = {valid.shape} like positions, got {yaws.shape}")
    check_finite_where_valid(yaws, valid, "yaws")
    return yaws


def select_adversary(
    method: str,
    positions: np.ndarray,
    valid: np.ndarray,
    ego: int,
    *,
    speeds: np.ndarray | None = None,
    extents: np.ndarray | None = None,
    yaws: np.ndarray | None = None,
    eligible: np.ndarray | None = None,
    dt: float = 0.1,
    start_step: int = 0,
    strict: bool = True,
    rng: np.random.Generator | None = None,
    min_joint_steps: int = MIN_JOINT_STEPS,
    yielders_first: bool = False,
    reachable_first: bool = False,
) -> Selection:
    """Choose the adversary and its conflict with one of ``METHODS``.

    ``causal`` is Algorithm 1: the tiered candidate first by ``(tier, -score)``, ties to the
    lower row. The baselines choose among every candidate (``strict``: every moving one, mean
    speed > 1 m/s), ignoring tiers: ``random`` uniformly with ``rng.integers``; ``distance``
    the nearest to the ego at its first jointly valid step; ``ttc`` the smallest
    constant-velocity box time to collision with the ego at that step (ties, and all-infinite
    TTCs, by that distance, then by row).

    Args:
        method: one of ``METHODS``.
        positions: ``[N, T, 2] m`` future tracks (NaN allowed at invalid steps).
        valid: ``[N, T] bool``.
        ego: the ego's row; never a candidate.
        speeds: ``[N, T] m/s`` (the moving gate); None: finite differences of positions.
        extents: ``[N, 2] m`` (length, width) for ``ttc``; None: 4.5 x 2.0 m for all.
        yaws: ``[N, T] rad`` for ``ttc``; None: direction of motion.
        eligible: ``[N] bool`` rows that may be chosen; None: all.
        dt: s per step.
        start_step: absolute episode step of index 0.
        strict: the strict gates (see module doc); False is the paper preset.
        rng: required for ``random``.
        min_joint_steps: jointly valid steps a candidate needs.
        yielders_first: ``causal`` only: a crossing conflict whose candidate reaches the
            conflict point before the ego ranks after every other tiered conflict (ours, see
            :func:`passes_first`); False is the paper's ``(tier, -score)``.
        reachable_first: ``causal`` only: a conflict the candidate cannot reach by the ego's
            arrival (:func:`reachable`) ranks after every reachable one (ours); it comes
            before ``yielders_first`` in the ranking key.

    Returns:
        A :class:`Selection`. Its conflict is the chosen agent's mined conflict (for a baseline
        possibly with ``tier=None``), or None with the reason in ``fallback``.

    Raises:
        ValueError: unknown method, ``random`` without ``rng``, inconsistent shapes, ``ego`` out
            of range, a non-finite value at a valid step.
    """
    method = Selector.parse(method, "method")
    if method == "random" and rng is None:
        raise ValueError("method 'random' needs rng (a numpy.random.Generator)")
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    tracks = check_tracks(
        positions, valid, ego, speeds=speeds, dt=dt, min_joint_steps=min_joint_steps
    )
    n = tracks.valid.shape[0]
    eligible = check_eligible(eligible, n)
    extents = _check_extents(extents, n)
    yaws = _check_yaws(yaws, tracks.valid)
    start_step = check_start_step(start_step)
    strict = bool(strict)

    conflicts = mine(tracks, eligible, start_step, strict, min_joint_steps)
    count = len(conflicts)
    if not conflicts:
        return Selection(
            method,
            None,
            f"no candidate with >= {min_joint_steps} jointly valid future steps",
            0,
        )

    if method == "causal":
        tiered = [c for c in conflicts if c.tier is not None]
        if not tiered:
            rules = "the tier rules and strict gates" if strict else "the tier rules"
            return Selection(
                method, None, f"no candidate passed {rules} ({count} candidates)", count
            )
        best = min(
            tiered,
            key=lambda c: (
                reachable_first and not reachable(tracks, c, start_step),
                yielders_first and passes_first(c),
                c.tier,
                -c.score,
                c.agent,
            ),
        )
        return Selection(method, best, None, count)

    # Baselines: the pool ignores tiers and conflict gates; strict keeps only movers, as
    # guidance on a parked car's actions cannot make it an adversary.
    pool = [c for c in conflicts if not strict or mean_speed(tracks, c.agent) > STRICT_MIN_SPEED]
    if not pool:
        return Selection(
            method,
            None,
            f"no moving candidate (mean speed > {STRICT_MIN_SPEED} m/s) among {count} candidates",
            count,
        )
    agents = np.array([c.agent for c in pool])
    if method == "random":
        return Selection(method, pool[int(rng.integers(len(pool)))], None, count)

    steps = _first_joint_steps(tracks, agents)
    distance = _start_distances(tracks, agents, steps)
    if method == "distance":
        order = np.lexsort((agents, distance))
    else:  # ttc
        ego_rows = np.full_like(agents, tracks.ego)
        ttc = box_time_to_collision(
            tracks.positions[ego_rows, steps],
            tracks.velocities[ego_rows, steps],
            _headings(tracks, ego_rows, steps, yaws),
            extents[ego_rows],
            tracks.positions[agents, steps],
            tracks.velocities[agents, steps],
            _headings(tracks, agents, steps, yaws),
            extents[agents],
            horizon=TTC_HORIZON,
            step=tracks.dt,
        )
        order = np.lexsort((agents, distance, ttc))
    return Selection(method, pool[int(order[0])], None, count)
