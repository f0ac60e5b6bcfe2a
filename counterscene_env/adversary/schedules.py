"""The guidance's schedules and weights: how hard, when and on what the counterfactual
guidance pulls (paper appendix "Progressive Guidance Configuration", Algorithm 2 and
"Conflict-aware base weights"; docs/design.md, "Counterfactual guidance").

Plain functions of the denoising progress ``p`` in [0, 1] and of a mined conflict, used by
``adversary/guidance.py`` at every guided denoising step:

- :func:`stage_multiplier`, ``m(p)``: the progressive schedule (weak early, strong late);
- :func:`compressed_arrivals`: the arrival-time compression's target steps;
- :func:`base_weights`: ``(lambda_s, lambda_t, lambda_j)`` by conflict type;
- :func:`jerk`: the smoothness term's mean jerk magnitude.
"""

from __future__ import annotations

import torch

from counterscene_env.adversary.conflicts import (
    INTERSECTION,
    LEAD_BRAKING,
    REAR_APPROACH,
    Conflict,
)

__all__ = [
    "COMPRESSION_START",
    "base_weights",
    "compressed_arrivals",
    "jerk",
    "stage_multiplier",
]


def stage_multiplier(p: float) -> float:
    """m(p): 0.2 below 0.3, linear 0.2 -> 1.5 on [0.3, 0.7), linear 1.5 -> 3.0 on [0.7, 1]."""
    if p < 0.3:
        return 0.2
    if p < 0.7:
        return 0.2 + (p - 0.3) / 0.4 * (1.5 - 0.2)
    return 1.5 + (min(p, 1.0) - 0.7) / 0.3 * (3.0 - 1.5)


#: Progress from which arrival-time compression is active (appendix: p >= 0.5).
COMPRESSION_START = 0.5


def compressed_arrivals(tau_e: float, tau_a: float, p: float) -> tuple[float, float]:
    """Target arrival steps (tau_e^, tau_a^) after compression (appendix, Algorithm 2).

    For p < 0.5 the mined steps; from p = 0.5 the later agent's target moves to the earlier
    one's step plus ``|tau_e - tau_a| (1 - p)``, so the gap closes linearly to 0 at p = 1.
    The result is not rounded (the caller rounds and clips to its window).
    """
    if p < COMPRESSION_START:
        return float(tau_e), float(tau_a)
    gap = abs(tau_e - tau_a) * (1.0 - p)
    if tau_e <= tau_a:
        return float(tau_e), float(tau_e + gap)
    return float(tau_a + gap), float(tau_a)


def base_weights(conflict: Conflict, conflict_aware: bool = True) -> tuple[float, float, float]:
    """(lambda_s, lambda_t, lambda_j) of a conflict (appendix "Conflict-aware base weights")."""
    s = conflict.score
    if not conflict_aware:
        return max(1.5 * s, 0.3), max(1.0 * s, 0.2), 0.5
    if conflict.subtype == REAR_APPROACH:
        return max(1.5 * s, 0.3), max(1.0 * s, 0.2), 0.5
    if conflict.subtype == LEAD_BRAKING:
        return max(2.5 * s, 0.3), max(0.8 * s, 0.2), 0.8
    if conflict.type != INTERSECTION:
        raise ValueError(f"unknown conflict type {conflict.type!r}/{conflict.subtype!r}")
    return max(2.0 * s, 0.3), max(1.5 * s, 0.2), 0.3


def jerk(positions: torch.Tensor, dt: float) -> torch.Tensor:
    """Mean jerk magnitude [m/s^3] of ``[..., F, 2]`` m positions: third differences / dt^3."""
    j = torch.diff(positions, n=3, dim=-2) / dt**3
    # sqrt has an infinite gradient at 0: a straight constant-speed path has jerk exactly 0.
    return (j.pow(2).sum(-1) + 1e-12).sqrt().mean(-1)
