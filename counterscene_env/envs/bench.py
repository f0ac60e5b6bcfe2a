"""Env throughput: steps per second of ``CounterScene-v0`` (``counterscene bench-env``)."""

from __future__ import annotations

import time

import numpy as np

from counterscene_env.config import check_int


def bench_env(
    config: dict | None = None,
    steps: int = 500,
    seed: int = 0,
    threads: int | None = None,
    policy: str = "random",
) -> dict:
    """Step ``CounterScene-v0`` ``steps`` times, resetting at episode ends, and time it.

    ``policy``: ``random`` (actions sampled from the action space, seeded; episodes end early
    in collisions, so resets weigh more) or ``hold`` (keep speed and course: zero
    acceleration and steering, or ``IDLE``; episodes mostly run to the time limit).

    Returns:
        ``{"steps", "episodes", "seconds", "steps_per_second", "reset_seconds_mean",
        "step_seconds_mean", "replan_share", "threads", "config"}``: ``steps_per_second``
        counts resets in (what a training loop sees); ``step_seconds_mean`` excludes them;
        ``replan_share`` is the fraction of step time spent in world-model replans.
    """
    import torch

    from counterscene_env.envs.single_agent import CounterSceneEnv

    # Everything is checked before the process-wide thread count changes.
    check_int("steps", steps, ge=1)
    check_int("seed", seed, ge=0)
    if threads is not None:
        check_int("threads", threads, ge=1)
    if policy not in ("random", "hold"):
        raise ValueError(f"policy must be 'random' or 'hold', got {policy!r}")
    env = CounterSceneEnv(config=config)
    if threads is not None:
        torch.set_num_threads(threads)
    if policy == "hold":
        from gymnasium import spaces

        space = env.action_space
        if isinstance(space, spaces.Box):
            hold = np.zeros(space.shape, space.dtype)
        else:
            hold = env.action_type.actions_indexes["IDLE"]
    rng = np.random.default_rng(seed)
    reset_times, step_times = [], []
    replan = 0.0
    start = time.perf_counter()
    t = time.perf_counter()
    env.reset(seed=seed)
    reset_times.append(time.perf_counter() - t)
    episodes = 1
    for _ in range(steps):
        t = time.perf_counter()
        if policy == "random":
            # Seeded from the run's generator at every step, as the bench's anchor must be
            # (highway-env builds a new, unseeded action space at every reset; ours keeps it).
            env.action_space.seed(int(rng.integers(2**31)))
            action = env.action_space.sample()
        else:
            action = hold
        _, _, terminated, truncated, _ = env.step(action)
        step_times.append(time.perf_counter() - t)
        if terminated or truncated:
            replan += env.loop.episodes[0].replan_seconds
            t = time.perf_counter()
            env.reset()
            reset_times.append(time.perf_counter() - t)
            episodes += 1
    seconds = time.perf_counter() - start
    replan += env.loop.episodes[0].replan_seconds
    env.close()
    return {
        "steps": steps,
        "episodes": episodes,
        "seconds": seconds,
        "steps_per_second": steps / seconds,
        "reset_seconds_mean": float(np.mean(reset_times)),
        "step_seconds_mean": float(np.mean(step_times)),
        "replan_share": replan / float(np.sum(step_times)),
        "threads": torch.get_num_threads(),
        "policy": policy,
        "config": dict(env.config),
    }
