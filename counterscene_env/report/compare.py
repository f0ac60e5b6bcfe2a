"""Several stress runs side by side (``counterscene compare``): episode CR, ego-adversary CR,
HBR, ORR and ADE of each run with 95 % intervals, and, for every run that shares episodes
with the first one (the baseline), the paired difference to it with a test that says whether
it lies outside the noise (``report.stats``).

Two runs share an episode when both ran the same scene (``scenario_id``, ``scene_seed``) with
the same closed-loop seed (``seed``): same scenario spec and ``--seed``, so episode i of
one is episode i of the other, whatever their planner, guidance or episode count. Only those
episodes enter the paired test; the per-run intervals use all of each run's episodes.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from counterscene_env.metrics import json_safe
from counterscene_env.report import html, markdown, stats
from counterscene_env.report.document import (
    Block,
    Bullets,
    Figure,
    Heading,
    Paragraph,
    Table,
    count,
    fmt,
    interval,
    unit_label,
)
from counterscene_env.report.plots import compare_plot
from counterscene_env.report.rundir import Run, load_run
from counterscene_env.report.stats import Estimate, Paired
from counterscene_env.report.tables import COMPARE_KEYS, EPISODE_METRICS
from counterscene_env.sim.config import shown_setting
from counterscene_env.stress.config import effective_identity

#: Identity keys left out of labels: ``batch`` does not change an episode's outcome, and a
#: difference of ``metrics_version`` is a warning of its own (:func:`compare_runs`).
_NOT_SETTINGS = ("batch", "metrics_version")


@dataclass(frozen=True)
class PairedRun:
    """A run against the baseline over the episodes both ran.

    Attributes:
        run: index of the run (into ``Comparison.runs``; the baseline is 0).
        shared: episodes both ran.
        metrics: ``{key: Paired}`` for :data:`tables.COMPARE_KEYS` (empty: nothing shared).
    """

    run: int
    shared: int
    metrics: dict[str, Paired]


@dataclass(frozen=True)
class Comparison:
    """Runs side by side (module docstring).

    Attributes:
        runs: the runs, baseline first; labels: one name each (the directory's name, plus
            the settings that differ between the runs).
        estimates: ``{key: [Estimate per run]}``.
        paired: one :class:`PairedRun` per run after the baseline.
        warnings: one sentence per run that is unfinished (:func:`unfinished`), and one if
            the runs were scored by different metric definitions, shown first
            in every output.
    """

    runs: list[Run]
    labels: list[str]
    estimates: dict[str, list[Estimate]]
    paired: list[PairedRun]
    warnings: list[str] = field(default_factory=list)


def compare_runs(directories: Sequence[str | os.PathLike]) -> Comparison:
    """Compare the stress runs in ``directories`` (the first is the baseline).

    Raises:
        ValueError: fewer than two directories, or one given twice.
        FileNotFoundError, ValueError: a directory is not a readable run
            (``report.rundir.load_run``; the message names the file and the field).
    """
    if isinstance(directories, str | os.PathLike):
        raise TypeError("directories must be a list of run directories, not one path")
    if len(directories) < 2:
        raise ValueError(f"compare needs at least two run directories, got {len(directories)}")
    resolved = [Path(d).resolve() for d in directories]
    twice = sorted({str(d) for d in resolved if resolved.count(d) > 1})
    if twice:
        raise ValueError(f"run directory given more than once: {', '.join(twice)}")
    runs = [load_run(d) for d in directories]
    estimates = {k: [EPISODE_METRICS[k].estimate(r.records) for r in runs] for k in COMPARE_KEYS}
    paired = [_paired(runs[0], run, i) for i, run in enumerate(runs) if i]
    labels = _labels(runs)
    warnings = [w for label, r in zip(labels, runs, strict=True) if (w := unfinished(label, r))]
    versions = {r.identity.get("metrics_version", 1) for r in runs}  # none recorded: 1
    if len(versions) > 1:
        warnings.append(
            "the runs were scored by different definitions of the metrics (metrics_version "
            f"{', '.join(map(str, sorted(versions)))}; docs/metrics.md): their rates are not "
            "comparable"
        )
    return Comparison(runs, labels, estimates, paired, warnings)


def episode_key(record: dict) -> tuple:
    """What makes two records the same episode: the scene and the closed-loop seed."""
    return (record["scenario_id"], record.get("scene_seed"), record["seed"])


def _paired(base: Run, run: Run, index: int) -> PairedRun:
    theirs = {episode_key(r): r for r in run.records}
    pairs = [(r, theirs[k]) for r in base.records if (k := episode_key(r)) in theirs]
    if not pairs:
        return PairedRun(index, 0, {})
    a, b = [p[0] for p in pairs], [p[1] for p in pairs]
    out = {}
    for key in COMPARE_KEYS:
        metric = EPISODE_METRICS[key]
        test = stats.paired_rate if metric.is_rate else stats.paired_mean
        out[key] = test(metric.values(a), metric.values(b))
    return PairedRun(index, len(pairs), out)


#: How a label spells a setting a run did not record.
NOT_RECORDED = "not recorded"


def _flat(identity: dict) -> dict:
    """A run's settings as one flat dict, each as it took effect: run.json leaves some out at
    their default (``stress.config.effective_identity`` puts them back), and a closed-loop
    setting of None is shown as what it means (``sim.config.shown_setting``)."""
    ident = effective_identity(identity)
    out = {k: v for k, v in ident.items() if k != "sim" and k not in _NOT_SETTINGS}
    out.update({k: shown_setting(k, v) for k, v in ident["sim"].items()})
    return out


def _labels(runs: Sequence[Run]) -> list[str]:
    """Each run's directory name plus the settings in which the runs differ."""
    flats = [_flat(r.identity) for r in runs]
    every = {k for f in flats for k in f}
    keys = sorted(
        k
        for k in every
        if len({json.dumps(f.get(k, NOT_RECORDED), sort_keys=True) for f in flats}) > 1
    )
    names = [r.name for r in runs]
    if len(set(names)) < len(names):  # same directory names: tell them apart by their paths
        names = [str(r.directory) for r in runs]
    settings = [", ".join(f"{k}={_short(f.get(k, NOT_RECORDED))}" for k in keys) for f in flats]
    return [f"{n} ({s})" if keys else n for n, s in zip(names, settings, strict=True)]


