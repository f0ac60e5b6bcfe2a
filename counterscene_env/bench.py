"""The one benchmark (``counterscene bench``): every speed figure in one process and one run, so
that ratios are honest on a noisy machine.

In order, on the same machine state:

1. **Anchor**: highway-env's newest ``intersection`` env with its IDM traffic, policy and
   simulation at 10 Hz (the frequency of our scenes), random continuous actions: env steps/s,
   timed before and after step 2 (the same episodes; the recorder process idle) and
   averaged, so that a machine that speeds up or slows down during the run moves both.
2. **Env**: ``CounterScene-v0`` with its default config (``envs/bench.py``, random actions,
   resets included): env steps/s and the share of step time spent in world-model replans.
3. **Replans**: every replan of step 2 timed on its own by the closed loop: median and p95 [ms].
   FLOPs of one replan are counted with torch's flop counter (matmuls and attention only:
   element-wise work is not counted, so the fraction of peak is a lower bound), for an
   episode's first replan (from pure noise) and for a warm-started one (every later replan,
   so the median's), and the warm one is set against the median replan time and the CPU's
   matmul peak (``world_model/bench.py``).
4. **Stress**: seconds per ``counterscene stress`` episode (intersection, IDM planner, full
   guidance, the default batch).
5. **Vector env**: ``gymnasium.make_vec("CounterScene-v0", num_envs=N)`` for N = 4, 16, 64
   (one world-model call per replan for all N envs, ``envs/vector.py``), random actions,
   autoresets included: aggregate env steps/s over all N envs, after the first reset (timed
   apart); once with the default config (every reset records a fresh highway-env scene) and
   once on a stored set of generated scenes (what a training run reads: a reset loads one),
   there also with the envs split over ``STORED_WORKERS`` processes (``workers=2``).
6. **Memory**: peak resident set size of the process [MB] (``getrusage``).

The model's own sampling call (``world_model/bench.py``, the previous ``bench``) is reported
beside them under ``"model"``.
"""

from __future__ import annotations

import resource
import statistics
import time
from typing import Any

import numpy as np

#: Scenes of the stored scene set the vector env is also timed on.
STORED_SCENES = 16
#: Processes the vector env on stored scenes is also split over (``envs/sharded.py``).
STORED_WORKERS = 2
#: highway-env's anchor env and the frequencies it runs at [Hz].
ANCHOR_ENV = "intersection-v2"
ANCHOR_FREQUENCY = 10


def bench_highway_env(steps: int, seed: int = 0) -> dict[str, Any]:
    """Steps per second of highway-env's IDM traffic env (module docstring, item 1)."""
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the envs)

    env = gym.make(
        ANCHOR_ENV,
        config={"policy_frequency": ANCHOR_FREQUENCY, "simulation_frequency": ANCHOR_FREQUENCY},
    )
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    start, episodes = time.perf_counter(), 1
    for _ in range(steps):
        # Seeded at every step, as ours below: each reset builds a new, unseeded action space.
        env.action_space.seed(int(rng.integers(2**31)))
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
            episodes += 1
    seconds = time.perf_counter() - start
    env.close()
    return {"env": ANCHOR_ENV, "steps": steps, "episodes": episodes, "steps_per_s": steps / seconds}


def bench_env_and_replans(steps: int, seed: int = 0) -> dict[str, Any]:
    """``CounterScene-v0`` steps/s and the time of each replan it made (items 2 and 3)."""
    from counterscene_env.envs.single_agent import CounterSceneEnv

    env = CounterSceneEnv()
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    replans: list[float] = []
    replan_s = step_s = 0.0
    start, episodes = time.perf_counter(), 1
    for _ in range(steps):
        ep = env.loop.episodes[0]
        n, before = ep.replans, ep.replan_seconds
        # Seeded at every step, as the anchor above (the same actions as earlier benches).
        env.action_space.seed(int(rng.integers(2**31)))
        action = env.action_space.sample()
        t = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        step_s += time.perf_counter() - t
        if ep.replans > n:  # the loop times its own replans: read its figure
            replans.append((ep.replan_seconds - before) / (ep.replans - n))
            replan_s += ep.replan_seconds - before
        if terminated or truncated:
            env.reset()
            episodes += 1
    seconds = time.perf_counter() - start
    flops = _replan_flops(env)
    env.close()
    return {
        "steps": steps,
        "episodes": episodes,
        "steps_per_s": steps / seconds,
        "replan_share": replan_s / step_s if step_s else float("nan"),
        "replan_s": replans,
        "flops_per_replan": flops,
    }


