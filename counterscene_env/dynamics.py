"""Vehicle motion: the differentiable unicycle the world model rolls its actions out through.

State per agent: ``x`` [m], ``y`` [m], ``yaw`` [rad], ``speed`` [m/s]. Action per step:
``acceleration`` [m/s^2] and ``yaw_rate`` [rad/s], held for one step of ``dt`` seconds. For the
world model ``yaw`` is the direction of motion (the course), not the body heading: a car's centre
moves along its course, and highway-env's bicycle model slips up to ~0.25 rad between the two in
turns, which a heading-driven unicycle cannot follow (see :func:`course_angles`).

Bounds (docs/design.md, "Action space and unicycle dynamics"): acceleration in [-10, 8] m/s^2, and
``|yaw_rate| <= max(0.1, min(g |v|, a_lat / max(|v|, 0.1)))`` with the reference ``g = 0.5`` rad/m and
``a_lat = 2 pi`` m/s^2 as defaults: a stopped car cannot spin, a fast one cannot turn sharply.
Both constants are arguments because recorded traffic can exceed them (highway-env's roundabout
traffic corners at more than 2 pi m/s^2 in a quarter of its steps). Speed never goes below 0.

Integration is semi-implicit: the new speed and course move the car over the step::

    v[k+1]   = max(v[k] + a[k] dt, 0)
    yaw[k+1] = yaw[k] + w[k] dt
    p[k+1]   = p[k] + dt v[k+1] (cos yaw[k+1], sin yaw[k+1])

which is exactly consistent with courses measured from backward differences of logged positions
(``yaw[k+1]`` = the direction of ``p[k+1] - p[k]``), so rolling out a log's own actions retraces it.
"""

from __future__ import annotations

import math

import torch

from counterscene_env.geometry import wrap_angle

ACC_MIN = -10.0  # m/s^2
ACC_MAX = 8.0  # m/s^2


YAW_GAIN = 0.5  # rad/m: |yaw rate| <= YAW_GAIN * speed at low speed
LATERAL_LIMIT = 2 * math.pi  # m/s^2: |yaw rate| <= LATERAL_LIMIT / speed at high speed


def max_yaw_rate(
    speed: torch.Tensor, yaw_gain: float = YAW_GAIN, lateral_limit: float = LATERAL_LIMIT
) -> torch.Tensor:
    """Largest allowed |yaw rate| [rad/s] at ``speed`` [m/s] (any shape)."""
    v = speed.abs()
    return torch.clamp(torch.minimum(yaw_gain * v, lateral_limit / v.clamp(min=0.1)), min=0.1)


def unicycle_rollout(
    state: torch.Tensor,
    actions: torch.Tensor,
    dt: float = 0.1,
    bound: bool = True,
    yaw_gain: float = YAW_GAIN,
    lateral_limit: float = LATERAL_LIMIT,
) -> torch.Tensor:
    """Roll actions out from a start state.

    Args:
        state: ``[..., 4]`` start state (x [m], y [m], yaw [rad], speed [m/s]).
        actions: ``[..., T, 2]`` (acceleration [m/s^2], yaw rate [rad/s]) for steps 1..T.
        dt: step length [s].
        bound: clip actions to the bounds in the module docstring. The clip is a clamp, so
            gradients stop at the bound, which is what the guidance wants (it cannot push an
            agent beyond what a car can do).
        yaw_gain, lateral_limit: the yaw-rate bound's constants (module docstring).

    Returns:
        ``[..., T, 4]`` states after each step (the start state is not repeated).
    """
    x0, y0, yaw0, v0 = (c[..., None] for c in state.unbind(-1))
    acc, rate = actions.unbind(-1)  # [..., T]
    if bound:
        acc = acc.clamp(ACC_MIN, ACC_MAX)
    # The recursion in closed form, so the rollout is a few whole-tensor ops instead of a
    # loop over steps (it runs inside every guidance and steering gradient). The speed floor
    # v[k] = max(v[k-1] + a[k] dt, 0) is Lindley's recursion: with S[k] = v[0] + dt sum a[1..k],
    # v[k] = S[k] - min(0, S[1], ..., S[k]).
    s = v0 + torch.cumsum(acc * dt, -1)
    v = s - torch.cummin(s.clamp(max=0.0), -1).values
    if bound:  # the bound of step k is set by the speed entering it
        limit = max_yaw_rate(torch.cat([v0, v[..., :-1]], -1), yaw_gain, lateral_limit)
        rate = torch.maximum(torch.minimum(rate, limit), -limit)
    yaw = yaw0 + torch.cumsum(rate * dt, -1)
    x = x0 + torch.cumsum(dt * v * torch.cos(yaw), -1)
    y = y0 + torch.cumsum(dt * v * torch.sin(yaw), -1)
    return torch.stack([x, y, yaw, v], -1)


def actions_from_states(states: torch.Tensor, dt: float = 0.1) -> torch.Tensor:
    """Inverse of the speed/yaw part of the rollout: the actions between consecutive states.

    Args:
        states: ``[..., T + 1, 4]`` (x, y, yaw, speed) at steps 0..T, ``dt`` apart.

    Returns:
        ``[..., T, 2]`` (acceleration [m/s^2], yaw rate [rad/s]); yaw differences are wrapped
        to [-pi, pi) first, so a heading crossing +-pi gives a small rate, not a 2 pi jump.
    """
    dv = states[..., 1:, 3] - states[..., :-1, 3]
    dyaw = wrap_angle(states[..., 1:, 2] - states[..., :-1, 2])
    return torch.stack([dv / dt, dyaw / dt], -1)


def course_angles(
    positions: torch.Tensor,
    headings: torch.Tensor,
    speeds: torch.Tensor,
    valid: torch.Tensor,
    min_speed: float = 1.0,
    dt: float = 0.1,
) -> torch.Tensor:
    """Direction of motion [rad] at each frame, from backward differences of positions.

    Args:
        positions: ``[..., T, 2]`` m; headings ``[..., T]`` rad; speeds ``[..., T]`` m/s;
            valid ``[..., T]`` bool.
        min_speed: below this speed [m/s] (or over this much displacement per step), or where
            the previous frame is missing, the course is the heading: the direction of a
            near-zero displacement is noise.

    Returns:
        ``[..., T]`` courses: frame k's course is the direction of ``p[k] - p[k-1]``.
    """
    d = torch.diff(positions, dim=-2)
    course = torch.atan2(d[..., 1], d[..., 0])
    moving = (
        (speeds[..., 1:] >= min_speed)
        & (d.norm(dim=-1) >= min_speed * dt * 0.5)
        & valid[..., 1:]
        & valid[..., :-1]
    )
    course = torch.where(moving, course, headings[..., 1:])
    return torch.cat([headings[..., :1], course], dim=-1)