def unfinished(label: str, run: Run) -> str | None:
    """A warning when ``run`` holds fewer episodes than it was started for (None: it holds
    them all): ``"run LABEL is unfinished: 37 of 200 episodes"``, or that its
    ``metrics.json``, which says how many were asked for, is missing."""
    done = len(run.records)
    if run.complete is None:
        return (
            f"run {label} has no metrics.json: whether its {count(done, 'episode')} are the "
            "whole run is unknown"
        )
    if not run.complete:
        return f"run {label} is unfinished: {done} of {run.planned_episodes} episodes"
    return None


#: Longest setting value spelled out in a run's label; longer ones (a borrowed env config) are
#: cut, their whole value stays in the run's run.json.
LABEL_VALUE_CHARS = 40


def _short(value) -> str:
    text = str(value)
    return text if len(text) <= LABEL_VALUE_CHARS else text[: LABEL_VALUE_CHARS - 3] + "..."


def verdict(c: Comparison, p: PairedRun, key: str) -> str:
    """One sentence on a paired difference: its size and interval, and whether it is outside
    the noise."""
    d = p.metrics[key]
    if not d.n:
        return "no shared episode with a value"
    metric = EPISODE_METRICS[key]
    # A difference of two percentages is in percentage points.
    unit = "points" if unit_label(metric.unit) == "%" else metric.unit
    size = (
        f"{fmt(d.difference, metric.unit)} {unit} [{fmt(d.low, metric.unit)}, "
        f"{fmt(d.high, metric.unit)}] over {d.n} shared episodes"
    )
    if d.p_value is not None:
        size += f", McNemar p = {d.p_value:.3g} ({d.a_only} vs {d.b_only} discordant)"
    if not d.significant:
        return f"inside the noise: {size}"
    direction = "higher" if d.difference > 0 else "lower"
    return f"{direction} than {c.labels[0]}, outside the noise: {size}"


