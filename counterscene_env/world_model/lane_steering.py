"""Final-step lane keeping: the finished samples' yaw rates corrected so that every on-lane
agent stays inside a strip of a lane going its way (a lane going against its course counts
``map_guidance.WRONG_WAY_PENALTY`` m farther; docs/world_model_experiments.md, "Wrong-way
driving") of its window's map (``ModelConfig.lane_steering``, on in both
presets; paper hyper-parameter "final-step guidance", restricted to steering; measured in
docs/world_model.md).

The correction is a small optimisation per agent (``iterations`` Adam steps on the yaw-rate
tokens). Its cost and gradient are written out in closed form over numpy arrays: a few
thousand numbers per replan, where torch's per-operation overhead and its autograd engine
cost more than the arithmetic (docs/history/performance.md, "What changed in the fifth
fast-replans session").
"""

from __future__ import annotations

import numpy as np
import torch

from counterscene_env.dynamics import max_yaw_rate
from counterscene_env.world_model.map_guidance import on_lane_agents, wrong_way

LANE_MARGIN = 0.2  # m: steered points end at least this far inside a lane strip's edge
CANDIDATES = 6  # lane segments per predicted point that the steering may aim at
STEER_LR = 0.1  # Adam step on the normalised yaw-rate tokens
STEER_PRIOR = 0.01  # weight of the squared change of the tokens (normalised units)
ADAM_BETAS = (0.9, 0.999)  # the steering's Adam moments (torch.optim.Adam's defaults)
ADAM_EPS = 1e-8


def steer_onto_lanes(
    model,
    batch: dict[str, torch.Tensor],
    normalized: torch.Tensor,
    iterations: int,
    any_way: torch.Tensor | None = None,
) -> torch.Tensor:
    """Correct the *yaw-rate* tokens of finished samples so that every on-lane agent's
    rolled-out centre stays inside a strip of a lane of the window's map going its way.

    ``iterations`` Adam steps (``STEER_LR``) minimise, per agent, the mean squared distance
    by which its centre lies outside the nearest candidate strip narrowed by ``LANE_MARGIN``
    (a candidate going against the plan's course counted ``WRONG_WAY_PENALTY`` m farther),
    plus ``STEER_PRIOR`` x the squared change of its tokens (:class:`SteeringCost`).
    Acceleration is never touched: braking is the cheapest way to stay on a lane (a car that
    stops stays where it is), and it is not what an under-turning sample gets wrong. Each
    agent keeps the iterate of lowest cost. A point past a lane's end (beyond the first or
    last point of the lane piece nearest to it) is not off its lane: a real map is a crop,
    and the road goes on beyond it. The candidates are each point's ``CANDIDATES`` nearest
    segments before the correction, so one step costs ``K x F x CANDIDATES`` distances per
    sample instead of every segment of the map.

    Args:
        model: the ``WorldModel`` that sampled (its rollout and normalisation).
        batch: the scene windows, ``B`` of them.
        normalized: ``[B * S, K, Ta, 2]`` sampled action tokens, normalised (S samples per
            scene, scene-major as ``WorldModel.sample`` draws them).
        iterations: Adam steps; 0 returns ``normalized`` unchanged.
        any_way: ``[B, K]`` bool, agents kept on any lane strip, whichever its way (the
            closed loop's guided adversary, whose counterfactual may cross into the ego's
            lane); None: every agent keeps to the lanes going its way.

    Returns:
        ``[B * S, K, Ta, 2]``: the tokens with corrected yaw rates (agents off every lane at
        "now", padding and acceleration unchanged).
    """
    if iterations <= 0:
        return normalized
    S = normalized.shape[0] // batch["map"].shape[0]
    lanes, lanes_ok, widths, state, guided = on_lane_agents(model, batch, S)
    if not guided.any() or not lanes_ok.any():
        return normalized
    N, M, P, _ = lanes.shape  # segments: [N, M * (P - 1)] ends, allowed half-widths, validity
    a, b = lanes[:, :, :-1].reshape(N, -1, 2), lanes[:, :, 1:].reshape(N, -1, 2)
    half = (widths[:, :, None] / 2 - LANE_MARGIN).expand(N, M, P - 1).reshape(N, -1)
    ok = lanes_ok[:, :, None].expand(N, M, P - 1).reshape(N, -1)
    c = model.config
    with torch.no_grad():
        traj = model.rollout(normalized, state)  # [N, K, F, 4]
        free = None if any_way is None else any_way.to(torch.bool).repeat_interleave(S, 0)
        cands = _candidates(traj[..., :2], traj[..., 2], a, b, half, ok, P, free)
        v = traj[..., 3]  # [N, K, F] speed after each step
        entering = torch.cat([state[..., None, 3], v[..., :-1]], -1)  # speed entering step k
        limit = max_yaw_rate(entering, c.yaw_gain, c.lateral_limit)
    # The optimisation runs on the CPU in numpy ([N, K, ...] -> [N K, ...] rows).
    rows = lambda t: t.detach().flatten(0, 1).cpu().numpy()  # noqa: E731
    problem = SteeringCost(
        rows(v.double()),
        rows(limit.double()),
        rows(state[..., :3].double()),
        tuple(rows(x) for x in cands),
        float(model.action_std[1]),
        float(model.action_mean[1]),
        c.action_stride,
        c.dt,
    )
    tokens = rows(normalized[..., 1].double())  # [N K, Ta] yaw-rate tokens
    # Only agents off their lanes now move: elsewhere the cost and its gradient are 0, Adam's
    # step is 0, and the tokens stay as they are. Steering those alone is the same result for
    # a fraction of the work (most agents keep to their lanes).
    active = rows(guided) & (problem.lane_cost(tokens) > 0)
    if not active.any():
        return normalized
    best = _adam(problem.subset(active), tokens[active], iterations)
    out = normalized.clone()
    yaw = out[..., 1]  # a view of ``out``
    change = torch.from_numpy(best.astype(np.float32)).to(yaw.device)
    yaw[torch.from_numpy(active.reshape(yaw.shape[:2])).to(yaw.device)] += change
    return out.detach()


