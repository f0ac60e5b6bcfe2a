"""Train a DQN ego policy on highway-env's own ``intersection-v2`` and evaluate it.

A single-file recipe (CleanRL style). It

1. trains a Stable-Baselines3 DQN (``MlpPolicy``) on ``intersection-v2`` with the env's
   default observation and action configuration (Kinematics, 15 vehicles x 7 features;
   DiscreteMetaAction, longitudinal only: SLOWER / IDLE / FASTER; policy frequency 1 Hz).
   DQN is the algorithm highway-env's documentation uses for its discrete-action tasks; it
   reuses every transition from a replay buffer, and since the env itself and not the network is
   the bottleneck (15,000 steps of training took 1,031 s on one core, docs/environment.md), it
   learns more per wall-clock second than PPO;
2. saves ``OUT/model.zip`` and the sidecar ``OUT/model.env.json`` holding
   ``{"observation": ..., "action": ..., "policy_frequency": ...}`` copied verbatim from the
   training env's config, so that another tool can rebuild matching spaces elsewhere;
3. evaluates the greedy policy on ``--eval-episodes`` fresh episodes (reset seeds
   ``--eval-seed``, ``--eval-seed + 1``, ...) next to a constant-IDLE baseline on the same
   seeds, prints the result and writes ``OUT/eval.json``.

Run (keep torch on one thread):

    OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 SDL_VIDEODRIVER=dummy \\
        python agents/highway_intersection.py --total-timesteps 20000 \\
        --out runs/highway_intersection

A smoke test: ``--total-timesteps 64 --eval-episodes 1`` finishes in a few seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import gymnasium as gym
import highway_env  # noqa: F401  (registers intersection-v2)
import numpy as np
import torch
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import set_random_seed

IDLE = 1  # DiscreteMetaAction index of IDLE (0: SLOWER, 1: IDLE, 2: FASTER)


@dataclass
class Args:
    env_id: str = "intersection-v2"
    """the highway-env environment id (its default config is used)"""
    seed: int = 0
    """seed of the training run (torch, numpy, env resets)"""
    total_timesteps: int = 20_000
    """environment steps (1 step = 1 s of driving at policy frequency 1)"""
    out: str = "runs/highway_intersection"
    """output folder: model.zip, model.env.json, eval.json"""
    learning_rate: float = 5e-4
    buffer_size: int = 15_000
    learning_starts: int = 200
    """capped at total_timesteps // 2 so that tiny runs still take gradient steps"""
    batch_size: int = 32
    gamma: float = 0.8
    train_freq: int = 1
    gradient_steps: int = 1
    target_update_interval: int = 50
    exploration_fraction: float = 0.3
    exploration_final_eps: float = 0.05
    net_arch: str = "256,256"
    """hidden layer sizes of the Q network, comma separated"""
    log_every: int = 1000
    """print one progress line every this many steps"""
    eval_episodes: int = 20
    eval_seed: int = 10_000
    """first reset seed of the evaluation episodes"""


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    for field in dataclasses.fields(Args):
        kind = {"int": int, "float": float, "str": str}[str(field.type)]
        parser.add_argument(
            "--" + field.name.replace("_", "-"),
            type=kind,
            default=field.default,
            help=f"(default: {field.default})",
        )
    return Args(**vars(parser.parse_args(argv)))


