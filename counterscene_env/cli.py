"""The ``counterscene`` command.

Subcommands import what they need when they run, so ``counterscene --help`` is instant.

- ``generate``: build a dataset directory of scenes (highway-env traffic or ScenarioNet logs).
- ``inspect``: load scenes and report their size, timing and factual metrics.
- ``train``: train a world model on dataset directories (resumable).
- ``evaluate-model``: open-loop ADE/FDE/off-road of a world model vs constant velocity.
- ``bench``: latency and FLOPs of a world model's sampling call.
- ``bench-env``: steps per second of ``CounterScene-v0``.
- ``stress``: stress-test an ego planner against guided world-model traffic (paper's table).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

from counterscene_env.config import Scenario  # a light module: --help stays instant


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        # Errors users can act on: one clear line, no traceback.
        print(f"counterscene {args.command}: error: {exc}", file=sys.stderr)
        return 1


def _parser() -> argparse.ArgumentParser:
    """The ``counterscene`` argument parser with one subparser per command."""
    from importlib.metadata import version

    __version__ = version("counterscene-env")
    parser = argparse.ArgumentParser(
        prog="counterscene",
        description="CounterScene: adversarial multi-agent driving scenes and environments.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_generate(sub)
    _add_inspect(sub)
    _add_train(sub)
    _add_evaluate_model(sub)
    _add_bench(sub)
    _add_bench_env(sub)
    _add_stress(sub)
    return parser


#: The highway-env roads ``generate`` and ``evaluate-model`` can record scenes on.
_SCENARIO_CHOICES = Scenario.values()


def _add_model_flag(p: argparse.ArgumentParser) -> None:
    """Add ``--model DIR`` (a world-model checkpoint directory; default: the shipped one)."""
    p.add_argument("--model", default="default", help="model directory (default: shipped)")


def _add_json_flag(p: argparse.ArgumentParser, help: str = "print one JSON object") -> None:
    """Add ``--json`` (print the result as one JSON object instead of a table)."""
    p.add_argument("--json", action="store_true", help=help)


def _add_quiet_flag(p: argparse.ArgumentParser) -> None:
    """Add ``--quiet`` (no progress bar)."""
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_seed_flag(p: argparse.ArgumentParser, default: int, help: str) -> None:
    """Add ``--seed N`` (an int) with the given default and help text."""
    p.add_argument("--seed", type=int, default=default, help=help)


def _add_generate(sub) -> None:
    """Register ``counterscene generate``."""
    gen = sub.add_parser(
        "generate",
        help="generate a dataset of scenes (highway-env traffic or ScenarioNet logs)",
        description=(
            "Write scenes as compressed shards plus manifest.json into --out. Highway-env: the "
            "first --scenes safe seeds from --seed. Resumable: rerun the same command."
        ),
    )
    src = gen.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--scenario",
        choices=_SCENARIO_CHOICES,
        help="highway-env road to record traffic on",
    )
    src.add_argument("--from-scenarionet", metavar="DIR", help="convert ScenarioNet .pkl files")
    gen.add_argument("--scenes", type=int, default=100, help="scenes to generate (default 100)")
    _add_seed_flag(gen, 0, "first seed (default 0)")
    gen.add_argument("--out", required=True, metavar="DIR", help="output dataset directory")
    gen.add_argument("--duration", type=float, default=13.0, help="log length in s (default 13)")
    gen.add_argument("--shard-size", type=int, default=50, help="seeds or files per shard")
    gen.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    _add_quiet_flag(gen)
    gen.set_defaults(func=_cmd_generate)


def _add_inspect(sub) -> None:
    """Register ``counterscene inspect``."""
    ins = sub.add_parser(
        "inspect",
        help="report size, timing and factual metrics of scenes",
        description=(
            "PATH: a dataset directory, a shard .npz, a ScenarioNet .pkl, or a directory of .pkl "
            "files. Factual metrics are computed over the whole log (every step after the first)."
        ),
    )
    ins.add_argument("path", help="scenes to inspect")
    _add_json_flag(ins)
    ins.add_argument(
        "--smooth",
        type=float,
        default=0.0,
        help="acceleration smoothing window for HBR, s (0.5 suits nuScenes' interpolated logs)",
    )
    ins.set_defaults(func=_cmd_inspect)


def _add_train(sub) -> None:
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
    _add_seed_flag(tr, 0, "seed (default 0)")
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
    _add_quiet_flag(tr)
    tr.set_defaults(func=_cmd_train)


def _add_evaluate_model(sub) -> None:
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
    ev_src.add_argument("--scenario", choices=_SCENARIO_CHOICES)
    ev_src.add_argument("--scenarionet", metavar="DIR", help="ScenarioNet .pkl file or directory")
    ev_src.add_argument(
        "--data", nargs="+", metavar="DIR", help="dataset directories or shards (pooled)"
    )
    ev.add_argument(
        "--scenes", type=int, default=50, help="scenes (per --data dataset; default 50)"
    )
    _add_seed_flag(ev, 100000, "first seed (default 100000)")
    _add_model_flag(ev)
    ev.add_argument("--samples", type=int, default=6, help="samples per scene (default 6)")
    ev.add_argument(
        "--lane-steering",
        type=int,
        metavar="N",
        help="Adam steps of final-step lane keeping (default: the model's; 0: the network alone)",
    )
    _add_json_flag(ev)
    _add_quiet_flag(ev)
    ev.set_defaults(func=_cmd_evaluate_model)


def _add_bench(sub) -> None:
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
    _add_model_flag(be)
    be.add_argument("--preset", help="benchmark an untrained model of this preset instead")
    be.add_argument("--runs", type=int, default=50, help="timed calls (default 50)")
    be.add_argument("--samples", type=int, default=1, help="samples per call (default 1)")
    be.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    _add_json_flag(be)
    be.set_defaults(func=_cmd_bench)


def _add_bench_env(sub) -> None:
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
    bv.add_argument("--steps", type=int, default=500, help="env steps (default 500)")
    _add_seed_flag(bv, 0, "seed (default 0)")
    bv.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
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
    _add_json_flag(bv)
    bv.set_defaults(func=_cmd_bench_env)


def _add_stress(sub) -> None:
    """Register ``counterscene stress``."""
    st = sub.add_parser(
        "stress",
        help="stress-test an ego planner against guided world-model traffic",
        description=(
            "Run --episodes closed-loop episodes (scene and noise of episode i from seed "
            "--seed + i): the world model drives traffic, --planner drives the ego, and the "
            "adversary picked by --selector is steered by --guidance. Prints the paper's table "
            "row: ADE, FDE, ORR, HBR, CR for 1-4 s, 5-7 s, 8-10 s and per second."
        ),
    )
    st.add_argument(
        "--scenario",
        required=True,
        help="highway, merge, intersection, roundabout, or scenarionet:DIR",
    )
    st.add_argument("--episodes", type=int, default=50, help="episodes (default 50)")
    _add_seed_flag(st, 100000, "seed of episode 0 (default 100000)")
    st.add_argument(
        "--planner",
        default="idm",
        help=(
            "ego planner: idm, idm_yield, constant_velocity, log, or sb3:PATH.zip (a "
            "Stable-Baselines3 policy, run through CounterScene-v0) (default idm)"
        ),
    )
    st.add_argument(
        "--env-config",
        help=(
            "sb3 planners: JSON object (or a .json file) of CounterScene-v0 config keys, e.g. "
            "the policy's observation and action; default: PATH.env.json next to the zip"
        ),
    )
    _add_sim_flags(st)
    st.add_argument(
        "--batch",
        type=int,
        default=4,
        help="episodes advanced together (4; sb3 planners run one at a time)",
    )
    _add_model_flag(st)
    _add_json_flag(st, "print the summary as one JSON object")
    st.add_argument("--out", help="also write DIR/metrics.json and DIR/episodes.jsonl")
    _add_quiet_flag(st)
    st.set_defaults(func=_cmd_stress)


#: Spellings of the closed-loop flags kept from before they were derived from SimConfig.
_SIM_ALIASES = {"num_samples": ["--samples"], "selection_source": ["--source"]}
_SIM_SWITCHES = {
    "strict_gates": [
        (
            "--paper-gates",
            False,
            "the paper's selection (no strict gates: parked or far adversaries allowed)",
        )
    ],
    "traffic_yields": [
        ("--no-yield", False, "traffic follows its plans to the letter (no yielding rule)")
    ],
}  # --no-road-keeping is the generated negation of --road-keeping


def _add_sim_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per ``SimConfig`` field (``--field-name``, help from its docstring), plus the
    documented short spellings; :func:`_sim_config` turns them into a ``SimConfig``."""
    from counterscene_env.config import add_arguments
    from counterscene_env.sim.config import SimConfig

    group = parser.add_argument_group("closed-loop settings (SimConfig; unset: its default)")
    add_arguments(group, SimConfig, _SIM_ALIASES, _SIM_SWITCHES)


