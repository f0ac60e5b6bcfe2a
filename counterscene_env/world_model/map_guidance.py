"""The off-lane distance, and keeping sampled trajectories on the lanes while sampling (paper
hyper-parameter "map guidance").

- ``lane_excess``: how far points lie outside every lane strip (where a car's course is given,
  every strip of a lane going its way; a lane going against it counts
  :data:`WRONG_WAY_PENALTY` m farther), the measure of the training loss's off-lane term, the
  realism cost, final-step lane keeping and the guidance's off-lane term.
- ``make_map_guidance``: like the public CounterScene/CCDiff code, a guidance hook that moves
  every on-lane agent's posterior mean down the gradient of its off-lane loss while sampling
  (``ModelConfig.map_guidance``, off by default: it costs more accuracy than it buys; measured
  in docs/world_model.md). Final-step lane keeping is ``lane_steering.py``.

The off-lane loss is the distance by which a predicted centre lies outside the nearest lane
strip of the window's map (``|p - segment| - width / 2``, hinged at 0; plus the wrong-way
penalty for a lane going against the car's course, where that is known). Only agents on a lane
of the window at "now" are guided or steered: a car parked on the verge, or one whose road the
window does not hold, must not be pulled onto someone else's lane.
"""

from __future__ import annotations

import torch

ON_LANE_TOLERANCE = 1.0  # m outside a lane strip at "now" that still counts as on a lane
#: A lane goes a car's way when its direction is less than 90 degrees from the car's course
#: (the cosine of the angle between them is above this).
SAME_WAY_COS = 0.0
#: m: how much farther than it is a lane going the other way counts, for a car whose course
#: is known (``lane_excess``'s ``headings``). The oncoming lane, 4 m over, is no lane to keep
#: to: a plan in it is off its lanes by the distance to its own. Where no lane goes its way
#: within this (a U-turn), the nearest lane still counts, this much farther
#: (docs/world_model_experiments.md, "Wrong-way driving").
WRONG_WAY_PENALTY = 10.0
NEAREST_PIECES = 8  # lane pieces per point that ``lane_excess`` measures before its check


def _segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance [m] of points ``p [..., 2]`` to segments ``a -> b [..., 2]`` (broadcast)."""
    return _segment_projection(p, a, b)[0]


def _segment_projection(
    p: torch.Tensor, a: torch.Tensor, b: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance [m] of points ``p [..., 2]`` to segments ``a -> b [..., 2]`` (broadcast), and
    where the point projects along the segment (``u``: 0 at ``a``, 1 at ``b``, unclamped)."""
    ab = b - a
    u = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-9)
    return (p - (a + u.clamp(0, 1)[..., None] * ab)).norm(dim=-1), u


