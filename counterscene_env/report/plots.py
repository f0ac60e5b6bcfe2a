"""The report's plots, as PNGs (matplotlib, drawn off-screen: no display needed): rates and
displacements against the horizon second, histograms of per-episode safety margins, and one
plot per metric for a comparison of runs. Every axis is labelled with its unit; every
interval is 95 % (``report.stats``).
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure as MplFigure
from matplotlib.ticker import MaxNLocator

from counterscene_env.report.document import Figure
from counterscene_env.report.stats import Estimate
from counterscene_env.report.tables import EPISODE_METRICS, field

#: The per-episode record field the deceleration histogram reads: the ego's largest
#: deceleration over the rollout, m/s^2, ``max(0, -min a_lon)`` of the ego's signed
#: longitudinal acceleration (``metrics.longitudinal_acceleration``, the samples HBR
#: thresholds at -3 m/s^2); 0 when the ego never slows down.
DECELERATION_FIELD = "ego_peak_deceleration"

DPI = 110

#: Where the PNGs go, relative to the report's directory.
PLOTS = Path("plots")
#: The plots of a run's report (``plots/NAME``).
CR_HBR_PLOT = "cr_hbr_by_second.png"
DISPLACEMENT_PLOT = "ade_fde_by_second.png"
TTC_PLOT = "hist_min_ttc.png"
CLEARANCE_PLOT = "hist_min_clearance.png"
DECELERATION_PLOT = "hist_ego_deceleration.png"
#: Every plot a run's report may draw (a rebuilt report removes those it no longer draws).
REPORT_PLOTS = (CR_HBR_PLOT, DISPLACEMENT_PLOT, TTC_PLOT, CLEARANCE_PLOT, DECELERATION_PLOT)


def _save(fig: MplFigure, root: Path, name: str) -> Path:
    """Write ``root/plots/name``; returns the path relative to ``root``."""
    (root / PLOTS).mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(root / PLOTS / name, dpi=DPI)
    return PLOTS / name


def _errorbar(ax, x, ests: Sequence[Estimate], scale: float = 1.0, **kw) -> None:
    """Points with their interval as error bars (``scale``: 100 for percentages)."""
    v = np.array([e.value for e in ests]) * scale
    lo = np.array([e.low for e in ests]) * scale
    hi = np.array([e.high for e in ests]) * scale
    err = np.nan_to_num(np.stack([v - lo, hi - v]).clip(min=0))
    ax.errorbar(x, v, yerr=err, capsize=3, marker="o", **kw)


def per_second_plots(table: dict[str, dict[str, Estimate]], root: Path) -> list[Figure]:
    """CR and HBR (% of episodes) and ADE and FDE (m) against the horizon second, from
    ``tables.per_second_table``; the PNGs go to ``root/plots/``."""
    rates = _by_second(
        table,
        root,
        (("CR", "CR: ego collided by then"), ("HBR", "HBR: ego braked hard")),
        CR_HBR_PLOT,
        "Collision and hard-braking rate against the horizon",
        "CR and HBR at each horizon second: episodes with an ego collision (hard braking) "
        "at or before it; bars are 95 % Wilson intervals.",
        ylabel="episodes [%]",
        scale=100,
        ylim=(-3, 103),
    )
    displacement = _by_second(
        table,
        root,
        (("ADE", "ADE"), ("FDE", "FDE")),
        DISPLACEMENT_PLOT,
        "Traffic's displacement from the factual log",
        "ADE and FDE of the non-ego vehicles against the factual log at each horizon "
        "second; bars are 95 % bootstrap intervals. FDE is missing past the rollout's end.",
        ylabel="displacement from the log [m]",
    )
    return [rates, displacement]


def _by_second(
    table: dict[str, dict[str, Estimate]],
    root: Path,
    series: tuple[tuple[str, str], tuple[str, str]],
    name: str,
    title: str,
    caption: str,
    ylabel: str,
    scale: float = 1.0,
    ylim: tuple[float, float] | None = None,
) -> Figure:
    """Two ``(key, label)`` series of ``table`` against the horizon second, with intervals."""
    seconds = list(table)
    x = np.array([float(s) for s in seconds])
    fig = MplFigure(figsize=(6.4, 4))
    ax = fig.add_subplot()
    # The two series side by side, so their bars do not hide each other.
    for dx, (key, label) in zip((-0.06, 0.06), series, strict=True):
        _errorbar(ax, x + dx, [table[s][key] for s in seconds], scale, label=label)
    ax.set(xlabel="horizon [s]", ylabel=ylabel, xticks=x)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    return Figure(_save(fig, root, name), caption)


def histograms(records: Sequence[dict], root: Path) -> tuple[list[Figure], list[str]]:
    """Histograms of min TTC (s), min clearance to the adversary (m) and the ego's peak
    deceleration (m/s^2) over episodes; the PNGs go to ``root/plots/``.

    Returns:
        The figures, and a note for each histogram that could not be drawn (no values, or
        the records lack :data:`DECELERATION_FIELD`).
    """
    figures, notes = [], []
    ttc = field("min_ttc")(records)
    no_conflict = int(np.isinf(ttc).sum())
    specs = [
        (
            TTC_PLOT,
            ttc[np.isfinite(ttc)],
            "min TTC [s]",
            f"Smallest constant-velocity time to collision of the ego per episode; "
            f"{no_conflict} episodes with no projected conflict are not shown.",
        ),
        (
            CLEARANCE_PLOT,
            field("min_clearance_adversary")(records),
            "min clearance to the adversary [m]",
            "Smallest box-to-box distance between ego and adversary per episode (0: they "
            "touched); episodes without an adversary are not shown.",
        ),
    ]
    if any(DECELERATION_FIELD in r for r in records):
        specs.append(
            (
                DECELERATION_PLOT,
                field(DECELERATION_FIELD)(records),
                "ego peak deceleration [m/s²]",
                "The ego's largest deceleration per episode; hard braking is above 3 m/s².",
            )
        )
    else:
        notes.append(
            f"No ego deceleration histogram: the episode records have no "
            f"'{DECELERATION_FIELD}' field (the ego's peak deceleration, m/s²)."
        )
    for name, values, xlabel, caption in specs:
        values = values[np.isfinite(values)]
        if not values.size:
            notes.append(f"No histogram of {xlabel}: no episode has a value.")
            continue
        fig = MplFigure(figsize=(6.4, 3.6))
        ax = fig.add_subplot()
        # Every quantity here is >= 0: bins from 0 show how close to nothing they came.
        top = max(float(values.max()), 1e-3)
        bins = min(30, max(5, values.size // 2))
        ax.hist(values, bins=bins, range=(0.0, top), color="#4477aa", edgecolor="white")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        if name == DECELERATION_PLOT:
            ax.axvline(3.0, color="#cc3311", linestyle="--", label="hard braking (3 m/s²)")
            ax.legend()
        ax.set(xlabel=xlabel, ylabel="episodes", xlim=(0.0, None))
        ax.set_title(f"{xlabel.split(' [')[0].capitalize()} per episode", fontsize=10)
        ax.grid(alpha=0.3)
        figures.append(Figure(_save(fig, root, name), caption))
    return figures, notes


def compare_plot(
    key: str, labels: Sequence[str], estimates: Sequence[Estimate], root: Path
) -> Figure:
    """One metric of several runs side by side (one row per run, baseline on top), with
    95 % intervals; ``root/plots/compare_<key>.png``."""
    metric = EPISODE_METRICS[key]
    percent = metric.unit in ("rate", "fraction")
    names = [textwrap.fill(label, 34) for label in labels]  # long labels wrap, not overflow
    lines = sum(n.count("\n") + 1 for n in names)
    fig = MplFigure(figsize=(7.5, 1.2 + 0.3 * lines + 0.25 * len(names)))
    ax = fig.add_subplot()
    y = np.arange(len(names))[::-1]
    scale = 100 if percent else 1
    v = np.array([e.value for e in estimates]) * scale
    err = np.nan_to_num(
        np.stack([v - np.array([e.low for e in estimates]) * scale,
                  np.array([e.high for e in estimates]) * scale - v]).clip(min=0)
    )  # fmt: skip
    ax.errorbar(v, y, xerr=err, capsize=4, marker="o", linestyle="none")
    ax.set_yticks(y, names, fontsize=8)
    unit = "% of episodes" if metric.unit == "rate" else "%" if percent else metric.unit
    ax.set(xlabel=f"{metric.label} [{unit}]", ylim=(-0.6, len(names) - 0.4))
    ax.set_title(f"{metric.label}, 95 % intervals", fontsize=10)
    ax.grid(alpha=0.3, axis="x")
    return Figure(
        _save(fig, root, f"compare_{key}.png"),
        f"{metric.label} of each run with its 95 % interval ({estimates[0].method}).",
    )
