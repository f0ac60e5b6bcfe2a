"""Map guidance: keep sampled trajectories on the lanes (paper hyper-parameter "map guidance").

The denoiser already sees the lanes (cross-attention); like the public CounterScene/CCDiff code we
also guide every agent's posterior mean toward the road while sampling. The loss is the squared
distance by which each predicted centre lies outside the nearest lane strip of the window's map
(``|p - segment| - width / 2``, hinged at 0), averaged over the horizon.

Only agents that are on a lane of the window at "now" are guided: the window holds the lanes
nearest the ego, so an agent far away may have no lane of its own in it, and pulling it toward
someone else's lane would be wrong.
"""

from __future__ import annotations

import torch

ON_LANE_TOLERANCE = 1.0  # m outside a lane strip at "now" that still counts as on a lane


def lane_excess(
    points: torch.Tensor, lanes: torch.Tensor, lanes_valid: torch.Tensor, widths: torch.Tensor
) -> torch.Tensor:
    """Distance [m] by which points lie outside every lane strip (0 inside one).

    Args:
        points: ``[N, A, T, 2]`` m (ego frame).
        lanes: ``[N, M, P, 2]`` lane centre points, m; ``lanes_valid [N, M]``; ``widths [N, M]`` m.

    Returns:
        ``[N, A, T]``; a large value (1e3 m) where a scene has no lanes at all.
    """
    a, b = lanes[:, :, :-1], lanes[:, :, 1:]  # [N, M, P-1, 2] segments
    N, M, S, _ = a.shape
    a, b = a.reshape(N, 1, 1, M * S, 2), b.reshape(N, 1, 1, M * S, 2)
    half = (widths / 2)[:, :, None].expand(N, M, S).reshape(N, 1, 1, M * S)
    ok = lanes_valid[:, :, None].expand(N, M, S).reshape(N, 1, 1, M * S)
    ab = b - a
    p = points[..., None, :]  # [N, A, T, 1, 2]
    u = (((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-9)).clamp(0, 1)
    dist = (p - (a + u[..., None] * ab)).norm(dim=-1)  # [N, A, T, M*S]
    excess = torch.where(ok, (dist - half).clamp(min=0), torch.full_like(dist, 1e3))
    return excess.min(dim=-1).values


def make_map_guidance(model, batch: dict[str, torch.Tensor], num_samples: int, step_size: float):
    """A ``guidance(mean, sigma, t, x0)`` hook that moves the posterior mean of on-lane agents
    down the gradient of the off-lane loss: ``mean - step_size * grad``, clipped to ``+-sigma``
    so guidance never moves a sample further than the noise of that step would; at the last
    step (``sigma = 0``) it does nothing.
    """
    lanes = batch["map"].repeat_interleave(num_samples, 0)
    lanes_ok = batch["map_valid"].repeat_interleave(num_samples, 0)
    widths = batch["map_widths"].repeat_interleave(num_samples, 0)
    state = model.current_state(batch).repeat_interleave(num_samples, 0)  # [N, K, 4]
    valid = model.agent_mask(batch).repeat_interleave(num_samples, 0)
    with torch.no_grad():
        now_excess = lane_excess(state[:, :, None, :2], lanes, lanes_ok, widths)[..., 0]
    guided = valid & (now_excess <= ON_LANE_TOLERANCE)  # [N, K]

    def hook(mean: torch.Tensor, sigma: float, t: int, x0: torch.Tensor) -> torch.Tensor:
        if sigma <= 0 or not guided.any():
            return mean
        with torch.enable_grad():
            x = mean.detach().requires_grad_(True)
            xy = model.rollout(x, state)[..., :2]
            loss = (lane_excess(xy, lanes, lanes_ok, widths) ** 2).mean(-1)  # [N, K]
            (grad,) = torch.autograd.grad((loss * guided).sum(), x)
        delta = (-step_size * grad).clamp(-sigma, sigma)
        return mean + torch.where(guided[..., None, None], delta, 0.0)

    return hook
