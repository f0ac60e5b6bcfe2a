"""PPO ego against CounterScene's guided adversary: train, save, stress-test (one file).

Trains Stable-Baselines3 PPO on ``CounterScene-v0`` (world-model traffic, the causal adversary
guided with ``--guidance``, default ``full``) on ``--num-envs`` envs batched in one process
(``counterscene_env.envs.sb3_vec.SB3VecEnv``: every replan is one world-model call for all of
them; ``--workers 2`` splits them over two processes), for ``--total-timesteps`` steps or
``--max-minutes`` of training, saves ``OUT/model.zip`` and its env sidecar ``OUT/model.env.json`` (the observation and action config,
so ``counterscene stress --planner sb3:OUT/model.zip`` rebuilds matching spaces), then
stress-tests the policy on ``--eval-episodes`` held-out episodes (seeds from ``--eval-seed``)
with ``--guidance none`` and ``full``, next to highway-env's IDM planner on the same episodes,
and writes ``OUT/eval.json``.

The default ego acts like highway-env's ``intersection-v2`` ego: ``DiscreteMetaAction``
(SLOWER / IDLE / FASTER among 0, 4.5 and 9 m/s; the vehicle follows the lanes of its logged
route) at 2 Hz, observing ``Kinematics``. Run::

    counterscene generate --scenario intersection --scenes 400 --seed 0 --out data/intersection
    python agents/ppo_ego.py --scenario data/intersection --eval-scenario intersection \
        --total-timesteps 100000 --max-minutes 20 --out runs/ppo_ego   # 20 min on 2 cores
    python agents/ppo_ego.py --total-timesteps 64 --eval-episodes 1 --num-envs 1   # smoke test
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

from stable_baselines3.common.callbacks import BaseCallback


@dataclass
class Args:
    scenario: str = "intersection"
    """training scenario (a CounterScene-v0 ``scenario`` spec: a name, or a dataset directory
    from ``counterscene generate``, which saves generating a scene per episode)"""
    eval_scenario: str = ""
    """evaluation scenario (default: ``scenario``)"""
    total_timesteps: int = 4800
    """policy steps of training, all envs together"""
    num_envs: int = 16
    """envs batched in one vector env (one world-model call per replan for all)"""
    workers: int = 1
    """processes the envs are split over (stored scenes: 2 steps 1.2x as fast on 2 cores)"""
    max_minutes: float = 0.0
    """stop training after this many minutes (0: no limit)"""
    seed: int = 0
    """seed of training (envs, PPO)"""
    guidance: str = "full"
    """guidance preset of the training traffic"""
    policy_frequency: int = 2
    """decisions per second [Hz] (divides 10)"""
    action: str = "DiscreteMetaAction"
    """highway-env action type: DiscreteMetaAction or ContinuousAction"""
    duration: float = 10.0
    """episode length [s]"""
    num_samples: int = 0
    """world-model samples per replan (0: the env's default, ``SimConfig.num_samples``)"""
    learning_rate: float = 5e-4
    n_steps: int = 16
    """rollout steps per env and update (16 envs x 16 = 256 steps per update)"""
    batch_size: int = 64
    n_epochs: int = 10
    gamma: float = 0.9
    eval_episodes: int = 20
    """stress episodes per row of the evaluation"""
    eval_seed: int = 100000
    """seed of evaluation episode 0 (held out: training scenes take random seeds)"""
    out: str = "runs/ppo_ego"
    torch_threads: int = 0
    """torch threads (0: torch's default, every core)"""


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for f in dataclasses.fields(Args):
        flag = "--" + f.name.replace("_", "-")
        parser.add_argument(flag, type=type(f.default), default=f.default)
    return Args(**vars(parser.parse_args(argv)))


def env_config(args: Args) -> dict:
    """The CounterScene-v0 config of training (and the sidecar's observation and action)."""
    action = (
        {"type": "DiscreteMetaAction", "longitudinal": True, "lateral": False,
         "target_speeds": [0, 4.5, 9]}
        if args.action == "DiscreteMetaAction"
        else {"type": args.action}
    )  # fmt: skip
    return {
        "scenario": args.scenario,
        "guidance": args.guidance,
        "policy_frequency": args.policy_frequency,
        "duration": args.duration,
        **({"num_samples": args.num_samples} if args.num_samples else {}),
        "action": action,
        "reward_speed_range": [4.0, 9.0],
    }


class TimeLimit(BaseCallback):
    """Stops training after ``minutes`` of it (0: never)."""

    def __init__(self, minutes: float) -> None:
        super().__init__()
        self.minutes = minutes

    def _on_training_start(self) -> None:
        self.start = time.perf_counter()

    def _on_step(self) -> bool:
        return not self.minutes or time.perf_counter() - self.start < 60 * self.minutes


def train(args: Args, out: Path) -> Path:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    from counterscene_env.envs.sb3_vec import SB3VecEnv

    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    config = env_config(args)
    venv = VecMonitor(SB3VecEnv(args.num_envs, config=config, workers=args.workers))
    venv.seed(args.seed)
    model = PPO(
        "MlpPolicy",
        venv,
        learning_rate=args.learning_rate,
        n_steps=args.n_steps,
        batch_size=args.batch_size,
        n_epochs=args.n_epochs,
        gamma=args.gamma,
        seed=args.seed,
        device="cpu",
        verbose=1,
    )
    start = time.perf_counter()
    model.learn(total_timesteps=args.total_timesteps, callback=TimeLimit(args.max_minutes))
    seconds = time.perf_counter() - start
    venv.close()
    path = out / "model.zip"
    model.save(path)
    sidecar = {k: config[k] for k in ("observation", "action", "policy_frequency") if k in config}
    sidecar.setdefault("observation", _default_observation())
    (out / "model.env.json").write_text(json.dumps(sidecar, indent=2) + "\n")
    (out / "train.json").write_text(
        json.dumps(
            {"args": dataclasses.asdict(args), "train_seconds": seconds,
             "timesteps": int(model.num_timesteps)},
            indent=2,
        ) + "\n"
    )  # fmt: skip
    print(f"trained {model.num_timesteps} steps in {seconds:.0f} s -> {path}")
    return path


def _default_observation() -> dict:
    from counterscene_env.envs.single_agent import CounterSceneEnv

    return CounterSceneEnv.default_config()["observation"]


def eval_config(args: Args, planner: str, guidance: str):
    """The ``StressConfig`` of one evaluation row."""
    from counterscene_env.sim import SimConfig
    from counterscene_env.stress import StressConfig

    samples = {"num_samples": args.num_samples} if args.num_samples else {}
    return StressConfig(
        scenario=args.eval_scenario or args.scenario,
        episodes=args.eval_episodes,
        seed=args.eval_seed,
        planner=planner,
        sim=SimConfig(duration=args.duration, guidance=guidance, **samples),
    )


def evaluate(args: Args, path: Path, out: Path) -> dict:
    """Stress rows: the PPO policy and IDM, each with guidance none and full."""
    from counterscene_env.metrics import json_safe
    from counterscene_env.stress import run_episodes, run_policy_episodes, summarize, timings
    from counterscene_env.world_model import load_model

    keys = ("cr", "cr_ego_adversary", "hbr_ego", "orr", "mean_min_ttc",
            "mean_min_clearance_adversary", "fallbacks")  # fmt: skip
    rows = {}
    for planner in (f"sb3:{path}", "idm"):
        for guidance in ("none", "full"):
            config = eval_config(args, planner, guidance)
            if planner == "idm":
                records = run_episodes(load_model(), config, progress=False)
            else:
                records = run_policy_episodes(config, progress=False)
            summary = summarize(records, config)
            name = f"{'ppo' if planner != 'idm' else 'idm'} {guidance}"
            rows[name] = {k: summary[k] for k in keys}
            rows[name]["seconds_per_episode"] = timings(records)["seconds_per_episode"]
            print(name, json.dumps(json_safe(rows[name])))
    (out / "eval.json").write_text(json.dumps(json_safe(rows), indent=2) + "\n")
    return rows


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    # The evaluation's settings are checked before training, not after it has run.
    try:
        for guidance in ("none", "full"):
            eval_config(args, "idm", guidance)
    except ValueError as exc:
        raise SystemExit(f"ppo_ego.py: the evaluation (--eval-*, --duration): {exc}") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = train(args, out)
    return evaluate(args, path, out)


if __name__ == "__main__":
    main()
