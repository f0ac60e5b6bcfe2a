"""Giving way by gap acceptance: recorded intersection traffic that stops smoothly before a
crossing instead of pulsing its brakes.

highway-env's intersection (``RegulatedRoad``) decides twice a second who gives way: when two
cars, each driven on at constant speed, would meet within 3 s, the one with the lower lane
priority gets target speed 0, which its IDM turns into a brake at the 6 m/s^2 limit. A car
brought to a stop meets no one at constant speed, so half a second later it is released and
sets off again: giving way is a train of hard-brake pulses, decided at most 3 s before the
crossing (4.6 % of the agent-steps of the 400 generated intersection training scenes brake
harder than 3 m/s^2, ``counterscene inspect``'s ``hbr_all``; docs/scenes.md). Drivers judge the
gap instead: a car that is to give way slows early for the point where its path enters the
other car's and waits there until the gap is large enough.

:class:`GapAcceptanceRoad` decides five times a second, for every ordered pair of cars
``(a, b)``, whether ``a`` gives way to ``b``:

1. Both paths are laid out along the cars' routes, one point per metre: ``a``'s as far as it
   would drive in :data:`HORIZON` at ``max(speed, GO_SPEED)`` (a waiting car judges the gap at
   the speed it would cross at), ``b``'s as far as it drives in :data:`HORIZON` at its speed.
2. The conflict zone is where the paths come within :func:`clearance` of each other at an
   angle between 30 and 150 degrees (a crossing, not a car ahead in the lane, which IDM
   follows, nor an oncoming one in its own lane).
3. ``a`` gives way when ``b`` has the right of way (highway-env's ``respect_priorities``: the
   higher lane priority, else the car ahead) or is already in the zone, ``a`` is not yet in
   it, and their times in the zone come within :data:`GAP` of each other. ``a``'s time runs
   from its entry at its target speed to its exit at ``max(speed, GO_SPEED)`` (the widest
   its speed may make it); ``b``'s is at its own speed, and a ``b`` still in the zone where
   its path ends (at the horizon, or where it stands) stays in it.

A car that gives way gets a *stop distance*, the path length to the zone's entry less 1 m,
and brakes for it as IDM brakes for a stopped car ahead (:class:`GapAcceptingVehicle`).
"""

from __future__ import annotations

import numpy as np
from highway_env.road.regulation import RegulatedRoad

from counterscene_env.scene.highway_vehicle import ForwardIDMVehicle

#: How far ahead a give-way decision looks [s] (highway-env's rule: 3 s).
HORIZON = 6.0
#: The speed a slow or waiting car is assumed to cross at when it judges a gap [m/s].
GO_SPEED = 5.0
#: Least time between one car leaving the conflict zone and the other entering it [s].
GAP = 1.0
#: Path points are this far apart [m].
SPACING = 1.0
#: A give-way decision per this many seconds of simulation (highway-env's rule: 0.5 s).
DECISION_PERIOD = 0.2
#: A car giving way stops this far before the zone's entry [m].
STOP_MARGIN = 1.0
#: Jam distance of the braking for a stop point [m] (IDM's ``s0``).
STOP_GAP = 1.0
#: Below this speed a car outside the other's path is not coming [m/s].
STILL_SPEED = 0.5
#: Paths cross at an angle in this range [deg]; below, a car follows another; above, they pass.
CROSSING_ANGLES = (30.0, 150.0)


def clearance(a, b) -> float:
    """Centre distance [m] under which car ``a``'s path point conflicts with ``b``'s: half
    ``a``'s length plus half ``b``'s width, and 1 m (a crossing car's front reaches the other's
    side at ``(L_a + W_b) / 2``)."""
    return 0.5 * (a.LENGTH + b.WIDTH) + 1.0


class GapAcceptingVehicle(ForwardIDMVehicle):
    """A recorded car that brakes for its stop point as IDM brakes for a stopped car ahead.

    ``stop_distance`` [m] is set by :class:`GapAcceptanceRoad` at each decision (None: the car
    gives way to no one) and shortened by the distance driven in between.
    """

    stop_distance: float | None = None

    def acceleration(self, ego_vehicle, front_vehicle=None, rear_vehicle=None) -> float:
        """IDM's acceleration, and for this car no more than IDM's braking for a stopped car
        ``stop_distance`` ahead [m/s^2]: ``a_max (1 - (v/v0)^delta - (s*/s)^2)``, ``s* = s0 +
        v T + v^2 / (2 sqrt(a_max b))`` with ``s0`` = :data:`STOP_GAP` and the car's own
        ``T``, ``a_max`` and ``b``, ``v0`` its target speed (not capped at the lane's limit,
        as IDM's free-road term is)."""
        accel = super().acceleration(ego_vehicle, front_vehicle, rear_vehicle)
        if ego_vehicle is not self or self.stop_distance is None:
            return accel
        v = max(self.speed, 0.0)
        ab = self.COMFORT_ACC_MAX * -self.COMFORT_ACC_MIN
        s_star = STOP_GAP + v * self.TIME_WANTED + v * v / (2 * np.sqrt(ab))
        s = max(self.stop_distance, 0.1)
        v0 = max(self.target_speed, 1e-2)
        stop = self.COMFORT_ACC_MAX * (1 - (v / v0) ** self.DELTA - (s_star / s) ** 2)
        return min(accel, stop)

    def step(self, dt: float) -> None:
        before = self.speed
        super().step(dt)
        if self.stop_distance is not None:
            self.stop_distance -= 0.5 * (before + self.speed) * dt


