"""The agents of a CommonRoad scenario, read by ``commonroad-io``, on the scene's 0.1 s grid
(``scene/commonroad.py`` builds the scenes from them).

Agents: the file must have 0.1 s steps; scene step t is the file's time step t, and the log ends
at the last state of any obstacle. Dynamic obstacles of type car, truck, bus, taxi, motorcycle,
priorityVehicle or parkedVehicle are ``"vehicle"``, bicycle ``"cyclist"``, pedestrian
``"pedestrian"``, any other ``"other"``. Static obstacles are ``"other"`` whatever their type
(the world model drives only vehicles, and must not move them) and valid at every step. A track
is the initial state plus the trajectory's states (an obstacle without a prediction has only its
initial state); steps without a state are invalid. ``velocity`` is the signed speed along the
heading (m/s). Where any state of a track lacks it, the track's speeds are derived from its
positions (mean of the backward and forward differences that exist, signed by the heading; newer
commonroad-io silently fills a missing initial velocity with 0) and its id is listed in
``metadata["repairs"]``. Extents are a rectangle's (length, width), else the bounding box
of a circle or polygon; a rectangle's ``origin_x_shift`` (newer commonroad-io) is undone so that
positions are box centres. Obstacles with a set-based prediction (occupancy sets, not a log) or
states without a point position or orientation are dropped, with the reason, into
``metadata["dropped_tracks"]`` (the same two keys as the ScenarioNet importer's, which
``counterscene inspect`` prints). Rows are sorted by obstacle id.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from counterscene_env.geometry import wrap_angle
from counterscene_env.scene.commonroad_map import CommonRoadError
from counterscene_env.scene.core import DEFAULT_DT, SceneError, drop_impossible_jumps

VEHICLE_TYPES = ("car", "truck", "bus", "taxi", "motorcycle", "priorityVehicle", "parkedVehicle")
#: Agent type of each CommonRoad obstacle type of a dynamic obstacle; any other is "other".
AGENT_TYPE = {
    **dict.fromkeys(VEHICLE_TYPES, "vehicle"),
    "bicycle": "cyclist",
    "pedestrian": "pedestrian",
}


@dataclass
class Tracks:
    """The agents of one CommonRoad file on the 0.1 s grid, rows sorted by obstacle id."""

    ids: list[str]
    types: list[str]
    positions: np.ndarray  # [N, T, 2] m, box centres
    yaws: np.ndarray  # [N, T] rad
    speeds: np.ndarray  # [N, T] m/s
    valid: np.ndarray  # [N, T] bool
    extents: np.ndarray  # [N, 2] m, (length, width)
    notes: dict  # repairs and dropped_tracks (for the metadata)


@contextlib.contextmanager
def file_fault(source: str, what: str) -> Iterator[None]:
    """Turn an error from data of a type or shape not foreseen into a CommonRoadError: still
    the file's fault, and said with its name rather than a traceback."""
    try:
        yield
    except SceneError:
        raise
    except (TypeError, ValueError, AttributeError, IndexError, KeyError) as exc:
        raise CommonRoadError(f"{source}: malformed {what} ({type(exc).__name__}: {exc})") from exc


def read_tracks(scenario: Any, source: str) -> Tracks:
    """The agents of a parsed scenario (module docstring, "Agents")."""
    if abs(float(scenario.dt) - DEFAULT_DT) > 1e-9:
        raise CommonRoadError(f"{source}: timeStepSize {scenario.dt} s; only 0.1 s is supported")
    with file_fault(source, "obstacle"):
        rows, dropped = [], {}
        obstacles = [(o, False) for o in scenario.dynamic_obstacles]
        for obs, static in sorted(
            obstacles + [(o, True) for o in scenario.static_obstacles],
            key=lambda pair: int(pair[0].obstacle_id),
        ):
            states, why = _states(obs, static)
            if why is None and (extent := _extent(obs.obstacle_shape)) is None:
                why = f"unsupported shape {type(obs.obstacle_shape).__name__}"
            if why is None:
                rows.append((obs, static, states, extent))
            else:
                dropped[str(obs.obstacle_id)] = why
        if not rows:
            some = next(iter(dropped.items()), "none in the file")
            raise CommonRoadError(f"{source}: no usable obstacle ({len(dropped)} dropped: {some})")
        tracks = _stack(rows)
    tracks.notes["dropped_tracks"] = dropped
    return tracks


def _states(obs: Any, static: bool) -> tuple[list[Any], str | None]:
    """The logged states of an obstacle, or why it cannot be used."""
    states = [obs.initial_state]
    pred = None if static else obs.prediction
    if pred is not None:
        traj = getattr(pred, "trajectory", None)
        if traj is None:
            return [], f"{type(pred).__name__}: a prediction, not a logged trajectory"
        states += list(traj.state_list)
    for s in states:
        if not isinstance(s.time_step, int | np.integer) or s.time_step < 0:
            return [], f"a state at time {s.time_step!r}, not a step >= 0"
        if np.shape(getattr(s, "position", None)) != (2,):
            return [], "a state without a point position"
        if getattr(s, "orientation", None) is None:
            return [], "a state without orientation"
    return states, None


