"""How far the guided adversary is from its log before and after it first touches the ego.

    python tools/after_contact.py --scenario merge --episodes 40 --seed 5000

For each selector (causal and distance by default), the episodes with an adversary, IDM ego,
today's default settings: the adversary's distance from its logged position at 2, 4, 6, 8
and 10 s [m], for the episodes where it hits the ego and for the others, and the mean
displacement of every non-ego vehicle over 0-10 s [m] (what the tables' ADE averages). Tells
whether a selector's higher ADE comes after the contact (a guided adversary that keeps
pushing once it has hit) or from the choice itself (docs/history/closed_loop.md, "After the
contact").
"""

from __future__ import annotations

import argparse

import numpy as np

from counterscene_env.geometry import overlaps_over_time
from counterscene_env.planners import make_planner
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.stress.batch import play_batch
from counterscene_env.world_model import load_model

SECONDS = (2, 4, 6, 8, 10)
BATCH = 4


def episode_row(loop: ClosedLoop, b: int, scene) -> dict | None:
    """One finished episode: first ego-adversary contact [s after now] (None: none), the
    adversary's distance from its log at :data:`SECONDS` [m], all non-ego vehicles' mean."""
    ep = loop.episodes[b]
    if ep.adversary is None:
        return None
    sim = loop.scene(b)
    fac = scene.time_slice(0, sim.num_steps)
    t0, e, a = sim.current_index, sim.ego_index, ep.adversary
    pair = [e, a]
    touch = overlaps_over_time(
        sim.positions[pair], sim.yaws[pair], sim.extents[pair], sim.valid[pair]
    )[t0 + 1 :, 0, 1]
    hit = np.flatnonzero(touch)
    dist = np.linalg.norm(sim.positions[a] - fac.positions[a], axis=-1)  # [T] m
    others = [i for i in range(sim.num_agents) if i != e and sim.agent_types[i] == "vehicle"]
    steps = np.arange(t0 + 1, min(t0 + 101, sim.num_steps))
    disp = np.linalg.norm(
        sim.positions[others][:, steps] - fac.positions[others][:, steps], axis=-1
    )
    ok = sim.valid[others][:, steps] & fac.valid[others][:, steps]
    return {
        "hit_s": (hit[0] + 1) * sim.dt if hit.size else None,
        "adversary_m": [
            float(dist[min(t0 + round(s / sim.dt), sim.num_steps - 1)]) for s in SECONDS
        ],
        "all_mean_m": float(disp[ok].mean()),
    }


def contact_line(selector: str, rows: list[dict]) -> str:
    """How many of the episodes with an adversary (:func:`episode_row`) hit the ego, and the
    median first contact of those that did."""
    times = [r["hit_s"] for r in rows if r["hit_s"] is not None]
    if not times:
        return f"{selector}: {len(rows)} episodes with an adversary, no episode hit the ego"
    return (
        f"{selector}: {len(rows)} episodes with an adversary, {len(times)} hit the ego "
        f"(median first contact {np.median(times):.1f} s)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="merge")
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--seed", type=int, default=5000, help="first seed (development: 5000)")
    ap.add_argument("--selectors", nargs="+", default=["causal", "distance"])
    args = ap.parse_args()
    model = load_model("default")
    scenes = list(scenes_for(args.scenario, args.episodes, args.seed))
    for selector in args.selectors:
        loop = ClosedLoop(model, SimConfig(selector=selector))
        rows = []
        for k in range(0, len(scenes), BATCH):
            chunk = scenes[k : k + BATCH]
            seeds = [args.seed + k + j for j in range(len(chunk))]
            play_batch(loop, chunk, seeds, [make_planner("idm") for _ in chunk])
            rows += [episode_row(loop, b, s) for b, s in enumerate(chunk)]
        rows = [r for r in rows if r is not None]
        hits = [r for r in rows if r["hit_s"] is not None]
        print(contact_line(selector, rows))
        for name, group in (("hit", hits), ("no hit", [r for r in rows if r["hit_s"] is None])):
            if group:
                adv = np.mean([r["adversary_m"] for r in group], axis=0)
                mean = np.mean([r["all_mean_m"] for r in group])
                print(
                    f"  {name}: adversary from its log at {'/'.join(map(str, SECONDS))} s: "
                    f"{np.round(adv, 2).tolist()} m; every non-ego vehicle, mean 0-10 s {mean:.2f} m"
                )


if __name__ == "__main__":
    main()
