"""Safety measures of a scene's rollout: collisions (CR), hard braking (HBR, signed and the
paper's), time to collision and clearance."""

from __future__ import annotations

import math

import numpy as np

from counterscene_env import geometry
from counterscene_env.metrics.common import (
    HARD_BRAKE_THRESHOLD,
    AccelerationSource,
    adversary_index,
    in_horizon,
    is_hard_braking,
    rollout_slice,
    rollout_steps,
)
from counterscene_env.metrics.realism import logged_rollout
from counterscene_env.scene.core import Scene
from counterscene_env.ttc import box_time_to_collision


def ego_collision_steps(scene: Scene) -> np.ndarray:
    """``[T_roll]`` bool: at each rollout step, the ego's box overlaps another valid agent's.

    This is the paper's CR event (oriented boxes from centroid, yaw and extent); every agent
    type counts (pedestrians, cyclists, static objects), each masked by its own validity.
    """
    sl, e = rollout_slice(scene), scene.ego_index
    pos, yaw, ok = scene.positions[:, sl], scene.yaws[:, sl], scene.valid[:, sl]
    hit = geometry.boxes_overlap(
        pos[e][None], yaw[e][None], scene.extents[e], pos, yaw, scene.extents[:, None]
    )  # [N, T_roll]
    hit &= ok & ok[e][None]
    hit[e] = False
    return hit.any(0)


def ego_collided(scene: Scene, horizon: float | None = None) -> bool:
    """Whether the ego collided at any rollout step within ``horizon`` s (None: whole rollout)."""
    return bool((ego_collision_steps(scene) & in_horizon(scene, horizon)).any())


def agent_overlaps(scene: Scene) -> np.ndarray:
    """``[T_roll, N, N]`` bool: pairwise overlap of valid agents at each rollout step."""
    sl = rollout_slice(scene)
    return geometry.overlaps_over_time(
        scene.positions[:, sl], scene.yaws[:, sl], scene.extents, scene.valid[:, sl]
    )


def logged_overlap_pairs(sim: Scene, factual: Scene) -> np.ndarray:
    """``[N_sim, N_sim]`` bool: the pairs of ``sim``'s agents whose boxes overlap in the
    factual log at some step of ``sim``'s rollout (:func:`~counterscene_env.metrics.realism.
    logged_rollout` aligns rows and steps). Real logs have such pairs of their own:
    pedestrians walking in groups, imprecise boxes (docs/metrics.md)."""
    pos, yaw, ok = logged_rollout(sim, factual)
    return geometry.overlaps_over_time(pos, yaw, sim.extents, ok).any(0)


def new_vehicle_collisions(sim: Scene, factual: Scene) -> list[tuple[int, int, int]]:
    """Pairs of vehicles other than the ego whose boxes overlap in ``sim``'s rollout but
    never in ``factual`` over the same steps (:func:`logged_overlap_pairs`): ``(a, b, t)`` with rows
    ``a < b`` of ``sim`` and ``t`` the first overlapping rollout step (an index into
    ``rollout_slice(sim)``)."""
    vehicle = sim.vehicle_mask.copy()
    vehicle[sim.ego_index] = False
    overlaps = agent_overlaps(sim) & ~logged_overlap_pairs(sim, factual)[None]
    overlaps &= vehicle[None, :, None] & vehicle[None, None, :]
    new = np.triu(overlaps.any(0), 1)
    return [
        (int(a), int(b), int(np.argmax(overlaps[:, a, b])))
        for a, b in zip(*np.nonzero(new), strict=True)
    ]


def any_collision(overlaps: np.ndarray, ego: int, include_ego: bool) -> np.ndarray:
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
    return any_collision(agent_overlaps(scene), scene.ego_index, include_ego)


def ego_adversary_collision_steps(scene: Scene, adversary: int | str, since: int = 0) -> np.ndarray:
    """``[T_roll]`` bool: the ego's and the adversary's boxes overlap (both valid), at rollout
    steps from ``since`` on (before it the agent was not yet the adversary)."""
    sl, e, a = rollout_slice(scene), scene.ego_index, adversary_index(scene, adversary)
    rows = [e, a]
    hit = geometry.boxes_overlap(
        scene.positions[e, sl],
        scene.yaws[e, sl],
        scene.extents[e],
        scene.positions[a, sl],
        scene.yaws[a, sl],
        scene.extents[a],
    )
    hit &= scene.valid[rows][:, sl].all(0)
    hit[:since] = False
    return hit


