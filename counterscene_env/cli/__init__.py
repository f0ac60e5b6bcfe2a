"""The ``counterscene`` command.

Subcommands import what they need when they run, so ``counterscene --help`` is instant.

- ``generate``: build a dataset directory of scenes (highway-env traffic or ScenarioNet logs).
- ``inspect``: load scenes and report their size, timing and factual metrics.
- ``train``: train a world model on dataset directories (resumable).
- ``evaluate-model``: open-loop ADE/FDE/off-road of a world model vs constant velocity.
- ``bench``: every speed figure in one run (highway-env anchor, env, replans, stress, RSS).
- ``bench-env``: steps per second of ``CounterScene-v0``.
- ``stress``: stress-test an ego planner against guided world-model traffic (paper's table).
- ``report``: (re)build a stress run's report: html, markdown, plots, videos, command line.
- ``compare``: several stress runs side by side, with intervals and paired tests.
- ``paper-tables``: the paper's comparisons (every row on the same episodes), with intervals.
"""

from __future__ import annotations

import argparse
import os
import sys

from counterscene_env.cli import bench, data, evaluate, model, paper, report, run
from counterscene_env.cli.run import STOPPED_EXIT_CODE

#: A shell's status of a command killed by SIGPIPE (128 + 13).
BROKEN_PIPE_EXIT_CODE = 141

#: What a command stopped by Ctrl-C keeps: each of these rerun as it was goes on from there.
RESUMABLE = {
    "generate": ". The finished shards are kept: rerun the same command to go on",
    "train": ". The last checkpoint is kept: rerun the same command to go on from it",
    "paper-tables": ". The finished episodes are kept: rerun the same command to go on",
}


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    # The command as given (records name it: paper-tables' tables, a run's command.txt).
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    written = _written_directory(args)
    try:
        if written is None:
            return int(args.func(args) or 0)
        from counterscene_env.cli.lock import out_lock

        with out_lock(written, args.command):
            return int(args.func(args) or 0)
    except BrokenPipeError:  # the reader went away (| head): stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return BROKEN_PIPE_EXIT_CODE
    except (ValueError, TypeError, RuntimeError, OSError) as exc:
        # Errors users can act on (bad input, a path that cannot be read or made): one clear
        # line, no traceback.
        print(f"counterscene {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C (stress handles its own: it writes a partial report)
        hint = RESUMABLE.get(args.command, "")
        print(f"counterscene {args.command}: stopped{hint}", file=sys.stderr)
        return STOPPED_EXIT_CODE


def _written_directory(args: argparse.Namespace) -> str | None:
    """The directory the command writes into (``--out``; ``report``'s run directory), which
    one command at a time may write (``cli/lock.py``)."""
    if args.command == "report":
        return args.directory
    return getattr(args, "out", None)


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
    data.add_generate(sub)
    data.add_inspect(sub)
    model.add_train(sub)
    evaluate.add_evaluate_model(sub)
    bench.add_bench(sub)
    bench.add_bench_env(sub)
    run.add_stress(sub)
    report.add_report(sub)
    report.add_compare(sub)
    paper.add_paper_tables(sub)
    return parser
