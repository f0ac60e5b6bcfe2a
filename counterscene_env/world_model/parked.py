"""Parked cars added to training windows (``counterscene train --parked-cars SHARE``).

Why (docs/world_model.md, "Why the first models lost to constant velocity on real logs"): the
generated traffic and the NGSIM recordings have almost no parked car, so every stopped vehicle
the model ever saw was queued traffic, which the cars behind it brake for, and which moves
off again. On nuScenes half the vehicles are parked at the kerb: the shipped model brakes the
moving cars near them, and release 4 (the shipped model then) started 5.3 % of those off every
lane where the log starts 1.2 % (26 Nov 2026, fourth sitting; docs/history/world_model.md,
"Real driving (releases 4 and 5)").

A share of the training windows gets 1 to :data:`MAX_CARS` parked cars in free agent slots:
a car-sized box beside a lane of the window (its centre :data:`KERB_OFFSET` m outside the lane
strip), aligned with the lane, standing still over the whole window, and :data:`MARGIN` m clear
of every logged box of the window's agents at every step, so that the traffic may pass right
beside it, as it passes a row of parked cars on a street. The other agents' logged
futures stay as they are, so the model learns both that a parked car stays and that the
traffic beside it does not brake for it. The draws come from a generator the caller seeds per
training step, so a resumed run adds the same cars.
"""

from __future__ import annotations

import torch

from counterscene_env.world_model.map_guidance import lane_excess

#: Parked cars added to one window, at most.
MAX_CARS = 3
#: How far the parked car's centre lies outside the lane strip it stands beside [m]:
#: kerbside parking, from a car half on the strip to one on the verge.
KERB_OFFSET = (0.3, 1.5)
#: Its gap to every logged box of the window's agents and to the other parked cars, at
#: least [m] (each box bounded by its rectangle in the parked car's frame).
MARGIN = 0.3
#: Its box, length and width ranges [m].
LENGTH = (4.2, 5.0)
WIDTH = (1.75, 2.0)
#: Parked cars stand within this distance of the window's centre [m] (the window's agent
#: radius at the default preset).
RADIUS = 50.0
#: Placements tried per car before giving up on it.
TRIES = 8


def _uniform(lo_hi: tuple[float, float], g: torch.Generator) -> float:
    lo, hi = lo_hi
    return lo + (hi - lo) * float(torch.rand((), generator=g))


def _clear(at: torch.Tensor, yaw: float, size: torch.Tensor, boxes: torch.Tensor) -> bool:
    """Whether a box at ``at [2]`` m, ``yaw`` rad, ``size [2]`` m (length, width) keeps
    :data:`MARGIN` from every box of ``boxes [n, 5]`` (x, y, yaw, length, width): each of them
    bounded by its rectangle along the first box's axes (exact for boxes aligned with it, a
    little wider for others)."""
    if len(boxes) == 0:
        return True
    c, s = torch.cos(torch.tensor(yaw)), torch.sin(torch.tensor(yaw))
    d = boxes[:, :2] - at
    along, across = (d[:, 0] * c + d[:, 1] * s).abs(), (-d[:, 0] * s + d[:, 1] * c).abs()
    rel = boxes[:, 2] - yaw
    co, so = torch.cos(rel).abs(), torch.sin(rel).abs()
    half_along = (co * boxes[:, 3] + so * boxes[:, 4]) / 2
    half_across = (so * boxes[:, 3] + co * boxes[:, 4]) / 2
    hit = (along < size[0] / 2 + half_along + MARGIN) & (
        across < size[1] / 2 + half_across + MARGIN
    )
    return not bool(hit.any())


def _place(
    batch: dict[str, torch.Tensor],
    b: int,
    size: torch.Tensor,
    taken: torch.Tensor,
    g: torch.Generator,
) -> tuple[torch.Tensor, float] | None:
    """A kerbside pose ``([2] m, yaw rad)`` in window ``b``'s frame for a box of ``size [2]``
    m clear of ``taken [n, 5]`` (x, y, yaw, length, width), or None."""
    lanes, ok, widths = batch["map"][b], batch["map_valid"][b], batch["map_widths"][b]
    segs = ok.nonzero().flatten()
    if len(segs) == 0:
        return None
    for _ in range(TRIES):
        m = int(segs[torch.randint(len(segs), (), generator=g)])
        pts = lanes[m]  # [P, 2]
        i = int(torch.randint(pts.shape[0] - 1, (), generator=g))
        a, c = pts[i], pts[i + 1]
        d = c - a
        if float(d.norm()) < 1e-3:
            continue
        u = d / d.norm()
        side = 1.0 if float(torch.rand((), generator=g)) < 0.5 else -1.0
        offset = float(widths[m]) / 2 + _uniform(KERB_OFFSET, g)
        at = a + float(torch.rand((), generator=g)) * d + side * offset * torch.stack([-u[1], u[0]])
        if float(at.norm()) > RADIUS:
            continue
        # Outside every lane strip of the window (not on the next lane over).
        excess = lane_excess(at[None, None, None], lanes[None], ok[None], widths[None])
        if float(excess) < KERB_OFFSET[0] - 1e-6:
            continue
        yaw = float(torch.atan2(u[1], u[0]))
        if not _clear(at, yaw, size, taken):
            continue
        return at, yaw
    return None


def add_parked_cars(
    batch: dict[str, torch.Tensor], share: float, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """A copy of a training ``batch`` (``world_model/window.py`` keys, window frame) in which
    about ``share`` of the windows hold 1 to :data:`MAX_CARS` parked cars in free agent slots
    (module docstring). Windows without a free slot, a lane or a clear place stay as they are.
    """
    if share <= 0:
        return batch
    out = {k: v.clone() for k, v in batch.items()}
    hist, fut = out["history"], out["future"]
    B = out["agent_valid"].shape[0]
    for b in range(B):
        if float(torch.rand((), generator=generator)) >= share:
            continue
        free = (~out["agent_valid"][b]).nonzero().flatten().tolist()
        n = min(len(free), 1 + int(torch.randint(MAX_CARS, (), generator=generator)))
        states = torch.cat([hist[b], fut[b]], 1)  # [K, H + F, 4]
        valid = torch.cat([out["history_valid"][b], out["future_valid"][b]], 1)
        sizes = out["extents"][b][:, None].expand(-1, states.shape[1], 2)
        logged = torch.cat([states[..., :3], sizes], -1)[valid]  # [n, 5] x, y, yaw, l, w
        for k in free[:n]:
            size = torch.tensor(
                [_uniform(LENGTH, generator), _uniform(WIDTH, generator)],
                dtype=hist.dtype,
                device=hist.device,
            )
            pose = _place(out, b, size, logged, generator)
            if pose is None:
                break
            at, yaw = pose
            state = torch.tensor(
                [float(at[0]), float(at[1]), yaw, 0.0], dtype=hist.dtype, device=hist.device
            )
            hist[b, k] = state
            fut[b, k] = state
            out["history_valid"][b, k] = True
            out["future_valid"][b, k] = True
            out["agent_valid"][b, k] = True
            out["extents"][b, k] = size
            logged = torch.cat([logged, torch.cat([state[:3], size])[None]])
    return out
