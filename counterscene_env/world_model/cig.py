"""Causal Interaction Graph edge features (paper eq. "e_ij"; docs/design.md,
"Denoiser and Causal Interaction Graph").

For every ordered pair (i, j) of agents, from their current positions and velocities projected
at constant velocity over the horizon, six scores in [0, 1] (1 = most interaction):

=====  ==============================================================================
index  feature
=====  ==============================================================================
0      dp:    closeness now, ``1 - min(|p_j - p_i|, 20 m) / 20 m``
1      dv:    relative speed, ``min(|v_j - v_i|, 20 m/s) / 20 m/s``
2      TTC:   ``1 - TTC / 5.2 s`` where TTC is the first time the two centres come within
              ``COLLISION_RADIUS`` under constant velocity (0 when they never do in the horizon)
3      TTI:   ``1 - TTI / 5.2 s`` where TTI is the time agent i needs to reach the crossing point
              of the two straight paths (0 when the paths do not cross ahead of both within the
              horizon, e.g. parallel lanes); the one directed feature
4      d_int: closest approach over the horizon, ``1 - min(d_min, 20 m) / 20 m``
5      v_int: closing speed now, ``max(0, -dp . dv / |dp|)`` capped at 20 m/s, divided by 20
=====  ==============================================================================

Computed once per sampling call (the features do not depend on the diffusion step). Rows and
columns of invalid agents are zero; the diagonal is zero.
"""

from __future__ import annotations

import torch

HORIZON = 5.2  # s, the paper's prediction horizon; cap for TTC and TTI
DIST_CAP = 20.0  # m
SPEED_CAP = 20.0  # m/s
COLLISION_RADIUS = 3.0  # m between centres: two car half-lengths, roughly
NUM_EDGE_FEATURES = 6


def edge_features(
    positions: torch.Tensor,
    velocities: torch.Tensor,
    valid: torch.Tensor,
    horizon: float = HORIZON,
) -> torch.Tensor:
    """Edge features of every ordered agent pair.

    Args:
        positions: ``[..., K, 2]`` current positions [m].
        velocities: ``[..., K, 2]`` current velocity vectors [m/s].
        valid: ``[..., K]`` bool.
        horizon: projection horizon [s].

    Returns:
        ``[..., K, K, 6]`` scores in [0, 1]; entry ``[..., i, j, :]`` is the edge i -> j.
    """
    dp = positions[..., None, :, :] - positions[..., :, None, :]  # p_j - p_i  [..., K, K, 2]
    dv = velocities[..., None, :, :] - velocities[..., :, None, :]
    dist = dp.norm(dim=-1)
    rel_speed = dv.norm(dim=-1)
    dv2 = (dv * dv).sum(-1)
    dpdv = (dp * dv).sum(-1)

    # Closest approach of the relative motion dp + dv t over t in [0, horizon].
    t_star = torch.where(dv2 > 1e-9, -dpdv / dv2.clamp(min=1e-9), torch.zeros_like(dv2))
    t_star = t_star.clamp(0.0, horizon)
    d_min = (dp + dv * t_star[..., None]).norm(dim=-1)

    # TTC: first root of |dp + dv t| = R, i.e. dv2 t^2 + 2 dpdv t + (dist^2 - R^2) = 0.
    c = dist**2 - COLLISION_RADIUS**2
    disc = dpdv**2 - dv2 * c
    root = (-dpdv - disc.clamp(min=0).sqrt()) / dv2.clamp(min=1e-9)
    ttc = torch.where(c <= 0, torch.zeros_like(c), root)
    hits = (c <= 0) | ((disc >= 0) & (dv2 > 1e-9) & (root >= 0) & (root <= horizon))
    ttc_score = torch.where(hits, 1 - ttc.clamp(0, horizon) / horizon, torch.zeros_like(c))

    # TTI: solve p_i + v_i t = p_j + v_j s for (t, s) by Cramer's rule on [v_i, -v_j].
    vi = velocities[..., :, None, :].expand_as(dp)
    vj = velocities[..., None, :, :].expand_as(dp)
    det = -vi[..., 0] * vj[..., 1] + vi[..., 1] * vj[..., 0]
    ok = det.abs() > 1e-6
    safe = torch.where(ok, det, torch.ones_like(det))
    t_i = (-dp[..., 0] * vj[..., 1] + dp[..., 1] * vj[..., 0]) / safe
    t_j = (vi[..., 0] * dp[..., 1] - vi[..., 1] * dp[..., 0]) / safe
    crosses = ok & (t_i >= 0) & (t_j >= 0) & (t_i <= horizon) & (t_j <= horizon)
    tti_score = torch.where(crosses, 1 - t_i / horizon, torch.zeros_like(t_i))

    closing = (-dpdv / dist.clamp(min=1e-6)).clamp(min=0)
    feats = torch.stack(
        [
            1 - dist.clamp(max=DIST_CAP) / DIST_CAP,
            rel_speed.clamp(max=SPEED_CAP) / SPEED_CAP,
            ttc_score,
            tti_score,
            1 - d_min.clamp(max=DIST_CAP) / DIST_CAP,
            closing.clamp(max=SPEED_CAP) / SPEED_CAP,
        ],
        -1,
    )
    K = positions.shape[-2]
    pair = valid[..., :, None] & valid[..., None, :]
    pair = pair & ~torch.eye(K, dtype=torch.bool, device=positions.device)
    return torch.where(pair[..., None], feats, torch.zeros_like(feats))
