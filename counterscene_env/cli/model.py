"""``counterscene train``: training a world model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from counterscene_env.cli.common import (
    add_quiet_flag,
    add_seed_flag,
    json_safe,
    parse_overrides,
    warn_shadowed_default,
)


def add_train(sub) -> None:
    """Register ``counterscene train``."""
    tr = sub.add_parser(
        "train",
        help="train a world model (resumable)",
        description=(
            "Train on dataset directories and write model.safetensors + config.json (the EMA "
            "weights), last.pt (to resume) and log.jsonl into --out. Rerun the same command to "
            "continue; a larger --steps extends the run. A new run (no last.pt in --out) "
            "replaces any log.jsonl there and refuses an --out that holds a model."
        ),
    )
    tr.add_argument("--data", required=True, nargs="+", metavar="DIR", help="dataset directories")
    tr.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output directory: a new one, or a run's to resume (never another model's)",
    )
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
    tr.add_argument(
        "--checkpoint-every", type=int, default=500, help="steps between checkpoints (default 500)"
    )
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
        "--init",
        metavar="DIR",
        help="start from this model's weights ('default': the shipped model; ./default: a "
        "directory of that name)",
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
    tr.add_argument(
        "--smooth-tracks",
        nargs="+",
        default=[],
        metavar="DIR",
        help="those --data datasets whose tracks are low-pass filtered before training "
        "(video-tracked recordings such as NGSIM, whose speeds carry measurement noise; "
        "docs/world_model.md)",
    )
    tr.add_argument(
        "--smooth-sigma",
        type=float,
        default=0.5,
        metavar="SECONDS",
        help="the --smooth-tracks filter's standard deviation (default 0.5 s)",
    )
    add_quiet_flag(tr)
    tr.set_defaults(func=_cmd_train)


def _cmd_train(args: argparse.Namespace) -> int:
    from counterscene_env.world_model.config import ModelConfig, preset
    from counterscene_env.world_model.train import train
    from counterscene_env.world_model.train_config import TrainConfig

    overrides = parse_overrides(args.set)
    warn_shadowed_default(args.init, "--init")
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
        smooth_tracks=tuple(args.smooth_tracks),
        smooth_sigma=args.smooth_sigma,
        data_weights=None if args.data_weights is None else tuple(args.data_weights),
        parked_cars=args.parked_cars,
    )
    record = train(cfg, progress=not args.quiet)
    print(json.dumps(json_safe(record)))
    return 0