def lane_excess(
    points: torch.Tensor,
    lanes: torch.Tensor,
    lanes_valid: torch.Tensor,
    widths: torch.Tensor,
    headings: torch.Tensor | None = None,
) -> torch.Tensor:
    """Distance [m] by which points lie outside every lane strip (0 inside one).

    Args:
        points: ``[N, A, T, 2]`` m (ego frame).
        lanes: ``[N, M, P, 2]`` lane centre points in driving direction, m; ``lanes_valid
            [N, M]``; ``widths [N, M]`` m.
        headings: ``[N, A, T]`` rad, the car's course at each point: a lane segment going
            the other way counts :data:`WRONG_WAY_PENALTY` m farther than it is (its way:
            :data:`SAME_WAY_COS`). None: every strip counts as it is (a parked car, the log's
            own positions).

    Returns:
        ``[N, A, T]``; a large value (1e3 m) where a scene has no lanes at all.

    Exactly the minimum over every segment of the map, values and gradients alike, for a
    fraction of the work: each point is measured against the segments of its
    :data:`NEAREST_PIECES` nearest lane pieces only, ranked by a lower bound (the distance to a
    piece's bounding box less its half-width; a segment lies inside its piece's box), and the
    few points for which a piece left out could still be nearer (its bound below the excess
    found) are measured against every segment (docs/performance.md).
    """
    N, M, P, _ = lanes.shape
    k = min(NEAREST_PIECES, M)
    if k == M:
        return _excess_all(points, lanes, lanes_valid, widths, headings)
    shape = points.shape[:-1]
    q = points.reshape(N, -1, 2)  # [N, Q, 2]
    half = widths / 2  # [N, M]
    with torch.no_grad():
        lo, hi = lanes.amin(2)[:, None], lanes.amax(2)[:, None]  # [N, 1, M, 2] piece boxes
        p = q.detach()[:, :, None]
        outside = torch.maximum(torch.maximum(lo - p, p - hi), torch.zeros(()))
        bound = (outside.norm(dim=-1) - half[:, None]).clamp(min=0)  # [N, Q, M]
        bound = torch.where(lanes_valid[:, None], bound, torch.inf)
        pick = bound.topk(k, dim=-1, largest=False).indices  # [N, Q, k]
        n = torch.arange(N, device=lanes.device)[:, None, None]
        seg = lanes[n, pick]  # [N, Q, k, P, 2]
        S = k * (P - 1)
        a = seg[..., :-1, :].reshape(*pick.shape[:2], S, 2)
        b = seg[..., 1:, :].reshape(*pick.shape[:2], S, 2)
        h = half[n, pick][..., None].expand(*pick.shape, P - 1).reshape(*pick.shape[:2], S)
        ok = lanes_valid[n, pick][..., None].expand(*pick.shape, P - 1).reshape(h.shape)
        # The bound stays a lower bound: the penalty only adds.
        extra = None if headings is None else wrong_way(b - a, headings.reshape(N, -1)[..., None])
    excess = _segment_excess(q, a, b, h, ok, extra).min(dim=-1).values  # [N, Q]
    with torch.no_grad():
        left_out = bound.scatter(-1, pick, torch.inf).amin(-1)
        unsure = (left_out < excess) | ~lanes_valid.any(-1, keepdim=True)
    if unsure.any():
        rows, cols = unsure.nonzero(as_tuple=True)
        way = None if headings is None else headings.reshape(N, -1)[rows, cols][:, None, None]
        full = _excess_all(
            q[rows, cols][:, None, None], lanes[rows], lanes_valid[rows], widths[rows], way
        )
        excess = excess.index_put((rows, cols), full[:, 0, 0])
    return excess.reshape(shape)


