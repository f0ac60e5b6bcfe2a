"""The numbers of a run, with 95 % intervals: the paper's table (ADE, FDE, ORR, HBR, CR for
the horizon groups), the per-second curves, and the whole-episode metrics that reports and
comparisons show (:data:`EPISODE_METRICS`).

The point values are those of ``metrics.aggregate`` (``metrics.json``); the intervals come
from the per-episode values (``report.stats``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from counterscene_env.metrics import GROUPS, PER_SECOND_KEYS, horizon_values, rate_value
from counterscene_env.report import stats
from counterscene_env.report.stats import Estimate

#: Per-second keys that are 0/1 episode flags (a rate), the others being means.
RATE_KEYS = ("CR", "HBR")

#: Unit of each per-second key, for labels.
UNITS = {"ADE": "m", "FDE": "m", "ORR": "fraction", "HBR": "rate", "CR": "rate"}


@dataclass(frozen=True)
class EpisodeMetric:
    """A whole-episode metric of a run.

    Attributes:
        key: its name in JSON output (a record field, or ``ade`` / ``fde``).
        label: its name in tables and on axes.
        unit: ``rate`` (a fraction of episodes), ``fraction``, ``m`` or ``s``.
        is_rate: per-episode 0/1 flags (Wilson interval, McNemar test) rather than values
            (bootstrap intervals, paired bootstrap).
        values: ``records -> [E]`` per-episode values (NaN: not measured).
    """

    key: str
    label: str
    unit: str
    is_rate: bool
    values: Callable[[Sequence[dict]], np.ndarray]

    def estimate(self, records: Sequence[dict]) -> Estimate:
        vals = self.values(records)
        return stats.rate(vals) if self.is_rate else stats.mean(vals)


def field(key: str) -> Callable[[Sequence[dict]], np.ndarray]:
    """``records -> [E]``: record field ``key`` of each episode (NaN where missing), as a
    rate counts it (``metrics.rate_value``: no adversary, no collision with one).

    Records read from a run directory were checked as the file was read (naming its line,
    ``stress.log.record_problem``); records handed over from Python are checked here.

    Raises:
        ValueError: a value that is not a number (naming the episode and the field).
    """

    def values(records: Sequence[dict]) -> np.ndarray:
        out = []
        for i, r in enumerate(records):
            try:
                out.append(rate_value(r, key, r.get(key)))
            except (TypeError, ValueError):
                episode = r.get("episode", i)
                raise ValueError(
                    f"episode {episode}: field {key!r} is {r.get(key)!r}, not a number"
                ) from None
        return np.array(out, dtype=np.float64)

    return values


def last_second(key: str) -> Callable[[Sequence[dict]], np.ndarray]:
    """``records -> [E]``: per-second value ``key`` at each episode's last horizon second
    (the whole rollout, up to 10 s)."""

    def values(records: Sequence[dict]) -> np.ndarray:
        out = []
        for r in records:
            row = r["per_second"][max(r["per_second"], key=float)] if r["per_second"] else {}
            out.append(row.get(key, np.nan))
        return np.array(out, dtype=np.float64)

    return values


def _finite_ttc(records: Sequence[dict]) -> np.ndarray:
    ttc = field("min_ttc")(records)
    return np.where(np.isfinite(ttc), ttc, np.nan)  # inf: no projected conflict, not a value


#: Whole-episode metrics, in table order.
EPISODE_METRICS = {
    m.key: m
    for m in (
        EpisodeMetric("cr", "episode CR (ego collides)", "rate", True, field("cr")),
        EpisodeMetric(
            "cr_ego_adversary", "ego-adversary CR", "rate", True, field("cr_ego_adversary")
        ),
        EpisodeMetric("cr_non_ego", "non-ego CR (traffic)", "rate", True, field("cr_non_ego")),
        EpisodeMetric(
            "cr_non_ego_new",
            "non-ego CR, pairs the log does not have",
            "rate",
            True,
            field("cr_non_ego_new"),
        ),
        EpisodeMetric("hbr_ego", "HBR (ego brakes < -3 m/s²)", "rate", True, field("hbr_ego")),
        EpisodeMetric("orr", "ORR", "fraction", False, field("orr")),
        EpisodeMetric(
            "orr_log",
            "ORR of the log itself (same vehicles and map)",
            "fraction",
            False,
            field("orr_log"),
        ),
        EpisodeMetric("ade", "ADE (whole rollout)", "m", False, last_second("ADE")),
        EpisodeMetric(
            "min_ttc", "min TTC (episodes with a projected conflict)", "s", False, _finite_ttc
        ),
        EpisodeMetric(
            "min_clearance_adversary",
            "min clearance to the adversary",
            "m",
            False,
            field("min_clearance_adversary"),
        ),
    )
}

#: The metrics ``counterscene compare`` puts side by side.
COMPARE_KEYS = ("cr", "cr_ego_adversary", "cr_non_ego_new", "hbr_ego", "orr", "ade")


def per_second_values(records: Sequence[dict], key: str) -> tuple[list[str], np.ndarray]:
    """The horizon seconds of a run (sorted) and ``[E, S]`` per-episode values of per-second
    ``key`` (NaN where an episode has none, or ended before that second)."""
    seconds = sorted({s for r in records for s in r["per_second"]}, key=float)
    values = np.array(
        [[horizon_values(r, s).get(key, np.nan) for s in seconds] for r in records],
        dtype=np.float64,
    ).reshape(len(records), len(seconds))
    return seconds, values


def horizon_table(records: Sequence[dict]) -> dict[str, dict[str, Estimate]]:
    """The paper's table: ``{group: {key: Estimate}}`` for the groups of ``metrics.GROUPS``
    and the keys ``ADE``, ``FDE`` (m), ``ORR``, ``HBR``, ``CR``; each value is the mean over
    the group's seconds of the per-second means, with a bootstrap interval over episodes."""
    out: dict[str, dict[str, Estimate]] = {}
    for name, secs in GROUPS.items():
        row = {}
        for key in PER_SECOND_KEYS:
            seconds, values = per_second_values(records, key)
            cols = [seconds.index(s) for s in (f"{x:g}" for x in secs) if s in seconds]
            row[key] = stats.group_mean(values[:, cols])
        out[name] = row
    return out


def per_second_table(records: Sequence[dict]) -> dict[str, dict[str, Estimate]]:
    """``{second: {key: Estimate}}``: CR and HBR at each horizon second as rates (Wilson),
    ADE, FDE and ORR as means (bootstrap)."""
    out: dict[str, dict[str, Estimate]] = {}
    for key in PER_SECOND_KEYS:
        seconds, values = per_second_values(records, key)
        for j, s in enumerate(seconds):
            est = stats.rate(values[:, j]) if key in RATE_KEYS else stats.mean(values[:, j])
            out.setdefault(s, {})[key] = est
    return out


def episode_table(
    records: Sequence[dict], keys: Sequence[str] | None = None
) -> dict[str, Estimate]:
    """``{key: Estimate}`` of the whole-episode metrics ``keys`` (default: all of
    :data:`EPISODE_METRICS`)."""
    return {k: EPISODE_METRICS[k].estimate(records) for k in keys or EPISODE_METRICS}
