"""Helpers shared by the ``counterscene`` subcommands: common flags, model loading, output."""

from __future__ import annotations

import argparse
import json
import sys

from counterscene_env.config import MAX_RUN_SEED, Scenario  # light: --help stays instant

#: The highway-env roads ``generate`` and ``evaluate-model`` can record scenes on.
SCENARIO_CHOICES = Scenario.values()


def add_model_flag(p: argparse.ArgumentParser) -> None:
    """Add ``--model DIR`` (a world-model checkpoint directory; default: the shipped one)."""
    p.add_argument(
        "--model",
        default="default",
        help="model directory ('default', the default: the shipped model; ./default: a "
        "directory of that name)",
    )


def add_json_flag(p: argparse.ArgumentParser, help: str = "print one JSON object") -> None:
    """Add ``--json`` (print the result as one JSON object instead of a table)."""
    p.add_argument("--json", action="store_true", help=help)


def add_quiet_flag(p: argparse.ArgumentParser) -> None:
    """Add ``--quiet`` (no progress bar)."""
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def int_at_least(low: int, high: int | None = None):
    """An ``argparse`` type: an int ``>= low`` (and ``<= high``, if given; the parser names the
    flag in its error)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an int, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be <= {high}, got {value}")
        return value

    return parse


def float_in(low: float, high: float):
    """An ``argparse`` type: a finite float in ``[low, high]`` (the parser names the flag)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
        if not low <= value <= high:  # NaN fails this too
            raise argparse.ArgumentTypeError(f"must be in [{low:g}, {high:g}], got {text}")
        return value

    return parse


def add_seed_flag(p: argparse.ArgumentParser, default: int, help: str) -> None:
    """Add ``--seed N`` (an int in [0, ``config.MAX_RUN_SEED``]: a first seed, from which the
    episodes', scenes' or training steps' seeds are derived) with the given default and help."""
    p.add_argument("--seed", type=int_at_least(0, MAX_RUN_SEED), default=default, help=help)


def parse_overrides(items: list[str]) -> dict:
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


def warn_shadowed_default(name: str | None, flag: str = "--model") -> None:
    """Say on stderr that ``flag default`` loads the shipped model when the working directory
    also holds a model directory ``default``, which it does not load (``checkpoint.model_dir``:
    the name is never a guess), and how to name that one."""
    from counterscene_env.world_model.checkpoint import shadowed_default

    if shadowed_default(name) is not None:
        print(
            f"counterscene: warning: {flag} default is the shipped model, not the model "
            f"directory ./default here; write {flag} ./default for that one",
            file=sys.stderr,
        )


def load_model(name: str):
    """The model ``--model name`` names (``checkpoint.model_dir``); a checkpoint that does not
    load raises ``ValueError`` with the reason (one line on stderr, no traceback)."""
    from counterscene_env.world_model.checkpoint import CheckpointError, load_model

    warn_shadowed_default(name)
    try:
        return load_model(name)
    except CheckpointError as exc:
        raise ValueError(str(exc)) from None


def fmt(v) -> str:
    """A figure for a text table: 4 significant digits; None (nothing measured) as ``n/a``."""
    if v is None:
        return "n/a"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def json_safe(obj):
    from counterscene_env.metrics import json_safe as safe  # lazy: keeps --help instant

    return safe(obj)