def _adam(problem: SteeringCost, tokens: np.ndarray, iterations: int) -> np.ndarray:
    """``[A, Ta]`` the change of the yaw-rate tokens ``[A, Ta]`` of lowest cost among
    ``iterations`` Adam steps (Kingma & Ba 2015) from no change."""
    delta = np.zeros_like(tokens)
    m, v = np.zeros_like(delta), np.zeros_like(delta)
    # Adam on a hinge overshoots: once a plan is on the lane its gradient vanishes, and the
    # prior and the momentum carry it back off. So each agent keeps its best iterate.
    best = np.zeros_like(tokens)
    best_cost = np.full(tokens.shape[0], np.inf)
    for i in range(iterations + 1):
        cost, grad = problem(tokens + delta, delta, gradient=i < iterations)
        better = cost < best_cost
        best[better], best_cost[better] = delta[better], cost[better]
        if grad is not None:
            # m_k = b1 m + (1 - b1) g, v_k = b2 v + (1 - b2) g^2, bias-corrected by 1 - b^k.
            m = ADAM_BETAS[0] * m + (1 - ADAM_BETAS[0]) * grad
            v = ADAM_BETAS[1] * v + (1 - ADAM_BETAS[1]) * grad**2
            m_hat = m / (1 - ADAM_BETAS[0] ** (i + 1))
            v_hat = v / (1 - ADAM_BETAS[1] ** (i + 1))
            delta = delta - STEER_LR * m_hat / (np.sqrt(v_hat) + ADAM_EPS)
    return best


