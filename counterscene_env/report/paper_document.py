"""``counterscene paper-tables`` output: ``tables.md`` (the page ``docs/reproducing_the_paper.md``
is made from) and ``tables.json`` (every figure with its interval and paired test), written
from the runs' records by ``report.paper_tables``. Compute times go to ``timings.json`` (and
to ``tables.md``'s table headers), not to ``tables.json``, so two runs of the same episodes
give the same ``tables.json`` results.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

from counterscene_env.metrics import json_safe
from counterscene_env.report.document import count, fmt, interval
from counterscene_env.report.paper_tables import (
    COLUMNS,
    EPISODE,
    EPISODE_RATES,
    METRICS,
    PAIRED,
    PAPER,
    PAPER_SOURCE,
    TITLES,
    table,
    to_json,
)


def build(
    results: dict[str, dict[str, list[dict]]],
    table_rows: dict[str, Sequence[str]],
    tables_of: dict[str, Sequence[str]],
    labels: dict[str, str],
    paper_names: dict[str, str | None],
) -> dict:
    """``{"tables": {scenario: {table: cells}}, "missing": {scenario: {table: [row]}}, ...}``:
    the cells (``paper_tables.table``) of every table a scenario has (``tables_of[scenario]``)
    from the rows of ``table_rows[table]`` it ran, and the rows it has no episode of yet
    (``--tables-only`` before every row ran), which the markdown and ``tables.json`` name
    rather than leave out in silence."""
    out: dict = {}
    missing: dict = {}
    for where, names in tables_of.items():
        runs = results.get(where, {})
        for name in names:
            rows = {r: runs[r] for r in table_rows[name] if r in runs}
            absent = [r for r in table_rows[name] if r not in runs]
            if absent:
                missing.setdefault(where, {})[name] = absent
            if rows:
                out.setdefault(where, {})[name] = table(name, rows)
    return {
        "tables": out,
        "missing": missing,
        "reference": {t: rows[0] for t, rows in table_rows.items()},
        "labels": labels,
        "paper_names": paper_names,
    }


def missing_lines(built: dict, meta: dict) -> list[str]:
    """Markdown naming the rows with no episode yet, per scenario and table, and the command
    that runs them (empty when every row has episodes)."""
    if not built.get("missing"):
        return []
    labels = built["labels"]
    lines = [
        "**Rows not run yet**: no episode of these rows is in the output directory, so the "
        "tables below leave them out:",
        "",
    ]
    for where, tables in built["missing"].items():
        for name, rows in tables.items():
            names = ", ".join(f"{labels.get(r, r)} (`{where}/{r}/`)" for r in rows)
            lines.append(f"- {where}, {name} table: {names}")
            reference = built["reference"].get(name)
            kept = built["tables"].get(where, {}).get(name)
            if reference in rows and kept:
                lines[-1] += (
                    f"; the table's reference row {labels.get(reference, reference)} is among "
                    f"them, so its rows are paired with {labels.get(next(iter(kept)), '?')}"
                    " instead"
                )
    command = meta.get("run_command") or "the same command without --tables-only"
    lines += ["", f"Run them with: `{command}` (it resumes the rows already run).", ""]
    return lines


def write(out: str | Path, built: dict, meta: dict, seconds: dict[str, dict[str, float]]) -> Path:
    """Write ``tables.json``, ``tables.md`` and ``timings.json`` to ``out``; returns the
    markdown's path. ``meta``: the command, planner, episodes, seed, model; ``seconds``:
    ``{scenario: {row: compute seconds}}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tables = built["tables"]
    doc = {
        **meta,
        "tables": {w: {t: to_json(c) for t, c in ts.items()} for w, ts in tables.items()},
        # Rows with no episode yet, per scenario and table: left out of "tables" above.
        "missing_rows": built.get("missing", {}),
        "paper": {t: {"source": PAPER_SOURCE[t], "rows": PAPER[t]} for t in PAPER},
    }
    (out / "tables.json").write_text(json.dumps(json_safe(doc), indent=1) + "\n")
    (out / "timings.json").write_text(
        json.dumps(json_safe({"row_seconds": seconds}), indent=1) + "\n"
    )
    page = out / "tables.md"
    page.write_text(markdown(built, meta, seconds))
    return page


def markdown(built: dict, meta: dict, seconds: dict[str, dict[str, float]]) -> str:
    """The tables as one markdown document."""
    lines = [
        "# The paper's tables",
        "",
        f"Command: `{meta['command']}`",
        "",
        f"Planner `{meta['planner']}`, "
        + (
            f"the episodes run so far of {meta['episodes']} per row (n below)"
            if meta.get("tables_only")
            else f"{count(meta['episodes'], 'episode')} per row"
        )
        + " from seed "
        f"{meta['seed']} (every row on the same scenes and noise), model `{meta['model']}`"
        + (
            f", up to {meta['egos']} ego choices per real scene (the recorded ego first)"
            if meta.get("egos", 1) > 1
            else ""
        )
        + (
            f", real scenes with at least {meta['min_future']:g} s of log after their start"
            if meta.get("min_future") and any("real" in t for t in built["tables"].values())
            else ""
        )
        + (
            f", each episode the most severe of {meta['rollouts']} candidate rollouts"
            if meta.get("rollouts", 1) > 1
            else ""
        )
        + (f", closed-loop settings {meta['settings']}." if meta.get("settings") else "."),
        "Values: `value [95 % interval]`; rates and ORR in %, ADE and FDE in m. A single "
        "horizon's rate has a Wilson interval, means and averages over several seconds a "
        "bootstrap interval over episodes. CR ego-adversary counts an episode without an "
        "adversary as no collision with one. HBR -3: the ego brakes harder than 3 m/s² within "
        "the horizon; HBR -6: at 6 m/s² (the IDM's full braking) or harder.",
        "",
        "The paper's rows are its own figures (its data set, its models), printed for "
        "reference, not comparable data; its HBR is a share of all agents' steps, not the "
        "ego's, and its CR the ego-adversary one.",
        "",
        *missing_lines(built, meta),
    ]
    for where, tables in built["tables"].items():
        lines += [f"## {where}", ""]
        for name, cells in tables.items():
            lines += _table(name, cells, built, seconds.get(where, {}))
    return "\n".join(lines) + "\n"


