"""Scene metrics: collision, hard braking, off-road, displacement and safety-margin measures.

This module's one job is to score a simulated :class:`~counterscene_env.scene.Scene` (against
its factual log where needed), per scene and per horizon second, and to average those scores
over scenes the way the paper's tables do (appendix "Metric Definitions";
docs/design.md, "Metric definitions").

What is scored: the rollout, steps ``current_index + 1 ..`` of the scene (the history is shared
with the log). Horizon ``h`` s means the first ``round(h / dt)`` rollout steps; steps a scene does
not have (a rollout cut short, e.g. by a terminating collision) are treated as invalid, so e.g.
CR at 8 s still counts a collision at 3 s and FDE at 8 s is NaN.

Conventions: rates are fractions in [0, 1] (per-scene flags are 0.0/1.0); a value with nothing
to average is NaN, never 0; ``min_ttc`` is ``inf`` when no conflict is projected. Results are
plain Python floats, so ``json.dumps`` writes them (as ``NaN``/``Infinity`` where they are).

Where we depart from the paper (docs/design.md, "Metric definitions" and
"Where we depart from the paper and its public code"):

- HBR uses the *signed* longitudinal acceleration. The paper's ``||a|| cos(world yaw)`` is kept
  as :func:`hbr_paper` for comparison only.
- Collision checks mask validity per agent (geometry layer).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np

from counterscene_env import geometry
from counterscene_env.scene.core import Scene

#: Hard-braking threshold on the longitudinal acceleration, m/s^2 (paper: -3.0).
HARD_BRAKE_THRESHOLD = -3.0

#: Per-second keys of :func:`evaluate_scene` and :func:`aggregate`.
PER_SECOND_KEYS = ("ADE", "FDE", "ORR", "HBR", "CR")

#: Whole-rollout keys of :func:`evaluate_scene` (numbers averaged by :func:`aggregate`).
SCENE_KEYS = (
    "cr",
    "cr_all_agents",
    "cr_non_ego",
    "cr_ego_adversary",
    "hbr_ego",
    "hbr_all",
    "hbr_paper",
    "orr",
    "min_ttc",
    "min_clearance_adversary",
)

#: The paper's horizon groups (main tables), in seconds.
GROUPS = {"1-4s": (1, 2, 3, 4), "5-7s": (5, 6, 7), "8-10s": (8, 9, 10)}

AccelerationSource = Literal["position", "speed"]

# Steps after t that an acceleration sample at t reads: p_t, p_{t+1}, p_{t+2} for positions,
# s_t, s_{t+1} for speeds. A sample belongs to a horizon only if all of them lie within it.
_REACH = {"position": 2, "speed": 1}


# ---------------------------------------------------------------------- rollout helpers
def rollout_steps(scene: Scene) -> int:
    """Number of rollout steps, ``T - current_index - 1``."""
    return scene.num_steps - scene.current_index - 1


def horizon_steps(scene: Scene, seconds: float | None) -> int:
    """Rollout steps in the first ``seconds`` s: ``round(seconds / dt)``; None: all of them."""
    if seconds is None:
        return rollout_steps(scene)
    return round(float(seconds) / scene.dt)


def _roll(scene: Scene) -> slice:
    return slice(scene.current_index + 1, scene.num_steps)


def _in_horizon(scene: Scene, seconds: float | None, reach: int = 0) -> np.ndarray:
    """``[T_roll]`` bool: rollout steps r whose samples (reading r .. r + reach) lie within h."""
    return np.arange(rollout_steps(scene)) + reach < horizon_steps(scene, seconds)


def agent_index(scene: Scene, agent: int | str) -> int:
    """Row of an agent given by row index or by id; raises ValueError if there is none."""
    if isinstance(agent, str):
        rows = np.flatnonzero(scene.agent_ids == agent)
        if rows.size == 0:
            raise ValueError(f"no agent with id {agent!r} in scene {scene.scenario_id!r}")
        return int(rows[0])
    idx = int(agent)
    if not 0 <= idx < scene.num_agents:
        raise ValueError(f"agent index {idx} out of range for {scene.num_agents} agents")
    return idx


def _adversary_index(scene: Scene, adversary: int | str) -> int:
    idx = agent_index(scene, adversary)
    if idx == scene.ego_index:
        raise ValueError("the adversary cannot be the ego")
    return idx


def _mean(values: np.ndarray) -> float:
    """Mean ignoring NaN; NaN (without a warning) when nothing is left."""
    values = np.asarray(values, dtype=np.float64)
    values = values[~np.isnan(values)]
    return float(values.mean()) if values.size else math.nan


# ---------------------------------------------------------------------- collisions (CR)
def ego_collision_steps(scene: Scene) -> np.ndarray:
    """``[T_roll]`` bool: at each rollout step, the ego's box overlaps another valid agent's.

    This is the paper's CR event (oriented boxes from centroid, yaw and extent); every agent
    type counts (pedestrians, cyclists, static objects), each masked by its own validity.
    """
    sl, e = _roll(scene), scene.ego_index
    pos, yaw, ok = scene.positions[:, sl], scene.yaws[:, sl], scene.valid[:, sl]
    hit = geometry.boxes_overlap(
        pos[e][None], yaw[e][None], scene.extents[e], pos, yaw, scene.extents[:, None]
    )  # [N, T_roll]
    hit &= ok & ok[e][None]
    hit[e] = False
    return hit.any(0)


def ego_collided(scene: Scene, horizon: float | None = None) -> bool:
    """Whether the ego collided at any rollout step within ``horizon`` s (None: whole rollout)."""
    return bool((ego_collision_steps(scene) & _in_horizon(scene, horizon)).any())


def _agent_overlaps(scene: Scene) -> np.ndarray:
    """``[T_roll, N, N]`` bool: pairwise overlap of valid agents at each rollout step."""
    sl = _roll(scene)
    return geometry.overlaps_over_time(
        scene.positions[:, sl], scene.yaws[:, sl], scene.extents, scene.valid[:, sl]
    )


def _any_collision(overlaps: np.ndarray, ego: int, include_ego: bool) -> np.ndarray:
    if include_ego:
        return overlaps.any((1, 2))
    keep = np.ones(overlaps.shape[1], dtype=bool)
    keep[ego] = False
    return overlaps[:, keep][:, :, keep].any((1, 2))


def agent_collision_steps(scene: Scene, include_ego: bool = True) -> np.ndarray:
    """``[T_roll]`` bool: any pair of valid agents overlaps at that rollout step.

    The traffic-realism view of collisions; ``include_ego=False`` scores only the traffic
    among itself (what the world model alone is responsible for).
    """
    return _any_collision(_agent_overlaps(scene), scene.ego_index, include_ego)


def ego_adversary_collision_steps(scene: Scene, adversary: int | str) -> np.ndarray:
    """``[T_roll]`` bool: the ego's and the adversary's boxes overlap (both valid)."""
    sl, e, a = _roll(scene), scene.ego_index, _adversary_index(scene, adversary)
    rows = [e, a]
    hit = geometry.boxes_overlap(
        scene.positions[e, sl],
        scene.yaws[e, sl],
        scene.extents[e],
        scene.positions[a, sl],
        scene.yaws[a, sl],
        scene.extents[a],
    )
    return hit & scene.valid[rows][:, sl].all(0)


# ---------------------------------------------------------------------- hard braking (HBR)
def _finite_difference_acceleration(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The paper's finite differences over the rollout positions.

    ``v_t = (p_{t+1} - p_t) / dt``, ``a_t = (v_{t+1} - v_t) / dt`` (appendix HBR equation),
    with ``a_t`` stored at rollout step t (it reads steps t, t+1, t+2).

    Returns:
        ``[N, T_roll, 2]`` m/s^2 (NaN where undefined) and ``[N, T_roll]`` bool validity.
    """
    sl = _roll(scene)
    p, ok = scene.positions[:, sl], scene.valid[:, sl]
    n, t = ok.shape
    acc = np.full((n, t, 2), np.nan)
    valid = np.zeros((n, t), dtype=bool)
    if t >= 3:
        acc[:, :-2] = (p[:, 2:] - 2.0 * p[:, 1:-1] + p[:, :-2]) / scene.dt**2
        valid[:, :-2] = ok[:, :-2] & ok[:, 1:-1] & ok[:, 2:]
    acc[~valid] = np.nan
    return acc, valid


