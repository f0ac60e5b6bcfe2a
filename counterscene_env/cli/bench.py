"""``counterscene bench`` and ``bench-env``: how fast the model, the env and stress runs are."""

from __future__ import annotations

import argparse
import json

from counterscene_env.cli.common import (
    add_json_flag,
    add_model_flag,
    add_seed_flag,
    int_at_least,
    json_safe,
    load_model,
    parse_overrides,
)


def add_bench(sub) -> None:
    """Register ``counterscene bench``."""
    be = sub.add_parser(
        "bench",
        help="every speed figure in one run: highway-env's anchor, the env, replans, stress, RSS",
        description=(
            "One process, one run: highway-env's intersection with IDM traffic at 10 Hz (the "
            "anchor), CounterScene-v0 with its default config (env steps/s, replan latency, "
            "FLOPs per replan against this CPU's measured peak), seconds per stress episode, peak "
            "RSS, and the model's sampling call alone. With --model-only (or --preset) only the "
            "sampling call is timed, as the earlier `bench` did."
        ),
    )
    add_model_flag(be)
    be.add_argument("--preset", help="time an untrained model of this preset (model only)")
    be.add_argument("--model-only", action="store_true", help="only the model's sampling call")
    be.add_argument(
        "--runs", type=int_at_least(1), default=50, help="timed sampling calls (default 50)"
    )
    be.add_argument(
        "--samples", type=int_at_least(1), default=1, help="samples per call (default 1)"
    )
    be.add_argument(
        "--threads", type=int_at_least(1), help="torch threads (default: torch's choice)"
    )
    # The whole-run flags default to None so that --model-only can refuse them when given
    # (they would be ignored); _full_bench fills in FULL_BENCH_DEFAULTS.
    be.add_argument("--steps", type=int_at_least(1), help="env steps of each env (default 300)")
    be.add_argument("--episodes", type=int_at_least(1), help="stress episodes (default 4)")
    be.add_argument(
        "--vector-envs",
        help="sizes of the batched vector env to time, comma-separated (default 4,16,64; "
        "'' to skip)",
    )
    be.add_argument(
        "--vector-steps", type=int_at_least(1), help="vector steps of each size (default 50)"
    )
    add_json_flag(be)
    be.set_defaults(func=_cmd_bench)


#: The defaults of the flags that only the whole run reads.
FULL_BENCH_DEFAULTS = {"steps": 300, "episodes": 4, "vector_envs": "4,16,64", "vector_steps": 50}


def _cmd_bench(args: argparse.Namespace) -> int:
    if not (args.model_only or args.preset):
        for key, value in FULL_BENCH_DEFAULTS.items():
            if getattr(args, key) is None:
                setattr(args, key, value)
        return _full_bench(args)
    given = [
        f"--{k.replace('_', '-')}" for k in FULL_BENCH_DEFAULTS if getattr(args, k) is not None
    ]
    if given:
        raise ValueError(
            f"{', '.join(given)}: only the whole run reads this; --model-only and --preset time "
            "the sampling call alone (its flags: --runs, --samples, --threads)"
        )
    from counterscene_env.world_model.bench import bench_model

    if args.preset:
        if args.model != "default":
            raise ValueError("--preset times an untrained model of that preset: drop --model")
        from counterscene_env.world_model.config import preset
        from counterscene_env.world_model.model import WorldModel

        model, name = WorldModel(preset(args.preset)).eval(), f"preset {args.preset} (untrained)"
    else:
        model, name = load_model(args.model), args.model
    result = bench_model(model, runs=args.runs, samples=args.samples, threads=args.threads)
    result["model"] = name
    if args.json:
        print(json.dumps(json_safe(result)))
        return 0
    print(
        f"{name}: {result['agents']} agents, {result['sampling_steps']} {result['sampler']} steps, "
        f"{result['samples']} sample(s), {result['threads']} threads"
    )
    print(
        f"  sampling call: median {result['latency_median_s'] * 1000:.1f} ms over {result['runs']} "
        f"runs (p90 {result['latency_p90_s'] * 1000:.1f} ms)"
    )
    print(
        f"  denoiser forward: {result['flops_per_forward'] / 1e9:.3f} GFLOP; "
        f"{result['flops_per_call'] / 1e9:.2f} GFLOP per call"
    )
    print(
        f"  achieved {result['achieved_gflops']:.2f} GFLOP/s of a measured matmul peak "
        f"{result['peak_gflops']:.1f} GFLOP/s ({100 * result['peak_fraction']:.1f} %)"
    )
    return 0


