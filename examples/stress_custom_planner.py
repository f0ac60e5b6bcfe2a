"""Stress-test your own planner: a cautious lane keeper against guided world-model traffic.

A planner is two methods: ``reset(scene, seed)`` and ``act(state) -> [acceleration m/s^2,
steering rad]``. This one keeps its speed, but brakes when anything is within 15 m ahead in
a 3 m wide corridor. It is compared with the unguided world model (``none``) and with the full
counterfactual guidance.

The figures are the run summary's (``counterscene_env.stress.summarize``), as ``counterscene
stress`` prints them: an episode in which no adversary was found (a fallback) counts as one
without an ego-adversary collision.

python examples/stress_custom_planner.py --scenario intersection --episodes 8
"""

from __future__ import annotations

import argparse

import numpy as np

from counterscene_env.sim import SimConfig, WorldState
from counterscene_env.stress import StressConfig, run_episodes, summarize
from counterscene_env.world_model import load_model


class CautiousPlanner:
    name = "cautious"
    replays_log = False

    def reset(self, scene, seed: int) -> None:
        self.dt = scene.dt

    def act(self, state: WorldState) -> np.ndarray:
        e = state.ego_index
        heading = np.array([np.cos(state.yaws[e]), np.sin(state.yaws[e])])
        rel = state.positions - state.positions[e]
        ahead = rel @ heading
        side = np.abs(rel @ np.array([-heading[1], heading[0]]))
        others = state.valid & (np.arange(len(ahead)) != e)
        blocked = (others & (ahead > 0) & (ahead < 15) & (side < 1.5)).any()
        acc = -6.0 if blocked else 0.0
        return np.array([max(acc, -state.speeds[e] / self.dt), 0.0])  # never reverse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="intersection")
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=100000)
    args = parser.parse_args()
    model = load_model()
    for guidance in ("none", "full"):
        config = StressConfig(
            scenario=args.scenario,
            episodes=args.episodes,
            seed=args.seed,
            sim=SimConfig(guidance=guidance),
        )
        records = run_episodes(model, config, planner_factory=CautiousPlanner, progress=False)
        print(summary_line(guidance, summarize(records, config)))


def summary_line(guidance: str, s: dict) -> str:
    """One run's figures, straight from its summary."""
    ttc = (
        f"mean min TTC {s['mean_min_ttc']:.2f} s"
        if s["episodes_without_ttc_conflict"] < s["episodes"]
        else "no TTC conflict in any episode"
    )
    return (
        f"guidance {guidance:5s}: CR {s['cr']:.2f}  ego-adversary CR "
        f"{s['cr_ego_adversary']:.2f}  HBR {s['hbr_ego']:.2f}  {ttc}  "
        f"(no adversary found in {s['fallbacks']} of {s['episodes']} episodes)"
    )


if __name__ == "__main__":
    main()