def _moving_average(x: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average along the last axis over valid samples only (``[..., T]``)."""
    k = window // 2
    vals = np.where(valid, x, 0.0)
    pad = [(0, 0)] * (x.ndim - 1) + [(k + 1, k)]
    csum = np.cumsum(np.pad(vals, pad), axis=-1)
    ccnt = np.cumsum(np.pad(valid.astype(np.float64), pad), axis=-1)
    total = csum[..., 2 * k + 1 :] - csum[..., : -2 * k - 1]
    count = ccnt[..., 2 * k + 1 :] - ccnt[..., : -2 * k - 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = total / count
    return np.where(valid, out, np.nan)


def longitudinal_acceleration(
    scene: Scene, source: AccelerationSource = "position", smooth: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Signed longitudinal acceleration of every agent over the rollout.

    Args:
        scene: the (simulated) scene.
        source: ``"position"``: the paper's finite differences of positions, projected with
            sign on the heading, ``a_lon,t = a_t . (cos psi_t, sin psi_t)`` (negative = braking,
            whatever the direction of travel); ``"speed"``: ``(s_{t+1} - s_t) / dt`` of the
            signed speed.
        smooth: s, width of a centred moving average over the valid samples of the signal
            (``round(smooth / dt)`` samples, rounded up to an odd count; 0: none). The nuScenes
            10 Hz logs interpolate 2 Hz labels, whose second differences spike at the knots;
            about 0.5 s removes that. Near a horizon's end the average reads up to half a
            window past it.

    Returns:
        ``[N, T_roll]`` m/s^2 (NaN where undefined) and ``[N, T_roll]`` bool, valid where every
        step the sample reads (t .. t+2 for positions, t .. t+1 for speeds) is valid.
    """
    if source == "position":
        acc_vec, valid = _finite_difference_acceleration(scene)
        yaw = scene.yaws[:, _roll(scene)]
        acc = acc_vec[..., 0] * np.cos(yaw) + acc_vec[..., 1] * np.sin(yaw)
    elif source == "speed":
        sl = _roll(scene)
        s, ok = scene.speeds[:, sl], scene.valid[:, sl]
        acc = np.full(s.shape, np.nan)
        valid = np.zeros(s.shape, dtype=bool)
        if s.shape[1] >= 2:
            acc[:, :-1] = (s[:, 1:] - s[:, :-1]) / scene.dt
            valid[:, :-1] = ok[:, 1:] & ok[:, :-1]
    else:
        raise ValueError(f"source must be 'position' or 'speed', got {source!r}")
    window = round(float(smooth) / scene.dt)
    if window > 1:
        acc = _moving_average(acc, valid, window)
    acc = np.where(valid, acc, np.nan)
    return acc, valid


def _hard_braking(
    scene: Scene, horizon: float | None, source: AccelerationSource, smooth: float, threshold
) -> tuple[np.ndarray, np.ndarray]:
    """``[N, T_roll]`` hard-braking flags and the sample mask within the horizon."""
    acc, valid = longitudinal_acceleration(scene, source, smooth)
    mask = valid & _in_horizon(scene, horizon, _REACH[source])[None]
    return (acc < threshold) & mask, mask


def hbr_ego(
    scene: Scene,
    horizon: float | None = None,
    source: AccelerationSource = "position",
    smooth: float = 0.0,
    threshold: float = HARD_BRAKE_THRESHOLD,
) -> float:
    """1.0 if the ego brakes harder than ``threshold`` m/s^2 at any sample within the horizon.

    The stress-test signal: did the scenario force the ego into an emergency stop. NaN if the
    ego has no valid acceleration sample within the horizon.
    """
    return _hbr_ego_of(*_hard_braking(scene, horizon, source, smooth, threshold), scene)


def hbr_all(
    scene: Scene,
    horizon: float | None = None,
    source: AccelerationSource = "position",
    smooth: float = 0.0,
    threshold: float = HARD_BRAKE_THRESHOLD,
) -> float:
    """Fraction of valid acceleration samples of vehicles (ego included) that brake hard.

    The traffic view, normalised as the paper's per-scene HBR (samples, not agents). NaN if no
    vehicle has a valid sample within the horizon.
    """
    return _hbr_all_of(*_hard_braking(scene, horizon, source, smooth, threshold), scene)


def _hbr_ego_of(flags: np.ndarray, mask: np.ndarray, scene: Scene) -> float:
    e = scene.ego_index
    return float(flags[e].any()) if mask[e].any() else math.nan


def _hbr_all_of(flags: np.ndarray, mask: np.ndarray, scene: Scene) -> float:
    veh = scene.vehicle_mask
    n = mask[veh].sum()
    return float(flags[veh].sum() / n) if n else math.nan


def hbr_paper(
    scene: Scene, horizon: float | None = None, threshold: float = HARD_BRAKE_THRESHOLD
) -> float:
    """The paper's HBR formula, verbatim. PHYSICALLY WRONG: kept only to compare with the paper.

    ``a_lon,t = ||a_t||_2 cos(psi_t)`` with the appendix finite differences, hard braking where
    ``a_lon,t < threshold``; rate = flagged samples over all agents / valid acceleration samples
    over all agents. The magnitude has no sign and ``cos`` of the *world* yaw only says whether
    the car points east or west: it flags any strong acceleration (braking or speeding up) of a
    westbound car and never flags an eastbound one. Use :func:`hbr_ego` / :func:`hbr_all`.
    """
    acc_vec, valid = _finite_difference_acceleration(scene)
    valid = valid & _in_horizon(scene, horizon, _REACH["position"])[None]
    yaw = scene.yaws[:, _roll(scene)]
    a_lon = np.linalg.norm(acc_vec, axis=-1) * np.cos(yaw)
    n = valid.sum()
    return float(((a_lon < threshold) & valid).sum() / n) if n else math.nan


# ---------------------------------------------------------------------- off-road (ORR)
def off_road_steps(scene: Scene) -> np.ndarray:
    """``[N, T_roll]`` bool: agent valid and its centre outside ``scene.road.drivable_area``."""
    sl = _roll(scene)
    inside = geometry.points_in_area(scene.road.drivable_area, scene.positions[:, sl])
    return ~inside & scene.valid[:, sl]


def _off_road_rate(
    scene: Scene, off: np.ndarray, horizon: float | None, include_ego: bool
) -> float:
    veh = scene.vehicle_mask.copy()
    if not include_ego:
        veh[scene.ego_index] = False
    mask = scene.valid[:, _roll(scene)] & _in_horizon(scene, horizon)[None] & veh[:, None]
    n = mask.sum()
    return float((off & mask).sum() / n) if n else math.nan


def off_road_rate(scene: Scene, horizon: float | None = None, include_ego: bool = True) -> float:
    """ORR: fraction of valid vehicle agent-steps within the horizon whose centre is off-road.

    The paper's ``1/(NT) sum 1[p not in D]`` over valid steps only. NaN if there are none.
    """
    return _off_road_rate(scene, off_road_steps(scene), horizon, include_ego)


# ---------------------------------------------------------------------- displacement (ADE/FDE)
def align_agents(sim: Scene, factual: Scene) -> np.ndarray:
    """``[N_sim]`` rows of the factual scene holding each simulated agent (by ``agent_ids``).

    Raises:
        ValueError: naming the simulated agent ids the factual scene lacks, or if the two
            scenes have different ``dt``.
    """
    if not math.isclose(sim.dt, factual.dt, rel_tol=1e-9):
        raise ValueError(f"sim dt {sim.dt} s differs from factual dt {factual.dt} s")
    lookup = {aid: i for i, aid in enumerate(factual.agent_ids.tolist())}
    missing = [aid for aid in sim.agent_ids.tolist() if aid not in lookup]
    if missing:
        raise ValueError(
            f"simulated agents missing from the factual scene {factual.scenario_id!r}: {missing}"
        )
    return np.array([lookup[aid] for aid in sim.agent_ids.tolist()], dtype=np.int64)


def displacement_steps(sim: Scene, factual: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Displacement of each simulated agent from its factual log over the rollout.

    Rollout step r of the sim is compared with step ``factual.current_index + 1 + r`` of the
    factual scene (both start from "now"); factual steps past its end count as invalid.

    Returns:
        ``[N_sim, T_roll]`` m (NaN where undefined) and ``[N_sim, T_roll]`` bool, True where both
        are valid.
    """
    rows = align_agents(sim, factual)
    sl = _roll(sim)
    p_sim, ok_sim = sim.positions[:, sl], sim.valid[:, sl]
    t_roll = ok_sim.shape[1]
    start = factual.current_index + 1
    avail = max(0, min(t_roll, factual.num_steps - start))
    p_fac = np.zeros_like(p_sim)
    ok_fac = np.zeros_like(ok_sim)
    p_fac[:, :avail] = factual.positions[rows, start : start + avail]
    ok_fac[:, :avail] = factual.valid[rows, start : start + avail]
    ok = ok_sim & ok_fac
    dist = np.where(ok, np.linalg.norm(p_sim - p_fac, axis=-1), np.nan)
    return dist, ok


def _ade_fde(dist: np.ndarray, ok: np.ndarray, n: int) -> tuple[float, float]:
    """ADE/FDE over the first n rollout steps of ``[A, T_roll]`` displacements."""
    d, m = dist[:, :n], ok[:, :n]
    counts = m.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_agent = np.where(m, d, 0.0).sum(1) / counts  # mean over jointly valid steps
    ade = _mean(per_agent[counts > 0])
    fde = math.nan
    if 0 < n <= ok.shape[1]:
        last = ok[:, n - 1]
        fde = _mean(dist[last, n - 1])
    return ade, fde


def _non_ego_vehicles(scene: Scene) -> np.ndarray:
    rows = scene.vehicle_mask.copy()
    rows[scene.ego_index] = False
    return rows


def ade_fde(sim: Scene, factual: Scene, horizon: float | None = None) -> tuple[float, float]:
    """ADE and FDE, m, of the non-ego vehicles against the factual log over ``horizon`` s.

    ADE_h: mean over agents of each agent's mean displacement over its jointly valid steps among
    the first h seconds; FDE_h: mean over the agents valid (in both) at the horizon's last step
    of the displacement there. NaN when there is nothing to average.
    """
    dist, ok = displacement_steps(sim, factual)
    rows = _non_ego_vehicles(sim)
    return _ade_fde(dist[rows], ok[rows], horizon_steps(sim, horizon))


# ---------------------------------------------------------------------- safety margins
def min_ttc_ego(scene: Scene, horizon: float = 10.0, step: float = 0.1) -> float:
    """Smallest constant-velocity TTC, s, of the ego against any other agent over the rollout.

    At every rollout step where the ego is valid, each other valid agent is projected at its
    current velocity with its heading held (:func:`geometry.box_time_to_collision`, horizon
    ``horizon`` s at resolution ``step`` s). 0 while overlapping; ``inf`` if never.
    """
    sl, e = _roll(scene), scene.ego_index
    pos, yaw, ok = scene.positions[:, sl], scene.yaws[:, sl], scene.valid[:, sl]
    vel = scene.velocities[:, sl]
    ttc = geometry.box_time_to_collision(
        pos[e][None],
        vel[e][None],
        yaw[e][None],
        scene.extents[e],
        pos,
        vel,
        yaw,
        scene.extents[:, None],
        horizon=horizon,
        step=step,
    )  # [N, T_roll]
    mask = ok & ok[e][None]
    mask[e] = False
    ttc = ttc[mask]
    return float(ttc.min()) if ttc.size else math.inf


def min_clearance(scene: Scene, adversary: int | str) -> float:
    """Smallest box-to-box distance, m, between ego and adversary over rollout steps where both
    are valid (0 once they touch); NaN if there are none."""
    sl, e, a = _roll(scene), scene.ego_index, _adversary_index(scene, adversary)
    both = scene.valid[e, sl] & scene.valid[a, sl]
    if not both.any():
        return math.nan
    d = geometry.box_distance(
        scene.positions[e, sl][both],
        scene.yaws[e, sl][both],
        scene.extents[e],
        scene.positions[a, sl][both],
        scene.yaws[a, sl][both],
        scene.extents[a],
    )
    return float(d.min())


# ---------------------------------------------------------------------- per scene
def _second_key(h: float) -> str:
    return f"{h:g}"


def evaluate_scene(
    sim: Scene,
    factual: Scene | None = None,
    adversary: int | str | None = None,
    horizons: Sequence[float] = tuple(range(1, 11)),
    smooth: float = 0.0,
) -> dict:
    """All metrics of one simulated scene, as a JSON-serialisable dict of plain Python values.

    Args:
        sim: the simulated scene (history + rollout).
        factual: its factual log (same agent ids), for ADE/FDE; None: ADE/FDE are NaN.
        adversary: the adversary's row or id, for ``cr_ego_adversary`` and
            ``min_clearance_adversary`` (NaN without one).
        horizons: seconds at which the per-second values are reported.
        smooth: s, moving-average window of the acceleration signal for HBR (0: none).

    Returns:
        ``{"scenario_id", "rollout_s", "adversary_id", "per_second", <SCENE_KEYS>}`` where
        ``per_second[str(h)]`` holds ``ADE``/``FDE`` (m), ``ORR``, ``HBR`` (= hbr_ego within h)
        and ``CR`` (ego collided at or before h) for each h, and the whole-rollout values are
        ``cr``, ``cr_all_agents``, ``cr_non_ego``, ``cr_ego_adversary``, ``hbr_ego``,
        ``hbr_all``, ``hbr_paper``, ``orr`` (fractions), ``min_ttc`` (s) and
        ``min_clearance_adversary`` (m).
    """
    ego_hits = ego_collision_steps(sim)
    overlaps = _agent_overlaps(sim)
    off = off_road_steps(sim)
    flags, mask = _hard_braking(sim, None, "position", smooth, HARD_BRAKE_THRESHOLD)
    e = sim.ego_index
    dist = ok = None
    if factual is not None:
        dist, ok = displacement_steps(sim, factual)
        rows = _non_ego_vehicles(sim)
        dist, ok = dist[rows], ok[rows]

    per_second = {}
    steps = np.arange(rollout_steps(sim))
    for h in horizons:
        n = horizon_steps(sim, h)
        brake_in = mask[e] & (steps + _REACH["position"] < n)
        ade, fde = _ade_fde(dist, ok, n) if dist is not None else (math.nan, math.nan)
        per_second[_second_key(h)] = {
            "ADE": ade,
            "FDE": fde,
            "ORR": _off_road_rate(sim, off, h, include_ego=True),
            "HBR": float(flags[e][brake_in].any()) if brake_in.any() else math.nan,
            "CR": float(ego_hits[steps < n].any()),
        }

    if adversary is not None:
        adv = _adversary_index(sim, adversary)
        adversary_id = str(sim.agent_ids[adv])
        cr_adv = float(ego_adversary_collision_steps(sim, adv).any())
        clearance = min_clearance(sim, adv)
    else:
        adversary_id, cr_adv, clearance = None, math.nan, math.nan

    return {
        "scenario_id": str(sim.scenario_id),
        "rollout_s": float(rollout_steps(sim) * sim.dt),
        "adversary_id": adversary_id,
        "per_second": per_second,
        "cr": float(ego_hits.any()),
        "cr_all_agents": float(_any_collision(overlaps, e, include_ego=True).any()),
        "cr_non_ego": float(_any_collision(overlaps, e, include_ego=False).any()),
        "cr_ego_adversary": cr_adv,
        "hbr_ego": _hbr_ego_of(flags, mask, sim),
        "hbr_all": _hbr_all_of(flags, mask, sim),
        "hbr_paper": hbr_paper(sim),
        "orr": _off_road_rate(sim, off, None, include_ego=True),
        "min_ttc": min_ttc_ego(sim),
        "min_clearance_adversary": clearance,
    }


# ---------------------------------------------------------------------- over scenes
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
            key: _mean([r["per_second"].get(s, {}).get(key, math.nan) for r in records])
            for key in PER_SECOND_KEYS
        }
        for s in seconds
    }
    groups = {}
    for name, secs in GROUPS.items():
        present = [_second_key(s) for s in secs if _second_key(s) in per_second]
        groups[name] = {
            key: _mean([per_second[s][key] for s in present]) for key in PER_SECOND_KEYS
        }
    overall = {}
    for key in SCENE_KEYS:
        values = np.array([r.get(key, math.nan) for r in records], dtype=np.float64)
        if key == "min_ttc":
            values = values[~np.isnan(values)]
            overall[key] = float(np.median(values)) if values.size else math.nan
        else:
            overall[key] = _mean(values)
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
