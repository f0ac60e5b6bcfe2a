"""The ``counterscene`` command.

Subcommands import what they need when they run, so ``counterscene --help`` is instant.

- ``generate``: build a dataset directory of scenes (highway-env traffic or ScenarioNet logs).
- ``inspect``: load scenes and report their size, timing and factual metrics.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path


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
    from counterscene_env import __version__

    parser = argparse.ArgumentParser(
        prog="counterscene",
        description="CounterScene: adversarial multi-agent driving scenes and environments.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

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
        choices=("highway", "merge", "intersection", "roundabout"),
        help="highway-env road to record traffic on",
    )
    src.add_argument("--from-scenarionet", metavar="DIR", help="convert ScenarioNet .pkl files")
    gen.add_argument("--scenes", type=int, default=100, help="scenes to generate (default 100)")
    gen.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    gen.add_argument("--out", required=True, metavar="DIR", help="output dataset directory")
    gen.add_argument("--duration", type=float, default=13.0, help="log length in s (default 13)")
    gen.add_argument("--shard-size", type=int, default=50, help="seeds or files per shard")
    gen.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    gen.set_defaults(func=_cmd_generate)

    ins = sub.add_parser(
        "inspect",
        help="report size, timing and factual metrics of scenes",
        description=(
            "PATH: a dataset directory, a shard .npz, a ScenarioNet .pkl, or a directory of .pkl "
            "files. Factual metrics are computed over the whole log (every step after the first)."
        ),
    )
    ins.add_argument("path", help="scenes to inspect")
    ins.add_argument("--json", action="store_true", help="print one JSON object")
    ins.add_argument(
        "--smooth",
        type=float,
        default=0.0,
        help="acceleration smoothing window for HBR, s (0.5 suits nuScenes' interpolated logs)",
    )
    ins.set_defaults(func=_cmd_inspect)
    return parser


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

    rows = []
    for scene, load_time in _iter_scenes(Path(args.path)):
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
        print(json.dumps(_finite({"summary": summary, "scenes": rows})))
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


def _iter_scenes(path: Path):
    """Yield (scene, seconds to produce it) from any supported PATH."""
    from counterscene_env.scene.datagen import MANIFEST, read_manifest, shard_paths
    from counterscene_env.scene.scenarionet import load_scenarionet
    from counterscene_env.scene.shards import load_scenes

    if path.is_dir() and (path / MANIFEST).is_file():
        read_manifest(path)
        for shard in shard_paths(path):
            for scene in load_scenes(shard):
                yield scene, float(scene.metadata.get("generation_time_s", math.nan))
    elif path.is_dir():
        files = sorted(path.rglob("*.pkl"))
        if not files:
            raise FileNotFoundError(f"{path}: no dataset manifest and no .pkl files")
        for f in files:
            start = time.perf_counter()
            scene = load_scenarionet(f)
            yield scene, time.perf_counter() - start
    elif path.suffix == ".pkl":
        start = time.perf_counter()
        scene = load_scenarionet(path)
        yield scene, time.perf_counter() - start
    elif path.is_file():
        for scene in load_scenes(path):
            yield scene, float(scene.metadata.get("generation_time_s", math.nan))
    else:
        raise FileNotFoundError(f"{path}: no such file or directory")


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _finite(obj):
    """JSON has no NaN or inf: write them as null."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    return obj


if __name__ == "__main__":
    sys.exit(main())