def to_jsonable(value: Any) -> Any:
    """Plain JSON types for a config value (numpy scalars and arrays become Python ones)."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def env_sidecar(env: gym.Env) -> dict[str, Any]:
    """The spaces contract: observation and action configs and the policy frequency."""
    config = env.unwrapped.config
    return {
        "observation": to_jsonable(config["observation"]),
        "action": to_jsonable(config["action"]),
        "policy_frequency": int(config["policy_frequency"]),
    }


class ProgressLog(BaseCallback):
    """One line every ``every`` steps: fps, epsilon and the last 100 training episodes."""

    def __init__(self, every: int):
        super().__init__()
        self.every = every
        self.returns: deque[float] = deque(maxlen=100)
        self.lengths: deque[int] = deque(maxlen=100)
        self.crashes: deque[bool] = deque(maxlen=100)
        self.ep_return = 0.0
        self.ep_length = 0
        self.ep_crashed = False
        self.start = time.perf_counter()

    def _on_step(self) -> bool:
        info = self.locals["infos"][0]
        self.ep_return += float(self.locals["rewards"][0])
        self.ep_length += 1
        self.ep_crashed |= bool(info.get("crashed", False))
        if self.locals["dones"][0]:
            self.returns.append(self.ep_return)
            self.lengths.append(self.ep_length)
            self.crashes.append(self.ep_crashed)
            self.ep_return, self.ep_length, self.ep_crashed = 0.0, 0, False
        if self.num_timesteps % self.every == 0 and self.returns:
            elapsed = time.perf_counter() - self.start
            print(
                f"step {self.num_timesteps:7d}  {self.num_timesteps / elapsed:5.1f} steps/s  "
                f"eps {self.model.exploration_rate:.3f}  "
                f"last {len(self.returns)} ep: return {np.mean(self.returns):6.2f}  "
                f"len {np.mean(self.lengths):5.2f}  crash {np.mean(self.crashes):.2f}",
                flush=True,
            )
        return True


def evaluate(env: gym.Env, act, episodes: int, seed: int) -> dict[str, float | int | None]:
    """Run ``episodes`` episodes with reset seeds ``seed + i``; ``act(obs) -> action``."""
    returns, lengths, crashes, arrivals = [], [], [], []
    base = env.unwrapped
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        done, ep_return, length, crashed = False, 0.0, 0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(act(obs))
            ep_return += float(reward)
            length += 1
            crashed |= bool(info.get("crashed", False))
            done = terminated or truncated
        returns.append(ep_return)
        lengths.append(length)
        crashes.append(crashed)
        if hasattr(base, "has_arrived"):
            arrivals.append(bool(base.has_arrived(base.vehicle)))
    return {
        "episodes": episodes,
        "mean_return": float(np.mean(returns)),
        "crash_rate": float(np.mean(crashes)),
        "arrival_rate": float(np.mean(arrivals)) if arrivals else None,
        "mean_episode_length": float(np.mean(lengths)),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    torch.set_num_threads(1)
    set_random_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    env = gym.make(args.env_id)
    print(f"{args.env_id}: observation {env.observation_space}, action {env.action_space}")
    model = DQN(
        "MlpPolicy",
        env,
        learning_rate=args.learning_rate,
        buffer_size=args.buffer_size,
        learning_starts=min(args.learning_starts, args.total_timesteps // 2),
        batch_size=args.batch_size,
        gamma=args.gamma,
        train_freq=args.train_freq,
        gradient_steps=args.gradient_steps,
        target_update_interval=args.target_update_interval,
        exploration_fraction=args.exploration_fraction,
        exploration_final_eps=args.exploration_final_eps,
        policy_kwargs={"net_arch": [int(n) for n in args.net_arch.split(",")]},
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    start = time.perf_counter()
    model.learn(total_timesteps=args.total_timesteps, callback=ProgressLog(args.log_every))
    train_time = time.perf_counter() - start
    print(f"trained {args.total_timesteps} steps in {train_time:.1f} s")

    model_path = out / "model.zip"
    model.save(model_path)
    sidecar_path = out / "model.env.json"
    sidecar_path.write_text(json.dumps(env_sidecar(env), indent=2) + "\n")
    env.close()
    print(f"saved {model_path} and {sidecar_path}")

    eval_env = gym.make(args.env_id)
    trained = evaluate(
        eval_env,
        lambda obs: int(model.predict(obs, deterministic=True)[0]),
        args.eval_episodes,
        args.eval_seed,
    )
    idle = evaluate(eval_env, lambda obs: IDLE, args.eval_episodes, args.eval_seed)
    eval_env.close()
    result = {
        "env_id": args.env_id,
        "algo": "DQN",
        "seed": args.seed,
        "eval_seed": args.eval_seed,
        **trained,
        "training_wall_time_s": round(train_time, 2),
        "total_timesteps": args.total_timesteps,
        "idle_baseline": idle,
    }
    (out / "eval.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
