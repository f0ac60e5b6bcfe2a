"""Yielding: traffic slows down along its planned path rather than drive into another car.

The world model plans every agent jointly, but its plans are open-loop for ``replan_every``
steps and a sample that is 1 m off in a dense intersection puts two boxes on top of each other.
Human drivers do not follow a plan into an occupied spot: they brake. This module is that
reflex, applied by the closed loop (``sim/motion.py``) to the ordinary traffic at every step:

- the agent keeps the *path* the world model planned (so its route, lane and turn are the
  model's), and only its *progress* along that path may fall behind the plan's schedule;
- it may advance no farther than the first point of its path ahead whose box (grown by
  :data:`MARGIN`) overlaps another agent's current box, and no faster than it could still stop
  there with :data:`BRAKE` while that agent brakes too (the safe-distance rule behind IDM's
  and Gipps' models: ``v^2 <= 2 b d + v_lead^2``, ``v_lead`` the other's speed along our
  heading, 0 for a crossing car);
- an agent held back speeds up again by at most :data:`ACCEL` towards the plan's speed, and
  the next replan starts the world model from where it really is.

Egos are never filtered (their policy drives them), and neither is a guided adversary: its
safety margins are exactly what the counterfactual guidance removes (paper, "Counterfactual
Guidance"). With guidance off, the selected agent is ordinary traffic and yields like the rest.
"""

from __future__ import annotations

import math

import numpy as np

from counterscene_env import geometry

#: Braking the yielding rule plans with [m/s^2] (a firm but ordinary stop).
BRAKE = 6.0
#: Most an agent held back may speed up per second towards its plan [m/s^2].
ACCEL = 4.0
#: Growth of the yielding agent's box when its path is checked: (length, width) [m]. The length
#: is added in front only, so it stops about a metre short of the other car, not bumper to
#: bumper; the width adds 0.2 m on each side.
MARGIN = np.array([1.0, 0.4])


def point_at(points: np.ndarray, yaws: np.ndarray, arc: np.ndarray, s: float):
    """Position ``[2]`` m and yaw (rad) at arc length ``s`` m along a path.

    ``points`` ``[P, 2]`` m, ``yaws`` ``[P]`` rad and ``arc`` ``[P]`` m (non-decreasing, from
    :func:`counterscene_env.geometry.arc_length`). Where the path stands still (repeated points) the first one wins.
    """
    j = int(np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(arc) - 2))
    seg = arc[j + 1] - arc[j]
    w = 0.0 if seg <= 1e-9 else float(np.clip((s - arc[j]) / seg, 0.0, 1.0))
    xy = points[j] + w * (points[j + 1] - points[j])
    dyaw = geometry.wrap_angle(yaws[j + 1] - yaws[j])
    return xy, float(yaws[j] + w * dyaw)