def _cmd_bench_env(args: argparse.Namespace) -> int:
    from counterscene_env.envs.bench import bench_env

    config = {"scenario": args.scenario, **_parse_overrides(args.set)}
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


def _sim_config(args: argparse.Namespace):
    """The ``SimConfig`` of the given closed-loop flags (the rest at their defaults)."""
    from counterscene_env.config import parsed_fields
    from counterscene_env.sim.config import SimConfig

    return SimConfig(**parsed_fields(args, SimConfig))


def _cmd_stress(args: argparse.Namespace) -> int:
    from counterscene_env.stress import (
        SB3_PREFIX,
        StressConfig,
        run_episodes,
        run_policy_episodes,
        summarize,
        write_outputs,
    )

    sim = _sim_config(args)
    config = StressConfig(
        scenario=args.scenario,
        episodes=args.episodes,
        seed=args.seed,
        planner=args.planner,
        sim=sim,
        batch=args.batch,
    )
    if args.planner.startswith(SB3_PREFIX):
        env_config = None
        if args.env_config:
            text = args.env_config
            if not text.lstrip().startswith("{"):
                text = Path(text).read_text()
            env_config = json.loads(text)
        records = run_policy_episodes(config, args.model, env_config, progress=not args.quiet)
    else:
        if args.env_config:
            raise ValueError("--env-config applies to sb3:PATH.zip planners only")
        model = _load_model(args.model)
        records = run_episodes(model, config, progress=not args.quiet)
    summary = summarize(records, config)
    if args.out:
        write_outputs(args.out, summary, records)
    if args.json:
        print(json.dumps(json_safe(summary)))
        return 0
    print(
        f"{summary['episodes']} episodes of {args.scenario}, planner {args.planner}, selector "
        f"{sim.selector}, guidance {sim.guidance} (source {sim.selection_source}, "
        f"{sim.num_samples} samples)"
    )
    print(f"{'':8s}" + "".join(f"{k:>10s}" for k in ("ADE", "FDE", "ORR", "HBR", "CR")))
    for name, row in summary["horizons"].items():
        print(
            f"{name:8s}"
            + "".join(f"{_fmt(row[k]):>10s}" for k in ("ADE", "FDE", "ORR", "HBR", "CR"))
        )
    print(
        f"episode CR {_fmt(summary['cr'])}, ego-adversary CR {_fmt(summary['cr_ego_adversary'])}, "
        f"non-ego CR {_fmt(summary['cr_non_ego'])}, ORR {_fmt(summary['orr'])}, "
        f"mean min TTC {_fmt(summary['mean_min_ttc'])} s, min clearance to adversary "
        f"{_fmt(summary['mean_min_clearance_adversary'])} m, fallbacks {summary['fallbacks']}"
    )
    print(
        f"{_fmt(summary['seconds_per_episode'])} s per episode, "
        f"{_fmt(summary['seconds_per_replan'])} s per replan"
    )
    return 0