def _replan_flops(env) -> dict[str, int]:
    """FLOPs of a fresh episode's first replan (``"cold"``: from pure noise) and of its
    second (``"warm"``: warm-started, as every later replan is, ``SimConfig.warm_start_steps``).
    """
    from torch.utils.flop_counter import FlopCounterMode

    env.reset(seed=12345)
    ep = env.loop.episodes[0]
    found: list[int] = []
    for _ in range(100):
        n = ep.replans
        counter = FlopCounterMode(display=False)
        with counter:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if ep.replans > n:
            found.append(int(counter.get_total_flops()))
            if len(found) == 2:
                break
        if terminated or truncated:
            break
    found += [0] * (2 - len(found))
    return {"cold": found[0], "warm": found[1]}


def bench_stress(episodes: int, model_dir: str = "default", seed: int = 100000) -> dict[str, Any]:
    """Seconds per stress episode: intersection, IDM, full guidance (item 4)."""
    from counterscene_env.stress import StressConfig, run_episodes
    from counterscene_env.world_model import load_model

    config = StressConfig(scenario="intersection", episodes=episodes, seed=seed, planner="idm")
    model = load_model(model_dir)
    start = time.perf_counter()
    run_episodes(model, config, progress=False)
    return {"episodes": episodes, "s_per_episode": (time.perf_counter() - start) / episodes}


def bench_vector_env(
    num_envs: int, steps: int, seed: int = 0, scenario: str | None = None, workers: int = 1
) -> dict[str, Any]:
    """Aggregate env steps/s of the batched vector env of ``num_envs`` envs over ``steps``
    vector steps (item 5); ``scenario``: a stored scene set instead of fresh recordings;
    ``workers``: processes the envs are split over (``envs/sharded.py``)."""
    from counterscene_env.envs.sharded import vector_env

    # What gymnasium.make_vec("CounterScene-v0", num_envs=N, workers=W, config=...) makes.
    venv = vector_env(
        num_envs, workers, config=None if scenario is None else {"scenario": scenario}
    )
    venv.action_space.seed(seed)
    start = time.perf_counter()
    venv.reset(seed=seed)
    reset_s = time.perf_counter() - start
    start, ends = time.perf_counter(), 0
    for _ in range(steps):
        _, _, terminated, truncated, _ = venv.step(venv.action_space.sample())
        ends += int((terminated | truncated).sum())
    seconds = time.perf_counter() - start
    venv.close()
    return {
        "num_envs": num_envs,
        "workers": workers,
        "vector_steps": steps,
        "episode_ends": ends,
        "first_reset_s": reset_s,
        "steps_per_s": num_envs * steps / seconds,
    }


def _stored_vector_runs(sizes: tuple[int, ...], steps: int, seed: int) -> dict[str, Any]:
    """The vector env on stored scenes (what a training run reads, ``agents/ppo_ego.py``):
    up to ``STORED_SCENES`` intersection scenes generated into a temporary dataset first (timed
    apart), so that resets load a scene instead of recording one."""
    import tempfile

    from counterscene_env.scene.datagen import generate_dataset

    if not sizes:
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        scenes = min(STORED_SCENES, max(sizes))
        generate_dataset(tmp, "intersection", scenes, seed=seed, progress=False)
        generate_s = time.perf_counter() - start
        runs = {str(n): bench_vector_env(n, steps, seed, scenario=tmp) for n in sizes}
        sharded = {
            str(n): bench_vector_env(n, steps, seed, scenario=tmp, workers=STORED_WORKERS)
            for n in sizes
            if n >= STORED_WORKERS
        }
    return {"scenes": scenes, "generate_s": generate_s, "runs": runs, "workers_runs": sharded}


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far [MB] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _wait_for_recorder(timeout: float = 10.0) -> None:
    """Wait until the background recorder has nothing queued or in progress (at most
    ``timeout`` s): a recording left from step 2 would take a core from the anchor."""
    from counterscene_env.scene import prefetch

    end = time.perf_counter() + timeout
    while prefetch.recording() and time.perf_counter() < end:
        time.sleep(0.01)


