"""Motion: how every agent moves into the next step (docs/closed_loop.md, "One episode",
**Who moves how**).

An agent exists at a step when the log says so, with one exception: an agent that would
enter (appear in the log) where another agent's box already is waits outside the scene until
its logged pose is clear (:func:`_hold_entries`). Each step, in this order:

- an agent in a model window follows its current plan (``MotionSource.PLAN``); one that was
  never planned, or just entered, replays its log (``LOG``); one handed to the IDM lane
  follower drives by IDM (``IDM``); one whose plan ran out keeps its speed and course
  (``COAST``);
- **reflexes of the ordinary traffic** (never the egos): an agent about to run into another
  brakes along its path instead (``YIELD``, ``sim/yielding.py``; a guided adversary yields
  to everyone but the egos, its margins toward them being what the guidance removes, or to
  no one with ``adversary_yields_to_others`` off), and a step that would leave the road is
  moved sideways onto the lane (``KEEP``, ``sim/road_keeping.py``);
- the egos advance by their actions through highway-env's bicycle model, or are written from
  given states (``EGO``).

Shapes: N agents, T steps, F planned steps, P path points.
"""

from __future__ import annotations

import math

import numpy as np

from counterscene_env import geometry
from counterscene_env.sim import road_keeping, yielding
from counterscene_env.sim.config import SimConfig
from counterscene_env.sim.state import Episode, MotionSource


def advance(
    ep: Episode,
    actions: np.ndarray | None,
    states: list[np.ndarray | None],
    config: SimConfig,
    guided: bool,
) -> None:
    """Move every agent of ``ep`` from step ``t`` to ``t + 1`` (module docstring).

    Args:
        actions: ``[E, 2]`` the egos' actions (acceleration m/s^2, steering rad), or None.
        states: per ego, ``[4]`` (x m, y m, yaw rad, speed m/s) written as its next state, or
            None to use its action.
        config: closed-loop settings (``traffic_yields``, ``adversary_yields_to_others``,
            ``road_keeping``).
        guided: the guidance is on (a guided adversary never yields to an ego).
    """
    t, t1 = ep.t, ep.t + 1
    log = ep.factual
    egos = ep.egos
    present = log.valid[:, t1].copy()
    present[egos] = True
    k = t1 - ep.plan_start
    F = ep.plan_positions.shape[1]
    entered = present & ~ep.valid[:, t]
    idm = np.zeros_like(present)
    idm[list(ep.background)] = True
    idm &= present & ~entered
    on_plan = ep.planned & (k >= 0) & (k < F) & present & ~idm
    replay = present & ~on_plan & ~idm & (~ep.planned | entered)
    coast = present & ~on_plan & ~replay & ~idm
    if idm.any():
        now = ep.state()  # everyone at step t, before anyone moves
        for r in np.flatnonzero(idm):
            x, y, yaw, speed = ep.background[int(r)].drive(now)
            ep.positions[r, t1], ep.yaws[r, t1], ep.speeds[r, t1] = (x, y), yaw, speed
    i = np.flatnonzero(on_plan)
    ep.positions[i, t1] = ep.plan_positions[i, k[i]]
    ep.yaws[i, t1] = ep.plan_yaws[i, k[i]]
    ep.speeds[i, t1] = ep.plan_speeds[i, k[i]]
    i = np.flatnonzero(replay)
    ep.positions[i, t1] = log.positions[i, t1]
    ep.yaws[i, t1] = log.yaws[i, t1]
    ep.speeds[i, t1] = log.speeds[i, t1]
    ep.progress[entered] = np.nan
    held = _yield(ep, on_plan, k, replay & ~entered, idm, config, guided)
    kept = _keep_on_road(ep, (on_plan | replay | idm) & ep.valid[:, t], config)
    i = np.flatnonzero(coast)
    heading = np.stack([np.cos(ep.yaws[i, t]), np.sin(ep.yaws[i, t])], -1)
    ep.positions[i, t1] = ep.positions[i, t] + log.dt * ep.speeds[i, t, None] * heading
    ep.yaws[i, t1] = ep.yaws[i, t]
    ep.speeds[i, t1] = ep.speeds[i, t]
    ep.valid[:, t1] = present
    ep.source[:, t1] = np.select(
        [on_plan, replay, coast, idm],
        [MotionSource.PLAN, MotionSource.LOG, MotionSource.COAST, MotionSource.IDM],
        MotionSource.NONE,
    )
    ep.source[held, t1] = MotionSource.YIELD
    ep.source[kept, t1] = MotionSource.KEEP
    ep.source[egos, t1] = MotionSource.EGO

    _move_egos(ep, actions, states)
    # Egos never enter: they are present at every step (``present[egos]`` above).
    ep.source[_hold_entries(ep, entered), t1] = MotionSource.NONE
    ep.t = t1