def _parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _cmd_train(args: argparse.Namespace) -> int:
    from counterscene_env.world_model.config import ModelConfig, preset
    from counterscene_env.world_model.train import TrainConfig, train

    overrides = _parse_overrides(args.set)
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


def _load_model(name: str):
    from counterscene_env.world_model.checkpoint import CheckpointError, load_model

    try:
        return load_model(name)
    except CheckpointError as exc:
        raise ValueError(str(exc)) from None


def _cmd_evaluate_model(args: argparse.Namespace) -> int:
    from counterscene_env.scene.datagen import iter_scenes
    from counterscene_env.world_model.evaluate import evaluate_model

    model = _load_model(args.model)
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
        print(f"{name:22s}" + "".join(f"{_fmt(vals[h]):>8s}" for h in hz))
    print(
        f"off-road: model {_fmt(result['model']['offroad_rate'])}, constant velocity "
        f"{_fmt(result['constant_velocity']['offroad_rate'])}, log {_fmt(result['log_offroad_rate'])}"
    )
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from counterscene_env.world_model.bench import bench_model

    if args.preset:
        from counterscene_env.world_model.config import preset
        from counterscene_env.world_model.model import WorldModel

        model, name = WorldModel(preset(args.preset)).eval(), f"preset {args.preset} (untrained)"
    else:
        model, name = _load_model(args.model), args.model
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


