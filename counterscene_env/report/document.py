"""A report as a list of blocks (headings, text, tables, figures, videos), which
``report.markdown`` and ``report.html`` render. Content is decided once, here and by the
modules that build documents; the renderers only spell it out.

Text is plain (renderers escape it); a table cell may be a :class:`Link`. Paths of figures
and videos are relative to the report's directory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from counterscene_env.report.stats import Estimate


@dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]


@dataclass(frozen=True)
class Link:
    """A link to a file beside the report (``href`` relative to it)."""

    text: str
    href: str


Cell = str | Link


@dataclass(frozen=True)
class Table:
    header: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]


@dataclass(frozen=True)
class Figure:
    """A PNG beside the report (``path`` relative to it); html embeds it, markdown links it."""

    path: Path
    caption: str


@dataclass(frozen=True)
class Video:
    """An episode's video files beside the report (relative paths; html shows the mp4 or the
    gif, markdown links both)."""

    mp4: Path | None
    gif: Path | None
    caption: str


Block = Heading | Paragraph | Bullets | Table | Figure | Video


#: Units shown as percentages: a rate of episodes, a fraction of agent-steps.
PERCENT_UNITS = ("rate", "fraction")


def unit_label(unit: str) -> str:
    """How a unit is written in a header: rates and fractions as ``%``."""
    return "%" if unit in PERCENT_UNITS else unit


def count(n: int, noun: str) -> str:
    """``"1 episode"``, ``"4 episodes"``."""
    return f"{n} {noun}{'s' * (n != 1)}"


def fmt(value: float | None, unit: str = "") -> str:
    """A number for a table, without its unit (the header says it): 3 significant digits,
    ``n/a`` for NaN or None, ``∞`` for inf; a rate or fraction as a percentage."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if math.isinf(value):
        return "∞" if value > 0 else "-∞"
    if unit in PERCENT_UNITS:
        value = 100 * value
    return f"{value:.3g}"


def interval(est: Estimate, unit: str = "") -> str:
    """``value [low, high]`` of an estimate (percentages for rates and fractions); a value
    without an interval (a mean over one episode) says so."""
    if math.isnan(est.value):
        return "n/a"
    if math.isnan(est.low) or math.isnan(est.high):
        return f"{fmt(est.value, unit)} (no interval: {est.n} episode{'s' * (est.n != 1)})"
    return f"{fmt(est.value, unit)} [{fmt(est.low, unit)}, {fmt(est.high, unit)}]"
