"""The paper's tables from the runs of ``counterscene paper-tables``, every figure with its
95 % interval and every row tested against CounterScene on the shared episodes.

Tables (rows: ``stress.paper.TABLE_ROWS``; metrics: :data:`METRICS`):

- ``main``: the paper's main table, values averaged over the horizon groups 1-4 s, 5-7 s and
  8-10 s (the mean over the group's seconds of each second's mean over episodes);
- ``selection``: the selectors, averaged over 3 s and 7 s (the paper's selection table);
- ``ablation``: the guidance ablations at 3 s, 7 s and 10 s (the paper's appendix table);
- ``real``: real logs at 3 s, 5 s and 7 s (the shape of the paper's zero-shot table). A log
  whose rollout ends before a horizon gives no value there, except an episode that ended in
  the ego's collision, which counts as collided (``metrics.horizon_values``); nothing is
  extrapolated.

Under every table, the whole-episode rates (:data:`EPISODE_RATES`): the ego's collisions over
the whole rollout, and collisions between two other agents that the log does not have.

Metrics. ADE, FDE (m) and ORR as in ``metrics``, with the log's own ORR beside it (its
logged positions on the same map); two CRs, named: **CR ego-adversary** (the
paper's main text: the ego collides with the selected adversary; an episode without an
adversary counts as no such collision) and **CR ego-any** (the paper's appendix and
``docs/metrics.md``: the ego collides with anyone); two HBRs on the ego's signed longitudinal
acceleration: **HBR -3** (the paper's -3 m/s^2) and **HBR -6** (an emergency stop: about
0.6 g, beyond the -3 to -5 m/s^2 of firm comfort braking that a careful driver uses at a
junction, docs/reproducing_the_paper.md). Rates are shares of episodes.

Intervals: a single horizon's rate gets a Wilson interval, every mean and every group
average a bootstrap interval over episodes (``report.stats``). Each row is paired with the
CounterScene row on the episodes both ran: McNemar's exact test for a single horizon's rate,
a paired bootstrap for the rest.

The paper's own figures (:data:`PAPER`) are printed beside ours as what they are: nuScenes
(zero-shot: nuPlan) results of the paper's models, not comparable data.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from counterscene_env.metrics import (
    HARD_BRAKE_THRESHOLD,
    brakes_at_least,
    horizon_values,
    is_hard_braking,
    rate_value,
)
from counterscene_env.report import stats
from counterscene_env.report.stats import Estimate, Paired
from counterscene_env.report.tables import field

#: Metric -> (label, unit, is a rate). Values come from the records' per-second entries.
METRICS = {
    "ADE": ("ADE", "m", False),
    "FDE": ("FDE", "m", False),
    "ORR": ("ORR", "fraction", False),
    # The same vehicles' logged positions over the same steps on the same map: a real map
    # lacks the car parks and driveways where logged cars stand, so ORR reads against this.
    "ORR_log": ("ORR of the log", "fraction", False),
    "HBR3": ("HBR -3", "rate", True),
    "HBR6": ("HBR -6", "rate", True),
    "CR_adv": ("CR ego-adversary", "rate", True),
    "CR": ("CR ego-any", "rate", True),
}
#: The two HBR columns: whether an episode's strongest braking within the horizon (``DEC``,
#: m/s^2, positive) flags it. HBR -3 is the paper's, braking harder than 3 m/s^2; HBR -6 is
#: braking at 6 m/s^2 or harder: highway-env's IDM never commands more than 6, so it flags an
#: ego that needed all of its brakes (a strict "harder than 6" flagged that only where floats
#: rounded the finite difference above 6).
HBR_RULES: dict[str, Callable[[float], bool]] = {
    "HBR3": lambda dec: bool(is_hard_braking(-dec, HARD_BRAKE_THRESHOLD)),
    "HBR6": lambda dec: bool(brakes_at_least(dec, 6.0)),
}

#: Each table's columns: name -> the horizon seconds averaged in it.
COLUMNS = {
    "main": {"1-4s": (1, 2, 3, 4), "5-7s": (5, 6, 7), "8-10s": (8, 9, 10)},
    "selection": {"3s+7s": (3, 7)},
    "ablation": {"3s": (3,), "7s": (7,), "10s": (10,)},
    "real": {"3s": (3,), "5s": (5,), "7s": (7,)},
}
TITLES = {
    "main": "Main results by horizon (the paper's main table)",
    "selection": "Agent selection, averaged over 3 s and 7 s (the paper's selection table)",
    "ablation": "Guidance ablations at 3 s, 7 s and 10 s (the paper's appendix table)",
    "real": "Real logs at 3 s, 5 s and 7 s (the shape of the paper's zero-shot table)",
}
#: The metrics paired with the CounterScene row in every table.
PAIRED = ("CR_adv", "CR", "ADE")

#: The column of whole-episode rates under every table (record key -> label), each paired
#: with the CounterScene row: the ego's collisions over the whole rollout, and collisions
#: between two other agents that the log does not have (``metrics.evaluate_scene``'s
#: ``cr_non_ego_new``: real logs hold overlapping boxes of their own).
EPISODE = "whole episode"
EPISODE_RATES = {
    "cr": "CR ego-any",
    "cr_ego_adversary": "CR ego-adversary",
    "cr_non_ego_new": "CR third parties",
}

# The paper's figures: {table: {paper row: {column: (ADE, FDE, ORR, HBR, CR)}}}, ORR, HBR,
# CR as fractions. Its HBR is a share of agent-steps and its CR the ego-adversary one.
PAPER = {
    "main": {
        "CounterScene": {
            "1-4s": (0.288, 0.703, 0.005, 0.016, 0.033),
            "5-7s": (0.982, 2.639, 0.013, 0.020, 0.147),
            "8-10s": (1.877, 5.141, 0.019, 0.018, 0.227),
        },
    },
    "selection": {
        "Random": {"3s+7s": (1.024, 2.696, 0.014, 0.018, 0.100)},
        "CCDiff": {"3s+7s": (1.036, 2.708, 0.014, 0.017, 0.080)},
        "SafeSim": {"3s+7s": (1.004, 2.643, 0.013, 0.017, 0.095)},
        "CounterScene": {"3s+7s": (0.721, 1.898, 0.011, 0.018, 0.110)},
    },
    "ablation": {
        name: dict(zip(("3s", "7s", "10s"), values, strict=True))
        for name, values in {
            "CounterScene": (
                (0.338, 0.814, 0.005, 0.017, 0.04),
                (1.155, 3.141, 0.014, 0.019, 0.18),
                (2.320, 6.380, 0.022, 0.021, 0.32),
            ),
            "No Jerk": (
                (0.362, 0.875, 0.006, 0.015, 0.04),
                (1.205, 3.320, 0.015, 0.017, 0.17),
                (2.380, 6.560, 0.023, 0.019, 0.30),
            ),
            "No Conflict Aware": (
                (0.350, 0.845, 0.006, 0.015, 0.03),
                (1.185, 3.260, 0.015, 0.017, 0.15),
                (2.350, 6.500, 0.023, 0.019, 0.27),
            ),
            "No Progressive": (
                (0.355, 0.855, 0.006, 0.015, 0.03),
                (1.195, 3.290, 0.015, 0.017, 0.15),
                (2.360, 6.520, 0.023, 0.019, 0.27),
            ),
            "No Adaptive": (
                (0.340, 0.820, 0.005, 0.016, 0.02),
                (1.165, 3.180, 0.014, 0.018, 0.13),
                (2.330, 6.420, 0.022, 0.020, 0.24),
            ),
            "Minimal": (
                (0.372, 0.895, 0.007, 0.013, 0.02),
                (1.225, 3.420, 0.017, 0.015, 0.11),
                (2.420, 6.700, 0.025, 0.018, 0.20),
            ),
        }.items()
    },
    "real": {
        "CounterScene": {
            "3s": (0.535, 1.293, 0.009, 0.176, 0.054),
            "5s": (1.111, 2.782, 0.014, 0.164, 0.228),
            "7s": (2.021, 5.020, 0.015, 0.155, 0.402),
        },
    },
}
PAPER_SOURCE = {
    "main": "nuScenes, the paper's main table",
    "selection": "nuScenes, the paper's selection table",
    "ablation": "nuScenes, the paper's appendix ablation table",
    "real": "nuPlan zero-shot, the paper's transfer table",
}


@dataclass(frozen=True)
class Cell:
    """One metric of one row in one column: its estimate and, for rows other than the
    reference, the paired difference to the reference row (None for the reference)."""

    estimate: Estimate
    paired: Paired | None = None


def per_episode(records: Sequence[dict], key: str, seconds: Sequence[int]) -> np.ndarray:
    """``[E, S]`` value of metric ``key`` at each of ``seconds`` per episode; NaN where the
    episode's rollout did not reach that second (or nothing was measured)."""
    out = np.full((len(records), len(seconds)), np.nan)
    for i, r in enumerate(records):
        for j, s in enumerate(seconds):
            row = horizon_values(r, f"{s:g}")
            if row:
                out[i, j] = _value(r, row, key)
    return out


