"""Why the causal selector finds no adversary in some episodes (docs/reproducing_the_paper.md).

Selects on each scene's logged future as the closed loop does at reset
(``sim.adversaries.select_on_log``, today's default settings) and, for every episode without
an adversary, asks what the paper's rules alone (no strict gates) would have chosen: which
strict gates that choice fails (``far``: closest approach ``d_min`` >= 15 m; ``truncated``:
closest on the last jointly valid step; ``drifting_apart``; ``parked``) and its ``d_min``
and arrival gap. Prints JSON. Develop on the development seeds
(5000-5199), never on the held-out ones:

    python tools/no_adversary.py intersection --episodes 200 --seed 5000
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np

from counterscene_env.adversary.conflicts import MIN_JOINT_STEPS, strict_gate_failures
from counterscene_env.adversary.selection import select_adversary
from counterscene_env.adversary.tracks import check_tracks
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim.config import SimConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenario", help="a generated road or a stored scene spec")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--seed", type=int, default=5000)
    args = ap.parse_args()
    config = SimConfig()
    counts: collections.Counter = collections.Counter()
    gates: collections.Counter = collections.Counter()
    episodes = []
    for scene in scenes_for(args.scenario, args.episodes, args.seed):
        lo = scene.current_index + 1
        hi = min(scene.num_steps, lo + round(config.duration / scene.dt))
        pos, valid, speeds = (a[:, lo:hi] for a in (scene.positions, scene.valid, scene.speeds))
        vehicles = scene.agent_types == "vehicle"
        kw = dict(
            speeds=speeds,
            extents=scene.extents,
            eligible=vehicles,
            dt=scene.dt,
            start_step=lo,
            yielders_first=config.yielders_first,
            reachable_first=config.reachable_first,
        )
        ours = select_adversary("causal", pos, valid, scene.ego_index, strict=True, **kw)
        if ours.conflict is not None:
            counts["adversary"] += 1
            continue
        paper = select_adversary("causal", pos, valid, scene.ego_index, strict=False, **kw)
        record = {"scene_seed": scene.metadata.get("seed"), "fallback": ours.fallback}
        if paper.conflict is None:
            counts["no adversary, nor by the paper's rules"] += 1
        else:
            c = paper.conflict
            tracks = check_tracks(
                pos,
                valid,
                scene.ego_index,
                speeds=speeds,
                dt=scene.dt,
                min_joint_steps=MIN_JOINT_STEPS,
            )
            failed = strict_gate_failures(tracks, c, lo)
            gates.update(failed)
            counts["no adversary; the paper's rules have one"] += 1
            record["paper_choice"] = {
                "subtype": c.subtype,
                "tier": c.tier,
                "d_min_m": round(float(c.min_distance), 2),
                "arrival_gap_s": round(float(c.arrival_gap), 2),
                "strict_gates_failed": failed,
            }
        episodes.append(record)
    d_min = [e["paper_choice"]["d_min_m"] for e in episodes if "paper_choice" in e]
    summary = {
        "scenario": args.scenario,
        "episodes": args.episodes,
        "seed": args.seed,
        "counts": dict(counts),
        "the paper's choice fails (episodes)": dict(gates),
        "the paper's choice, d_min m: median, min, max": (
            [float(np.median(d_min)), min(d_min), max(d_min)] if d_min else None
        ),
        "without an adversary": episodes,
    }
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
