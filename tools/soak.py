"""Soak run: resident memory over a long run of an env, with resets, to catch leaks.

    OMP_NUM_THREADS=1 python tools/soak.py --kind single --steps 20000 --out reports/soak-single.json
    OMP_NUM_THREADS=1 python tools/soak.py --kind parallel --steps 20000 --out reports/soak-parallel.json

``single`` steps ``CounterScene-v0``; ``parallel`` steps the PettingZoo env with two egos (an
env step = one ``step`` call). Actions are drawn from the action spaces with a seeded
generator; every episode end resets with the next seed. RSS (``/proc/self/statm``) is sampled
every ``--every`` steps. The report gives RSS at the first reset, at the end of the warm-up
(``--warmup``, default a tenth of the steps: the first sample at or after it, whose step is
``warmup_steps``) and at the end, and the growth after warm-up in percent: a leak shows as
steady growth, the allocator's caches as a plateau.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def rss_mb() -> float:
    """Resident set size of this process [MB]."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def make(kind: str, config: dict):
    """(reset, step, close) of the env kind; step returns True at an episode end."""
    import gymnasium as gym

    import counterscene_env

    if kind == "single":
        env = gym.make("CounterScene-v0", config=config)

        def step(rng) -> bool:
            action = rng.uniform(-1, 1, size=env.action_space.shape).astype(np.float32)
            _, _, terminated, truncated, _ = env.step(action)
            return terminated or truncated

        return (lambda seed: env.reset(seed=seed)), step, env.close
    env = counterscene_env.parallel_env(num_egos=2, config=config)

    def step(rng) -> bool:
        actions = {a: rng.uniform(-1, 1, size=2).astype(np.float32) for a in env.agents}
        env.step(actions)
        return not env.agents

    return (lambda seed: env.reset(seed=seed)), step, env.close


def soak(kind: str, steps: int, every: int, warmup: int, config: dict, seed: int = 0) -> dict:
    reset, step, close = make(kind, config)
    rng = np.random.default_rng(seed)
    reset(seed)
    episodes, samples = 1, [(0, rss_mb())]
    start = time.perf_counter()
    for i in range(1, steps + 1):
        if step(rng):
            reset(seed + episodes)
            episodes += 1
        if i % every == 0:
            samples.append((i, rss_mb()))
    seconds = time.perf_counter() - start
    close()
    # The warm-up ends at the first sample not before it (the last if it outlasts the run): a
    # sample before it would count warm-up growth as growth after warm-up.
    warm = next((s for s in samples if s[0] >= warmup), samples[-1])
    end = samples[-1]
    return {
        "kind": kind,
        "steps": steps,
        "episodes": episodes,
        "config": config,
        "rss_start_mb": round(samples[0][1], 1),
        "rss_after_warmup_mb": round(warm[1], 1),
        "warmup_steps": warm[0],
        "rss_end_mb": round(end[1], 1),
        "rss_max_mb": round(max(s[1] for s in samples), 1),
        "growth_after_warmup_pct": round(100 * (end[1] - warm[1]) / warm[1], 2),
        "samples": [[i, round(m, 1)] for i, m in samples],
        "timing": {"seconds": round(seconds, 1), "steps_per_s": round(steps / seconds, 2)},
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", choices=("single", "parallel"), default="single")
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--every", type=int, default=250, help="steps between RSS samples")
    parser.add_argument("--warmup", type=int, help="warm-up steps (default: steps / 10)")
    parser.add_argument("--config", default='{"scenario": "intersection", "duration": 5.0}')
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="also write the report here (JSON)")
    args = parser.parse_args()
    warmup = args.warmup if args.warmup is not None else args.steps // 10
    report = soak(args.kind, args.steps, args.every, warmup, json.loads(args.config), args.seed)
    text = json.dumps(report)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    summary = {k: v for k, v in report.items() if k != "samples"}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