def episode_flags(records: Sequence[dict], key: str) -> np.ndarray:
    """``[E]`` whole-episode 0/1 flag ``key`` (of :data:`EPISODE_RATES`) per episode; NaN
    where a record lacks it (one written before the key existed); as every report reads a
    record field (``report.tables.field``)."""
    return field(key)(records)


def _value(record: dict, row: dict, key: str) -> float:
    if key in HBR_RULES:
        dec = row.get("DEC")
        if dec is None:  # a record written before DEC existed: only the -3 threshold
            return row.get("HBR", math.nan) if key == "HBR3" else math.nan
        return math.nan if math.isnan(dec) else float(HBR_RULES[key](dec))
    return rate_value(record, key, row.get(key))


def estimate(values: np.ndarray, is_rate: bool) -> Estimate:
    """A column's estimate from ``[E, S]`` values: one second's rate (Wilson) or mean, or a
    group average (bootstrap)."""
    if values.shape[1] == 1:
        return stats.rate(values[:, 0]) if is_rate else stats.mean(values[:, 0])
    return stats.group_mean(values)


def paired(reference: np.ndarray, other: np.ndarray, is_rate: bool) -> Paired:
    """The other row minus the reference over shared episodes (rows ``[E, S]``, episode i
    of one is episode i of the other)."""
    n = min(len(reference), len(other))
    if reference.shape[1] == 1 and is_rate:
        return stats.paired_rate(reference[:n, 0], other[:n, 0])
    with warnings.catch_warnings():  # an episode with no value in the columns: NaN, left out
        warnings.simplefilter("ignore", RuntimeWarning)
        a, b = np.nanmean(reference[:n], 1), np.nanmean(other[:n], 1)
    return stats.paired_mean(a, b)


