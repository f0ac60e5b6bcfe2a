"""Checked future tracks: the one input record that conflict mining and the selectors read.

:func:`check_tracks` checks shapes and finiteness and derives velocities and speeds once;
:class:`Tracks` carries them (``adversary/conflicts.py`` documents what the arrays mean).
Plain numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Tracks",
    "check_eligible",
    "check_finite_where_valid",
    "check_index",
    "check_start_step",
    "check_tracks",
    "finite_difference_velocities",
    "mean_speed",
    "travel_direction",
]


@dataclass(frozen=True)
class Tracks:
    """Checked inputs. ``positions`` is zero (not NaN) at invalid steps, so nothing propagates."""

    positions: np.ndarray  # [N, T, 2] m
    valid: np.ndarray  # [N, T] bool
    velocities: np.ndarray  # [N, T, 2] m/s, finite difference, 0 where none / invalid
    speeds: np.ndarray  # [N, T] m/s, 0 at invalid steps
    ego: int
    dt: float


def check_index(value: object, n: int, name: str) -> int:
    """An agent row in ``[0, n)``, as a Python int."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer row index, got {value!r}")
    if not 0 <= int(value) < n:
        raise ValueError(f"{name} index {int(value)} out of range for {n} agents")
    return int(value)


def check_finite_where_valid(values: np.ndarray, valid: np.ndarray, name: str) -> None:
    """``values [N, T, ...]`` must be finite at every valid step; say where it is not."""
    bad = ~np.isfinite(values).reshape(*valid.shape, -1).all(-1) & valid
    if bad.any():
        agent, step = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{name} is not finite at a valid step (agent {agent}, step {step}; "
            f"{int(bad.sum())} such entries)"
        )


def finite_difference_velocities(positions: np.ndarray, valid: np.ndarray, dt: float) -> np.ndarray:
    """``[N, T, 2] m/s`` velocities by finite difference, as the paper's v_rel.

    Backward difference ``(p(t) - p(t-1)) / dt`` where steps t-1 and t are both valid (the
    paper's formula); else the forward difference ``(p(t+1) - p(t)) / dt`` (index 0, or after a
    gap); else 0 (an isolated valid step has no velocity). 0 at invalid steps.
    """
    n, t, _ = positions.shape
    if t < 2:
        return np.zeros_like(positions)
    diff = (positions[:, 1:] - positions[:, :-1]) / dt  # [N, T-1, 2]: step k -> k+1
    pair_ok = valid[:, 1:] & valid[:, :-1]  # [N, T-1]
    backward = np.zeros_like(positions)
    backward[:, 1:] = diff
    forward = np.zeros_like(positions)
    forward[:, :-1] = diff
    backward_ok = np.zeros((n, t), dtype=bool)
    backward_ok[:, 1:] = pair_ok
    forward_ok = np.zeros((n, t), dtype=bool)
    forward_ok[:, :-1] = pair_ok
    return np.where(backward_ok[..., None], backward, np.where(forward_ok[..., None], forward, 0.0))


def check_tracks(
    positions: np.ndarray,
    valid: np.ndarray,
    ego: int,
    *,
    speeds: np.ndarray | None,
    dt: float,
    min_joint_steps: int,
) -> Tracks:
    """Check shapes, finiteness and scalars; derive velocities and speeds."""
    positions = np.array(positions, dtype=np.float64)  # a copy: we overwrite invalid steps
    if positions.ndim != 3 or positions.shape[-1] != 2:
        raise ValueError(f"positions must be [N, T, 2], got shape {positions.shape}")
    n, t, _ = positions.shape
    if n == 0 or t == 0:
        raise ValueError(
            f"positions must have at least one agent and one step, got {positions.shape}"
        )
    valid = np.asarray(valid)
    if valid.shape != (n, t):
        raise ValueError(f"valid must be [N, T] = {(n, t)} like positions, got shape {valid.shape}")
    valid = valid.astype(bool)
    ego = check_index(ego, n, "ego")
    if not (isinstance(dt, (int, float, np.floating, np.integer)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
    dt = float(dt)
    if isinstance(min_joint_steps, bool) or not isinstance(min_joint_steps, (int, np.integer)):
        raise ValueError(f"min_joint_steps must be an integer, got {min_joint_steps!r}")
    if min_joint_steps < 1:
        raise ValueError(f"min_joint_steps must be >= 1, got {min_joint_steps}")
    check_finite_where_valid(positions, valid, "positions")
    positions[~valid] = 0.0
    velocities = finite_difference_velocities(positions, valid, dt)
    if speeds is None:
        speed = np.hypot(velocities[..., 0], velocities[..., 1])
    else:
        speed = np.array(speeds, dtype=np.float64)
        if speed.shape != (n, t):
            raise ValueError(f"speeds must be [N, T] = {(n, t)} like positions, got {speed.shape}")
        check_finite_where_valid(speed, valid, "speeds")
        speed[~valid] = 0.0
    return Tracks(positions, valid, velocities, speed, ego, dt)


def check_eligible(eligible: np.ndarray | None, n: int) -> np.ndarray:
    """``[N] bool``; all True when None."""
    if eligible is None:
        return np.ones(n, dtype=bool)
    eligible = np.asarray(eligible)
    if eligible.shape != (n,):
        raise ValueError(f"eligible must be [N] = ({n},), got shape {eligible.shape}")
    return eligible.astype(bool)


def check_start_step(start_step: int) -> int:
    if isinstance(start_step, bool) or not isinstance(start_step, (int, np.integer)):
        raise ValueError(f"start_step must be an integer step, got {start_step!r}")
    return int(start_step)


def travel_direction(positions: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``[2] m`` coarse travel direction: last valid position minus first valid position."""
    steps = np.flatnonzero(valid)
    if steps.size == 0:
        return np.zeros(2)
    return positions[steps[-1]] - positions[steps[0]]


def mean_speed(tracks: Tracks, agent: int) -> float:
    """m/s, mean over the agent's valid steps (0 if it has none)."""
    on = tracks.valid[agent]
    return float(tracks.speeds[agent, on].mean()) if on.any() else 0.0
