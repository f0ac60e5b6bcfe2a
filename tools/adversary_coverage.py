"""Where the causal selection finds an adversary, against where the log holds a near miss.

    python tools/adversary_coverage.py --episodes 30 --egos 3 --seed 300000 \
        --scenarionet ../shared/data/nuscenes_mini_scenarionet ../shared/data/waymo_scenarionet \
        --commonroad data/ngsim_split/heldout [--set strict_gates=false] [--json]

The episodes are those of every ``paper-tables`` row (and of ``counterscene stress``) with the
same scenario, ``--episodes``, ``--seed``, ``--egos`` and ``--min-future`` (default: as
``paper-tables``, real scenes with 3 s of log after their start): each real scene seats up to
``--egos`` egos in turn. For each episode:

- **near miss in the log**: some other vehicle's logged path passes within 3 m (centre to
  centre) of the ego's logged path, at any two steps from "now" + 1 to the episode's end
  (10 s or the log's end): a vehicle whose route meets the ego's;
- **adversary**: the closed loop's own selection at reset (``ClosedLoop.reset``, selection on
  the factual future), with the default closed-loop settings unless ``--set`` changes them.

Prints, per source: episodes, those with a near miss in the log, the share of those with an
adversary (95 % Wilson interval), and the share of all episodes with an adversary.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from counterscene_env.cli.common import parse_overrides
from counterscene_env.config import COMMONROAD_PREFIX, REAL_MIN_FUTURE, SCENARIONET_PREFIX
from counterscene_env.metrics import wilson_interval
from counterscene_env.scene.core import Scene
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.world_model import load_model

#: A vehicle whose logged path comes this close to the ego's [m] is a near miss in the log.
NEAR = 3.0


def near_miss(scene: Scene, lo: int, hi: int) -> bool:
    """Whether another vehicle's logged path over steps ``[lo, hi)`` passes within
    :data:`NEAR` m of the ego's logged path over the same steps (any two steps)."""
    e = scene.ego_index
    ego = scene.positions[e, lo:hi][scene.valid[e, lo:hi]]  # [Te, 2] m
    if not len(ego):
        return False
    for a in np.flatnonzero(scene.agent_types == "vehicle"):
        other = scene.positions[a, lo:hi][scene.valid[a, lo:hi]]
        if a == e or not len(other):
            continue
        gap = np.linalg.norm(ego[:, None] - other[None], axis=-1)  # [Te, Ta] m
        if gap.min() < NEAR:
            return True
    return False


def coverage(
    loop: ClosedLoop, spec: str, episodes: int, seed: int, egos: int, min_future: float
) -> dict:
    """The counts of the module docstring for one scenario spec."""
    rows = []
    for i, scene in enumerate(scenes_for(spec, episodes, seed, egos, min_future=min_future)):
        loop.reset([scene], [seed + i])
        ep = loop.episodes[0]
        near = near_miss(ep.factual, ep.start + 1, ep.end + 1)
        found = loop.selection(0).conflict is not None
        rows.append((near, found, scene.scenario_id, int(ep.egos[0])))
    n = len(rows)
    near = sum(r[0] for r in rows)
    both = sum(r[0] and r[1] for r in rows)
    low, high = wilson_interval(both, near)
    return {
        "episodes": n,
        "distinct_scene_egos": len({(r[2], r[3]) for r in rows}),
        "near_miss_in_log": near,
        "adversary_where_near_miss": both,
        "share": both / near if near else float("nan"),
        "interval": [low, high],
        "adversary_all": sum(r[1] for r in rows),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarionet", nargs="*", default=[], metavar="DIR")
    parser.add_argument("--commonroad", nargs="*", default=[], metavar="DIR")
    parser.add_argument("--scenario", nargs="*", default=[], metavar="SPEC")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--egos", type=int, default=3)
    parser.add_argument("--seed", type=int, default=300000)
    parser.add_argument("--min-future", type=float, default=REAL_MIN_FUTURE, metavar="S")
    parser.add_argument("--model", default="default")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    specs = list(args.scenario)
    specs += [SCENARIONET_PREFIX + d for d in args.scenarionet]
    specs += [COMMONROAD_PREFIX + d for d in args.commonroad]
    loop = ClosedLoop(load_model(args.model), SimConfig.from_mapping(parse_overrides(args.set)))
    out = {
        spec: coverage(loop, spec, args.episodes, args.seed, args.egos, args.min_future)
        for spec in specs
    }
    if args.json:
        print(json.dumps(out, indent=1))
        return
    for spec, c in out.items():
        low, high = c["interval"]
        print(
            f"{spec}: {c['episodes']} episodes ({c['distinct_scene_egos']} scene-ego pairs), "
            f"{c['near_miss_in_log']} with a near miss in the log; an adversary in "
            f"{c['adversary_where_near_miss']} of those ({100 * c['share']:.0f} % "
            f"[{100 * low:.0f}, {100 * high:.0f}]), in {c['adversary_all']} of all"
        )


if __name__ == "__main__":
    main()
