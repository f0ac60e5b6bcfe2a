"""Keeping sampled trajectories on the lanes (paper hyper-parameters "map guidance" and
"final-step guidance").

Two tools, both measured in docs/world_model.md:

- ``make_map_guidance``: like the public CounterScene/CCDiff code, a guidance hook that moves
  every on-lane agent's posterior mean down the gradient of its off-lane loss while sampling
  (``ModelConfig.map_guidance``, off by default: it costs more accuracy than it buys).
- ``steer_onto_lanes``: final-step lane keeping, a correction of the finished samples' yaw
  rates (``ModelConfig.lane_steering``, on in both presets).

The off-lane loss is the distance by which a predicted centre lies outside the nearest lane
strip of the window's map (``|p - segment| - width / 2``, hinged at 0). Only agents on a lane
of the window at "now" are guided or steered: a car parked on the verge, or one whose road the
window does not hold, must not be pulled onto someone else's lane.
"""

from __future__ import annotations

import torch

from counterscene_env.dynamics import max_yaw_rate

ON_LANE_TOLERANCE = 1.0  # m outside a lane strip at "now" that still counts as on a lane
LANE_MARGIN = 0.2  # m: steered points end at least this far inside a lane strip's edge
CANDIDATES = 6  # lane segments per predicted point that the steering may aim at
STEER_LR = 0.1  # Adam step on the normalised yaw-rate tokens
STEER_PRIOR = 0.01  # weight of the squared change of the tokens (normalised units)
ADAM_BETAS = (0.9, 0.999)  # the steering's Adam moments (torch.optim.Adam's defaults)
ADAM_EPS = 1e-8
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
    points: torch.Tensor, lanes: torch.Tensor, lanes_valid: torch.Tensor, widths: torch.Tensor
) -> torch.Tensor:
    """Distance [m] by which points lie outside every lane strip (0 inside one).

    Args:
        points: ``[N, A, T, 2]`` m (ego frame).
        lanes: ``[N, M, P, 2]`` lane centre points, m; ``lanes_valid [N, M]``; ``widths [N, M]`` m.

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
        return _excess_all(points, lanes, lanes_valid, widths)
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
    excess = _segment_excess(q, a, b, h, ok).min(dim=-1).values  # [N, Q]
    with torch.no_grad():
        left_out = bound.scatter(-1, pick, torch.inf).amin(-1)
        unsure = (left_out < excess) | ~lanes_valid.any(-1, keepdim=True)
    if unsure.any():
        rows, cols = unsure.nonzero(as_tuple=True)
        full = _excess_all(
            q[rows, cols][:, None, None], lanes[rows], lanes_valid[rows], widths[rows]
        )
        excess = excess.index_put((rows, cols), full[:, 0, 0])
    return excess.reshape(shape)


def _segment_excess(
    p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, half: torch.Tensor, ok: torch.Tensor
) -> torch.Tensor:
    """``[..., S]`` excess [m] of points ``p [..., 2]`` over strips of half-width ``half`` round
    segments ``a -> b [..., S, 2]`` (1e3 where not ``ok``)."""
    dist = _segment_distance(p[..., None, :], a, b)
    return torch.where(ok, (dist - half).clamp(min=0), torch.full_like(dist, 1e3))


def _excess_all(
    points: torch.Tensor, lanes: torch.Tensor, lanes_valid: torch.Tensor, widths: torch.Tensor
) -> torch.Tensor:
    """``lane_excess`` over every segment of the map (``[N, A, T, M (P - 1)]`` distances)."""
    a, b = lanes[:, :, :-1], lanes[:, :, 1:]  # [N, M, P-1, 2] segments
    N, M, S, _ = a.shape
    a, b = a.reshape(N, 1, 1, M * S, 2), b.reshape(N, 1, 1, M * S, 2)
    half = (widths / 2)[:, :, None].expand(N, M, S).reshape(N, 1, 1, M * S)
    ok = lanes_valid[:, :, None].expand(N, M, S).reshape(N, 1, 1, M * S)
    return _segment_excess(points, a, b, half, ok).min(dim=-1).values


# A predicted point counts against the training loss's off-lane term only where the log itself
# is within this of a window lane strip [m]: the term teaches the model to follow the lanes
# the log follows, never to pull a car parked on the verge (or outside the map) onto a lane.
OFF_LANE_LOG_TOLERANCE = 0.25


def off_lane_loss(
    model, batch: dict[str, torch.Tensor], pred: torch.Tensor, log: torch.Tensor, ok: torch.Tensor
) -> torch.Tensor:
    """Mean off-lane distance [m] of ``pred [B, K, F, 2]`` where ``log [B, K, F, 2]`` is on
    a window lane, at the last step of each action token (``ok [B, K, F]``): the training
    loss's off-lane term (``WorldModel.loss``)."""
    s = model.config.action_stride
    lanes = (batch["map"], batch["map_valid"], batch["map_widths"])
    pred, log, ok = pred[:, :, s - 1 :: s], log[:, :, s - 1 :: s], ok[:, :, s - 1 :: s]
    with torch.no_grad():
        ok = ok & (lane_excess(log, *lanes) <= OFF_LANE_LOG_TOLERANCE)
    excess = lane_excess(pred, *lanes)
    return (excess * ok).sum() / ok.float().sum().clamp(min=1)


