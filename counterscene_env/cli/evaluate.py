"""``counterscene evaluate-model``: a world model's open-loop predictions against the log and
constant velocity (``world_model/evaluate.py``), as a table or one JSON object."""

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
)

#: ``evaluate-model``'s first seed of generated scenes: the held-out range (training from 0).
EVALUATION_SEED = 100000
#: Scenes ``evaluate-model`` generates, or reads from each ``--data`` dataset, unless
#: ``--scenes`` says otherwise (real-log sources default to all their scenes).
DEFAULT_EVAL_SCENES = 50


def add_evaluate_model(sub) -> None:
    """Register ``counterscene evaluate-model``."""
    ev = sub.add_parser(
        "evaluate-model",
        help="open-loop prediction metrics of a world model vs constant velocity",
        description=(
            "Predict every agent of freshly generated scenes (the first --scenes safe seeds from "
            "--seed), of dataset directories, or of real logs (ScenarioNet or CommonRoad), and "
            "report ADE/FDE at 1, 2, 3 s and the full horizon (one sample, and the best of "
            "--samples) and the off-road rate, for all agents and split by their speed now "
            "(parked < 0.5 m/s <= slow < 3 m/s <= moving), and the share of windows whose "
            "sample puts two boxes on each other where the log's do not."
        ),
    )
    ev_src = ev.add_mutually_exclusive_group(required=True)
    ev_src.add_argument("--scenario", choices=SCENARIO_CHOICES)
    ev_src.add_argument("--scenarionet", metavar="DIR", help="ScenarioNet .pkl file or directory")
    ev_src.add_argument(
        "--commonroad", metavar="DIR", help="CommonRoad XML scenario file or directory"
    )
    ev_src.add_argument(
        "--data", nargs="+", metavar="DIR", help="dataset directories or shards (pooled)"
    )
    ev.add_argument(
        "--scenes",
        type=int,
        help=f"scenes: generated, or the first of each --data dataset (default "
        f"{DEFAULT_EVAL_SCENES}); the first of a real-log source (default: all)",
    )
    add_seed_flag(ev, EVALUATION_SEED, "--scenario: first seed (default 100000)")
    add_model_flag(ev)
    ev.add_argument("--samples", type=int, default=6, help="samples per scene (default 6)")
    ev.add_argument(
        "--lane-steering",
        type=int,
        metavar="N",
        help="Adam steps of final-step lane keeping (default: the model's; 0: the network alone)",
    )
    ev.add_argument(
        "--hold-parked",
        type=float,
        metavar="M",
        help="hold in place every vehicle stopped now more than M m outside every lane strip "
        "(default: the model's, 1.5 for the shipped one; 0: the network plans them too)",
    )
    ev.add_argument(
        "--every",
        type=float,
        metavar="S",
        help="score every S seconds of each log where 3 s of history and 3 s of future exist "
        "(default: each scene's now only)",
    )
    ev.add_argument(
        "--bootstrap",
        type=int,
        default=1000,
        help="scene resamples behind each 95 %% interval (default 1000; 0: none)",
    )
    add_json_flag(ev)
    add_quiet_flag(ev)
    ev.set_defaults(func=_cmd_evaluate_model)


def _evaluation_scenes(args: argparse.Namespace) -> list:
    """The scenes of ``evaluate-model``'s source (``--scenario``, ``--data``, ``--scenarionet``
    or ``--commonroad``), capped by ``--scenes``."""
    if args.scenes is not None and args.scenes < 1:
        raise ValueError(f"--scenes must be >= 1, got {args.scenes}")
    if args.seed != EVALUATION_SEED and not args.scenario:
        raise ValueError(
            "--seed picks generated scenes (--scenario); stored scenes are read in order"
        )
    if args.scenario:
        from tqdm.auto import tqdm

        from counterscene_env.scene.highway import generate

        # The first --scenes safe seeds from --seed, as `counterscene generate` picks them
        # (about 0.7 s each at the intersection: recording highway-env traffic, hence the bar).
        scenes, seed = [], args.seed
        n = args.scenes or DEFAULT_EVAL_SCENES
        with tqdm(total=n, desc="scenes", unit="scene", disable=args.quiet) as bar:
            while len(scenes) < n:
                scenes.append(generate(args.scenario, seed))
                seed = scenes[-1].metadata["seed"] + 1
                bar.update(1)
        return scenes
    if args.data:  # the first --scenes of each dataset (never logs to unpickle: --scenarionet)
        from counterscene_env.scene.reading import iter_dataset

        n = args.scenes or DEFAULT_EVAL_SCENES
        return [s for d in args.data for s, _ in itertools.islice(iter_dataset(Path(d)), n)]
    return _real_scenes(args)


