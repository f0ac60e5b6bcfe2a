"""Command-line flags from a frozen config dataclass: one ``--field-name`` per field, typed,
with its choices and its docstring's text (``counterscene stress`` builds its closed-loop
flags from ``SimConfig`` this way, so the flags cannot drift from the config)."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import typing
from collections.abc import Mapping, Sequence
from typing import Any

from counterscene_env.config import bare_type


def field_docs(cls: type) -> dict[str, str]:
    """Each field's text from the ``Attributes:`` section of ``cls``'s docstring.

    An entry is ``name: text`` (or ``a, b, c: text`` for several fields), continued on more
    deeply indented lines; the text is joined into one line.
    """
    doc = inspect.getdoc(cls) or ""
    lines = doc.split("\n")
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes:")
    except StopIteration:
        return {}
    out: dict[str, str] = {}
    names: list[str] = []
    indent = None
    for line in lines[start + 1 :]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        indent = depth if indent is None else indent
        if depth < indent:
            break
        entry = re.match(r"([\w, ]+):\s*(.*)", line.strip()) if depth == indent else None
        if entry:
            names = [n.strip() for n in entry.group(1).split(",")]
            for name in names:
                out[name] = entry.group(2)
        else:
            for name in names:
                out[name] += " " + line.strip()
    return out


def add_arguments(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    aliases: Mapping[str, Sequence[str]] | None = None,
    switches: Mapping[str, Sequence[tuple[str, Any, str]]] | None = None,
) -> None:
    """One flag per field of dataclass ``cls``: ``--field-name`` (``--x/--no-x`` for bools),
    typed by the field's annotation, choices from its :class:`Choice`, help from
    :func:`field_docs`. Every flag defaults to "not given"; :func:`parsed_fields` collects
    the given ones.

    Args:
        aliases: extra spellings of a field's flag (``{"num_samples": ["--samples"]}``).
        switches: extra flags that set a field to a constant (``{"strict_gates":
            [("--paper-gates", False, "the paper's selection")]}``).
    """
    aliases, switches = aliases or {}, switches or {}
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        kind = bare_type(hints[f.name])
        flags = [f"--{f.name.replace('_', '-')}", *aliases.get(f.name, ())]
        default = "" if f.default is None else f" (default {f.default})"  # None: doc says
        help_text = f"{docs.get(f.name, f.name)}{default}".replace("%", "%%")
        kwargs: dict[str, Any] = {"dest": f.name, "default": argparse.SUPPRESS, "help": help_text}
        if kind is bool:
            parser.add_argument(*flags, action=argparse.BooleanOptionalAction, **kwargs)
        else:
            choices = f.metadata.get("choices")
            meta = f.name.upper() if choices is None else None
            parser.add_argument(
                *flags,
                type=str if choices else kind,
                choices=choices.values() if choices else None,
                metavar=meta,
                **kwargs,
            )
        for flag, value, text in switches.get(f.name, ()):
            parser.add_argument(
                flag, dest=f.name, action="store_const", const=value, help=text,
                default=argparse.SUPPRESS,
            )  # fmt: skip


def parsed_fields(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The fields of ``cls`` that were given on the command line (:func:`add_arguments`)."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