def _cmd_generate(args: argparse.Namespace) -> int:
    from counterscene_env.scene.datagen import convert_scenarionet, generate_dataset

    start = time.perf_counter()
    if args.from_scenarionet:
        manifest = convert_scenarionet(
            args.from_scenarionet,
            args.out,
            shard_size=args.shard_size,
            workers=args.workers,
            progress=not args.quiet,
        )
    else:
        manifest = generate_dataset(
            args.out,
            args.scenario,
            args.scenes,
            args.seed,
            shard_size=args.shard_size,
            workers=args.workers,
            duration=args.duration,
            progress=not args.quiet,
        )
    print(
        f"{manifest['scenes']} scenes in {len(manifest['shards'])} shards at {args.out} "
        f"({manifest['rejected']} rejected; {time.perf_counter() - start:.1f} s)"
    )
    return 0


def _cmd_inspect(args: argparse.Namespace) -> int:
    import numpy as np

    from counterscene_env.metrics import evaluate_scene
    from counterscene_env.scene.datagen import iter_scenes

    rows = []
    for scene, load_time in iter_scenes(Path(args.path)):
        whole = scene.replace(current_index=0)
        m = evaluate_scene(whole, smooth=args.smooth)
        rows.append(
            {
                "scenario_id": scene.scenario_id,
                "agents": scene.num_agents,
                "vehicles": int(scene.vehicle_mask.sum()),
                "steps": scene.num_steps,
                "duration_s": round(scene.duration, 3),
                "lanes": len(scene.road.lane_centerlines),
                "time_s": round(load_time, 4),
                **{
                    k: m[k]
                    for k in ("cr", "cr_all_agents", "orr", "hbr_ego", "hbr_all", "hbr_paper")
                },
            }
        )
    if not rows:
        raise ValueError(f"{args.path}: no scenes found")

    def stat(key: str) -> dict:
        v = np.array([r[key] for r in rows], dtype=float)
        return {
            "mean": float(np.nanmean(v)),
            "min": float(np.nanmin(v)),
            "max": float(np.nanmax(v)),
        }

    summary = {"scenes": len(rows)} | {k: stat(k) for k in _INSPECT_COLUMNS[1:] if k != "steps"}
    if args.json:
        print(json.dumps(json_safe({"summary": summary, "scenes": rows})))
        return 0
    cols = _INSPECT_COLUMNS
    print("  ".join(f"{c:>14}" for c in cols))
    for r in rows:
        print("  ".join(f"{_fmt(r[c]):>14}" for c in cols))
    print(f"\n{len(rows)} scenes")
    for k, v in summary.items():
        if k != "scenes":
            print(f"  {k:>14}: mean {v['mean']:.4g}  min {v['min']:.4g}  max {v['max']:.4g}")
    return 0


#: Per-scene columns of ``counterscene inspect`` (numbers after the id are also summarised).
_INSPECT_COLUMNS = (
    "scenario_id",
    "agents",
    "vehicles",
    "steps",
    "duration_s",
    "lanes",
    "time_s",
    "cr",
    "cr_all_agents",
    "orr",
    "hbr_ego",
    "hbr_all",
    "hbr_paper",
)


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def json_safe(obj):
    from counterscene_env.metrics import json_safe as safe  # lazy: keeps --help instant

    return safe(obj)


if __name__ == "__main__":
    sys.exit(main())
