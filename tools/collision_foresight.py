"""Did the world model see its own collisions coming? (docs/world_model_experiments.md,
"The network's crossing collisions").

The tool runs the unguided closed loop with the log replayed for the ego on stored scenes, as
``tools/wrong_way.py`` does, and records every replan's samples and the one the choice among
samples kept. For each pair of vehicles other than the ego that collide where the log does
not, it looks back over the replans before the collision at which both were in the model's
window:

- **lead**: how long before the collision the kept plan first put the pair's boxes on each
  other [s] (a plan reads 5.2 s ahead; "never" when no kept plan had it: the collision came
  from the executed steps between two replans, or from a car the model did not plan);
- **samples with it**: at each replan, the share of the samples that put the pair on each
  other at some step of their plan, by lead time. When every sample has it, no choice among
  samples can avoid it; when only some do, a choice that reads far enough ahead can.

    python tools/collision_foresight.py data/eval-intersection [--episodes 50] [--set KEY=VALUE ...]

``--set`` takes closed-loop keys (JSON values), e.g. ``--set lane_steering=0
traffic_yields=false road_keeping=false`` for the network alone (the default here, since with
the reflexes on there are no such collisions to look at) and ``num_samples=8``.
"""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np

from counterscene_env.cli.common import parse_overrides
from counterscene_env.geometry import boxes_overlap
from counterscene_env.metrics.common import rollout_slice
from counterscene_env.metrics.safety import new_vehicle_collisions
from counterscene_env.planners import make_planner
from counterscene_env.scene.sources import loaded_scenes
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.sim.replan import Replanner
from counterscene_env.stress import run_batch
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.model import WorldModel

NETWORK_ALONE = {"lane_steering": 0, "traffic_yields": False, "road_keeping": False}
LEAD_BINS = (0.0, 1.0, 2.0, 3.0, 4.0, 5.3)  # s


class Recorder:
    """Records each replan of a one-episode closed loop through the public calls it makes:
    the window's scene rows (``Replanner.windows``), the samples (``WorldModel.sample``) and
    the kept one (``Replanner.choose``)."""

    def __init__(self) -> None:
        self.replans: list[dict] = []
        self._rows: np.ndarray | None = None

    def install(self) -> None:
        windows, sample, choose = Replanner.windows, WorldModel.sample, Replanner.choose
        recorder = self

        def rec_windows(replanner, ep, sim):
            out = windows(replanner, ep, sim)
            if len(out) != 1:
                raise SystemExit("collision_foresight reads one model window per replan")
            recorder._rows = np.asarray(out[0].rows)
            recorder._t = ep.t
            return out

        def rec_sample(model, batch, *args, **kwargs):
            pred = sample(model, batch, *args, **kwargs)
            recorder.replans.append(
                dict(
                    t=recorder._t,
                    rows=recorder._rows,
                    trajectory=pred.trajectory[0].numpy(),  # [S, K, F, 4] window frame
                    valid=np.asarray(pred.valid[0]),
                    kept=0,
                )
            )
            return pred

        def rec_choose(replanner, *args, **kwargs):
            best = choose(replanner, *args, **kwargs)
            recorder.replans[-1]["kept"] = int(best[0])
            return best

        Replanner.windows, WorldModel.sample, Replanner.choose = rec_windows, rec_sample, rec_choose


def look_back(replans: list[dict], a: int, b: int, hit: int, extents, dt: float) -> dict:
    """The pair's lead and, per replan before ``hit``, (lead s, share of samples with it)."""
    lead, shares = None, []
    for r in replans:
        if r["t"] >= hit:
            break
        rows = list(r["rows"])
        if a not in rows or b not in rows:
            continue
        ka, kb = rows.index(a), rows.index(b)
        if not (r["valid"][ka] and r["valid"][kb]):
            continue
        x = r["trajectory"]
        meets = boxes_overlap(
            x[:, ka, :, :2], x[:, ka, :, 2], extents[a], x[:, kb, :, :2], x[:, kb, :, 2], extents[b]
        ).any(-1)  # [S]
        ahead = (hit - r["t"]) * dt
        if meets[r["kept"]] and lead is None:
            lead = ahead
        shares.append((ahead, float(meets.mean())))
    return {"lead_s": lead, "samples_with_it": shares}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="stored scenes (a dataset directory or shard)")
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--model", default="default")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    settings = {**NETWORK_ALONE, **parse_overrides(args.set)}
    recorder = Recorder()
    recorder.install()
    loop = ClosedLoop(load_model(args.model), SimConfig(**{"guidance": "none", **settings}))
    pairs = []
    for i, scene in enumerate(loaded_scenes(args.data)[: args.episodes]):
        recorder.replans.clear()
        run_batch(loop, [scene], [i], [make_planner("log")])
        sim = loop.scene(0)
        log = scene.time_slice(0, sim.num_steps)
        start = rollout_slice(sim).start  # the replans' steps are the scene's
        for a, b, t in new_vehicle_collisions(sim, log):
            pairs.append(look_back(recorder.replans, a, b, start + t, sim.extents, sim.dt))
    leads = np.array([p["lead_s"] for p in pairs if p["lead_s"] is not None])
    by_lead = {}
    for lo, hi in itertools.pairwise(LEAD_BINS):
        s = [share for p in pairs for t, share in p["samples_with_it"] if lo <= t < hi]
        by_lead[f"{lo:g}-{hi:g} s"] = {
            "replans": len(s),
            "mean_share_of_samples": float(np.mean(s)) if s else None,
            "all_samples": int(sum(x == 1.0 for x in s)),
        }
    print(
        json.dumps(
            {
                "settings": settings,
                "pairs": len(pairs),
                "never_in_a_kept_plan": int(sum(p["lead_s"] is None for p in pairs)),
                "lead_s_median": float(np.median(leads)) if len(leads) else None,
                "lead_at_least_2_s": int((leads >= 2).sum()),
                "lead_at_least_3_s": int((leads >= 3).sum()),
                "samples_with_it_by_lead": by_lead,
            }
        )
    )


if __name__ == "__main__":
    main()
