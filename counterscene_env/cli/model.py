"""``counterscene train``, ``evaluate-model`` and ``bench``: world models."""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

from counterscene_env.cli.common import (
    SCENARIO_CHOICES,
    add_json_flag,
    add_model_flag,
    add_quiet_flag,
    add_seed_flag,
    fmt,
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
    add_quiet_flag(tr)
    tr.set_defaults(func=_cmd_train)


def _cmd_train(args: argparse.Namespace) -> int:
    from counterscene_env.world_model.config import ModelConfig, preset
    from counterscene_env.world_model.train import TrainConfig, train

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
    )
    record = train(cfg, progress=not args.quiet)
    print(json.dumps(json_safe(record)))
    return 0


def add_evaluate_model(sub) -> None:
    """Register ``counterscene evaluate-model``."""
    ev = sub.add_parser(
        "evaluate-model",
        help="open-loop prediction metrics of a world model vs constant velocity",
        description=(
            "Predict every agent of freshly generated scenes (the first --scenes safe seeds from "
            "--seed) or of a ScenarioNet directory, and report ADE/FDE at 1, 2, 3 s and the full "
            "horizon (one sample, and the best of --samples), plus the off-road rate."
        ),
    )
    ev_src = ev.add_mutually_exclusive_group(required=True)
    ev_src.add_argument("--scenario", choices=SCENARIO_CHOICES)
    ev_src.add_argument("--scenarionet", metavar="DIR", help="ScenarioNet .pkl file or directory")
    ev_src.add_argument(
        "--data", nargs="+", metavar="DIR", help="dataset directories or shards (pooled)"
    )
    ev.add_argument(
        "--scenes", type=int, default=50, help="scenes (per --data dataset; default 50)"
    )
    add_seed_flag(ev, 100000, "first seed (default 100000)")
    add_model_flag(ev)
    ev.add_argument("--samples", type=int, default=6, help="samples per scene (default 6)")
    ev.add_argument(
        "--lane-steering",
        type=int,
        metavar="N",
        help="Adam steps of final-step lane keeping (default: the model's; 0: the network alone)",
    )
    add_json_flag(ev)
    add_quiet_flag(ev)
    ev.set_defaults(func=_cmd_evaluate_model)


def _cmd_evaluate_model(args: argparse.Namespace) -> int:
    from counterscene_env.scene.datagen import iter_scenes
    from counterscene_env.world_model.evaluate import evaluate_model

    model = load_model(args.model)
    if args.lane_steering is not None:
        if args.lane_steering < 0:
            raise ValueError(f"--lane-steering must be >= 0, got {args.lane_steering}")
        model.config = model.config.replace(lane_steering=args.lane_steering)
    if args.scenario:
        from counterscene_env.scene.highway import generate

        # The first --scenes safe seeds from --seed, as `counterscene generate` picks them.
        scenes, seed = [], args.seed
        while len(scenes) < args.scenes:
            scenes.append(generate(args.scenario, seed))
            seed = scenes[-1].metadata["seed"] + 1
    else:
        if args.scenarionet:
            scenes = [s for s, _ in iter_scenes(Path(args.scenarionet))]
        else:  # the first --scenes of each dataset
            scenes = [
                s for d in args.data for s, _ in itertools.islice(iter_scenes(Path(d)), args.scenes)
            ]
    result = evaluate_model(model, scenes, args.samples, seed=0, progress=not args.quiet)
    result["source"] = (
        f"{args.scenario} seeds from {args.seed}"
        if args.scenario
        else str(args.scenarionet or args.data)
    )
    if args.json:
        print(json.dumps(json_safe(result)))
        return 0
    print(
        f"{result['scenes']} scenes, {result['agents']} agents, {result['samples']} samples, "
        f"horizon {result['horizon_s']:.1f} s ({result['source']})"
    )
    hz = list(result["model"]["ade"])
    print(f"{'':22s}" + "".join(f"{h:>8s}" for h in hz))
    rows = [
        ("model ADE [m]", result["model"]["ade"]),
        ("model FDE [m]", result["model"]["fde"]),
        (f"model minADE_{result['samples']} [m]", result["model"]["min_ade_6"]),
        ("const. vel. ADE [m]", result["constant_velocity"]["ade"]),
        ("const. vel. FDE [m]", result["constant_velocity"]["fde"]),
    ]
    for name, vals in rows:
        print(f"{name:22s}" + "".join(f"{fmt(vals[h]):>8s}" for h in hz))
    print(
        f"off-road: model {fmt(result['model']['offroad_rate'])}, constant velocity "
        f"{fmt(result['constant_velocity']['offroad_rate'])}, log {fmt(result['log_offroad_rate'])}"
    )
    return 0


def add_bench(sub) -> None:
    """Register ``counterscene bench``."""
    be = sub.add_parser(
        "bench",
        help="latency and FLOPs of one world-model sampling call",
        description=(
            "Time one sampling call (all agents of a scene, default sampler and steps) --runs "
            "times and report the median, FLOPs per denoiser forward (torch's flop counter) and "
            "the fraction of this CPU's measured matmul peak."
        ),
    )
    add_model_flag(be)
    be.add_argument("--preset", help="benchmark an untrained model of this preset instead")
    be.add_argument("--runs", type=int, default=50, help="timed calls (default 50)")
    be.add_argument("--samples", type=int, default=1, help="samples per call (default 1)")
    be.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    add_json_flag(be)
    be.set_defaults(func=_cmd_bench)


def _cmd_bench(args: argparse.Namespace) -> int:
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