def _on_lane_agents(model, batch: dict[str, torch.Tensor], num_samples: int):
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
    lanes, lanes_ok, widths, state, guided = _on_lane_agents(model, batch, num_samples)

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


def steer_onto_lanes(
    model, batch: dict[str, torch.Tensor], normalized: torch.Tensor, iterations: int
) -> torch.Tensor:
    """Final-step lane keeping: correct the *yaw-rate* tokens of finished samples so that every
    on-lane agent's rolled-out centre stays inside a lane strip of the window's map.

    This is the paper's final-step (map) guidance restricted to steering. ``iterations`` Adam
    steps (``STEER_LR``) minimise, per agent, the mean squared distance by which its centre
    lies outside the nearest candidate strip narrowed by ``LANE_MARGIN``, plus
    ``STEER_PRIOR`` x the squared change of its tokens. Acceleration is never touched: braking
    is the cheapest way to stay on a lane (a car that stops stays where it is), and it is not
    what an under-turning sample gets wrong. Each agent keeps the iterate of lowest cost. A
    point past a lane's end (beyond the first or last point of the lane piece nearest to it)
    is not off its lane: a real map is a crop, and the road goes on beyond it. The
    candidates are each point's ``CANDIDATES`` nearest segments before the correction, so one
    step costs ``K x F x CANDIDATES`` distances per sample instead of every segment of the map.

    Args:
        model: the ``WorldModel`` that sampled (its rollout and normalisation).
        batch: the scene windows, ``B`` of them.
        normalized: ``[B * S, K, Ta, 2]`` sampled action tokens, normalised (S samples per
            scene, scene-major as ``WorldModel.sample`` draws them).
        iterations: Adam steps; 0 returns ``normalized`` unchanged.

    Returns:
        ``[B * S, K, Ta, 2]``: the tokens with corrected yaw rates (agents off every lane at
        "now", padding and acceleration unchanged).
    """
    if iterations <= 0:
        return normalized
    S = normalized.shape[0] // batch["map"].shape[0]
    lanes, lanes_ok, widths, state, guided = _on_lane_agents(model, batch, S)
    if not guided.any() or not lanes_ok.any():
        return normalized
    N, M, P, _ = lanes.shape  # segments: [N, M * (P - 1)] ends, allowed half-widths, validity
    a, b = lanes[:, :, :-1].reshape(N, -1, 2), lanes[:, :, 1:].reshape(N, -1, 2)
    half = (widths[:, :, None] / 2 - LANE_MARGIN).expand(N, M, P - 1).reshape(N, -1)
    ok = lanes_ok[:, :, None].expand(N, M, P - 1).reshape(N, -1)
    rollout = _steering_rollout(model, normalized, state)
    with torch.no_grad():
        cands = _candidates(rollout(normalized), a, b, half, ok, P)
        # Only agents off their lanes now move: elsewhere the cost and its gradient are 0,
        # Adam's step is 0, and the tokens stay as they are. Steering those alone is the
        # same result for a fraction of the work (most agents keep to their lanes).
        active = guided & (_lane_cost(rollout(normalized), cands) > 0)
    if not active.any():
        return normalized
    rows = rollout.subset(active)
    tokens = normalized[active]  # [A, Ta, 2]
    cands = tuple(c[active] for c in cands)
    steer = torch.zeros_like(tokens)
    steer[..., 1] = 1.0  # only the yaw-rate channel moves
    delta = torch.zeros_like(tokens)
    # Adam (Kingma & Ba 2015), written out: torch.optim's first use imports torch._dynamo,
    # seconds per process, most of the first replan (docs/performance.md).
    m, v = torch.zeros_like(delta), torch.zeros_like(delta)
    # Adam on a hinge overshoots: once a plan is on the lane its gradient vanishes, and the
    # prior and the momentum carry it back off. So each agent keeps its best iterate.
    best = torch.zeros_like(tokens)
    best_cost = torch.full(tokens.shape[:1], torch.inf, device=tokens.device)
    for i in range(iterations + 1):
        with torch.enable_grad():
            x = delta.requires_grad_(True)
            change = x * steer
            cost = _lane_cost(rows(tokens + change), cands)
            cost = cost + STEER_PRIOR * (change**2).sum((-1, -2))  # [A]
            grad = torch.autograd.grad(cost.sum(), x)[0] if i < iterations else None
        delta = delta.detach()
        cost = cost.detach()
        better = cost < best_cost
        best = torch.where(better[..., None, None], delta, best)
        best_cost = torch.where(better, cost, best_cost)
        if grad is not None:
            # m_k = b1 m + (1 - b1) g, v_k = b2 v + (1 - b2) g^2, bias-corrected by 1 - b^k.
            m = ADAM_BETAS[0] * m + (1 - ADAM_BETAS[0]) * grad
            v = ADAM_BETAS[1] * v + (1 - ADAM_BETAS[1]) * grad**2
            m_hat = m / (1 - ADAM_BETAS[0] ** (i + 1))
            v_hat = v / (1 - ADAM_BETAS[1] ** (i + 1))
            delta = delta - STEER_LR * m_hat / (v_hat.sqrt() + ADAM_EPS)
    out = normalized.clone()
    out[active] = tokens + best * steer
    return out.detach()


