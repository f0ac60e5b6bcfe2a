"""A stress run's results: the paper's table row (:func:`summarize`, ``metrics.json``) and its
wall-clock figures (:func:`timings`, ``timings.json``), kept apart so that two runs of the same
episodes give identical ``metrics.json``."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from counterscene_env import metrics
from counterscene_env.scene.sources import SKIPPED
from counterscene_env.stress.config import StressConfig, model_identity


def summarize(records: Sequence[dict], config: StressConfig, model: str | None = None) -> dict:
    """The paper's table row of a run (package docstring), without timings: plain Python
    values, with NaN where there is nothing to measure (``metrics.json_safe`` writes it as
    JSON's null, as ``metrics.json`` and ``--json`` have it).

    ``complete`` says whether every requested episode (``episodes_requested``, the config's)
    is in ``records``; a stopped run's summary has ``complete: false`` and ``episodes`` the
    number it finished. ``model`` (``--model``, as given): the summary names the world model
    under ``model`` (``config.model_identity``: as given, and its directory).

    Two TTC aggregates, of the ego's min TTC per episode [s] (inf: no projected conflict):
    ``mean_min_ttc`` is the mean over the episodes with a projected conflict (inf when none
    has one; ``episodes_without_ttc_conflict`` counts the others), ``overall["min_ttc"]``
    (``metrics.aggregate``) the median over every episode, inf counted (inf when more than
    half have no conflict). docs/reports.md, "metrics.json"."""
    agg = metrics.aggregate(records)
    ttc = np.array([r["min_ttc"] for r in records], float)
    finite = ttc[np.isfinite(ttc)]
    overall = agg["overall"]
    named = {} if model is None else {"model": model_identity(model)}
    return {
        "complete": len(records) >= config.episodes,
        "episodes": len(records),
        "episodes_requested": config.episodes,
        **named,
        "horizons": agg["groups"],
        "per_second": agg["per_second"],
        "cr": overall["cr"],
        "cr_ego_adversary": overall["cr_ego_adversary"],
        "cr_non_ego": overall["cr_non_ego"],
        "cr_non_ego_new": overall["cr_non_ego_new"],
        "hbr_ego": overall["hbr_ego"],
        "orr": overall["orr"],
        "orr_moving": overall["orr_moving"],
        "orr_log": overall["orr_log"],
        "orr_moving_log": overall["orr_moving_log"],
        "mean_min_ttc": float(finite.mean()) if finite.size else math.inf,
        "episodes_without_ttc_conflict": int((~np.isfinite(ttc)).sum()),
        "mean_min_clearance_adversary": overall["min_clearance_adversary"],
        "fallbacks": sum(r["fallback"] is not None for r in records),
        # Real logs: an episode ends with its log; a log with no future at all is skipped.
        "episodes_cut_at_log_end": sum(
            r["rollout_s"] < config.sim.duration - 1e-6 for r in records
        ),
        # Stored scenes that could not be played, by reason (scene.sources.SKIPPED).
        "scenes_skipped": dict(SKIPPED.get(config.scenario, {})),
        "overall": overall,
        "config": config.to_dict(),
    }


def timings(
    records: Sequence[dict],
    wall_seconds: float | None = None,
    episodes_run: int | None = None,
    workers: int = 1,
) -> dict:
    """Wall-clock figures of a run [s].

    Args:
        records: every finished episode (earlier invocations' too, from ``episodes.jsonl``).
        wall_seconds: this invocation's wall-clock time, start to end.
        episodes_run: episodes this invocation ran (a resumed run ran only the rest).
        workers: processes this invocation ran episodes in.

    Returns:
        ``seconds_per_episode`` (mean compute time of an episode: its batch's time over the
        batch size, so with several workers more than wall-clock per episode),
        ``seconds_per_replan`` (NaN without replans), ``episodes``, and the arguments given.
    """
    # An episode whose timings a kill lost (``stress/log.py``) counts in neither mean.
    timed = [r for r in records if "seconds" in r]
    replans = sum(r["replans"] for r in timed)
    out = {
        "episodes": len(records),
        "seconds_per_episode": sum(r["seconds"] for r in timed) / len(timed) if timed else math.nan,
        "seconds_per_replan": sum(r["replan_seconds"] for r in timed) / replans
        if replans
        else math.nan,
        "workers": workers,
    }
    if wall_seconds is not None:
        out["wall_seconds"] = wall_seconds
    if episodes_run is not None:
        out["episodes_run"] = episodes_run
        if episodes_run:
            out["wall_seconds_per_episode"] = (wall_seconds or math.nan) / episodes_run
    return out