def _move_egos(ep: Episode, actions: np.ndarray | None, states: list[np.ndarray | None]) -> None:
    """The egos into step ``t + 1``: the policy's action through highway-env's bicycle, or a
    written state."""
    t1, dt = ep.t + 1, ep.factual.dt
    for k, (e, v, state) in enumerate(zip(ep.egos, ep.vehicles, states, strict=True)):
        if state is not None:
            v.position = np.array(state[:2], dtype=np.float64)
            v.heading, v.speed = float(state[2]), float(state[3])
        else:
            v.act({"acceleration": float(actions[k, 0]), "steering": float(actions[k, 1])})
            v.step(dt)
        ep.positions[e, t1] = v.position
        ep.yaws[e, t1] = v.heading
        ep.speeds[e, t1] = v.speed


def _hold_entries(ep: Episode, entering: np.ndarray) -> list[int]:
    """Keep out of step ``t + 1`` the ``entering`` ``[N]`` agents whose logged pose there
    overlaps another agent's box (docs/closed_loop.md, "Who moves how"); returns their rows.

    A log's agents enter where the log saw them first: at the edge of a recording or of a
    sensor's range. Another car in the simulation may be there by then (one that drove slower
    than its log), and appearing on top of it is an artefact of replaying the log, not a
    collision anyone drove into. Like highway-env's spawner, which does not place a car near
    another, such an agent waits: it is absent at this step and tries again at the next, at
    its logged pose then. It runs after everyone has moved, the egos too, so it checks the
    boxes the step's collisions are scored on; entering agents are checked in row order, each
    against those let in before it. A pair that overlaps in the log at that step too is the
    log's own and holds no one back.
    """
    t1 = ep.t + 1
    rows = np.flatnonzero(entering)
    if not rows.size:
        return []
    log = ep.factual
    occupied = ep.valid[:, t1].copy()
    occupied[rows] = False
    held = []

    def overlaps(r: int, others: np.ndarray, states) -> np.ndarray:
        """Whether row ``r``'s box overlaps each of ``others``' at step t + 1 in ``states``
        (the episode or its log)."""
        pos, yaw = states.positions[:, t1], states.yaws[:, t1]
        return geometry.boxes_overlap(
            pos[r], yaw[r], log.extents[r], pos[others], yaw[others], log.extents[others]
        )

    for r in rows:
        others = np.flatnonzero(occupied)
        # An overlap the log itself has (a group of pedestrians, a real log's annotations)
        # is the log's, not the replay's: it does not hold the agent back.
        logged = log.valid[others, t1] & overlaps(r, others, log)
        if (overlaps(r, others, ep) & ~logged).any():
            ep.valid[r, t1] = False
            held.append(int(r))
        else:
            occupied[r] = True
    return held


