"""``counterscene report`` and ``counterscene compare``: what a stress run shows, and several
runs side by side (docs/reports.md)."""

from __future__ import annotations

import argparse
import json

from counterscene_env.cli.common import add_json_flag, add_quiet_flag


def add_report(sub) -> None:
    """Register ``counterscene report``."""
    rp = sub.add_parser(
        "report",
        help="(re)build the report of a stress run directory",
        description=(
            "Write DIR/report.html (self-contained), DIR/report.md, DIR/plots/, DIR/videos/ "
            "and DIR/command.txt for the stress run in DIR (counterscene stress --out DIR), "
            "from its finished episodes: the paper's table with 95 % intervals, plots, and the "
            "worst episodes, the first --videos of them re-simulated from their seeds as MP4 "
            'and GIF (needs pip install "counterscene-env[video]").'
        ),
    )
    rp.add_argument("directory", metavar="DIR", help="a counterscene stress --out directory")
    rp.add_argument(
        "--videos",
        type=int,
        default=3,
        metavar="K",
        help="worst episodes to re-simulate and film (default 3; 0: none)",
    )
    add_quiet_flag(rp)
    rp.set_defaults(func=_cmd_report)


def _cmd_report(args: argparse.Namespace) -> int:
    from counterscene_env.report import write_report

    if args.videos < 0:
        raise ValueError(f"--videos must be >= 0, got {args.videos}")
    page = write_report(args.directory, videos=args.videos, progress=not args.quiet)
    print(f"{page} (and report.md, plots/, videos/, command.txt beside it)")
    return 0


def add_compare(sub) -> None:
    """Register ``counterscene compare``."""
    cp = sub.add_parser(
        "compare",
        help="compare stress runs: intervals and paired tests",
        description=(
            "One table for several stress run directories (the first is the baseline): "
            "episode CR, ego-adversary CR, HBR, ORR and ADE with 95 % intervals, and for "
            "runs that share episodes with the baseline (same scenario and --seed), the "
            "paired difference with a test saying whether it lies outside the noise."
        ),
    )
    cp.add_argument("directories", nargs="+", metavar="DIR", help="stress run directories")
    cp.add_argument(
        "--out",
        metavar="DIR",
        help="also write DIR/compare.html, compare.md, compare.json and one plot per metric",
    )
    add_json_flag(cp, "print the comparison as one JSON object")
    cp.set_defaults(func=_cmd_compare)


def _cmd_compare(args: argparse.Namespace) -> int:
    from counterscene_env.report import compare

    result = compare.compare_runs(args.directories)
    page = compare.write_comparison(result, args.out) if args.out else None
    if args.json:
        print(json.dumps(compare.to_json(result)))
        return 0
    from counterscene_env.report.markdown import render

    print(render(compare.document(result)), end="")
    if page is not None:
        print(f"\nwritten: {page} (and compare.md, compare.json, plots/ beside it)")
    return 0
