"""The network's input features from a window batch: history tokens, per-agent features, lane
features and each agent's agent-centric map (``WorldModel.context`` encodes them).

Shapes: B windows, K agent slots, H history frames, M lane segments of P points. Positions and
lengths are scaled by the constants below so that features are of order one.
"""

from __future__ import annotations

import torch

POSITION_SCALE = 20.0  # m: input positions are divided by this
SPEED_SCALE = 10.0  # m/s
LENGTH_SCALE = 5.0  # m
WIDTH_SCALE = 2.0  # m
LANE_WIDTH_SCALE = 4.0  # m
PRIORITY_SCALE = 3.0  # the highest lane priority of highway-env's intersection


def history_features(
    batch: dict[str, torch.Tensor], valid: torch.Tensor, stride: int, history_steps: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """History tokens: "now" and every ``stride``-th frame before it, oldest first.

    Args:
        batch: ``history [B, K, H, 4]`` (x m, y m, yaw rad, speed m/s) and ``history_valid``.
        valid: ``[B, K]`` bool, the agents the window holds.

    Returns:
        ``[B, K, Th, 9]`` features (position, position relative to "now", heading, speed,
        validity, age) and their ``[B, K, Th]`` mask, ``Th`` the history tokens.
    """
    hist, hist_ok = batch["history"], batch["history_valid"]
    idx = torch.arange(hist.shape[-2] - 1, -1, -stride).flip(0)
    hist, hist_ok = hist[..., idx, :], hist_ok[..., idx]
    hist_ok = hist_ok & valid[..., None]
    now = hist[..., -1, :]
    x, y, yaw, v = hist.unbind(-1)
    age = (idx - idx[-1]).to(hist.dtype) / max(history_steps - 1, 1)
    hfeat = torch.stack(
        [
            x / POSITION_SCALE,
            y / POSITION_SCALE,
            (x - now[..., None, 0]) / POSITION_SCALE,
            (y - now[..., None, 1]) / POSITION_SCALE,
            torch.cos(yaw),
            torch.sin(yaw),
            v / SPEED_SCALE,
            hist_ok.to(hist.dtype),
            age.expand_as(x),
        ],
        -1,
    )
    return torch.where(hist_ok[..., None], hfeat, 0.0), hist_ok


def agent_features(
    now: torch.Tensor, course: torch.Tensor, extents: torch.Tensor, valid: torch.Tensor
) -> torch.Tensor:
    """``[B, K, 9]`` per-agent features: position, heading, course and speed "now" (``now
    [B, K, 4]``, ``course [B, K]`` rad) and the box size (``extents [B, K, 2]`` m); zero for
    slots not ``valid``."""
    afeat = torch.stack(
        [
            now[..., 0] / POSITION_SCALE,
            now[..., 1] / POSITION_SCALE,
            torch.cos(now[..., 2]),
            torch.sin(now[..., 2]),
            torch.cos(course),
            torch.sin(course),
            now[..., 3] / SPEED_SCALE,
            extents[..., 0] / LENGTH_SCALE,
            extents[..., 1] / WIDTH_SCALE,
        ],
        -1,
    )
    return torch.where(valid[..., None], afeat, 0.0)


def lane_features(
    batch: dict[str, torch.Tensor], priority: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lane features from ``map [B, M, P, 2]`` m, ``map_valid`` and ``map_widths [B, M]`` m
    (and ``map_priority [B, M]`` with ``priority``).

    Returns:
        ``[B, M, P, C]`` features (points, unit tangents, width; with ``priority`` a sixth,
        the lane's right of way / 3), the ``[B, M]`` mask, and the tangents ``[B, M, P, 2]``
        and the per-point extras ``[B, M, P, C - 4]`` (width, priority; for
        :func:`local_map`).
    """
    lanes, lanes_ok = batch["map"], batch["map_valid"]
    direction = torch.diff(lanes, dim=-2, append=lanes[..., -1:, :] * 2 - lanes[..., -2:-1, :])
    direction = direction / direction.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    per_lane = [batch["map_widths"] / LANE_WIDTH_SCALE]
    if priority:
        per_lane.append(batch["map_priority"].to(lanes.dtype) / PRIORITY_SCALE)
    extras = torch.stack(per_lane, -1)[..., None, :].expand(*lanes.shape[:-1], len(per_lane))
    lfeat = torch.cat([lanes / POSITION_SCALE, direction, extras], -1)
    return torch.where(lanes_ok[..., None, None], lfeat, 0.0), lanes_ok, direction, extras


def local_map(
    lanes: torch.Tensor,
    direction: torch.Tensor,
    extras: torch.Tensor,
    lanes_ok: torch.Tensor,
    position: torch.Tensor,
    course: torch.Tensor,
    valid: torch.Tensor,
    local_lanes: int,
    local_radius: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each agent's agent-centric map: its ``Ml = min(local_lanes, M)`` nearest lane
    segments in its own frame (origin at its position, x along its course).

    Args:
        lanes: ``[B, M, P, 2]`` lane points [m] (ego frame).
        direction: ``[B, M, P, 2]`` unit tangents.
        extras: ``[B, M, P, C]`` per-point features that do not depend on the frame
            (``lane_features``: the width / 4 m, and the right of way where the model reads it).
        lanes_ok: ``[B, M]`` bool.
        position: ``[B, K, 2]`` agents at "now" [m]; ``course``: ``[B, K]`` rad.
        valid: ``[B, K]`` bool.
        local_lanes, local_radius: lanes per agent, and how near [m] a lane must be.

    Returns:
        ``[B, K, Ml, P, 4 + C]`` features (x, y [/20 m], tangent, the extras) and the
        ``[B, K, Ml]`` mask: a real lane within ``local_radius`` of a valid agent.
    """
    B, K = position.shape[:2]
    gap = (lanes[:, None] - position[:, :, None, None, :]).norm(dim=-1).amin(-1)  # [B, K, M]
    gap = torch.where(lanes_ok[:, None, :], gap, torch.inf)
    Ml = min(local_lanes, gap.shape[-1])
    near, idx = gap.topk(Ml, dim=-1, largest=False)  # [B, K, Ml]

    def pick(t: torch.Tensor) -> torch.Tensor:  # [B, M, P, C] -> [B, K, Ml, P, C]
        flat = idx.reshape(B, -1)[..., None, None].expand(-1, -1, *t.shape[2:])
        return t.gather(1, flat).reshape(B, K, Ml, *t.shape[2:])

    cos, sin = torch.cos(course)[..., None, None], torch.sin(course)[..., None, None]

    def rotate(v: torch.Tensor) -> torch.Tensor:  # world -> agent frame, [B, K, Ml, P, 2]
        x, y = v.unbind(-1)
        return torch.stack([cos * x + sin * y, -sin * x + cos * y], -1)

    rel = rotate(pick(lanes) - position[:, :, None, None, :])
    feat = torch.cat([rel / POSITION_SCALE, rotate(pick(direction)), pick(extras)], -1)
    ok = (near <= local_radius) & valid[..., None]
    return torch.where(ok[..., None, None], feat, 0.0), ok


CONTACT_SCALE = 5.0  # m: the distance over which the pair feature exp(-d / 5 m) fades


def plan_features(plan: torch.Tensor, valid: torch.Tensor, given: torch.Tensor) -> torch.Tensor:
    """Where each agent's plan takes it (``ModelConfig.plan_features``).

    Args:
        plan: ``[B, K, Ta, 4]`` a plan's rollout at each action token's last step: x [m],
            y [m], course [rad], speed [m/s] (window frame).
        valid: ``[B, K]`` bool.
        given: ``[B]`` bool, windows whose plan is a real one (self-conditioning's first
            step and half of its training windows have none: their ``plan`` is the
            rollout of zero actions, and this flag tells the network so).

    Returns:
        ``[B, K, Ta, 6]``: position [/20 m], course (cos, sin), speed [/10 m/s], the flag;
        zero for slots not ``valid``.
    """
    x, y, course, v = plan.unbind(-1)
    flag = given.to(plan.dtype)[:, None, None].expand_as(x)
    feat = torch.stack(
        [
            x / POSITION_SCALE,
            y / POSITION_SCALE,
            torch.cos(course),
            torch.sin(course),
            v / SPEED_SCALE,
            flag,
        ],
        -1,
    )
    return torch.where(valid[..., None, None], feat, 0.0)


def pair_features(plan: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Each pair of agents' rolled-out plans at every future token, for the social bias.

    Args:
        plan: ``[B, K, Ta, 4]`` as in :func:`plan_features`.
        valid: ``[B, K]`` bool.

    Returns:
        ``[B, Ta, K, K, 4]``: for query agent i and key agent j, j's position in i's frame
        (origin at i's planned position, x along i's planned course) [/20 m], their distance
        [/20 m] and ``exp(-d / 5 m)``; zero unless both are ``valid``. Two cars about to
        share a place are near 0 in the first three and near 1 in the last.
    """
    p = plan.transpose(1, 2)  # [B, Ta, K, 4]
    rel = p[:, :, None, :, :2] - p[:, :, :, None, :2]  # [B, Ta, K(i), K(j), 2]: j - i
    cos = torch.cos(p[..., 2])[..., None]
    sin = torch.sin(p[..., 2])[..., None]
    ahead = cos * rel[..., 0] + sin * rel[..., 1]
    aside = -sin * rel[..., 0] + cos * rel[..., 1]
    d = rel.norm(dim=-1)
    feat = torch.stack(
        [
            ahead / POSITION_SCALE,
            aside / POSITION_SCALE,
            d / POSITION_SCALE,
            torch.exp(-d / CONTACT_SCALE),
        ],
        -1,
    )
    both = (valid[:, :, None] & valid[:, None, :])[:, None, :, :, None]
    return torch.where(both, feat, 0.0)