def _lane_cost(p: torch.Tensor, cands: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``[...]`` mean squared distance [m^2] by which the centres ``p [..., F, 2]`` lie
    outside their nearest candidate strip (``_candidates``: ``[..., F, C]`` each); a point
    past a lane piece's end is not off its lane."""
    ca, cb, ch, cok, first, last = cands
    dist, u = _segment_projection(p[..., None, :], ca, cb)  # [..., F, C]
    gap = torch.where(cok, dist - ch, 1e3)
    nearest = gap.argmin(-1, keepdim=True)
    # A point is off its lane only beside a lane, not past a lane's end: a real map is a
    # crop, and beyond its last lane nothing is known (the road goes on). Without this, a
    # plan that runs past the end of the map is steered round in a circle toward the nearest
    # lane end (docs/world_model.md, "Real driving").
    beyond = ((u > 1) & last) | ((u < 0) & first)
    beyond = beyond.gather(-1, nearest)[..., 0]
    excess = gap.gather(-1, nearest)[..., 0].clamp(min=0)  # [..., F]
    return (torch.where(beyond, 0.0, excess) ** 2).mean(-1)


def _candidates(
    xy: torch.Tensor, a: torch.Tensor, b: torch.Tensor, half: torch.Tensor, ok: torch.Tensor, P: int
) -> tuple[torch.Tensor, ...]:
    """Each predicted point's ``CANDIDATES`` nearest lane sub-segments.

    Args:
        xy: ``[N, K, F, 2]`` predicted centres, m; ``a``, ``b``: ``[N, S, 2]`` sub-segment ends
            (``S = M (P - 1)``, lane piece by lane piece); ``half``: ``[N, S]`` allowed
            half-widths, m; ``ok``: ``[N, S]`` validity; ``P``: points per lane piece.

    Returns:
        ``[N, K, F, C, ...]``: the candidates' ends ``a``, ``b`` (``[..., 2]``), half-widths,
        validity, and whether each is the first or the last sub-segment of its lane piece.
    """
    # Chosen once: refreshing them as the points move bought little for its cost. They are
    # ranked by the distance to the segments' midpoints less their half-widths, one matrix
    # product (``torch.cdist``) instead of an exact point-to-segment distance to every segment
    # of the map, which dominated the steering's time (docs/performance.md); segments are
    # short (a lane piece over its points), so the nearest midpoints hold the nearest segments.
    N = xy.shape[0]
    mid = (a + b) / 2  # [N, S, 2]
    gap = torch.cdist(xy.flatten(1, 2), mid) - half[:, None]  # [N, K*F, S]
    gap = torch.where(ok[:, None], gap, torch.inf)
    idx = gap.topk(min(CANDIDATES, gap.shape[-1]), dim=-1, largest=False).indices
    scene = torch.arange(N, device=idx.device)[:, None, None]
    shape = (*xy.shape[:3], idx.shape[-1])  # [N, K, F, C]
    # Which sub-segment of its lane piece each candidate is: a point past the first or the
    # last one lies beyond the piece, not beside it.
    sub = (idx % (P - 1)).reshape(shape)
    return (
        a[scene, idx].reshape(*shape, 2),
        b[scene, idx].reshape(*shape, 2),
        half[scene, idx].reshape(shape),
        ok[scene, idx].reshape(shape),
        sub == 0,
        sub == P - 2,
    )


def _steering_rollout(model, normalized: torch.Tensor, state: torch.Tensor):
    """``tokens -> [N, K, F, 2]`` centres: ``model.rollout`` for tokens that differ from
    ``normalized [N, K, Ta, 2]`` in the yaw-rate channel only, without its step loop.

    The unicycle's speeds depend on the accelerations alone, so with those fixed the speeds,
    and with them the yaw-rate bounds, are known in advance; the courses and positions are
    then cumulative sums (the same update as ``dynamics.unicycle_rollout``:
    ``yaw_k = yaw_{k-1} + w_k dt``, ``x_k = x_{k-1} + v_k cos(yaw_k) dt``).
    """
    c = model.config
    with torch.no_grad():
        v = model.rollout(normalized, state)[..., 3]  # [N, K, F] speed after each step
        before = torch.cat([state[..., None, 3], v[..., :-1]], -1)  # speed entering step k
        limit = max_yaw_rate(before, c.yaw_gain, c.lateral_limit)
    return _YawRollout(model, v, limit, state[..., :3])


class _YawRollout:
    """``tokens [..., Ta, 2] -> [..., F, 2]`` centres for fixed speeds ``v [..., F]``, yaw-rate
    bounds ``limit [..., F]`` and start poses ``pose [..., 3]`` (x, y, yaw)."""

    def __init__(self, model, v: torch.Tensor, limit: torch.Tensor, pose: torch.Tensor) -> None:
        self.model, self.v, self.limit, self.pose = model, v, limit, pose

    def subset(self, rows: torch.Tensor) -> _YawRollout:
        """The rollout of the agents ``rows`` (a boolean mask over the leading axes)."""
        return _YawRollout(self.model, self.v[rows], self.limit[rows], self.pose[rows])

    def __call__(self, tokens: torch.Tensor) -> torch.Tensor:
        c = self.model.config
        rate = self.model.denormalize(tokens)[..., 1].repeat_interleave(c.action_stride, -1)
        rate = torch.maximum(torch.minimum(rate, self.limit), -self.limit)
        yaw = self.pose[..., 2, None] + c.dt * rate.cumsum(-1)
        x = self.pose[..., 0, None] + c.dt * (self.v * torch.cos(yaw)).cumsum(-1)
        y = self.pose[..., 1, None] + c.dt * (self.v * torch.sin(yaw)).cumsum(-1)
        return torch.stack([x, y], -1)