def wrong_way(d: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """``[...]`` m: :data:`WRONG_WAY_PENALTY` where a segment of direction ``d [..., 2]``
    goes against the course ``heading`` [rad] (broadcast), else 0."""
    same = d[..., 0] * torch.cos(heading) + d[..., 1] * torch.sin(heading) > SAME_WAY_COS
    return torch.where(same, 0.0, WRONG_WAY_PENALTY)


def _segment_excess(
    p: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    half: torch.Tensor,
    ok: torch.Tensor,
    extra: torch.Tensor | None = None,
) -> torch.Tensor:
    """``[..., S]`` excess [m] of points ``p [..., 2]`` over strips of half-width ``half`` round
    segments ``a -> b [..., S, 2]``, plus ``extra [..., S]`` m (1e3 where not ``ok``)."""
    dist = _segment_distance(p[..., None, :], a, b)
    gap = dist - half if extra is None else dist - half + extra
    return torch.where(ok, gap.clamp(min=0), torch.full_like(dist, 1e3))


def _excess_all(
    points: torch.Tensor,
    lanes: torch.Tensor,
    lanes_valid: torch.Tensor,
    widths: torch.Tensor,
    headings: torch.Tensor | None = None,
) -> torch.Tensor:
    """``lane_excess`` over every segment of the map (``[N, A, T, M (P - 1)]`` distances)."""
    a, b = lanes[:, :, :-1], lanes[:, :, 1:]  # [N, M, P-1, 2] segments
    N, M, S, _ = a.shape
    a, b = a.reshape(N, 1, 1, M * S, 2), b.reshape(N, 1, 1, M * S, 2)
    half = (widths / 2)[:, :, None].expand(N, M, S).reshape(N, 1, 1, M * S)
    ok = lanes_valid[:, :, None].expand(N, M, S).reshape(N, 1, 1, M * S)
    extra = None if headings is None else wrong_way(b - a, headings[..., None])
    return _segment_excess(points, a, b, half, ok, extra).min(dim=-1).values


# A predicted point counts against the training loss's off-lane term only where the log itself
# is within this of a window lane strip [m]: the term teaches the model to follow the lanes
# the log follows, never to pull a car parked on the verge (or outside the map) onto a lane.
OFF_LANE_LOG_TOLERANCE = 0.25


def off_lane_loss(
    model,
    batch: dict[str, torch.Tensor],
    pred: torch.Tensor,
    log: torch.Tensor,
    ok: torch.Tensor,
    course: torch.Tensor | None = None,
    log_course: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean off-lane distance [m] of ``pred [B, K, F, 2]`` where ``log [B, K, F, 2]`` is on
    a window lane, at the last step of each action token (``ok [B, K, F]``): the training
    loss's off-lane term (``loss.training_loss``). With the courses ``course [B, K, F]`` of
    the prediction and ``log_course [B, K, F]`` of the log (rad), both are measured against
    the lanes going their way, as lane keeping measures it (a lane going against a course
    counts :data:`WRONG_WAY_PENALTY` m farther): where the log itself drives against its
    lane (an overtake, a map error), the prediction is not pushed away from it. None:
    against every lane."""
    s = model.config.action_stride
    lanes = (batch["map"], batch["map_valid"], batch["map_widths"])
    pred, log, ok = pred[:, :, s - 1 :: s], log[:, :, s - 1 :: s], ok[:, :, s - 1 :: s]
    if course is not None:
        course = course[:, :, s - 1 :: s].detach()
    if log_course is not None:
        log_course = log_course[:, :, s - 1 :: s]
    with torch.no_grad():
        on_lane = lane_excess(log, *lanes, headings=log_course) <= OFF_LANE_LOG_TOLERANCE
        ok = ok & on_lane
    excess = lane_excess(pred, *lanes, headings=course)
    return (excess * ok).sum() / ok.float().sum().clamp(min=1)


def on_lane_agents(
    model, batch: dict[str, torch.Tensor], num_samples: int
) -> tuple[torch.Tensor, ...]:
    """The window's lanes and the agents' current states, repeated for ``num_samples`` samples
    per scene (``N = B * S`` rows), and ``guided [N, K]``: the real agents on a lane now."""
    lanes = batch["map"].repeat_interleave(num_samples, 0)  # [N, M, P, 2]
    lanes_ok = batch["map_valid"].repeat_interleave(num_samples, 0)
    widths = batch["map_widths"].repeat_interleave(num_samples, 0)
    state = model.current_state(batch).repeat_interleave(num_samples, 0)  # [N, K, 4]
    valid = model.agent_mask(batch).repeat_interleave(num_samples, 0)
    with torch.no_grad():
        now = lane_excess(state[:, :, None, :2], lanes, lanes_ok, widths)[..., 0]
    return lanes, lanes_ok, widths, state, valid & (now <= ON_LANE_TOLERANCE)


def make_map_guidance(model, batch: dict[str, torch.Tensor], num_samples: int, step_size: float):
    """A ``guidance(mean, sigma, t, x0)`` hook that moves the posterior mean of on-lane agents
    down the gradient of the off-lane loss: ``mean - step_size * grad``, clipped to ``+-sigma``
    so guidance never moves a sample further than the noise of that step would; at the last
    step (``sigma = 0``) it does nothing.
    """
    lanes, lanes_ok, widths, state, guided = on_lane_agents(model, batch, num_samples)

    def hook(mean: torch.Tensor, sigma: float, t: int, x0: torch.Tensor) -> torch.Tensor:
        if sigma <= 0 or not guided.any():
            return mean
        with torch.enable_grad():
            x = mean.detach().requires_grad_(True)
            traj = model.rollout(x, state)
            course = traj[..., 2].detach()  # against the lanes going each agent's way
            loss = (lane_excess(traj[..., :2], lanes, lanes_ok, widths, course) ** 2).mean(-1)
            (grad,) = torch.autograd.grad((loss * guided).sum(), x)
        delta = (-step_size * grad).clamp(-sigma, sigma)
        return mean + torch.where(guided[..., None, None], delta, 0.0)

    return hook