def _full_bench(args: argparse.Namespace) -> int:
    """``counterscene bench`` without ``--model-only``: ``counterscene_env/bench.py``."""
    import torch

    from counterscene_env.bench import STORED_WORKERS, run_bench

    try:
        sizes = tuple(int(n) for n in args.vector_envs.split(",") if n.strip())
    except ValueError:
        raise ValueError(
            f"--vector-envs must be comma-separated ints, got {args.vector_envs!r}"
        ) from None
    if any(n < 1 for n in sizes):
        raise ValueError(f"--vector-envs sizes must be >= 1, got {args.vector_envs!r}")
    if args.threads:
        torch.set_num_threads(args.threads)
    r = run_bench(
        args.steps,
        args.episodes,
        args.runs,
        model_dir=args.model,
        vector_envs=sizes,
        vector_steps=args.vector_steps,
    )
    if args.json:
        print(json.dumps(json_safe(r)))
        return 0
    print(f"torch threads {torch.get_num_threads()}; {args.steps} env steps each")
    before, after = r["runs"]["anchor"]["runs_steps_per_s"]
    print(
        f"  highway-env {r['runs']['anchor']['env']} (IDM, 10 Hz): "
        f"{r['highway_env_steps_per_s']:.1f} steps/s (before and after ours: {before:.1f}, "
        f"{after:.1f})"
    )
    print(
        f"  CounterScene-v0 (default config): {r['env_steps_per_s']:.1f} steps/s = "
        f"{r['env_vs_highway_env']:.2f}x highway-env; {100 * r['replan_share']:.0f} % of step "
        "time in replans"
    )
    ms = r["replan_ms"]
    print(
        f"  replan: median {ms['median']:.0f} ms, p95 {ms['p95']:.0f} ms over {ms['count']}; "
        f"{r['flops_per_replan'] / 1e9:.2f} GFLOP warm-started "
        f"({r['flops_per_cold_replan'] / 1e9:.2f} from noise) = {r['achieved_gflops']:.1f} GFLOP/s, "
        f"{100 * r['peak_fraction']:.1f} % of the {r['peak_gflops']:.0f} GFLOP/s matmul peak"
    )
    print(
        f"  stress (intersection, IDM, full guidance): {r['stress_s_per_episode']:.2f} s per "
        f"episode over {args.episodes}"
    )
    anchor = r["highway_env_steps_per_s"]
    stored = r["runs"]["vector_stored_scenes"]
    for label, runs in [
        ("fresh scenes", r["runs"]["vector"]),
        ("stored scenes", stored.get("runs", {})),
        (f"stored scenes, {STORED_WORKERS} workers", stored.get("workers_runs", {})),
    ]:
        for n, v in runs.items():
            print(
                f"  vector env, {n} envs, {label}: {v['steps_per_s']:.1f} env steps/s in total "
                f"= {v['steps_per_s'] / anchor:.2f}x highway-env ({v['vector_steps']} vector "
                f"steps, {v['episode_ends']} episode ends; first reset {v['first_reset_s']:.1f} s)"
            )
    if stored:
        print(f"    ({stored['scenes']} stored scenes generated in {stored['generate_s']:.1f} s)")
    m = r["model"]
    print(
        f"  model sampling call alone: median {1000 * m['latency_median_s']:.0f} ms "
        f"({m['sampling_steps']} {m['sampler']} steps, {m['samples']} sample)"
    )
    print(f"  peak RSS {r['peak_rss_mb']:.0f} MB")
    return 0


def add_bench_env(sub) -> None:
    """Register ``counterscene bench-env``."""
    bv = sub.add_parser(
        "bench-env",
        help="steps per second of CounterScene-v0",
        description=(
            "Step CounterScene-v0 --steps times with seeded random actions (resetting at "
            "episode ends) and report steps per second, with and without resets."
        ),
    )
    bv.add_argument("--scenario", default="intersection", help="scenario (default intersection)")
    bv.add_argument("--steps", type=int_at_least(1), default=500, help="env steps (default 500)")
    add_seed_flag(bv, 0, "seed (default 0)")
    bv.add_argument(
        "--threads", type=int_at_least(1), help="torch threads (default: torch's choice)"
    )
    bv.add_argument(
        "--policy",
        default="random",
        choices=("random", "hold"),
        help="random actions, or hold speed and course (default random)",
    )
    bv.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="other config keys (JSON values), e.g. policy_frequency=2 guidance=none",
    )
    add_json_flag(bv)
    bv.set_defaults(func=_cmd_bench_env)


def _cmd_bench_env(args: argparse.Namespace) -> int:
    from counterscene_env.envs.bench import bench_env

    config = {"scenario": args.scenario, **parse_overrides(args.set)}
    result = bench_env(
        config, steps=args.steps, seed=args.seed, threads=args.threads, policy=args.policy
    )
    if args.json:
        print(json.dumps(json_safe(result)))
        return 0
    c = result["config"]
    print(
        f"CounterScene-v0 {c['scenario']}, guidance {c['guidance']}, {c['num_samples']} samples, "
        f"policy {c['policy_frequency']} Hz, {result['threads']} torch threads, "
        f"{result['policy']} actions"
    )
    print(
        f"  {result['steps_per_second']:.1f} steps/s over {result['steps']} steps and "
        f"{result['episodes']} episodes (resets included)"
    )
    print(
        f"  step {1000 * result['step_seconds_mean']:.1f} ms mean ({100 * result['replan_share']:.0f} % "
        f"world-model replans), reset {result['reset_seconds_mean']:.2f} s mean"
    )
    return 0
