"""One scene's metrics as a record (:func:`evaluate_scene`), records averaged as the paper's
tables do (:func:`aggregate`), and JSON-safe output."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from counterscene_env.metrics.common import (
    GROUPS,
    PER_SECOND_KEYS,
    SCENE_KEYS,
    adversary_index,
    adversary_tenures,
    horizon_steps,
    is_hard_braking,
    nan_mean,
    one_agent,
    rollout_steps,
)
from counterscene_env.metrics.realism import (
    ade_fde_of,
    displacement_steps,
    judged_steps,
    logged_off_road_steps,
    non_ego_vehicles,
    off_road_rate_of,
    off_road_steps,
    parked_agents,
)
from counterscene_env.metrics.safety import (
    agent_overlaps,
    any_collision,
    braking_samples,
    ego_adversary_collision_steps,
    ego_collision_steps,
    hbr_all_of,
    hbr_ego_of,
    hbr_paper,
    logged_overlap_pairs,
    min_clearance,
    min_ttc_ego,
)
from counterscene_env.scene.core import Scene


def second_key(h: float) -> str:
    return f"{h:g}"


#: The per-second keys whose value an episode that ended in a collision keeps at every later
#: horizon: what happened to the ego "within h" is settled once it crashed.
EVENT_KEYS = ("CR", "CR_adv", "HBR", "DEC")


def horizon_values(record: dict, second: str) -> dict:
    """A record's per-second values at horizon ``second`` (a key of its ``per_second``).

    An episode whose rollout ended before that second counts there only if its termination
    cut it short after the ego had collided (``ends_in_ego_collision``: an env's
    ``terminate_on_collision`` ends it at the crash), and then only with its
    :data:`EVENT_KEYS`: a crash at 3 s is a collision within 8 s, but the crashed episode has
    no 8 s trajectory to score. Any other episode that ended early gives ``{}``: one whose
    log ended at 3 s is no episode "at 10 s", collided or not, for any row
    (docs/metrics.md). The tables of ``stress``, ``report``
    and ``paper-tables`` all read horizons through this."""
    values = record["per_second"].get(second, {})
    if float(second) <= float(record.get("rollout_s", math.inf)) + 1e-6:
        return values
    if record.get("ends_in_ego_collision", False):
        return {k: v for k, v in values.items() if k in EVENT_KEYS}
    return {}


#: The collision rates with the adversary, whole-episode and per second.
ADVERSARY_RATES = ("cr_ego_adversary", "CR_adv")


def rate_value(record: dict, key: str, value: float | None) -> float:
    """``value`` of ``key`` from ``record`` as a rate over episodes counts it (NaN: none).

    An episode without an adversary (``adversary_id`` None) made no collision with one: its
    :data:`ADVERSARY_RATES` count as 0, not as nothing to measure, so that a selector that
    finds no adversary is not scored on the episodes where it found one only (the paper's
    main-text CR). Its record keeps NaN; an episode with no rollout step stays NaN. Every
    table of ``stress``, ``report``, ``compare`` and ``paper-tables`` counts it so."""
    value = math.nan if value is None else float(value)
    if (
        key in ADVERSARY_RATES
        and math.isnan(value)
        and record.get("adversary_id") is None
        and float(record.get("rollout_s", 1.0)) > 0
    ):
        return 0.0
    return value


def _latest_adversary(sim: Scene, adversary) -> str | None:
    """The id of the adversary at the last rollout step that had one (None: none)."""
    if adversary is not None and not one_agent(adversary):
        adversary = next((a for a in reversed(list(adversary)) if a is not None), None)
    return None if adversary is None else str(sim.agent_ids[adversary_index(sim, adversary)])


def evaluate_scene(
    sim: Scene,
    factual: Scene | None = None,
    adversary: int | str | Sequence[int | str | None] | None = None,
    horizons: Sequence[float] = tuple(range(1, 11)),
    smooth: float = 0.0,
    terminated: bool = False,
) -> dict:
    """All metrics of one simulated scene, as a JSON-serialisable dict of plain Python values.

    Args:
        sim: the simulated scene (history + rollout).
        factual: its factual log (same agent ids), for ADE/FDE; None: ADE/FDE are NaN.
        adversary: the adversary's row or id, for ``cr_ego_adversary`` and
            ``min_clearance_adversary`` (NaN without one); or one entry per rollout step
            (None: none then), when the closed loop re-selects at its replans: every agent
            that was the adversary counts from the first step it was
            (``metrics.common.adversary_tenures``).
        horizons: seconds at which the per-second values are reported.
        smooth: s, moving-average window of the acceleration signal for HBR (0: none).
        terminated: the rollout was cut short at its last step by the episode's termination
            (an env's ``terminate_on_collision`` or ``terminate_on_off_road``), not ended by
            its duration or its log. Only such an episode, if the ego had collided, counts at
            the horizons past its end: a log that runs out ends every row's episode on it
            alike, crashed or not, and counting the crashed ones there would score the rows
            that crash on more episodes than the others.

    Returns:
        ``{"scenario_id", "rollout_s", "ends_in_ego_collision", "adversary_id",
        "adversary_ids", "per_second", <SCENE_KEYS>}`` where ``rollout_s`` is the rollout's
        length, s, ``ends_in_ego_collision`` whether the rollout was cut short by its
        termination after the ego had collided (``terminated``; with
        ``terminate_on_collision`` the crash ends it), so that it collided within every later
        horizon (:func:`horizon_values`),
        ``adversary_ids`` lists every agent that was the adversary, in
        the order they were first chosen, and ``adversary_id`` is the latest (None: none);
        ``per_second[str(h)]`` holds ``ADE``/``FDE`` (m), ``ORR``, ``HBR`` (= hbr_ego within h),
        ``CR`` (ego collided at or before h), ``ORR_log`` (the log's own ORR within h, as
        ``orr_log`` below), ``CR_adv`` (with the adversary; NaN without one)
        and ``DEC`` (the ego's strongest braking within h, m/s^2, so ``DEC > x`` is HBR at
        ``-x``) for each h, and the whole-rollout values are
        ``cr``, ``cr_all_agents``, ``cr_non_ego`` (two agents other than the ego overlap),
        ``cr_non_ego_new`` (the same without the pairs that overlap in ``factual`` too: the
        collisions the simulation made; NaN without ``factual``), ``cr_ego_adversary``, ``hbr_ego``,
        ``hbr_all``, ``hbr_paper``, ``orr`` (fractions; also split into ``orr_parked`` over the
        vehicles parked for the whole rollout, :func:`parked_agents`, and ``orr_moving`` over
        the others), ``orr_log`` and ``orr_moving_log`` (the same vehicles' logged positions
        over the same steps, on the same map: a real map's off-road share of the log itself;
        NaN without ``factual``), ``min_ttc`` (s), ``min_clearance_adversary`` (m) and
        ``ego_peak_deceleration`` (m/s^2, the ego's strongest braking over the rollout from the
        same samples HBR thresholds; 0 if it never slows, NaN without samples).
    """
    ego_hits = ego_collision_steps(sim)
    overlaps = agent_overlaps(sim)
    judged = judged_steps(sim)
    off = off_road_steps(sim, judged)
    parked = parked_agents(sim)
    acc, mask = braking_samples(sim, None, "position", smooth)
    flags = is_hard_braking(acc) & mask  # as hard_braking_flags, from one pass
    e = sim.ego_index
    ego_acc = acc[e][mask[e]]
    peak_decel = max(0.0, -float(ego_acc.min())) if ego_acc.size else math.nan
    dist = ok = off_log = ok_log = None
    cr_non_ego_new = orr_log = orr_moving_log = math.nan
    if factual is not None:
        dist, ok = displacement_steps(sim, factual)
        rows = non_ego_vehicles(sim)
        dist, ok = dist[rows], ok[rows]
        new = overlaps & ~logged_overlap_pairs(sim, factual)[None]
        cr_non_ego_new = float(any_collision(new, e, include_ego=False).any())
        off_log, ok_log = logged_off_road_steps(sim, factual)
        orr_log = off_road_rate_of(sim, off_log, None, True, valid=ok_log)
        orr_moving_log = off_road_rate_of(sim, off_log, None, True, ~parked, ok_log)

    tenures = [] if adversary is None else adversary_tenures(sim, adversary)
    adversary_ids = [str(sim.agent_ids[row]) for row, _ in tenures]
    adv_hits = None
    if tenures:
        adv_hits = np.zeros(rollout_steps(sim), bool)
        for row, since in tenures:
            adv_hits |= ego_adversary_collision_steps(sim, row, since)
        cr_adv = float(adv_hits.any())
        gaps = [min_clearance(sim, row, since) for row, since in tenures]
        clearance = min((g for g in gaps if not math.isnan(g)), default=math.nan)
    else:
        cr_adv, clearance = math.nan, math.nan

    per_second = {}
    steps = np.arange(rollout_steps(sim))
    for h in horizons:
        n = horizon_steps(sim, h)
        brake_in = mask[e] & (steps < n)
        ade, fde = ade_fde_of(dist, ok, n) if dist is not None else (math.nan, math.nan)
        per_second[second_key(h)] = {
            "ADE": ade,
            "FDE": fde,
            "ORR": off_road_rate_of(sim, off, h, include_ego=True, valid=judged),
            "ORR_log": math.nan
            if off_log is None
            else off_road_rate_of(sim, off_log, h, True, valid=ok_log),
            "HBR": float(flags[e][brake_in].any()) if brake_in.any() else math.nan,
            "CR": float(ego_hits[steps < n].any()) if steps.size else math.nan,
            "CR_adv": math.nan
            if adv_hits is None or not steps.size
            else float(adv_hits[steps < n].any()),
            # Any braking threshold's HBR within h: DEC > threshold (paper tables).
            "DEC": max(0.0, -float(acc[e][brake_in].min())) if brake_in.any() else math.nan,
        }

    out = {
        "scenario_id": str(sim.scenario_id),
        "rollout_s": float(rollout_steps(sim) * sim.dt),
        "ends_in_ego_collision": bool(terminated and ego_hits.any()),
        "adversary_id": _latest_adversary(sim, adversary),
        "adversary_ids": adversary_ids,
        "per_second": per_second,
        "cr": float(ego_hits.any()),
        "cr_all_agents": float(any_collision(overlaps, e, include_ego=True).any()),
        "cr_non_ego": float(any_collision(overlaps, e, include_ego=False).any()),
        "cr_non_ego_new": cr_non_ego_new,
        "cr_ego_adversary": cr_adv,
        "hbr_ego": hbr_ego_of(flags, mask, sim),
        "hbr_all": hbr_all_of(flags, mask, sim),
        "hbr_paper": hbr_paper(sim),
        "orr": off_road_rate_of(sim, off, None, include_ego=True, valid=judged),
        "orr_parked": off_road_rate_of(sim, off, None, True, parked, judged),
        "orr_moving": off_road_rate_of(sim, off, None, True, ~parked, judged),
        "orr_log": orr_log,
        "orr_moving_log": orr_moving_log,
        "min_ttc": min_ttc_ego(sim),
        "min_clearance_adversary": clearance,
        "ego_peak_deceleration": peak_decel,
    }
    if rollout_steps(sim) == 0:  # "now" is the log's last step: no collision to count, or not
        out.update({k: math.nan for k in _RATES_OF_STEPS})
    return out


#: The whole-rollout rates that count steps with an event: NaN over no step (never 0).
_RATES_OF_STEPS = ("cr", "cr_all_agents", "cr_non_ego", "cr_non_ego_new", "cr_ego_adversary")


def severity(record: dict) -> tuple[float, ...]:
    """How bad an episode record is for the ego, as a sort key: smaller is more severe.

    In turn: the ego collided (``cr``), with the adversary (``cr_ego_adversary``), the smallest
    time to collision (``min_ttc`` s; no projected conflict is inf, the least severe), the
    smallest clearance to the adversary (``min_clearance_adversary`` m; no adversary ranks
    after any clearance) and hard braking (``hbr_ego``). A report's worst episodes and a
    stress run's kept candidate rollout are both ordered by it.
    """

    def flag(key: str) -> float:
        v = record.get(key, math.nan)
        return 0.0 if v is None or math.isnan(v) else float(v)

    def low_first(key: str) -> float:
        v = record.get(key, math.nan)
        return math.inf if v is None or math.isnan(v) else float(v)

    return (
        -flag("cr"),
        -flag("cr_ego_adversary"),
        low_first("min_ttc"),
        low_first("min_clearance_adversary"),
        -flag("hbr_ego"),
    )


def aggregate(records: Sequence[dict]) -> dict:
    """Average :func:`evaluate_scene` records over scenes, as the paper's tables do.

    Every mean ignores NaN (a scene with nothing to measure does not count as 0).

    Returns:
        ``{"num_scenes", "per_second", "groups", "overall"}``: ``per_second[str(h)][key]`` the
        mean over scenes of each per-second value (keys :data:`PER_SECOND_KEYS`);
        ``groups["1-4s" | "5-7s" | "8-10s"][key]`` the mean over those seconds of the per-second
        means (NaN if the records have none of them); ``overall[key]`` the mean over scenes of
        each whole-rollout value (:data:`SCENE_KEYS`), except ``min_ttc``, whose median is
        reported (it is ``inf`` for scenes without any projected conflict).
    """
    if not records:
        raise ValueError("aggregate needs at least one scene record")
    seconds = sorted({k for r in records for k in r["per_second"]}, key=float)
    per_second = {
        s: {
            key: nan_mean([horizon_values(r, s).get(key, math.nan) for r in records])
            for key in PER_SECOND_KEYS
        }
        for s in seconds
    }
    groups = {}
    for name, secs in GROUPS.items():
        present = [second_key(s) for s in secs if second_key(s) in per_second]
        groups[name] = {
            key: nan_mean([per_second[s][key] for s in present]) for key in PER_SECOND_KEYS
        }
    overall = {}
    for key in SCENE_KEYS:
        values = np.array([rate_value(r, key, r.get(key)) for r in records], dtype=np.float64)
        if key == "min_ttc":
            values = values[~np.isnan(values)]
            overall[key] = float(np.median(values)) if values.size else math.nan
        else:
            overall[key] = nan_mean(values)
    return {
        "num_scenes": len(records),
        "per_second": per_second,
        "groups": groups,
        "overall": overall,
    }


def json_safe(obj):
    """``obj`` with NaN and inf floats as None (JSON has neither), dicts and lists walked."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj
