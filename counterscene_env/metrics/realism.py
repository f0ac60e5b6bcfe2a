"""Realism measures of a scene's rollout: off-road (ORR) and displacement from the log
(ADE/FDE)."""

from __future__ import annotations

import math

import numpy as np

from counterscene_env.metrics.common import (
    horizon_steps,
    in_horizon,
    nan_mean,
    rollout_slice,
    rollout_steps,
)
from counterscene_env.scene.core import Scene

#: An agent is parked if its speed stays below this at every valid step of the window, m/s.
PARKED_SPEED = 0.5
#: Speeds for the parked / moving split are read from positions over this window, s: the
#: logged velocity of a short real track is noise (docs/scenes.md, "Real maps").
SPEED_WINDOW = 1.0


def path_speeds(scene: Scene, window: float = SPEED_WINDOW) -> np.ndarray:
    """``[N, T]`` m/s: distance between the farthest valid positions within ``window / 2``
    before and after each step, over their time apart (the logged speed where an agent has
    no other valid step that near). 0 at invalid steps."""
    h = max(1, round(window / (2 * scene.dt)))
    n, t = scene.valid.shape
    idx = np.arange(t)
    lo = np.broadcast_to(idx, (n, t)).copy()
    hi = lo.copy()
    for d in range(1, h + 1):  # later (farther) offsets overwrite nearer ones
        back, ahead = np.maximum(idx - d, 0), np.minimum(idx + d, t - 1)
        lo = np.where(scene.valid[:, back] & (idx - d >= 0), back, lo)
        hi = np.where(scene.valid[:, ahead] & (idx + d < t), ahead, hi)
    rows = np.arange(n)[:, None]
    span = (hi - lo) * scene.dt
    dist = np.linalg.norm(scene.positions[rows, hi] - scene.positions[rows, lo], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        speed = np.where(span > 0, dist / span, np.abs(scene.speeds))
    return np.where(scene.valid, speed, 0.0)


def parked_agents(scene: Scene) -> np.ndarray:
    """``[N]`` bool: agents whose :func:`path_speeds` stay under :data:`PARKED_SPEED` at every
    valid step of the rollout window (agents with no valid step there count as parked)."""
    sl = rollout_slice(scene)
    fast = (path_speeds(scene)[:, sl] >= PARKED_SPEED) & scene.valid[:, sl]
    return ~fast.any(axis=1)


def off_road_steps(scene: Scene, judged: np.ndarray | None = None) -> np.ndarray:
    """``[N, T_roll]`` bool: agent valid and its centre off the road
    (:meth:`RoadMap.off_road`: outside the drivable area, inside the map's extent);
    ``judged``: :func:`judged_steps` of the scene where the caller has it already."""
    sl = rollout_slice(scene)
    return scene.road.off_road(scene.positions[:, sl], judged) & scene.valid[:, sl]


def judged_steps(scene: Scene) -> np.ndarray:
    """``[N, T_roll]`` bool: agent valid and its centre where the map can judge it (inside the
    map's extent, :meth:`RoadMap.judged`): the steps an off-road rate counts. A real map is a
    crop; a car beyond it is neither on nor off its roads."""
    sl = rollout_slice(scene)
    return scene.road.judged(scene.positions[:, sl]) & scene.valid[:, sl]


def off_road_rate_of(
    scene: Scene,
    off: np.ndarray,
    horizon: float | None,
    include_ego: bool,
    rows: np.ndarray | None = None,
    valid: np.ndarray | None = None,
) -> float:
    """ORR from precomputed :func:`off_road_steps`, over the vehicles among ``rows`` ([N] bool;
    None: all), at the steps where ``valid`` ``[N, T_roll]`` (None: :func:`judged_steps` of
    ``scene``; :func:`logged_off_road_steps` gives the log's)."""
    veh = scene.vehicle_mask.copy() if rows is None else scene.vehicle_mask & rows
    if not include_ego:
        veh[scene.ego_index] = False
    if valid is None:
        valid = judged_steps(scene)
    mask = valid & in_horizon(scene, horizon)[None] & veh[:, None]
    n = mask.sum()
    return float((off & mask).sum() / n) if n else math.nan


def off_road_rate(scene: Scene, horizon: float | None = None, include_ego: bool = True) -> float:
    """ORR: fraction of valid vehicle agent-steps within the horizon whose centre is off-road.

    The paper's ``1/(NT) sum 1[p not in D]`` over valid steps only, and only those inside the
    map's extent (:func:`judged_steps`). NaN if there are none.
    """
    return off_road_rate_of(scene, off_road_steps(scene), horizon, include_ego)


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


def logged_rollout(sim: Scene, factual: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The factual log over ``sim``'s rollout, row by row of ``sim`` (:func:`align_agents`).

    Rollout step r of the sim is step ``factual.current_index + 1 + r`` of the factual scene
    (both start from "now"); factual steps past its end count as invalid.

    Returns:
        ``[N_sim, T_roll, 2]`` m positions, ``[N_sim, T_roll]`` rad yaws and
        ``[N_sim, T_roll]`` bool validity (zeros where invalid).
    """
    rows = align_agents(sim, factual)
    n, t_roll = sim.num_agents, rollout_steps(sim)
    start = factual.current_index + 1
    avail = max(0, min(t_roll, factual.num_steps - start))
    pos, yaw = np.zeros((n, t_roll, 2)), np.zeros((n, t_roll))
    ok = np.zeros((n, t_roll), dtype=bool)
    pos[:, :avail] = factual.positions[rows, start : start + avail]
    yaw[:, :avail] = factual.yaws[rows, start : start + avail]
    ok[:, :avail] = factual.valid[rows, start : start + avail]
    return pos, yaw, ok


def logged_off_road_steps(sim: Scene, factual: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The factual log's own off-road steps on ``sim``'s map, row by row of ``sim``
    (:func:`logged_rollout` aligns the two): the reference for the simulation's ORR, since a
    real map lacks the car parks and driveways where logged cars stand.

    Returns:
        ``[N_sim, T_roll]`` bool off the road, and ``[N_sim, T_roll]`` bool where the log has
        the agent where the map can judge it (:meth:`RoadMap.judged`).
    """
    p_fac, _, ok_fac = logged_rollout(sim, factual)
    judged = sim.road.judged(p_fac) & ok_fac
    return sim.road.off_road(p_fac, judged), judged


def displacement_steps(sim: Scene, factual: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Displacement of each simulated agent from its factual log over the rollout
    (:func:`logged_rollout` aligns the two).

    Returns:
        ``[N_sim, T_roll]`` m (NaN where undefined) and ``[N_sim, T_roll]`` bool, True where both
        are valid.
    """
    sl = rollout_slice(sim)
    p_sim, ok_sim = sim.positions[:, sl], sim.valid[:, sl]
    p_fac, _, ok_fac = logged_rollout(sim, factual)
    ok = ok_sim & ok_fac
    dist = np.where(ok, np.linalg.norm(p_sim - p_fac, axis=-1), np.nan)
    return dist, ok


def ade_fde_of(dist: np.ndarray, ok: np.ndarray, n: int) -> tuple[float, float]:
    """ADE/FDE over the first n rollout steps of ``[A, T_roll]`` displacements."""
    d, m = dist[:, :n], ok[:, :n]
    counts = m.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_agent = np.where(m, d, 0.0).sum(1) / counts  # mean over jointly valid steps
    ade = nan_mean(per_agent[counts > 0])
    fde = math.nan
    if 0 < n <= ok.shape[1]:
        last = ok[:, n - 1]
        fde = nan_mean(dist[last, n - 1])
    return ade, fde


def non_ego_vehicles(scene: Scene) -> np.ndarray:
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
    rows = non_ego_vehicles(sim)
    return ade_fde_of(dist[rows], ok[rows], horizon_steps(sim, horizon))
