"""The content of a run's report (``report.md`` / ``report.html``) as document blocks: what
was run, the paper's table and the whole-episode metrics with 95 % intervals, the plots, the
worst episodes and their videos."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from counterscene_env.metrics import PER_SECOND_KEYS
from counterscene_env.report import ranking, stats
from counterscene_env.report.document import (
    Block,
    Bullets,
    Cell,
    Figure,
    Heading,
    Link,
    Paragraph,
    Table,
    Video,
    count,
    fmt,
    interval,
    unit_label,
)
from counterscene_env.report.rundir import Run
from counterscene_env.report.tables import (
    EPISODE_METRICS,
    UNITS,
    episode_table,
    horizon_table,
)
from counterscene_env.sim.config import shown_setting

#: Rows of the worst-episodes table (videos are made for the first few of them).
WORST_ROWS = 10

INTERVALS = (
    f"Intervals are 95 %: rates of episodes ({stats.RATE_METHOD} interval) for the "
    f"whole-episode CR, ego-adversary CR and HBR; means over episodes ({stats.MEAN_METHOD}, "
    "fixed seed) for everything else, including the horizon groups, whose value is the mean "
    "over the group's seconds of the per-second means (as in the paper). n counts the "
    "episodes with a value."
)


@dataclass(frozen=True)
class EpisodeVideo:
    """The video of one worst episode: its files (relative to the report) or why there is
    none, and fields where the replay differed from the record."""

    mp4: Path | None = None
    gif: Path | None = None
    problem: str | None = None
    mismatches: tuple[str, ...] = ()


#: Closed-loop settings the first lines of "What was run" name; the rest are listed after.
_SHOWN = ("selector", "selection_source", "guidance", "num_samples", "replan_every", "duration")


def what_was_run(run: Run, command: str) -> list[Block]:
    ident, sim = run.identity, run.sim()
    planned = run.planned_episodes
    done = len(run.records)
    episodes = count(done, "episode") + (f" of {planned}" if planned and planned != done else "")
    items = [
        f"scenario: {ident.get('scenario', '?')}; {episodes} (episode i: scene i of the source, "
        f"noise seed {ident.get('seed', '?')} + i)",
        f"ego planner: {ident.get('planner', '?')}; world model: {ident.get('model', '?')}",
        f"adversary: selector {sim.get('selector', '?')} on the {sim.get('selection_source', '?')}"
        f", guidance {sim.get('guidance', '?')}, {sim.get('num_samples', '?')} samples per "
        f"replan, replan every {sim.get('replan_every', '?')} steps, episodes of up to "
        f"{sim.get('duration', '?')} s{_short_logs(run, sim.get('duration'))}",
        "other settings: "
        + ", ".join(f"{k}={shown_setting(k, v)}" for k, v in sim.items() if k not in _SHOWN),
    ]
    if planned and done < planned:
        items.append(
            f"unfinished: {done} of {planned} episodes; this report covers the finished ones "
            "(rerun command.txt to finish the run)"
        )
    if run.cut_lines:
        items.append("the last line of episodes.jsonl was cut short by a kill and is left out")
    items.append(_timing(run))
    return [
        Heading("What was run"),
        Bullets(tuple(items)),
        Paragraph(f"Rerun (command.txt): {command}"),
    ]


def _short_logs(run: Run, duration: float | None) -> str:
    """How many episodes ended with their log before ``duration`` s (real logs)."""
    if not isinstance(duration, int | float):
        return ""
    short = sum(float(r.get("rollout_s", duration)) < duration - 1e-6 for r in run.records)
    if not short:
        return ""
    return (
        f" ({short} of {len(run.records)} ended with their log sooner; a horizon counts "
        "only the episodes that reached it)"
    )


def _timing(run: Run) -> str:
    """Wall-clock figures (timings.json, else the records' own): apart from the metrics."""
    t = run.timings or {}
    per_episode = t.get("seconds_per_episode")
    if per_episode is None:
        seconds = [r["seconds"] for r in run.records if isinstance(r.get("seconds"), float)]
        per_episode = sum(seconds) / len(seconds) if seconds else None
    if per_episode is None:
        return "timing: not recorded"
    out = f"timing (not a metric): {per_episode:.3g} s of compute per episode"
    if t.get("wall_seconds") is not None:
        out += f", {t['wall_seconds']:.0f} s wall-clock for the last invocation"
    if t.get("workers", 1) > 1:
        out += f" with {t['workers']} workers"
    return out


def tables(records: Sequence[dict]) -> list[Block]:
    groups = horizon_table(records)
    header = ("horizon", *(f"{k} [{unit_label(UNITS[k])}]" for k in PER_SECOND_KEYS))
    rows = tuple(
        (name, *(interval(row[k], UNITS[k]) for k in PER_SECOND_KEYS))
        for name, row in groups.items()
    )
    whole = episode_table(records)
    whole_rows = tuple(
        (
            EPISODE_METRICS[k].label,
            unit_label(EPISODE_METRICS[k].unit),
            interval(est, EPISODE_METRICS[k].unit),
            str(est.n),
        )
        for k, est in whole.items()
    )
    fallbacks = sum(r.get("fallback") is not None for r in records)
    kinds = Counter(r.get("adversary_type") or "none (fallback)" for r in records)
    return [
        Heading("The paper's table"),
        Paragraph(
            "ADE and FDE: displacement of the non-ego vehicles from the factual log; ORR: "
            "fraction of vehicle-steps off the road; HBR: the ego braked harder than 3 m/s²; "
            "CR: the ego collided; each within the horizon (docs/metrics.md). " + INTERVALS
        ),
        Table(header, rows),
        Heading("Whole episodes"),
        Table(("metric", "unit", "value [95 % interval]", "n"), whole_rows),
        Paragraph(
            f"Adversaries: {len(records) - fallbacks} of {len(records)} episodes had one; "
            "conflict types: " + ", ".join(f"{k} {v}" for k, v in kinds.most_common()) + "."
        ),
    ]


def figures(figs: Sequence[Figure], notes: Sequence[str]) -> list[Block]:
    out: list[Block] = [Heading("Plots"), *figs]
    if notes:
        out.append(Bullets(tuple(notes)))
    return out


def worst(
    records: Sequence[dict], videos: dict[int, EpisodeVideo], note: str | None
) -> list[Block]:
    ranked = ranking.worst_episodes(records, WORST_ROWS)
    rows = []
    for n, r in enumerate(ranked, start=1):
        video = videos.get(r["episode"])
        link: Cell = "-"
        if video and (video.mp4 or video.gif):
            link = Link("MP4" if video.mp4 else "GIF", (video.mp4 or video.gif).as_posix())
        elif video and video.problem:
            link = "not made"
        rows.append(
            (
                str(n),
                str(r["episode"]),
                r["scenario_id"],
                _seeds(r),
                r.get("adversary_id") or "none",
                r.get("adversary_type") or "-",
                ranking.describe(r),
                link,
            )
        )
    blocks: list[Block] = [
        Heading("Worst episodes"),
        Paragraph(
            "Most severe first: a collision, then a collision with the adversary, the smallest "
            "time to collision, the smallest clearance to the adversary, hard braking."
        ),
        Table(
            ("rank", "episode", "scene", "seeds", "adversary", "conflict", "why", "video"),
            tuple(rows),
        ),
        Heading("Videos"),
    ]
    if note:
        blocks.append(Paragraph(note))
    for r in ranked:
        video = videos.get(r["episode"])
        if video is None:
            continue
        caption = f"Episode {r['episode']} ({r['scenario_id']}): {ranking.describe(r)}"
        if video.problem:
            blocks.append(Paragraph(f"{caption}: no video ({video.problem})."))
            continue
        if video.mismatches:
            caption += (
                " - the replay differs from the record in "
                + ", ".join(video.mismatches)
                + " (not the recorded episode: the code or the source changed since the run)"
            )
        blocks.append(Video(video.mp4, video.gif, caption))
    return blocks


def _seeds(record: dict) -> str:
    """``scene S, noise N``: the generated scene's seed (stored scenes have none) and the
    episode's closed-loop seed (with candidate rollouts, the kept candidate's)."""
    scene_seed = record.get("scene_seed")
    scene = "" if scene_seed is None else f"scene {scene_seed}, "
    if "rollout_seed" in record:
        return (
            f"{scene}noise {record['rollout_seed']} "
            f"(candidate {record['rollout']} of {record['rollouts']})"
        )
    return f"{scene}noise {record['seed']}"


def document(
    run: Run,
    command: str,
    figs: Sequence[Figure],
    notes: Sequence[str],
    videos: dict[int, EpisodeVideo],
    video_note: str | None,
) -> list[Block]:
    """The whole report of ``run`` (module docstring)."""
    title = f"Stress report: {run.name}"
    cr = EPISODE_METRICS["cr"].estimate(run.records)
    head = Paragraph(
        f"{count(len(run.records), 'episode')}; the ego collided in "
        f"{fmt(cr.value, 'rate')} % of them "
        f"(95 % interval {fmt(cr.low, 'rate')}-{fmt(cr.high, 'rate')} %)."
    )
    return [
        Heading(title, 1),
        head,
        *what_was_run(run, command),
        *tables(run.records),
        *figures(figs, notes),
        *worst(run.records, videos, video_note),
    ]
