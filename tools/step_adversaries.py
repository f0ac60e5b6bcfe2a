"""Who the adversary is step by step when the closed loop re-selects at its replans.

With ``--source model`` the adversary is re-mined at every replan on the world model's own
unguided sample (docs/closed_loop.md, "Sources"). This plays episodes (IDM ego, today's
defaults otherwise) and counts, over all their steps, the share without an adversary and
why (the step info's ``fallback``), the conflict types chosen, and the adversaries per
episode. The figures of docs/history/closed_loop.md ("Re-selection at every replan, counted
right"). Develop on the development seeds (5000-5199), never on the held-out ones:

    python tools/step_adversaries.py --scenario merge --episodes 20 --seed 5000 --selector causal
"""

from __future__ import annotations

import argparse
import collections

import numpy as np

from counterscene_env.planners import make_planner
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.stress.batch import play_batch
from counterscene_env.world_model import load_model

BATCH = 4


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="merge")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=5000, help="first seed (development: 5000)")
    ap.add_argument("--selector", default="causal")
    ap.add_argument("--source", default="model", choices=("log", "model"))
    args = ap.parse_args()
    loop = ClosedLoop(
        load_model("default"), SimConfig(selector=args.selector, selection_source=args.source)
    )
    scenes = list(scenes_for(args.scenario, args.episodes, args.seed))
    types, reasons, per_episode = collections.Counter(), collections.Counter(), []
    steps = without = 0
    for k in range(0, len(scenes), BATCH):
        chunk = scenes[k : k + BATCH]
        seeds = [args.seed + k + j for j in range(len(chunk))]
        play_batch(loop, chunk, seeds, [make_planner("idm") for _ in chunk])
        for ep in loop.episodes:
            adversaries = set()
            for step in ep.records[1:]:  # the rollout steps' infos, the first ego's
                info = step[0]
                steps += 1
                if info["adversary"] is None:
                    without += 1
                    reasons[info["fallback"]] += 1
                else:
                    adversaries.add(info["adversary"])
                    types[info["conflict_type"]] += 1
            per_episode.append(len(adversaries))
    print(
        f"{args.scenario}, {args.selector}, source {args.source}: {len(per_episode)} episodes, "
        f"{np.mean(per_episode):.1f} adversaries per episode; "
        f"{100 * without / steps:.1f} % of {steps} steps without an adversary"
    )
    for reason, n in reasons.most_common():
        print(f"  no adversary, {n} steps: {reason}")
    for kind, n in types.most_common():
        print(f"  {kind}: {n} steps")


if __name__ == "__main__":
    main()
