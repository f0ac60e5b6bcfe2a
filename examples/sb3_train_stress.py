"""Stable-Baselines3 on CounterScene-v0: train PPO briefly, then stress-test it.

The short version of ``agents/ppo_ego.py``: PPO learns on the intersection with the guided
adversary; the saved policy (and its ``.env.json`` sidecar with the observation and action
config) is then stress-tested with ``counterscene stress --planner sb3:PATH.zip``, here called
in-process. Any SB3 policy whose spaces match runs the same way, including one trained on
highway-env's own ``intersection-v2`` (see ``agents/highway_intersection.py``).

python examples/sb3_train_stress.py --timesteps 400 --episodes 4
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
from stable_baselines3 import PPO

import counterscene_env  # noqa: F401  (registers CounterScene-v0)
from counterscene_env.cli import main as counterscene

CONFIG = {
    "scenario": "intersection",
    "action": {"type": "DiscreteMetaAction", "longitudinal": True, "lateral": False},
    "policy_frequency": 2,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--timesteps", type=int, default=400)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--out", default="runs/sb3_example")
    args = parser.parse_args()

    env = gym.make("CounterScene-v0", config=CONFIG)
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=32, gamma=0.9, seed=0, verbose=1)
    model.learn(args.timesteps)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "model.zip")
    sidecar = {k: env.unwrapped.config[k] for k in ("observation", "action", "policy_frequency")}
    (out / "model.env.json").write_text(json.dumps(sidecar))

    for guidance in ("none", "full"):
        counterscene(["stress", "--scenario", "intersection", "--episodes", str(args.episodes),
                      "--planner", f"sb3:{out / 'model.zip'}", "--guidance", guidance, "--quiet"])  # fmt: skip


if __name__ == "__main__":
    main()