class GapAcceptanceRoad(RegulatedRoad):
    """highway-env's regulated road whose give-way rule is a stop point chosen by gap
    acceptance (the module docstring). Only :class:`GapAcceptingVehicle` cars take part
    (the generator makes every recorded car one); others get no give-way rule."""

    REGULATION_FREQUENCY = round(1 / DECISION_PERIOD)

    def enforce_road_rules(self) -> None:
        cars = [v for v in self.vehicles if isinstance(v, GapAcceptingVehicle)]
        paths = [_path(v) for v in cars]
        for a, path_a in zip(cars, paths, strict=True):
            stops = [
                _stop_distance(a, b, path_a, path_b)
                for b, path_b in zip(cars, paths, strict=True)
                if b is not a
            ]
            a.stop_distance = min((d for d in stops if d is not None), default=None)


def _path(v) -> tuple[np.ndarray, np.ndarray, int]:
    """Car ``v``'s path along its route: points ``[K, 2]`` m one :data:`SPACING` apart from
    where it is, as far as ``max(speed, GO_SPEED)`` takes it in :data:`HORIZON`, their
    headings ``[K]`` rad, and how many of them its own speed reaches in :data:`HORIZON`."""
    s0 = v.lane.local_coordinates(v.position)[0]
    # The route from the current lane: highway-env drops a lane from the route when the car
    # targets the next one, so the route may start past the lane the car is still on.
    route = list(v.route or [])
    here = [k for k, lane in enumerate(route) if lane[:2] == v.lane_index[:2]]
    route = route[here[0] :] if here else [v.lane_index, *route]
    length = max(v.speed, GO_SPEED) * HORIZON
    arcs = np.arange(0.0, length + SPACING, SPACING)
    points, headings = zip(
        *(
            v.road.network.position_heading_along_route(route, s0 + s, 0, v.lane_index)
            for s in arcs
        ),
        strict=True,
    )
    reach = int(max(v.speed, 0.0) * HORIZON / SPACING) + 1
    return np.asarray(points, dtype=float), np.asarray(headings, dtype=float), reach


def _stop_distance(a, b, path_a, path_b) -> float | None:
    """How far car ``a`` may drive before it stops to give way to ``b`` [m], or None when it
    does not give way to it (the module docstring's steps 2 and 3)."""
    pa, ha, _ = path_a
    pb, hb, reach_b = path_b
    pb, hb = pb[:reach_b], hb[:reach_b]  # where b's own speed takes it
    r = clearance(a, b)
    if np.linalg.norm(pa[0] - pb[0]) > (len(pa) + len(pb)) * SPACING + r:
        return None
    dist = np.linalg.norm(pa[:, None] - pb[None], axis=-1)  # [Ka, Kb] m
    angle = np.degrees(np.abs((ha[:, None] - hb[None] + np.pi) % (2 * np.pi) - np.pi))
    lo, hi = CROSSING_ANGLES
    close = (dist < r) & (angle > lo) & (angle < hi)
    if not close.any():
        return None
    ka = np.flatnonzero(close.any(axis=1))  # a's points in the zone
    kb = np.flatnonzero(close.any(axis=0))  # b's points in the zone
    if ka[0] == 0:
        return None  # a is in the zone: it clears it rather than stop in it
    b_in_zone = kb[0] == 0
    if not b_in_zone and RegulatedRoad.respect_priorities(a, b) is not a:
        return None  # b gives way to a (respect_priorities names who gives way)
    # Times in the zone [s]. b at its speed; a b still in the zone where its path ends (at
    # the horizon, or where it stands) stays in it.
    if b.speed < STILL_SPEED:
        if not b_in_zone:
            return None  # b stands outside a's path: not coming
        t_b = (0.0, np.inf)
    else:
        out = np.inf if kb[-1] == reach_b - 1 else (kb[-1] + 1) * SPACING / b.speed
        t_b = (kb[0] * SPACING / b.speed, out)
    # a's window is the widest its speed may make it: it enters as if at its target speed
    # (a car that goes accelerates) and leaves as if at max(speed, GO_SPEED). Entering at
    # its current speed instead let a slowing car accept a gap, set off, and brake again.
    fast = max(a.speed, a.target_speed, GO_SPEED)
    slow = max(a.speed, GO_SPEED)
    t_a = (ka[0] * SPACING / fast, (ka[-1] + 1) * SPACING / slow)
    if t_b[0] < t_a[1] + GAP and t_a[0] < t_b[1] + GAP:
        return max(ka[0] * SPACING - STOP_MARGIN, 0.0)
    return None