def _stencils(scene: Scene) -> tuple[np.ndarray, np.ndarray, int]:
    """The positions the acceleration samples read: ``[N, T', 2]`` m and ``[N, T']`` valid
    from the step before "now" on (from "now" without history), and the rollout step of the
    first full three-step stencil (0, or 1 without history)."""
    c = scene.current_index
    lo = max(c - 1, 0)
    return scene.positions[:, lo:], scene.valid[:, lo:], lo + 2 - (c + 1)


def _finite_difference_acceleration(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The paper's finite differences of positions, each sample at the rollout step it ends on.

    ``v_t = (p_t - p_{t-1}) / dt``, ``a_t = (v_t - v_{t-1}) / dt`` (the appendix HBR equation's
    stencil, ``(p_t - 2 p_{t-1} + p_{t-2}) / dt^2``), at every rollout step t. The first two
    samples read "now" (and the history step before it): braking in the first rollout step
    is an acceleration of the rollout, as the per-step ``info["hard_braking"]`` counts it
    (docs/metrics.md, "Definitions").

    Returns:
        ``[N, T_roll, 2]`` m/s^2 (NaN where undefined) and ``[N, T_roll]`` bool validity.
    """
    p, ok, first = _stencils(scene)
    n, t_roll = scene.num_agents, rollout_steps(scene)
    acc = np.full((n, t_roll, 2), np.nan)
    valid = np.zeros((n, t_roll), dtype=bool)
    if p.shape[1] >= 3:
        acc[:, first:] = (p[:, 2:] - 2.0 * p[:, 1:-1] + p[:, :-2]) / scene.dt**2
        valid[:, first:] = ok[:, 2:] & ok[:, 1:-1] & ok[:, :-2]
    acc[~valid] = np.nan
    return acc, valid


def _travel_directions(scene: Scene) -> np.ndarray:
    """``[N, T_roll, 2]`` unit vectors: each acceleration sample's direction of travel, the
    central chord ``p_t - p_{t-2}`` of its stencil (the heading at ``t - 1`` where that chord
    is shorter than 1 mm: a car standing still).

    The longitudinal acceleration is the second difference's part along the path, the rate
    of change of speed. Read against the heading instead, a turning car's sideways
    acceleration leaks into it wherever heading and course differ: highway-env's bicycle
    moves at a slip angle to its heading, and a log's heading is a box annotation.
    Measured on the quickstart's junction turn at a steady 9.04 m/s: -4.04 m/s^2 against
    the heading a step early, -3.03 against the heading at the middle step, -0.01 along the
    chord (docs/metrics.md, "Definitions")."""
    p, _, first = _stencils(scene)
    yaw = scene.yaws[:, scene.current_index : scene.num_steps - 1]
    out = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    if p.shape[1] >= 3:
        chord = p[:, 2:] - p[:, :-2]
        length = np.linalg.norm(chord, axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, first:] = np.where(length > 1e-3, chord / length, out[:, first:])
    return out


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
        source: ``"position"``: the paper's finite differences of positions, their signed
            part along the direction of travel, ``a_lon,t = a_t . u_t`` with ``u_t`` the unit
            central chord of the stencil (negative = braking, whatever the direction of
            travel; :func:`_travel_directions`); ``"speed"``: ``(s_t - s_{t-1}) / dt`` of the
            signed speed. Either way the sample at rollout step t ends at t, and the first
            reads "now": the rollout's first step counts. highway-env's bicycle (the ego)
            moves with the speed before the action, so its positions show a speed change one
            step later than its speeds do: the ego's last action shows only in ``"speed"``.
        smooth: s, width of a centred moving average over the valid samples of the signal
            (``round(smooth / dt)`` samples, rounded up to an odd count; 0: none). The nuScenes
            10 Hz logs interpolate 2 Hz labels, whose second differences spike at the knots;
            about 0.5 s removes that. Near a horizon's end the average reads up to half a
            window past it.

    Returns:
        ``[N, T_roll]`` m/s^2 (NaN where undefined) and ``[N, T_roll]`` bool, valid where every
        step the sample reads (t-2 .. t for positions, t-1 .. t for speeds) is valid.
    """
    if source == "position":
        acc_vec, valid = _finite_difference_acceleration(scene)
        acc = (acc_vec * _travel_directions(scene)).sum(-1)
    elif source == "speed":
        c = scene.current_index
        s, ok = scene.speeds[:, c:], scene.valid[:, c:]
        acc = (s[:, 1:] - s[:, :-1]) / scene.dt
        valid = ok[:, 1:] & ok[:, :-1]
    else:
        raise ValueError(f"source must be 'position' or 'speed', got {source!r}")
    window = round(float(smooth) / scene.dt)
    if window > 1:
        acc = _moving_average(acc, valid, window)
    acc = np.where(valid, acc, np.nan)
    return acc, valid


def braking_samples(
    scene: Scene, horizon: float | None, source: AccelerationSource, smooth: float
) -> tuple[np.ndarray, np.ndarray]:
    """``[N, T_roll]`` longitudinal accelerations [m/s^2] and the mask of the samples that
    lie within the horizon (the samples HBR thresholds)."""
    acc, valid = longitudinal_acceleration(scene, source, smooth)
    return acc, valid & in_horizon(scene, horizon)[None]


def hard_braking_flags(
    scene: Scene, horizon: float | None, source: AccelerationSource, smooth: float, threshold
) -> tuple[np.ndarray, np.ndarray]:
    """``[N, T_roll]`` hard-braking flags and the sample mask within the horizon."""
    acc, mask = braking_samples(scene, horizon, source, smooth)
    return is_hard_braking(acc, threshold) & mask, mask


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
    return hbr_ego_of(*hard_braking_flags(scene, horizon, source, smooth, threshold), scene)


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
    return hbr_all_of(*hard_braking_flags(scene, horizon, source, smooth, threshold), scene)


def hbr_ego_of(flags: np.ndarray, mask: np.ndarray, scene: Scene) -> float:
    e = scene.ego_index
    return float(flags[e].any()) if mask[e].any() else math.nan


def hbr_all_of(flags: np.ndarray, mask: np.ndarray, scene: Scene) -> float:
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
    valid = valid & in_horizon(scene, horizon)[None]
    valid[:, :2] = False  # the paper's samples read rollout steps only
    # The paper's psi_t is the heading at the stencil's first step, t - 2 for our sample at t.
    first = scene.current_index - 1
    yaw = np.full(valid.shape, np.nan)
    yaw[:, max(-first, 0) :] = scene.yaws[:, max(first, 0) : scene.num_steps - 2]
    a_lon = np.linalg.norm(acc_vec, axis=-1) * np.cos(yaw)
    n = valid.sum()
    return float((is_hard_braking(a_lon, threshold) & valid).sum() / n) if n else math.nan


def min_ttc_ego(scene: Scene, horizon: float = 10.0, step: float = 0.1) -> float:
    """Smallest constant-velocity TTC, s, of the ego against any other agent over the rollout.

    At every rollout step where the ego is valid, each other valid agent is projected at its
    current velocity with its heading held
    (:func:`~counterscene_env.ttc.box_time_to_collision`, horizon ``horizon`` s at resolution
    ``step`` s). 0 while overlapping; ``inf`` if never.
    """
    sl, e = rollout_slice(scene), scene.ego_index
    pos, yaw, ok = scene.positions[:, sl], scene.yaws[:, sl], scene.valid[:, sl]
    vel = scene.velocities[:, sl]
    ttc = box_time_to_collision(
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


def min_clearance(scene: Scene, adversary: int | str, since: int = 0) -> float:
    """Smallest box-to-box distance, m, between ego and adversary over rollout steps from
    ``since`` on where both are valid (0 once they touch); NaN if there are none."""
    sl, e, a = rollout_slice(scene), scene.ego_index, adversary_index(scene, adversary)
    both = scene.valid[e, sl] & scene.valid[a, sl]
    both[:since] = False
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