def run_bench(
    steps: int = 300,
    episodes: int = 4,
    model_runs: int = 20,
    seed: int = 0,
    model_dir: str = "default",
    vector_envs: tuple[int, ...] = (4, 16, 64),
    vector_steps: int = 50,
) -> dict[str, Any]:
    """Every figure of the module docstring, in one process; the JSON of ``bench --json``.

    Args:
        steps: env steps of the anchor and of ``CounterScene-v0`` each.
        episodes: stress episodes.
        model_runs: timed sampling calls of the model alone.
        seed: seeds the actions and resets.
        model_dir: the world model of the stress run and the model figures (the env uses
            its config's model, the shipped one by default).
        vector_envs: the vector env's sizes (empty: skip item 5).
        vector_steps: vector steps per size.
    """
    from counterscene_env.world_model import load_model
    from counterscene_env.world_model.bench import bench_model, matmul_peak_gflops

    before = bench_highway_env(steps, seed)
    env = bench_env_and_replans(steps, seed)
    _wait_for_recorder()
    after = bench_highway_env(steps, seed)
    mean = (before["steps_per_s"] + after["steps_per_s"]) / 2
    anchor = {
        **before,
        "steps_per_s": mean,
        "runs_steps_per_s": [before["steps_per_s"], after["steps_per_s"]],
    }
    stress = bench_stress(episodes, model_dir)
    vector = {str(n): bench_vector_env(n, vector_steps, seed) for n in vector_envs}
    stored = _stored_vector_runs(vector_envs, vector_steps, seed)
    model = bench_model(load_model(model_dir), runs=model_runs)
    peak = matmul_peak_gflops()
    times = sorted(env.pop("replan_s"))
    median = statistics.median(times) if times else float("nan")
    flops = env.pop("flops_per_replan")
    achieved = flops["warm"] / median / 1e9 if times else float("nan")
    return {
        "highway_env_steps_per_s": anchor["steps_per_s"],
        "env_steps_per_s": env["steps_per_s"],
        "env_vs_highway_env": env["steps_per_s"] / anchor["steps_per_s"],
        "replan_share": env["replan_share"],
        "replan_ms": {
            "median": 1000 * median,
            "p95": 1000 * float(np.percentile(times, 95)) if times else float("nan"),
            "count": len(times),
        },
        "stress_s_per_episode": stress["s_per_episode"],
        "vector_env_steps_per_s": {n: v["steps_per_s"] for n, v in vector.items()},
        "vector_env_vs_highway_env": {
            n: v["steps_per_s"] / anchor["steps_per_s"] for n, v in vector.items()
        },
        "vector_env_stored_scenes_steps_per_s": {
            n: v["steps_per_s"] for n, v in stored.get("runs", {}).items()
        },
        "vector_env_stored_scenes_workers_steps_per_s": {
            n: v["steps_per_s"] for n, v in stored.get("workers_runs", {}).items()
        },
        "flops_per_replan": flops["warm"],
        "flops_per_cold_replan": flops["cold"],
        "achieved_gflops": achieved,
        "peak_gflops": peak,
        "peak_fraction": achieved / peak,
        "peak_rss_mb": peak_rss_mb(),
        "runs": {
            "anchor": anchor,
            "env": env,
            "stress": stress,
            "vector": vector,
            "vector_stored_scenes": stored,
        },
        "model": model,
    }