def _yield(
    ep: Episode,
    on_plan: np.ndarray,
    k: np.ndarray,
    replay: np.ndarray,
    idm: np.ndarray,
    config: SimConfig,
    guided: bool,
) -> list[int]:
    """Hold back, along their paths, the agents whose next step would run into another
    agent's current box (``sim/yielding.py``). The path is the plan's, the
    log's for a replaying agent, and the straight line through its next point for an IDM
    one. Rows free to advance keep their exact point. Returns the rows held back."""
    if not config.traffic_yields:
        return []
    t, t1, dt = ep.t, ep.t + 1, ep.factual.dt
    log = ep.factual
    # A guided adversary's margins toward the egos are what the guidance removes; with
    # ``adversary_yields_to_others`` it still yields to everyone else (docs/design.md,
    # "Where we depart"), else to no one.
    adversaries = {a for a in ep.adversaries if a is not None} if guided else set()
    exempt = set() if config.adversary_yields_to_others else adversaries
    here = np.flatnonzero(ep.valid[:, t])
    xy, yaw, speed = ep.positions[here, t], ep.yaws[here, t], ep.speeds[here, t]
    velocity = speed[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
    others = (here, xy, yaw, log.extents[here], velocity)
    if adversaries - exempt:  # what a yielding adversary sees: everyone but the egos
        keep = ~np.isin(here, ep.egos)
        third_parties = tuple(a[keep] for a in others)
    held = []
    moving = (on_plan | replay | idm) & ep.valid[:, t]
    # The egos move after everyone else, by their own policies: what the log or a plan
    # wrote for them at t + 1 is no place to yield to.
    moving[ep.egos] = False
    movers = np.flatnonzero(moving)
    # Rows whose next pose is final: written already and not subject to yielding (an
    # adversary that yields to no one, an entering car), then each yielding row once done.
    settled = (on_plan | replay | idm) & ep.valid[:, t1]
    settled[movers] = False
    settled[ep.egos] = False
    for r in movers:
        path, path_yaw, due = _path(ep, int(r), bool(on_plan[r]), int(k[r]), bool(idm[r]))
        arc = geometry.arc_length(path)
        done = ep.progress[r]
        if np.isnan(done):
            done = arc[due - 1]  # a log row's first step: on schedule
        if r in exempt:
            ep.progress[r] = arc[due]
            settled[r] = True
            continue
        lagging = done < arc[due - 1] - 1e-6 and not idm[r]  # IDM keeps its own speed
        desired = arc[due] - arc[due - 1]
        seen = third_parties if r in adversaries else others
        step = _allowed_step(ep, int(r), (path, path_yaw, arc), done, desired, lagging, seen)
        on_time = not lagging and step >= desired - 1e-9
        if on_time:  # the plan's (or log's, or IDM's) point, already written
            now_done, pose = arc[due], (ep.positions[r, t1].copy(), float(ep.yaws[r, t1]))
        else:
            now_done = min(done + step, arc[-1])
            pose = yielding.point_at(path, path_yaw, arc, now_done)
        # The last guard: never end a step inside a box we were clear of.
        if _moves_into_others(ep, int(r), pose, seen, settled):
            on_time, now_done = False, done
            pose = (ep.positions[r, t].copy(), float(ep.yaws[r, t]))
        settled[r] = True
        if on_time:
            ep.progress[r] = now_done
            continue
        ep.positions[r, t1], ep.yaws[r, t1] = pose
        ep.speeds[r, t1] = (now_done - done) / dt
        ep.progress[r] = now_done
        held.append(int(r))
    return held


def _allowed_step(
    ep: Episode,
    r: int,
    path: tuple[np.ndarray, np.ndarray, np.ndarray],
    done: float,
    desired: float,
    lagging: bool,
    others: tuple[np.ndarray, ...],
) -> float:
    """How far [m] agent ``r`` may advance along its path (points ``[P, 2]`` m, yaws ``[P]``
    rad, arc lengths ``[P]`` m) this step, from ``done`` m along it, wanting ``desired`` m
    (sim/yielding.py); ``others`` are everyone present now (rows, positions, yaws, extents,
    velocities)."""
    t, dt = ep.t, ep.factual.dt
    points, yaws, arc = path
    here, xy, yaw, extents, velocity = others
    ahead = np.flatnonzero(arc > done)
    stations = np.concatenate([ep.positions[r, t][None], points[ahead]])
    station_yaw = np.concatenate([[ep.yaws[r, t]], yaws[ahead]])
    station_arc = np.concatenate([[0.0], arc[ahead] - done])
    # Beyond the distance this step's speed needs to stop in, a car cannot change the answer
    # (allowed_advance gives ``desired`` then): check the path up to there.
    need = max(desired, (desired / dt) ** 2 / (2 * yielding.BRAKE))
    cut = int(np.searchsorted(station_arc, need)) + 1
    other = here != r
    d_free, v_lead = yielding.free_distance(
        stations[:cut],
        station_yaw[:cut],
        station_arc[:cut],
        ep.factual.extents[r],
        xy[other],
        yaw[other],
        extents[other],
        velocity[other],
    )
    return yielding.allowed_advance(d_free, v_lead, float(ep.speeds[r, t]), desired, dt, lagging)


def _moves_into_others(
    ep: Episode,
    r: int,
    pose: tuple[np.ndarray, float],
    others: tuple[np.ndarray, ...],
    settled: np.ndarray,
) -> bool:
    """Whether agent ``r`` at ``pose`` (centre m, yaw rad) ends its step inside a box it was
    clear of: where the others are now, or where those ``settled`` ``[N]`` will be. A plan may
    also turn a car on the spot, which sweeps its corners without moving along the path."""
    t, t1, extents_all = ep.t, ep.t + 1, ep.factual.extents
    here, xy, yaw, extents, _ = others
    other = here != r
    then = np.flatnonzero(settled)
    return yielding.moves_into(
        pose,
        (ep.positions[r, t], ep.yaws[r, t]),
        extents_all[r],
        np.concatenate([xy[other], ep.positions[then, t1]]),
        np.concatenate([yaw[other], ep.yaws[then, t1]]),
        np.concatenate([extents[other], extents_all[then]]),
    )


def _path(
    ep: Episode, r: int, on_plan: bool, k: int, idm: bool
) -> tuple[np.ndarray, np.ndarray, int]:
    """Agent ``r``'s path for the yielding rule: points ``[P, 2]`` m, yaws ``[P]`` rad, and
    the index of the point it is due at on step ``t + 1``."""
    t, t1 = ep.t, ep.t + 1
    if idm:
        # IDM's next point, then straight on for as far as it could need to stop in.
        now, then = ep.positions[r, t], ep.positions[r, t1]
        reach = ep.speeds[r, t1] ** 2 / (2 * yielding.BRAKE) + 5.0
        on = np.arange(0.5, reach, 0.5)[:, None]
        course = np.array([math.cos(ep.yaws[r, t1]), math.sin(ep.yaws[r, t1])])
        path = np.concatenate([now[None], then[None], then + on * course])
        path_yaw = np.concatenate([[ep.yaws[r, t]], np.full(len(on) + 1, ep.yaws[r, t1])])
        ep.progress[r] = 0.0  # a fresh path every step
        return path, path_yaw, 1
    if on_plan:
        start = ep.plan_start[r] - 1  # the step the plan was made from
        path = np.concatenate([ep.positions[r, start][None], ep.plan_positions[r]])
        path_yaw = np.concatenate([[ep.yaws[r, start]], ep.plan_yaws[r]])
        return path, path_yaw, k + 1
    log = ep.factual
    first, last = _valid_run(log.valid[r], t1)  # the log's path around t1
    return log.positions[r, first:last], log.yaws[r, first:last], t1 - first


def _keep_on_road(ep: Episode, movers: np.ndarray, config: SimConfig) -> list[int]:
    """Move sideways onto their lanes the non-ego agents whose step would leave the road
    (``sim/road_keeping.py``); returns the rows moved. A correction that
    would put an agent into another's box stops it where it was instead."""
    if not config.road_keeping:
        return []
    t, t1, log = ep.t, ep.t + 1, ep.factual
    movers = movers.copy()
    movers[ep.egos] = False
    rows = np.flatnonzero(movers)
    if not rows.size:
        return []
    road = log.road
    leaving = ~road.off_road(ep.positions[rows, t]) & road.off_road(ep.positions[rows, t1])
    kept = []
    for r in rows[leaving]:
        here, there = ep.positions[r, t], ep.positions[r, t1]
        step = there - here
        course = math.atan2(step[1], step[0]) if step @ step > 1e-6 else ep.yaws[r, t1]
        moved = road_keeping.keep_on_lane(there, course, ep.pieces)
        if moved is None or road.off_road(moved):
            continue
        step = moved - here
        yaw = math.atan2(step[1], step[0]) if step @ step > 1e-4 else float(ep.yaws[r, t])
        # Everyone else where they are now and where they will be (egos not yet moved).
        others = np.flatnonzero(ep.valid[:, t] & (np.arange(log.num_agents) != r))
        ahead = np.flatnonzero(movers & ep.valid[:, t1] & (np.arange(log.num_agents) != r))
        if yielding.moves_into(
            (moved, yaw),
            (here, ep.yaws[r, t]),
            log.extents[r],
            np.concatenate([ep.positions[others, t], ep.positions[ahead, t1]]),
            np.concatenate([ep.yaws[others, t], ep.yaws[ahead, t1]]),
            np.concatenate([log.extents[others], log.extents[ahead]]),
        ):
            moved, yaw = here.copy(), float(ep.yaws[r, t])
        ep.positions[r, t1], ep.yaws[r, t1] = moved, yaw
        ep.speeds[r, t1] = float(np.linalg.norm(moved - here)) / log.dt
        kept.append(int(r))
    return kept


def _valid_run(valid: np.ndarray, t: int) -> tuple[int, int]:
    """``[first, last)``: the run of consecutive valid steps of ``valid`` ``[T]`` around ``t``."""
    gaps = np.flatnonzero(~valid)
    first = int(gaps[gaps < t].max(initial=-1)) + 1
    last = int(gaps[gaps > t].min(initial=len(valid)))
    return first, last