class SteeringCost:
    """The lane-keeping cost of yaw-rate tokens and its gradient, for fixed speeds.

    The unicycle's speeds depend on the accelerations alone, so with those fixed the speeds,
    and with them the yaw-rate bounds, are known in advance; the courses and positions are
    cumulative sums (the update of ``dynamics.unicycle_rollout``: ``yaw_k = yaw_{k-1} + w_k
    dt``, ``x_k = x_{k-1} + v_k cos(yaw_k) dt``), and their gradients reversed cumulative
    sums.

    Args:
        v: ``[R, F]`` speed after each step, m/s; ``limit``: ``[R, F]`` yaw-rate bound of each
            step, rad/s; ``pose``: ``[R, 3]`` start x, y [m] and yaw [rad] (R agents).
        cands: ``_candidates``'s ``[R, F, C]`` candidate segments of each point.
        std, mean: the yaw-rate token's normalisation (rad/s per unit, rad/s).
        stride: steps per token; ``dt``: s per step.
    """

    def __init__(
        self,
        v: np.ndarray,
        limit: np.ndarray,
        pose: np.ndarray,
        cands: tuple[np.ndarray, ...],
        std: float,
        mean: float,
        stride: int,
        dt: float,
    ) -> None:
        self.v, self.limit, self.pose, self.cands = v, limit, pose, cands
        self.std, self.mean, self.stride, self.dt = std, mean, stride, dt
        ca, cb, ch, cok, first, last, extra = cands
        self._a = ca[..., 0], ca[..., 1]
        self._ab = cb[..., 0] - ca[..., 0], cb[..., 1] - ca[..., 1]
        self._ab2 = np.maximum(self._ab[0] ** 2 + self._ab[1] ** 2, 1e-9)
        # A lane going the other way: its strip counts as narrower by the wrong-way penalty.
        self._half, self._bad, self._first, self._last = ch - extra, ~cok, first, last

    def subset(self, rows: np.ndarray) -> SteeringCost:
        """The cost of the agents ``rows`` (a boolean mask over R)."""
        cands = tuple(c[rows] for c in self.cands)
        return SteeringCost(
            self.v[rows],
            self.limit[rows],
            self.pose[rows],
            cands,
            self.std,
            self.mean,
            self.stride,
            self.dt,
        )

    def centres(self, tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """x, y ``[R, F]`` centres [m] of yaw-rate tokens ``[R, Ta]``, and what the gradient
        needs."""
        rate = np.repeat(tokens * self.std + self.mean, self.stride, -1)  # [R, F] rad/s
        free = np.abs(rate) < self.limit  # where the bound does not hold the rate
        rate = np.clip(rate, -self.limit, self.limit)
        yaw = self.pose[:, 2, None] + self.dt * np.cumsum(rate, -1)
        cos, sin = np.cos(yaw), np.sin(yaw)
        x = self.pose[:, 0, None] + self.dt * np.cumsum(self.v * cos, -1)
        y = self.pose[:, 1, None] + self.dt * np.cumsum(self.v * sin, -1)
        return x, y, dict(free=free, cos=cos, sin=sin)

    def lane_cost(self, tokens: np.ndarray) -> np.ndarray:
        """``[R]`` mean squared distance [m^2] by which the centres of tokens ``[R, Ta]`` lie
        outside their nearest candidate strip (0 where no point is off its lane)."""
        return (self._excess(*self.centres(tokens)[:2])[0] ** 2).mean(-1)

    def _excess(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """``[R, F]`` distance [m] of points ``(x, y)`` outside their nearest candidate strip
        (0 past a lane piece's end), and ``[R, F]`` x and y of its gradient's direction."""
        rx, ry = x[..., None] - self._a[0], y[..., None] - self._a[1]  # [R, F, C]
        u = (rx * self._ab[0] + ry * self._ab[1]) / self._ab2
        along = np.clip(u, 0, 1)
        ox, oy = rx - along * self._ab[0], ry - along * self._ab[1]  # from the segment
        dist = np.sqrt(ox * ox + oy * oy)
        gap = dist - self._half
        gap[self._bad] = 1e3
        R, F = x.shape
        pick = (np.arange(R)[:, None], np.arange(F), gap.argmin(-1))  # the nearest strip
        # A point is off its lane only beside a lane, not past a lane's end: a real map is a
        # crop, and beyond its last lane nothing is known (the road goes on). Without this, a
        # plan that runs past the end of the map is steered round in a circle toward the
        # nearest lane end (docs/world_model.md, "Real driving").
        u = u[pick]
        beyond = ((u > 1) & self._last[pick]) | ((u < 0) & self._first[pick])
        excess = np.where(beyond, 0.0, np.maximum(gap[pick], 0.0))
        # d|p - q|/dp = (p - q) / |p - q| for q the segment's nearest point (q moves with p
        # along the segment, orthogonal to p - q).
        norm = np.maximum(dist[pick], 1e-12)
        return excess, ox[pick] / norm, oy[pick] / norm

    def __call__(
        self, tokens: np.ndarray, change: np.ndarray, gradient: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """``[R]`` cost of tokens ``[R, Ta]`` (``change [R, Ta]`` from the sampled ones, for the
        prior) and its ``[R, Ta]`` gradient (None unless ``gradient``)."""
        x, y, saved = self.centres(tokens)
        excess, away_x, away_y = self._excess(x, y)
        F = excess.shape[-1]
        cost = (excess**2).mean(-1) + STEER_PRIOR * (change**2).sum(-1)
        if not gradient:
            return cost, None
        g = (2 / F) * excess  # [R, F] d cost / d excess
        rev = lambda a: np.cumsum(a[:, ::-1], -1)[:, ::-1]  # noqa: E731
        g_x, g_y = self.dt * rev(g * away_x), self.dt * rev(g * away_y)  # d / d(v cos yaw)
        g_yaw = self.v * (g_y * saved["cos"] - g_x * saved["sin"])
        g_rate = np.where(saved["free"], self.dt * rev(g_yaw), 0.0)  # [R, F]
        g_tokens = self.std * g_rate.reshape(len(g_rate), -1, self.stride).sum(-1)
        return cost, g_tokens + 2 * STEER_PRIOR * change


def _candidates(
    xy: torch.Tensor,
    course: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    half: torch.Tensor,
    ok: torch.Tensor,
    P: int,
    any_way: torch.Tensor | None = None,
) -> tuple[torch.Tensor, ...]:
    """Each predicted point's ``CANDIDATES`` nearest lane sub-segments, a segment going the
    other way counted ``map_guidance.WRONG_WAY_PENALTY`` m farther (so a plan drifting into
    the oncoming lane is steered back to its own, not kept on the other's).

    Args:
        xy: ``[N, K, F, 2]`` predicted centres, m; ``course``: ``[N, K, F]`` rad, the plan's
            course there; ``a``, ``b``: ``[N, S, 2]`` sub-segment ends (``S = M (P - 1)``,
            lane piece by lane piece); ``half``: ``[N, S]`` allowed half-widths, m; ``ok``:
            ``[N, S]`` validity; ``P``: points per lane piece; ``any_way``: ``[N, K]`` bool,
            agents without the wrong-way penalty.

    Returns:
        ``[N, K, F, C, ...]``: the candidates' ends ``a``, ``b`` (``[..., 2]``), half-widths,
        validity, whether each is the first or the last sub-segment of its lane piece, and
        its wrong-way penalty, m.
    """
    # Chosen once: refreshing them as the points move bought little for its cost. They are
    # ranked by the distance to the segments' midpoints less their half-widths, one matrix
    # product (``torch.cdist``) instead of an exact point-to-segment distance to every segment
    # of the map, which dominated the steering's time (docs/performance.md); segments are
    # short (a lane piece over its points), so the nearest midpoints hold the nearest segments.
    N = xy.shape[0]
    mid = (a + b) / 2  # [N, S, 2]
    gap = torch.cdist(xy.flatten(1, 2), mid) - half[:, None]  # [N, K*F, S]
    # A lane going the other way counts WRONG_WAY_PENALTY m farther, here and in the cost.
    extra = wrong_way((b - a)[:, None], course.flatten(1, 2)[..., None])  # [N, K*F, S]
    if any_way is not None:
        free = any_way[:, :, None].expand(course.shape).flatten(1, 2)[..., None]  # [N, K*F, 1]
        extra = torch.where(free, 0.0, extra)
    gap = torch.where(ok[:, None], gap + extra, torch.inf)
    idx = gap.topk(min(CANDIDATES, gap.shape[-1]), dim=-1, largest=False).indices
    scene = torch.arange(N, device=idx.device)[:, None, None]
    shape = (*xy.shape[:3], idx.shape[-1])  # [N, K, F, C]
    # Which sub-segment of its lane piece each candidate is: a point past the first or the
    # last one lies beyond the piece, not beside it.
    sub = (idx % (P - 1)).reshape(shape)
    return (
        a[scene, idx].reshape(*shape, 2).double(),
        b[scene, idx].reshape(*shape, 2).double(),
        half[scene, idx].reshape(shape).double(),
        ok[scene, idx].reshape(shape),
        sub == 0,
        sub == P - 2,
        extra.gather(-1, idx).reshape(shape).double(),
    )