def document(c: Comparison, figures: Sequence[Figure] = ()) -> list[Block]:
    """The comparison as report blocks (tables, paired tests, plots)."""
    header = ("metric", "unit", *c.labels)
    rows = tuple(
        (
            EPISODE_METRICS[k].label,
            unit_label(EPISODE_METRICS[k].unit),
            *(f"{interval(e, EPISODE_METRICS[k].unit)} (n={e.n})" for e in ests),
        )
        for k, ests in c.estimates.items()
    )
    blocks: list[Block] = [Heading("Comparison of stress runs", 1)]
    if c.warnings:
        blocks.append(
            Paragraph(
                "Warning: "
                + "; ".join(c.warnings)
                + ". An unfinished run's figures cover its finished episodes only, and a "
                "paired test the episodes both runs finished; its stress command rerun with "
                "--resume (command.txt in its directory) finishes it."
            )
        )
    blocks += [
        Bullets(
            tuple(
                f"{label}: {r.directory}, {_episodes(r)}"
                for label, r in zip(c.labels, c.runs, strict=True)
            )
        ),
        Paragraph(
            "Values with 95 % intervals: rates of episodes with a Wilson interval (CR, "
            "ego-adversary CR, HBR), means over episodes with a percentile bootstrap interval "
            "(ORR, ADE over the whole rollout)."
        ),
        Table(header, rows),
        Heading("Paired differences to the baseline", 2),
        Paragraph(
            f"Each run minus {c.labels[0]} over the episodes both ran (same scene and seed). "
            "Rates: McNemar's exact test (p < 0.05) on the episodes where the two runs "
            "disagree; means: whether the paired bootstrap 95 % interval excludes 0. Anything "
            "else is inside the noise: more episodes would be needed to tell the runs apart."
        ),
    ]
    for p in c.paired:
        label = c.labels[p.run]
        if not p.shared:
            blocks.append(
                Paragraph(
                    f"{label}: no episode in common with {c.labels[0]} (other scenario or "
                    "seeds), so no paired test; compare the intervals above."
                )
            )
            continue
        blocks.append(Heading(f"{label} vs {c.labels[0]} ({p.shared} shared episodes)", 3))
        blocks.append(
            Bullets(tuple(f"{EPISODE_METRICS[k].label}: {verdict(c, p, k)}" for k in p.metrics))
        )
    if figures:
        blocks += [Heading("Plots", 2), *figures]
    return blocks


def _episodes(run: Run) -> str:
    """``"8 episodes"``, or ``"3 of 8 episodes (unfinished)"``."""
    if run.complete is False:
        return f"{len(run.records)} of {count(run.planned_episodes, 'episode')} (unfinished)"
    return count(len(run.records), "episode")


def to_json(c: Comparison) -> dict:
    """The comparison as plain JSON values (NaN and inf as null). Each run has ``complete``
    (false: unfinished; null: no ``metrics.json`` to tell) and ``episodes_requested``;
    ``warnings`` repeats the comparison's warnings."""
    out = {
        "warnings": list(c.warnings),
        "runs": [
            {
                "label": label,
                "directory": str(r.directory),
                "episodes": len(r.records),
                "episodes_requested": r.planned_episodes,
                "complete": r.complete,
            }
            for label, r in zip(c.labels, c.runs, strict=True)
        ],
        "metrics": {
            k: {
                "label": EPISODE_METRICS[k].label,
                "unit": EPISODE_METRICS[k].unit,
                "runs": [e.to_dict() for e in ests],
            }
            for k, ests in c.estimates.items()
        },
        "paired": [
            {
                "baseline": c.labels[0],
                "run": c.labels[p.run],
                "shared_episodes": p.shared,
                "metrics": {
                    k: {**d.to_dict(), "verdict": verdict(c, p, k)} for k, d in p.metrics.items()
                },
            }
            for p in c.paired
        ],
    }
    return json_safe(out)


def write_comparison(c: Comparison, out: str | os.PathLike) -> Path:
    """``out/compare.md``, ``out/compare.html`` (self-contained), ``out/compare.json`` and
    ``out/plots/compare_<metric>.png``; returns the html's path."""
    root = Path(out)
    if root.exists() and not root.is_dir():
        raise ValueError(f"--out {root} is a file, not a directory")
    root.mkdir(parents=True, exist_ok=True)
    figures = [compare_plot(k, c.labels, ests, root) for k, ests in c.estimates.items()]
    blocks = document(c, figures)
    (root / "compare.md").write_text(markdown.render(blocks))
    (root / "compare.json").write_text(json.dumps(to_json(c), indent=2) + "\n")
    page = root / "compare.html"
    page.write_text(html.render(blocks, root, "Comparison of stress runs"))
    return page
