"""``counterscene train`` and ``bench``: training a world model and timing it."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from counterscene_env.cli.common import (
    add_json_flag,
    add_model_flag,
    add_quiet_flag,
    add_seed_flag,
    int_at_least,
    json_safe,
    load_model,
    parse_overrides,
)


def add_train(sub) -> None:
    """Register ``counterscene train``."""
    tr = sub.add_parser(
        "train",
        help="train a world model (resumable)",
        description=(
            "Train on dataset directories and write model.safetensors + config.json (the EMA "
            "weights), last.pt (to resume) and log.jsonl into --out. Rerun the same command to "
            "continue; a larger --steps extends the run."
        ),
    )
    tr.add_argument("--data", required=True, nargs="+", metavar="DIR", help="dataset directories")
    tr.add_argument("--out", required=True, metavar="DIR", help="output directory")
    tr.add_argument("--preset", default="default", help="model preset: default or paper")
    tr.add_argument("--steps", type=int, default=20000, help="optimiser steps (default 20000)")
    tr.add_argument("--batch-size", type=int, default=32, help="windows per step (default 32)")
    tr.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (default 1e-4)")
    tr.add_argument("--ema-decay", type=float, default=0.995, help="EMA decay (default 0.995)")
    tr.add_argument("--ema-start", type=int, default=4000, help="first EMA step (default 4000)")
    tr.add_argument(
        "--lr-decay-start",
        type=int,
        help="step from which the learning rate falls linearly to lr/10 at --steps (default: none)",
    )
    tr.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    add_seed_flag(tr, 0, "seed (default 0)")
    tr.add_argument("--device", default="cpu", help="torch device (default cpu)")
    tr.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a model config field of the preset (repeatable), e.g. --set d_model=96",
    )
    tr.add_argument(
        "--init", metavar="DIR", help="start from this model's weights ('default': shipped)"
    )
    tr.add_argument(
        "--off-lane-weight",
        type=float,
        default=0.0,
        help="weight of the loss term on predicted points off the lanes the log follows "
        "(default 0: left out; the shipped model used 1.0)",
    )
    tr.add_argument(
        "--off-lane-by-course",
        action="store_true",
        help="measure the off-lane term against the lanes going the prediction's way (a lane "
        "going against it counts 10 m farther, as in lane keeping)",
    )
    tr.add_argument(
        "--overlap-weight",
        type=float,
        default=0.0,
        help="weight of the loss term on predicted boxes running into each other where the "
        "log's do not (default 0: left out)",
    )
    tr.add_argument(
        "--parked-cars",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="share of the training windows that get 1-3 parked cars beside their lanes, "
        "standing still while the logged traffic passes (default 0: none; "
        "docs/world_model.md)",
    )
    tr.add_argument(
        "--min-future",
        type=int,
        metavar="STEPS",
        help="future steps a window needs inside its log (default: the whole horizon); fewer "
        "trains on the ends of short real logs, the missing steps masked",
    )
    tr.add_argument(
        "--agent-centred",
        nargs="+",
        default=[],
        metavar="DIR",
        help="those --data datasets whose windows centre on every vehicle in turn, not on the "
        "ego alone (real recordings: most of their vehicles are never the ego)",
    )
    tr.add_argument(
        "--data-weights",
        nargs="+",
        type=float,
        metavar="W",
        help="share of each --data dataset in every batch, one value per dataset (default: "
        "in proportion to its windows)",
    )
    add_quiet_flag(tr)
    tr.set_defaults(func=_cmd_train)


def _cmd_train(args: argparse.Namespace) -> int:
    from counterscene_env.world_model.config import ModelConfig, preset
    from counterscene_env.world_model.train import train
    from counterscene_env.world_model.train_config import TrainConfig

    overrides = parse_overrides(args.set)
    ModelConfig.from_mapping({**preset(args.preset).to_dict(), **overrides})  # validate early
    for d in args.data:
        if not Path(d).exists():
            raise FileNotFoundError(f"no dataset at {d}")
    cfg = TrainConfig(
        data=tuple(args.data),
        out=args.out,
        preset=args.preset,
        model_overrides=overrides,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        ema_decay=args.ema_decay,
        ema_start=args.ema_start,
        lr_decay_start=args.lr_decay_start,
        checkpoint_every=args.checkpoint_every,
        seed=args.seed,
        device=args.device,
        init=args.init,
        off_lane_weight=args.off_lane_weight,
        overlap_weight=args.overlap_weight,
        off_lane_by_course=args.off_lane_by_course,
        min_future_steps=args.min_future,
        agent_centred=tuple(args.agent_centred),
        data_weights=None if args.data_weights is None else tuple(args.data_weights),
        parked_cars=args.parked_cars,
    )
    record = train(cfg, progress=not args.quiet)
    print(json.dumps(json_safe(record)))
    return 0


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
    be.add_argument(
        "--steps", type=int_at_least(1), default=300, help="env steps of each env (default 300)"
    )
    be.add_argument(
        "--episodes", type=int_at_least(1), default=4, help="stress episodes (default 4)"
    )
    be.add_argument(
        "--vector-envs",
        default="4,16,64",
        help="sizes of the batched vector env to time, comma-separated (default 4,16,64; "
        "'' to skip)",
    )
    be.add_argument(
        "--vector-steps",
        type=int_at_least(1),
        default=50,
        help="vector steps of each size (default 50)",
    )
    add_json_flag(be)
    be.set_defaults(func=_cmd_bench)


def _cmd_bench(args: argparse.Namespace) -> int:
    if not (args.model_only or args.preset):
        return _full_bench(args)
    from counterscene_env.world_model.bench import bench_model

    if args.preset:
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
