"""Who passes first where two logged paths cross: the log, the lanes' right of way and the
model's samples (docs/world_model_experiments.md, "The network's crossing collisions").

For every window (one every second) and every pair of vehicles whose logged paths cross
within the horizon (closest approach under 2 m, at 30-150 degrees, on lanes of different
priority), the crossing point is where the two logged paths meet. The log passes it in some
order; highway-env's intersection rule says the car on the lane of higher priority goes first.
Each sample is scored on the same point: which car reaches it (within 2 m) first, and whether
both do within 1 s of each other (a near miss the log never has). A pair is a *tie* when, at
their speeds now along their logged paths, both would reach the point within 1 s of each
other: the log settled who goes first, by the right of way, before the window began.

    python tools/crossing_order.py data/dev-intersection [--model DIR] [--scenes 150]
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import torch

from counterscene_env.scene.sources import stored_scenes
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.eval_windows import window_batches, window_jobs

MEET = 2.0  # m: two paths cross where they come this close; a sample reaches the point so near
TIE = 1.0  # s: arrivals this close are a tie (at today's speeds) or a near miss (in a sample)
NEVER = 10**6


def first_reach(path: np.ndarray, point: np.ndarray) -> int:
    """First step at which ``path [F, 2]`` m comes within MEET of ``point``, else NEVER."""
    hit = np.flatnonzero(np.linalg.norm(path - point, axis=-1) < MEET)
    return int(hit[0]) if hit.size else NEVER


def crossing(pa, pb, oka, okb):
    """``(i, j, point)``: the steps at which two logged paths ``[F, 2]`` pass their closest
    approach and its midpoint, if they cross (under MEET, at 30-150 degrees), else None."""
    d = np.linalg.norm(pa[:, None] - pb[None], axis=-1)
    d[~oka] = np.inf
    d[:, ~okb] = np.inf
    i, j = np.unravel_index(np.argmin(d), d.shape)
    last = len(pa) - 1
    if d[i, j] > MEET or i == 0 or j == 0 or i == last or j == last:
        return None
    da, db = pa[i + 1] - pa[i - 1], pb[j + 1] - pb[j - 1]
    na, nb = np.linalg.norm(da), np.linalg.norm(db)
    if na < 0.2 or nb < 0.2:
        return None
    angle = np.degrees(np.arccos(np.clip(da @ db / na / nb, -1.0, 1.0)))
    return (i, j, (pa[i] + pb[j]) / 2) if 30 < angle < 150 else None


def priorities(scene, t: int, rows: np.ndarray) -> dict[int, int]:
    """Window slot -> the priority of the lane each vehicle of the window is on at ``t``."""
    network = scene.road.network
    out = {}
    for a, r in enumerate(rows):
        if r >= 0 and scene.valid[r, t] and scene.agent_types[r] == "vehicle":
            lane = network.get_closest_lane_index(scene.positions[r, t], scene.yaws[r, t])
            out[a] = network.get_lane(lane).priority
    return out


def at_speed_now(path: np.ndarray, step: int, speed: float) -> float:
    """Seconds to cover ``path [F, 2]`` m up to ``step`` at ``speed`` m/s."""
    return float(np.linalg.norm(np.diff(path[: step + 1], axis=0), axis=-1).sum()) / max(speed, 0.1)


def score_window(count, scene, t, rows, future, ok, speed, xy, dt) -> None:
    """Add one window's crossing pairs to ``count`` (module docstring)."""
    priority = priorities(scene, t, rows)
    for a in priority:
        for c in priority:
            if c <= a or priority[a] == priority[c] or min(ok[a].sum(), ok[c].sum()) <= 20:
                continue
            met = crossing(future[a], future[c], ok[a], ok[c])
            if met is None:
                continue
            i, j, point = met
            tie = abs(at_speed_now(future[a], i, speed[a]) - at_speed_now(future[c], j, speed[c]))
            n = count["tie" if tie < TIE else "other"]
            ruled = a if priority[a] > priority[c] else c
            logged = a if i < j else c
            n["pairs"] += 1
            n["log: right of way first"] += logged == ruled
            for sample in xy:  # [S, K, F, 2]
                ra, rc = first_reach(sample[a], point), first_reach(sample[c], point)
                n["samples"] += 1
                if min(ra, rc) == NEVER:
                    continue
                first = a if ra < rc else c
                n["samples reaching"] += 1
                n["log order"] += first == logged
                n["right of way first"] += first == ruled
                n["near miss"] += max(ra, rc) < NEVER and abs(ra - rc) * dt <= TIE


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", help="a stored dataset of generated intersections")
    ap.add_argument("--model", default=None, help="model directory (default: shipped)")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--scenes", type=int, default=None, help="the first N scenes (all)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = load_model(args.model).eval()
    scenes = list(stored_scenes(args.source))[: args.scenes]
    F, dt = model.config.future_steps, model.config.dt
    jobs = window_jobs(scenes, model.config.history_steps, 10, F)
    g = torch.Generator().manual_seed(args.seed)
    count = {kind: Counter() for kind in ("tie", "other")}
    for part, batch in window_batches(model, scenes, jobs):
        with torch.no_grad():
            xy = model.sample(batch, args.samples, g).trajectory[..., :2].numpy()
        future, ok = batch["future"].numpy()[..., :2], batch["future_valid"].numpy()
        speed, rows = batch["history"].numpy()[:, :, -1, 3], batch["rows"].numpy()
        for b, (k, t) in enumerate(part):
            score_window(count, scenes[k], t, rows[b], future[b], ok[b], speed[b], xy[b], dt)
    for kind, n in count.items():
        reach, total = max(n["samples reaching"], 1), max(n["samples"], 1)
        print(
            f"{kind}: {n['pairs']} pairs, the log gives the right of way first in "
            f"{n['log: right of way first']}; of {n['samples reaching']} samples that reach "
            f"the point ({n['samples']} in all): the log's order {n['log order']} "
            f"({n['log order'] / reach:.0%}), the right of way first "
            f"{n['right of way first']} ({n['right of way first'] / reach:.0%}), "
            f"both within {TIE:.0f} s {n['near miss']} ({n['near miss'] / total:.0%} of all)"
        )


if __name__ == "__main__":
    main()