def _real_scenes(args: argparse.Namespace) -> list:
    """The scenes of ``--scenarionet`` or ``--commonroad`` DIR: all, or the first ``--scenes``."""
    from counterscene_env.config import COMMONROAD_PREFIX, SCENARIONET_PREFIX
    from counterscene_env.scene.sources import spec_path, stored_scenes

    spec = (
        SCENARIONET_PREFIX + args.scenarionet
        if args.scenarionet
        else COMMONROAD_PREFIX + args.commonroad
    )
    if not spec_path(spec).exists():
        raise FileNotFoundError(f"{spec_path(spec)}: no such file or directory")
    try:
        # stored_scenes imports the CommonRoad loader only for a commonroad: spec, so the
        # other sources never need its dependencies.
        scenes = list(itertools.islice(stored_scenes(spec), args.scenes))
    except ImportError as exc:
        raise RuntimeError(f"cannot read {spec}: {exc}") from exc
    if not scenes:
        raise FileNotFoundError(f"{spec_path(spec)}: no scenes")
    return scenes


def _cmd_evaluate_model(args: argparse.Namespace) -> int:
    from counterscene_env.world_model.evaluate import evaluate_model

    if args.samples < 1:
        raise ValueError(f"--samples must be >= 1, got {args.samples}")
    model = load_model(args.model)
    if args.lane_steering is not None:
        if args.lane_steering < 0:
            raise ValueError(f"--lane-steering must be >= 0, got {args.lane_steering}")
        model.config = model.config.replace(lane_steering=args.lane_steering)
    if args.hold_parked is not None:
        if not args.hold_parked >= 0:
            raise ValueError(f"--hold-parked must be >= 0 m, got {args.hold_parked}")
        model.config = model.config.replace(hold_parked=args.hold_parked)
    if args.every is not None and not args.every > 0:
        raise ValueError(f"--every must be > 0 s, got {args.every}")
    if args.bootstrap < 0:
        raise ValueError(f"--bootstrap must be >= 0, got {args.bootstrap}")
    scenes = _evaluation_scenes(args)
    result = evaluate_model(
        model,
        scenes,
        args.samples,
        seed=0,
        progress=not args.quiet,
        every=args.every,
        bootstrap=args.bootstrap,
    )
    result["source"] = (
        f"{args.scenario} seeds from {args.seed}"
        if args.scenario
        else str(args.scenarionet or args.commonroad or args.data)
    )
    result["checkpoint"] = _model_record(args.model, model)
    if args.json:
        print(json.dumps(json_safe(result)))
        return 0
    _print_evaluation(result)
    return 0


def _model_record(given: str, model) -> dict:
    """Which model was evaluated: ``given`` (``--model`` as typed), the ``directory`` it
    resolved to (absolute; ``checkpoint.model_dir``), its ``preset``, and its training
    provenance from its ``config.json``: ``training_step`` (steps of its own run), ``init``
    (the model a fine-tune started from, else None) and ``training_data`` (its --data)."""
    from counterscene_env.world_model.checkpoint import model_dir

    info = getattr(model, "training_info", {}) or {}
    return {
        "given": given,
        "directory": str(model_dir(given).resolve()),
        "preset": getattr(model, "preset", None),
        "training_step": info.get("step"),
        "init": info.get("init"),
        "training_data": info.get("data"),
    }


