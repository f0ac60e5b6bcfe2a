"""``counterscene generate`` and ``counterscene inspect``: datasets of scenes."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from counterscene_env.cli.common import (
    SCENARIO_CHOICES,
    add_json_flag,
    add_quiet_flag,
    add_seed_flag,
    float_in,
    fmt,
    json_safe,
)
from counterscene_env.config import Yielding

#: The longest ``inspect --smooth`` window [s]: longer ones average the braking away.
MAX_SMOOTH = 5.0
#: ``counterscene generate``'s defaults for generated traffic (a conversion refuses others).
GENERATE_DEFAULTS = {"scenes": 100, "seed": 0, "duration": 13.0}


def add_generate(sub) -> None:
    """Register ``counterscene generate``."""
    gen = sub.add_parser(
        "generate",
        help="generate a dataset of scenes (highway-env traffic, ScenarioNet or CommonRoad logs)",
        description=(
            "Write scenes as compressed shards plus manifest.json into --out. Highway-env: the "
            "first --scenes safe seeds from --seed. Resumable: rerun the same command."
        ),
    )
    src = gen.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--scenario",
        choices=SCENARIO_CHOICES,
        help="highway-env road to record traffic on",
    )
    src.add_argument("--from-scenarionet", metavar="DIR", help="convert ScenarioNet .pkl files")
    src.add_argument(
        "--from-commonroad",
        metavar="DIR",
        help="convert CommonRoad .xml scenarios (one scene per distinct recording; needs the "
        "commonroad extra)",
    )
    gen.add_argument(
        "--all-egos",
        action="store_true",
        help="CommonRoad: one scene per logged vehicle that can be the ego, not one per file",
    )
    gen.add_argument(
        "--scenes",
        type=int,
        default=GENERATE_DEFAULTS["scenes"],
        help="--scenario: scenes to generate (default 100)",
    )
    add_seed_flag(gen, GENERATE_DEFAULTS["seed"], "--scenario: first seed (default 0)")
    gen.add_argument("--out", required=True, metavar="DIR", help="output dataset directory")
    gen.add_argument(
        "--duration",
        type=float,
        default=GENERATE_DEFAULTS["duration"],
        help="--scenario: log length in s (default 13, the least: 3 s history + 10 s future)",
    )
    gen.add_argument(
        "--yielding",
        choices=Yielding.values(),
        default=Yielding.HIGHWAY_ENV.value,
        help="how intersection traffic gives way: highway-env's rule (target speed 0, decided "
        "3 s ahead; the default) or gap-acceptance (a smooth stop before the crossing, "
        "decided 6 s ahead)",
    )
    gen.add_argument(
        "--shard-size", type=int, default=50, help="seeds or files per shard (default 50)"
    )
    gen.add_argument("--workers", type=int, default=1, help="parallel worker processes (default 1)")
    add_quiet_flag(gen)
    gen.set_defaults(func=_cmd_generate)


def _cmd_generate(args: argparse.Namespace) -> int:
    from counterscene_env.scene.datagen import (
        convert_commonroad,
        convert_scenarionet,
        generate_dataset,
    )

    if not args.scenario:  # a conversion takes every log: the generator's flags mean nothing
        given = [
            flag
            for flag, value, default in (
                ("--scenes", args.scenes, GENERATE_DEFAULTS["scenes"]),
                ("--seed", args.seed, GENERATE_DEFAULTS["seed"]),
                ("--duration", args.duration, GENERATE_DEFAULTS["duration"]),
                ("--yielding", args.yielding, Yielding.HIGHWAY_ENV.value),
            )
            if value != default
        ]
        if given:
            raise ValueError(
                f"only generated traffic (--scenario) takes {', '.join(given)}; a conversion "
                "takes every log as it is"
            )
    if args.all_egos and not args.from_commonroad:
        raise ValueError("--all-egos applies to --from-commonroad only")
    start = time.perf_counter()
    blocks = {"shard_size": args.shard_size, "workers": args.workers, "progress": not args.quiet}
    if args.from_commonroad:
        manifest = convert_commonroad(
            args.from_commonroad, args.out, all_egos=args.all_egos, **blocks
        )
    elif args.from_scenarionet:
        manifest = convert_scenarionet(args.from_scenarionet, args.out, **blocks)
    else:
        manifest = generate_dataset(
            args.out,
            args.scenario,
            args.scenes,
            args.seed,
            duration=args.duration,
            yielding=args.yielding,
            **blocks,
        )
    print(
        f"{manifest['scenes']} scenes in {len(manifest['shards'])} shards at {args.out} "
        f"({manifest['rejected']} rejected; {time.perf_counter() - start:.1f} s)"
    )
    if args.from_commonroad or args.from_scenarionet:
        from counterscene_env.scene.manifest import MANIFEST

        # A log refused by the importer says why (each one's reason is in the manifest).
        refused = [r for shard in manifest["shards"] for r in shard["rejected"]]
        for name, why in refused[:REFUSALS_SHOWN]:
            print(f"  refused {name}: {why}", file=sys.stderr)
        if len(refused) > REFUSALS_SHOWN:
            print(f"  ... and {len(refused) - REFUSALS_SHOWN} more, in {MANIFEST}", file=sys.stderr)
        if not manifest["scenes"]:
            raise ValueError(f"no log converted: every file was refused (see {MANIFEST})")
    return 0


#: Refused logs of a conversion named on stderr (the manifest lists them all).
REFUSALS_SHOWN = 5


def add_inspect(sub) -> None:
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
    add_json_flag(ins)
    ins.add_argument(
        "--smooth",
        type=float_in(0.0, MAX_SMOOTH),
        default=0.0,
        help="acceleration smoothing window for HBR, s, at most 5 (0.5 suits nuScenes' "
        "interpolated logs)",
    )
    ins.set_defaults(func=_cmd_inspect)


def _cmd_inspect(args: argparse.Namespace) -> int:
    import numpy as np

    from counterscene_env.metrics import evaluate_scene
    from counterscene_env.scene.reading import iter_scenes

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
                **{k: m[k] for k in _METRIC_COLUMNS},
                "repaired": len(scene.metadata.get("repairs", {})),
                "dropped": len(scene.metadata.get("dropped_tracks", {})),
                "repairs": scene.metadata.get("repairs", {}),
                "dropped_tracks": scene.metadata.get("dropped_tracks", {}),
            }
        )
    if not rows:
        raise ValueError(f"{args.path}: no scenes found")

    def stat(key: str) -> dict:
        v = np.array([r[key] for r in rows], dtype=float)
        v = v[~np.isnan(v)]  # e.g. ORR of parked cars in a scene without one
        if not v.size:
            return {"mean": math.nan, "min": math.nan, "max": math.nan}
        return {"mean": float(v.mean()), "min": float(v.min()), "max": float(v.max())}

    summary = {"scenes": len(rows)} | {k: stat(k) for k in _INSPECT_COLUMNS[1:] if k != "steps"}
    if args.json:
        print(json.dumps(json_safe({"summary": summary, "scenes": rows})))
        return 0
    cols = _INSPECT_COLUMNS
    print("  ".join(f"{c:>14}" for c in cols))
    for r in rows:
        print("  ".join(f"{fmt(r[c]):>14}" for c in cols))
    _print_repairs(rows)
    print(f"\n{len(rows)} scenes")
    for k, v in summary.items():
        if k != "scenes":
            print(f"  {k:>14}: mean {v['mean']:.4g}  min {v['min']:.4g}  max {v['max']:.4g}")
    return 0


def _print_repairs(rows: list[dict]) -> None:
    """What the importer repaired or dropped, per scene (ScenarioNet and CommonRoad imports)."""
    for r in rows:
        for track, what in r["repairs"].items():
            print(f"  {r['scenario_id']}: track {track} repaired: {'; '.join(what)}")
        for track, why in r["dropped_tracks"].items():
            print(f"  {r['scenario_id']}: track {track} dropped: {why}")


#: Factual metrics of ``counterscene inspect`` (over the whole log).
_METRIC_COLUMNS = (
    "cr",
    "cr_all_agents",
    "orr",
    "orr_parked",
    "orr_moving",
    "hbr_ego",
    "hbr_all",
    "hbr_paper",
)

#: Per-scene columns of ``counterscene inspect`` (numbers after the id are also summarised).
_INSPECT_COLUMNS = (
    "scenario_id",
    "agents",
    "vehicles",
    "steps",
    "duration_s",
    "lanes",
    "time_s",
    "repaired",
    "dropped",
    *_METRIC_COLUMNS,
)