def _extent(shape: Any) -> tuple[float, float] | None:
    """(length, width) m of an obstacle shape; circles and polygons by their bounding box."""
    if hasattr(shape, "length") and hasattr(shape, "width"):
        return float(shape.length), float(shape.width)
    if hasattr(shape, "radius"):
        return 2.0 * float(shape.radius), 2.0 * float(shape.radius)
    vertices = getattr(shape, "vertices", None)
    if vertices is not None and np.ndim(vertices) == 2 and len(vertices) >= 3:
        size = np.ptp(np.asarray(vertices, dtype=np.float64)[:, :2], axis=0)
        return float(size[0]), float(size[1])
    return None


def _float(value: Any) -> float:
    return np.nan if value is None else float(value)


def _stack(rows: list[tuple]) -> Tracks:
    """Put each obstacle's states on the [N, T] grid; derive missing speeds from positions."""
    n, num_steps = len(rows), max(s.time_step for r in rows for s in r[2]) + 1
    pos, yaw = np.zeros((n, num_steps, 2)), np.zeros((n, num_steps))
    speed, valid = np.zeros((n, num_steps)), np.zeros((n, num_steps), dtype=bool)
    derived = []
    for i, (obs, static, states, _) in enumerate(rows):
        t = np.array([s.time_step for s in states])
        pos[i, t] = [np.asarray(s.position, dtype=np.float64) for s in states]
        yaw[i, t] = [float(s.orientation) for s in states]
        speed[i, t] = 0.0 if static else [_float(getattr(s, "velocity", None)) for s in states]
        valid[i, t] = True
        if static:  # it stands there for the whole log
            pos[i], yaw[i], valid[i] = pos[i, t[0]], yaw[i, t[0]], True
        if np.isnan(speed[i]).any():  # all of it: newer versions fill a missing first one with 0
            speed[i] = _derived_speed(pos[i], yaw[i], valid[i])
            derived.append(str(obs.obstacle_id))
        # The state's point sits origin_x_shift ahead of the box centre (newer commonroad-io).
        shift = float(getattr(obs.obstacle_shape, "origin_x_shift", 0.0) or 0.0)
        pos[i] -= shift * np.stack([np.cos(yaw[i]), np.sin(yaw[i])], -1)
    # A corrupt position (a jump no road user makes) costs its track's steps, not the file.
    valid, repaired = drop_impossible_jumps(pos, valid, DEFAULT_DT)
    ids = [str(r[0].obstacle_id) for r in rows]
    return Tracks(
        ids=ids,
        # Static obstacles are "other": the world model drives vehicles and must not move them.
        types=["other" if r[1] else AGENT_TYPE.get(_kind(r[0]), "other") for r in rows],
        positions=np.where(valid[..., None], pos, 0.0),
        yaws=wrap_angle(np.where(valid, yaw, 0.0)),
        speeds=np.where(valid, speed, 0.0),
        valid=valid,
        extents=np.array([r[3] for r in rows], dtype=np.float64),
        notes={"repairs": _repairs(derived, {ids[r]: k for r, k in repaired.items()})},
    )


def _repairs(derived: list[str], jumped: dict[str, int]) -> dict[str, list[str]]:
    """Track id -> what was repaired, worded as the ScenarioNet importer words it."""
    out: dict[str, list[str]] = {k: ["speed derived from positions (no velocity)"] for k in derived}
    for k, n in jumped.items():
        out.setdefault(k, []).append(f"{n} steps after an impossible jump made invalid")
    return out


def _kind(obs: Any) -> str:
    return str(getattr(obs.obstacle_type, "value", obs.obstacle_type))


def _derived_speed(pos: np.ndarray, yaw: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``[T]`` m/s from ``[T, 2]`` m positions: the mean of the backward and forward
    differences that exist (both ends valid), signed by the heading; 0 with neither."""
    ok = valid[1:] & valid[:-1]
    diff = np.where(ok[:, None], np.diff(pos, axis=0) / DEFAULT_DT, 0.0)  # [T-1, 2]
    pad = np.zeros((1, 2))
    vel = np.concatenate([pad, diff]) + np.concatenate([diff, pad])
    vel /= np.maximum(np.concatenate([[0], ok]) + np.concatenate([ok, [0]]), 1)[:, None]
    sign = np.where(vel[:, 0] * np.cos(yaw) + vel[:, 1] * np.sin(yaw) < 0, -1.0, 1.0)
    return sign * np.linalg.norm(vel, axis=1)