def _model_line(record: dict) -> str:
    """``model default: /abs/dir (preset default, 1500 training steps, fine-tuned from the
    shipped model before it)``: the text report's first line."""
    facts = [f"preset {record['preset']}"] if record["preset"] else []
    if record["training_step"] is not None:
        facts.append(f"{record['training_step']} training steps")
    if record["init"] is not None:
        start = record["init"]
        # A shipped model's "default" is the model shipped before it, not itself.
        facts.append(
            "fine-tuned from the shipped model before it"
            if start == "default"
            else f"fine-tuned from {start}"
        )
    tail = f" ({', '.join(facts)})" if facts else ""
    return f"model {record['given']}: {record['directory']}{tail}"


def _print_evaluation(result: dict) -> None:
    """The text report of ``evaluate-model``: the model, the pooled table, then ADE per speed
    bin."""
    skipped = result["skipped_scenes"]
    print(_model_line(result["checkpoint"]))
    print(
        f"{result['scenes']} scenes"
        + (f" ({skipped} skipped: log ends at now)" if skipped else "")
        + f", {result['agents']} agents, {result['samples']} samples, "
        f"horizon {result['horizon_s']:.1f} s ({result['source']})"
    )
    hz = list(result["model"]["ade"])
    print(f"{'':22s}" + "".join(f"{h:>8s}" for h in hz))
    rows = [
        ("model ADE [m]", result["model"]["ade"]),
        ("model FDE [m]", result["model"]["fde"]),
        ("  mean of samples ADE", result["model"]["ade_all_samples"]),
        (f"model minADE_{result['samples']} [m]", result["model"][f"min_ade_{result['samples']}"]),
        ("const. vel. ADE [m]", result["constant_velocity"]["ade"]),
        ("const. vel. FDE [m]", result["constant_velocity"]["fde"]),
    ]
    for name, vals in rows:
        print(f"{name:22s}" + "".join(f"{fmt(vals[h]):>8s}" for h in hz))
    print(
        f"off-road: model {fmt(result['model']['offroad_rate'])}, constant velocity "
        f"{fmt(result['constant_velocity']['offroad_rate'])}, log {fmt(result['log_offroad_rate'])}"
    )
    overlap = result["sample_overlap"]
    print(
        "windows whose first sample has two boxes overlapping (the log's do not): "
        + ", ".join(f"{h} {fmt(overlap[h])}" for h in hz)
    )
    windows = f", {result['windows']} windows" if result.get("every_s") else ""
    # One scene has no spread over scenes to resample: no interval (scene_bootstrap.py).
    band = (
        "one scene: no interval"
        if result["scenes"] < 2
        else "no interval: --bootstrap 0"
        if not result.get("bootstrap_resamples")
        else "95 % interval over scenes"
    )
    print(f"ADE / constant velocity's [{band}{windows}]:")
    for name, block in [("all", result), *result["by_speed"].items()]:
        cells = []
        for h in hz:
            ratio, ci = block["ade_ratio_to_cv"][h], block["ade_ratio_to_cv_ci95"][h]
            band = f" [{fmt(ci[0])}, {fmt(ci[1])}]" if ci else ""
            cells.append(f"{h} {fmt(ratio)}{band}")
        print(f"  {name:8s} " + "  ".join(cells))
    still = result["still"]
    if still["agents"]:
        fde3 = still["model"]["fde"].get("3s")
        all3 = still["model"]["fde_all_samples"].get("3s")
        print(
            f"still agents ({still['agents']}: parked, logged within "
            f"{fmt(result['still_displacement_m'])} m 3 s later): model FDE at 3 s {fmt(fde3)} m "
            f"(mean of the samples {fmt(all3)} m)"
        )
    lo, hi = (fmt(float(e)) for e in result["speed_bins_m_s"])
    print(f"ADE [m] by speed now (parked < {lo} m/s <= slow < {hi} m/s <= moving):")
    for name, block in result["by_speed"].items():
        head = f"  {name} ({block['agents']} agents)"
        print(f"{head:22s}" + "".join(f"{h:>8s}" for h in hz))
        for label, vals in (
            ("model", block["model"]["ade"]),
            ("const. vel.", block["constant_velocity"]["ade"]),
        ):
            print(f"{'    ' + label:22s}" + "".join(f"{fmt(vals[h]):>8s}" for h in hz))