def free_distance(
    stations: np.ndarray,
    station_yaws: np.ndarray,
    station_arc: np.ndarray,
    extent: np.ndarray,
    others: np.ndarray,
    other_yaws: np.ndarray,
    other_extents: np.ndarray,
    other_velocities: np.ndarray,
) -> tuple[float, float]:
    """How far an agent may go along its path before its box meets another agent's.

    Args:
        stations: ``[L, 2]`` m, points of the path ahead; row 0 is where the agent is now.
        station_yaws: ``[L]`` rad; station_arc: ``[L]`` m from row 0 (non-decreasing).
        extent: ``[2]`` m, the agent's (length, width).
        others: ``[M, 2]`` m, the other agents' current centres; other_yaws ``[M]`` rad;
            other_extents ``[M, 2]`` m; other_velocities ``[M, 2]`` m/s.

    Returns:
        ``(d, v_lead)``: the arc length [m] to the last station before the first one whose
        box (grown by :data:`MARGIN`, forward and sideways) overlaps another's, and that
        agent's speed along the path's heading there [m/s, >= 0]; ``(0, 0)`` if that is
        already the case where the agent stands, ``(inf, 0)`` if the path is clear. An agent
        already overlapping the agent's own box is ignored.
    """
    # Only cars within reach of the path can touch it (a cheap cut before the box tests).
    reach = station_arc[-1] + 0.5 * (np.hypot(*(extent + MARGIN)) + np.hypot(*other_extents.T))
    near = np.linalg.norm(others - stations[0], axis=-1) <= reach + 0.5 * MARGIN[0]
    others, other_yaws = others[near], other_yaws[near]
    other_extents, other_velocities = other_extents[near], other_velocities[near]
    if not len(others) or len(stations) < 2:
        return math.inf, 0.0
    heading = np.stack([np.cos(station_yaws), np.sin(station_yaws)], -1)  # [L, 2]
    # The box grown forward and sideways: the margin is kept to what lies ahead, never behind.
    centres = stations + 0.5 * MARGIN[0] * heading
    hit = geometry.boxes_overlap(
        centres[:, None],
        station_yaws[:, None],
        (extent + MARGIN)[None, None],
        others[None],
        other_yaws[None],
        other_extents[None],
    )  # [L, M]
    # Ignored: a car we already overlap, which braking cannot undo. (A car behind us touches
    # only the ungrown rear of the box, so it never holds us back.)
    touching = geometry.boxes_overlap(
        stations[0], station_yaws[0], extent, others, other_yaws, other_extents
    )
    hit[:, touching] = False
    rows = np.flatnonzero(hit.any(1))
    if not rows.size:
        return math.inf, 0.0
    if rows[0] == 0:
        return 0.0, 0.0
    j = int(rows[0])
    m = int(np.flatnonzero(hit[j])[0])
    return float(station_arc[j - 1]), max(0.0, float(other_velocities[m] @ heading[j]))


def moves_into(
    pose: tuple[np.ndarray, float],
    start: tuple[np.ndarray, float],
    extent: np.ndarray,
    others: np.ndarray,
    other_yaws: np.ndarray,
    other_extents: np.ndarray,
) -> bool:
    """Whether the agent's box at ``pose`` (centre ``[2]`` m, yaw rad) overlaps another agent's
    box (``others [M, 2]`` m, ``other_yaws [M]`` rad, ``other_extents [M, 2]`` m) that its box
    at ``start`` did not overlap. ``extent`` ``[2]`` m is the agent's (length, width)."""
    reach = np.linalg.norm(pose[0] - start[0]) + 0.5 * (
        np.hypot(*extent) + np.hypot(*np.asarray(other_extents).T)
    )
    near = np.linalg.norm(others - start[0], axis=-1) <= reach
    others, other_yaws, other_extents = others[near], other_yaws[near], other_extents[near]
    if not len(others):
        return False
    before = geometry.boxes_overlap(start[0], start[1], extent, others, other_yaws, other_extents)
    after = geometry.boxes_overlap(pose[0], pose[1], extent, others, other_yaws, other_extents)
    return bool((after & ~before).any())


def allowed_advance(
    d_free: float, v_lead: float, speed: float, desired: float, dt: float, lagging: bool
) -> float:
    """Arc length [m] the agent may advance this step.

    At most what the plan wants (``desired`` m); no farther than the free distance ``d_free``
    m plus what the one ahead covers meanwhile at ``v_lead`` m/s; and no faster than
    ``v = sqrt(2 BRAKE d_free + v_lead^2)``, so it could still stop in time if the one ahead
    braked as hard. An agent already behind its plan (``lagging``) regains speed from
    ``speed`` m/s by at most ``ACCEL``.
    """
    step = min(desired, d_free + v_lead * dt, math.sqrt(2.0 * BRAKE * d_free + v_lead**2) * dt)
    if lagging:
        step = min(step, (speed + ACCEL * dt) * dt)
    return max(step, 0.0)
