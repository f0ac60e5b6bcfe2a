"""``counterscene paper-tables``: the paper's comparisons in one command."""

from __future__ import annotations

import argparse
import shlex
import sys

from counterscene_env.cli.common import (
    add_json_flag,
    add_model_flag,
    add_quiet_flag,
    add_seed_flag,
    parse_overrides,
)
from counterscene_env.config import REAL_MIN_FUTURE  # a light module: --help stays instant


def add_paper_tables(sub) -> None:
    """Register ``counterscene paper-tables``."""
    pp = sub.add_parser(
        "paper-tables",
        help="the paper's tables (main, selection, ablation, real logs) with intervals",
        description=(
            "Run every row of the paper's comparisons (unguided world model; random, "
            "distance, TTC and causal selectors with full guidance; the guidance ablations) "
            "on the same episodes, one stress run per row and scenario in OUT/<scenario>/"
            "<row>/ (resumable: rerun the command to continue), and write OUT/tables.md and "
            "OUT/tables.json: every figure with its 95 % interval, every row paired with "
            "CounterScene, the paper's own figures beside ours (docs/reproducing_the_paper.md)."
        ),
    )
    pp.add_argument("--episodes", type=int, default=200, help="episodes per row (default 200)")
    pp.add_argument("--out", required=True, metavar="DIR", help="output directory")
    pp.add_argument(
        "--scenario",
        nargs="+",
        default=None,
        metavar="S",
        help="generated roads (default: intersection merge; 'none' for real logs only)",
    )
    pp.add_argument(
        "--scenarionet",
        nargs="*",
        default=[],
        metavar="DIR",
        help="folders of ScenarioNet real logs (the real-logs table)",
    )
    pp.add_argument(
        "--commonroad",
        nargs="*",
        default=[],
        metavar="DIR",
        help="folders of CommonRoad scenarios (the real-logs table)",
    )
    pp.add_argument("--planner", default="idm", help="ego planner (default idm)")
    add_seed_flag(pp, 300000, "seed of episode 0 (default 300000)")
    pp.add_argument("--workers", type=int, default=1, help="processes per row (default 1)")
    pp.add_argument("--batch", type=int, default=4, help="episodes per batch (default 4)")
    pp.add_argument(
        "--egos",
        type=int,
        default=1,
        help="ego choices per real scene where a folder has fewer scenes than --episodes: "
        "each pass over its scenes seats the next moving vehicle as the ego (default 1: "
        "the recorded ego only)",
    )
    pp.add_argument(
        "--min-future",
        type=float,
        default=REAL_MIN_FUTURE,
        metavar="S",
        help="s of log after its start a real scene needs to be seated (default "
        f"{REAL_MIN_FUTURE:g}: the real-logs table's first horizon; 0 seats every scene)",
    )
    pp.add_argument(
        "--rollouts",
        type=int,
        default=1,
        metavar="K",
        help="candidate rollouts per episode in every row (the paper's protocol: 16): the one "
        "most severe for the ego is kept, at K times the cost (default 1)",
    )
    add_model_flag(pp)
    pp.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="closed-loop settings for every row (JSON values), e.g. num_samples=16 "
        "duration=7; the rows' own keys (selector, guidance) cannot be set",
    )
    pp.add_argument(
        "--tables",
        nargs="+",
        choices=("main", "selection", "ablation"),
        default=["main", "selection", "ablation"],
        help="the generated roads' tables to run (default: all three; real logs always get "
        "the real-logs table)",
    )
    pp.add_argument(
        "--tables-only",
        action="store_true",
        help="run nothing: write the tables from the episodes already in OUT (a row may hold "
        "fewer than --episodes; its n says so)",
    )
    add_quiet_flag(pp)
    add_json_flag(
        pp, "print tables.json (every figure, interval and paired test) as one JSON object"
    )
    pp.set_defaults(func=_cmd_paper_tables)


def _cmd_paper_tables(args: argparse.Namespace) -> int:
    from counterscene_env.config import COMMONROAD_PREFIX, SCENARIONET_PREFIX
    from counterscene_env.report import paper_document
    from counterscene_env.scene.sources import check_spec
    from counterscene_env.stress import paper

    for flag in ("episodes", "workers", "egos", "rollouts"):
        if getattr(args, flag) < 1:
            raise ValueError(f"--{flag} must be >= 1, got {getattr(args, flag)}")
    base = parse_overrides(args.set)
    roads = ["intersection", "merge"] if args.scenario is None else args.scenario
    roads = [] if roads == ["none"] else roads
    specs = [check_spec(s) for s in roads]
    specs += [check_spec(SCENARIONET_PREFIX + d) for d in args.scenarionet]
    specs += [check_spec(COMMONROAD_PREFIX + d) for d in args.commonroad]
    if not specs:
        raise ValueError("nothing to run: give --scenario, --scenarionet or --commonroad")

    def on_row(where: str, row: str, done: int) -> None:
        if not args.quiet:
            left = args.episodes - min(done, args.episodes)
            print(f"{where} / {row}: {left} of {args.episodes} episodes to run", file=sys.stderr)

    results = paper.run_rows(
        args.out,
        specs,
        args.episodes,
        args.seed,
        args.planner,
        args.model,
        args.workers,
        args.batch,
        base=base,
        egos=args.egos,
        min_future=args.min_future,
        rollouts=args.rollouts,
        progress=not args.quiet,
        on_row=on_row,
        run=not args.tables_only,
        tables=args.tables,
    )
    run_command = "counterscene " + shlex.join(a for a in args.argv if a != "--tables-only")
    if not results:
        raise ValueError(
            f"{args.out}: no episodes of these scenarios to tabulate; run them with: {run_command}"
        )
    seconds: dict[str, dict[str, float]] = {}
    for where, runs in results.items():  # compute time from the records (resumes included)
        for row, records in runs.items():
            seconds.setdefault(where, {})[row] = sum(float(r.get("seconds", 0)) for r in records)
    tables_of = {paper.scenario_dir(s): paper.tables_for(s, args.tables) for s in specs}
    built = paper_document.build(
        results,
        paper.TABLE_ROWS,
        tables_of,
        {r.name: r.label for r in paper.ROWS.values()},
        {r.name: r.paper for r in paper.ROWS.values()},
    )
    meta = {
        "command": "counterscene " + shlex.join(args.argv),
        "planner": args.planner,
        "episodes": args.episodes,
        "seed": args.seed,
        "egos": args.egos,
        "min_future": args.min_future,
        "rollouts": args.rollouts,
        "model": args.model,
        "settings": base,
        "tables_only": args.tables_only,
        "tables": list(args.tables),
        "run_command": run_command,
    }
    page = paper_document.write(args.out, built, meta, seconds)
    _warn_missing(built["missing"], run_command)
    if args.json:
        import json

        from counterscene_env.metrics import json_safe

        print(json.dumps(json_safe(json.loads((page.parent / "tables.json").read_text()))))
        return 0
    print(page.read_text(), end="")
    return 0


def _warn_missing(missing: dict, run_command: str) -> None:
    """Name the rows with no episode yet on stderr too (``--json`` and a page scrolled past
    must not hide them); ``missing``: ``{scenario: {table: [row]}}``."""
    if not missing:
        return
    rows = sorted({f"{w}/{r}" for w, ts in missing.items() for rs in ts.values() for r in rs})
    print(
        f"counterscene paper-tables: rows not run yet, left out of the tables: "
        f"{', '.join(rows)}; run them with: {run_command}",
        file=sys.stderr,
    )