def table(table_name: str, runs: dict[str, Sequence[dict]]) -> dict[str, dict[str, dict]]:
    """``{row: {column: {metric: Cell}}}`` for the rows of ``runs`` (``{row: records}``,
    the reference row first)."""
    rows = list(runs)
    reference = rows[0]
    out: dict[str, dict[str, dict]] = {}
    for column, seconds in COLUMNS[table_name].items():
        for key, (_, _, is_rate) in METRICS.items():
            ref = per_episode(runs[reference], key, seconds)
            for row in rows:
                values = ref if row == reference else per_episode(runs[row], key, seconds)
                test = None
                if row != reference and key in PAIRED:
                    test = paired(ref, values, is_rate)
                cell = Cell(estimate(values, is_rate), test)
                out.setdefault(row, {}).setdefault(column, {})[key] = cell
    for key in EPISODE_RATES:
        ref = episode_flags(runs[reference], key)
        for row in rows:
            flags = ref if row == reference else episode_flags(runs[row], key)
            n = min(len(ref), len(flags))
            test = None if row == reference else stats.paired_rate(ref[:n], flags[:n])
            out[row].setdefault(EPISODE, {})[key] = Cell(stats.rate(flags), test)
    return out


def to_json(cells: dict[str, dict[str, dict]]) -> dict:
    """A table of :func:`table` as plain JSON values."""
    return {
        row: {
            column: {
                key: {
                    **cell.estimate.to_dict(),
                    "paired": None if cell.paired is None else cell.paired.to_dict(),
                }
                for key, cell in metrics.items()
            }
            for column, metrics in columns.items()
        }
        for row, columns in cells.items()
    }
