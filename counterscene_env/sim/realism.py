"""Realism cost of sampled plans: overlaps between agents and distance off their lanes.

The closed loop draws several samples per replan and keeps the one that best serves the
guidance; this cost is the other half of that choice, for everyone but the adversary: a sample
whose agents drive into each other, off the road or into the oncoming lane is a worse world,
whatever the guidance wants. Like the guidance loss it reads only the rolled-out positions of the samples, so it
chooses among the model's own futures and never edits one.

Shapes: N samples (scenes x samples), K window agents, F future steps.
"""

from __future__ import annotations

import numpy as np
import torch

from counterscene_env.geometry import boxes_overlap
from counterscene_env.world_model.map_guidance import ON_LANE_TOLERANCE, lane_excess

#: Steps of each plan whose off-lane distance counts (2 s). The overlaps read farther
#: (``steps``): a crossing must be seen while braking can still avoid it. The lanes need not:
#: a window's lanes are cropped about its centre, so far points of a plan may lie past the
#: crop of their own lane, and lane keeping holds the plans to the lanes anyway.
LANE_STEPS = 20


def plan_cost(
    trajectory: torch.Tensor,
    valid: torch.Tensor,
    extents: torch.Tensor,
    lanes: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    exclude: torch.Tensor | None = None,
    steps: int | None = None,
) -> torch.Tensor:
    """``[N]`` realism cost of sampled trajectories.

    Args:
        trajectory: ``[N, K, F, >=2]`` rolled-out states, x y first [m] (window frame).
        valid: ``[N, K]`` bool, real agents.
        extents: ``[N, K, 2]`` m (length, width).
        lanes: (points ``[N, M, P, 2]``, valid ``[N, M]``, widths ``[N, M]``) of the window map.
        exclude: ``[N, K]`` bool, agents the cost ignores (the ego, whose plan is never
            executed, and the adversary, which the guidance steers).
        steps: leading steps of each plan whose overlaps count (None: all F;
            ``SimConfig.realism_horizon``); the off-lane distance counts over the first
            ``min(steps, LANE_STEPS)``.

    Returns:
        Number of overlapping agent pairs summed over the steps, plus the mean squared
        off-lane distance [m^2] of agents that start on a lane (from the lanes going each
        one's way: ``lane_excess`` with the rollout's course).
    """
    xy = trajectory[:, :, :steps, :2]
    lane_steps = LANE_STEPS if steps is None else min(steps, LANE_STEPS)
    keep = valid if exclude is None else valid & ~exclude
    # Oriented boxes (heading = the rollout's course) of every pair at every step.
    pos = xy.detach().cpu().numpy().astype(np.float64)  # [N, K, T, 2]
    yaw = trajectory[:, :, :steps, 2].detach().cpu().numpy().astype(np.float64)
    ext = extents.detach().cpu().numpy().astype(np.float64)[:, :, None, :]  # [N, K, 1, 2]
    hit = boxes_overlap(
        pos[:, :, None], yaw[:, :, None], ext[:, :, None], pos[:, None], yaw[:, None], ext[:, None]
    )  # [N, K, K, T]
    ok = valid.cpu().numpy()
    kept = keep.cpu().numpy()
    # A pair counts when at least one of its agents is kept (the other may be the ego).
    pair = (kept[:, :, None] | kept[:, None, :]) & ok[:, :, None] & ok[:, None, :]
    pair = np.triu(np.ones(pair.shape[1:], bool), 1)[None] & pair
    overlaps = torch.from_numpy((hit & pair[..., None]).sum(axis=(1, 2, 3)).astype(np.float32))

    # Off the lanes going the agent's way: the oncoming lane is no lane to keep to.
    off = lane_excess(
        xy[:, :, :lane_steps], *lanes, headings=trajectory[:, :, :lane_steps, 2]
    )  # [N, K, T]
    # On a lane now, whichever its way (a car already in the oncoming lane is to go back).
    on_lane = lane_excess(xy[:, :, :1], *lanes)[..., 0] <= ON_LANE_TOLERANCE
    weight = (keep & on_lane).float()
    off_cost = ((off**2).mean(-1) * weight).sum(-1) / weight.sum(-1).clamp(min=1)
    return overlaps + off_cost