def _table(name: str, cells: dict, built: dict, seconds: dict[str, float]) -> list[str]:
    labels, paper_names = built["labels"], built["paper_names"]
    rows = list(cells)
    took = sum(seconds.get(r, 0.0) for r in rows)
    lines = [f"### {TITLES[name]}", ""]
    lines += [
        f"Compute time of its rows: {took / 60:.1f} min (rows shared between tables "
        "count in each).",
        "",
    ]
    head = (
        "| row | n | "
        + " | ".join(
            f"{label} ({'%' if unit in ('rate', 'fraction') else unit})"
            for label, unit, _ in METRICS.values()
        )
        + " |"
    )
    for column in COLUMNS[name]:
        lines += [f"#### {column}", "", head, "|" + "---|" * (len(METRICS) + 2)]
        for row in rows:
            metrics = cells[row][column]
            n = max(c.estimate.n for c in metrics.values())
            vals = [interval(metrics[k].estimate, METRICS[k][1]) for k in METRICS]
            lines.append(f"| {labels[row]} | {n} | " + " | ".join(vals) + " |")
        for row in rows:
            figures = PAPER.get(name, {}).get(paper_names.get(row) or "", {}).get(column)
            if figures is not None:
                lines.append(_paper_row(paper_names[row], name, figures))
        lines += ["", _paired_lines(rows, cells, column, labels), ""]
    lines += _episode_table(rows, cells, labels)
    return lines


def _episode_table(rows: list[str], cells: dict, labels: dict) -> list[str]:
    """The whole-episode rates (``paper_tables.EPISODE_RATES``), each row paired with the
    reference."""
    lines = [
        f"#### {EPISODE}",
        "",
        "CR third parties: two agents other than the ego collide, a pair whose boxes do not "
        "overlap in the log too.",
        "",
        "| row | n | " + " | ".join(f"{label} (%)" for label in EPISODE_RATES.values()) + " |",
        "|" + "---|" * (len(EPISODE_RATES) + 2),
    ]
    for row in rows:
        metrics = cells[row][EPISODE]
        n = max(c.estimate.n for c in metrics.values())
        vals = [interval(metrics[k].estimate, "rate") for k in EPISODE_RATES]
        lines.append(f"| {labels[row]} | {n} | " + " | ".join(vals) + " |")
    lines += ["", f"Paired with {labels[rows[0]]} ({EPISODE}, row minus reference):", ""]
    for row in rows[1:]:
        parts = []
        for key, label in EPISODE_RATES.items():
            test = cells[row][EPISODE][key].paired
            if test is None or test.n == 0 or math.isnan(test.difference):
                parts.append(f"{label} n/a")
                continue
            verdict = "outside the noise" if test.significant else "inside the noise"
            d, lo, hi = (_signed(100 * x) for x in (test.difference, test.low, test.high))
            parts.append(
                f"{label} {d} points [{lo}, {hi}], {test.a_only} against {test.b_only} "
                f"discordant, p = {test.p_value:.2g}, {verdict}"
            )
        lines.append(f"- {labels[row]}: " + "; ".join(parts))
    return [*lines, ""]


def _paper_row(paper_name: str, name: str, figures: tuple) -> str:
    """The paper's (ADE, FDE, ORR, HBR, CR) placed in our columns (HBR -> HBR -3, CR ->
    CR ego-adversary), marked as the paper's."""
    ade, fde, orr, hbr, cr = figures
    by_key = {"ADE": ade, "FDE": fde, "ORR": orr, "HBR3": hbr, "CR_adv": cr}
    vals = [fmt(by_key[k], METRICS[k][1]) if k in by_key else "" for k in METRICS]
    return f"| *paper: {paper_name} ({PAPER_SOURCE[name]})* | | " + " | ".join(vals) + " |"


def _paired_lines(rows: list[str], cells: dict, column: str, labels: dict) -> str:
    """One line per row: its difference to the reference row, and whether it is outside
    the noise."""
    out = [f"Paired with {labels[rows[0]]} ({column}, row minus reference):", ""]
    for row in rows[1:]:
        parts = []
        for key in PAIRED:
            test = cells[row][column][key].paired
            if test is None or math.isnan(test.difference):
                parts.append(f"{METRICS[key][0]} n/a")
                continue
            unit = METRICS[key][1]
            scale, suffix = (100, " points") if unit in ("rate", "fraction") else (1, " m")
            verdict = "outside the noise" if test.significant else "inside the noise"
            p = "" if test.p_value is None else f", p = {test.p_value:.2g}"
            d, lo, hi = (_signed(scale * x) for x in (test.difference, test.low, test.high))
            parts.append(f"{METRICS[key][0]} {d}{suffix} [{lo}, {hi}]{p}, {verdict}")
        out.append(
            f"- {labels[row]} (n = {cells[row][column][PAIRED[0]].paired.n}): " + "; ".join(parts)
        )
    return "\n".join(out)


def _signed(x: float) -> str:
    """A difference with its sign, 3 significant digits; rounding noise shows as 0, no
    value (an interval of one pair) as n/a."""
    if math.isnan(x):
        return "n/a"
    return "0" if abs(x) < 1e-9 else f"{x:+.3g}"
