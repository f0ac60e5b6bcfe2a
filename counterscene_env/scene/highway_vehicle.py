"""The vehicle that drives recorded highway-env traffic: :class:`ForwardIDMVehicle`.

highway-env's IDM/MOBIL vehicle with two changes, neither of which alters what it does:

- its speed never goes below 0 (the stock class lets a car that brakes to a stop roll
  backwards, at up to -40 m/s); this one is a behaviour fix and is why the class exists;
- two of its per-frame searches are made cheaper with the same results (docs/performance.md,
  item 4 of the second fast-replans session; the lane search alone was 39 % of recording a
  scene):

  1. **The closest lane.** After every integration step highway-env computes
     ``distance_with_heading`` to every lane of the network (``RoadNetwork.
     get_closest_lane_index``). That distance is never below the point's Euclidean distance
     to the lane's centre line (``|lateral|`` plus the overshoot past either end bounds it
     from above) plus, for a straight lane, the heading difference; so a lane whose bounding
     box (plus heading difference) is farther than the vehicle's current lane cannot be the
     closest. The remaining lanes are searched with
     highway-env's own function in the network's order, so ties go as they always did.
  2. **Constant-speed predictions.** ``RegulatedRoad.enforce_road_rules`` predicts both
     vehicles of every pair along their routes, so each vehicle ``n - 1`` times per call
     with the same state; the prediction is kept until the vehicle's state changes.
"""

from __future__ import annotations

import weakref

import numpy as np
from highway_env.road.lane import CircularLane, SineLane, StraightLane
from highway_env.road.road import LaneIndex, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle


class ForwardIDMVehicle(IDMVehicle):
    """highway-env's IDM/MOBIL vehicle that never reverses.

    The stock vehicle's speed floor (``MIN_SPEED = -40`` m/s, enforced softly) lets a car that
    brakes to a stop roll backwards; we floor the speed at 0 after each integration step.
    """

    def step(self, dt: float) -> None:
        super().step(dt)
        self.speed = max(self.speed, 0.0)

    def on_state_update(self) -> None:
        """highway-env's update (closest lane, history), with the pruned lane search."""
        if self.road:
            self.lane_index = closest_lane_index(
                self.road.network, self.position, self.heading, self.lane_index
            )
            self.lane = self.road.network.get_lane(self.lane_index)
            if self.road.record_history:
                self.history.appendleft(self.create_from(self))

    def predict_trajectory_constant_speed(
        self, times: np.ndarray
    ) -> tuple[list[np.ndarray], list[float]]:
        """highway-env's prediction along the route, kept while the inputs stay the same."""
        key = (
            self.position.tobytes(),
            float(self.speed),
            self.lane_index,
            tuple(self.route or ()),
            np.asarray(times).tobytes(),
        )
        cached = getattr(self, "_prediction", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        prediction = super().predict_trajectory_constant_speed(times)
        self._prediction = (key, prediction)
        return prediction


class _LaneBoxes:
    """Every lane of a network in its order, with an axis-aligned box around its centre line
    (``[L, 4]``: x min, y min, x max, y max, m; -inf/inf for lane kinds we cannot bound)."""

    def __init__(self, network) -> None:
        self.indexes, self.lanes, boxes, headings = [], [], [], []
        for start, to_dict in network.graph.items():
            for end, lanes in to_dict.items():
                for k, lane in enumerate(lanes):
                    self.indexes.append((start, end, k))
                    self.lanes.append(lane)
                    boxes.append(_box(lane))
                    headings.append(_fixed_heading(lane))
        self.boxes = np.array(boxes, dtype=float).reshape(-1, 4)
        self.headings = np.array(headings, dtype=float)
        self.size = len(self.lanes)
        self.known = set(self.indexes)


def _box(lane) -> tuple[float, float, float, float]:
    """A box containing the lane's centre line (any box that contains it keeps the search
    exact; a looser one only prunes less)."""
    if isinstance(lane, StraightLane) and not isinstance(lane, SineLane):
        (x0, y0), (x1, y1) = lane.start, lane.end
        return min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)
    if isinstance(lane, CircularLane):
        # Points along the arc, and the box widened by the sagitta of one step between
        # them, which the arc between two points never leaves.
        n = 64
        phase = np.linspace(lane.start_phase, lane.end_phase, n + 1)
        (cx, cy), r = lane.center, lane.radius
        x, y = cx + r * np.cos(phase), cy + r * np.sin(phase)
        pad = r * (1 - np.cos(abs(lane.end_phase - lane.start_phase) / n / 2)) + 1e-6
        return x.min() - pad, y.min() - pad, x.max() + pad, y.max() + pad
    return -np.inf, -np.inf, np.inf, np.inf  # never pruned


def _fixed_heading(lane) -> float:
    """The heading of a straight lane [rad], which its ``distance_with_heading`` adds
    ``|wrap(heading - this)|`` for; NaN for a lane whose heading varies."""
    if isinstance(lane, StraightLane) and not isinstance(lane, SineLane):
        return float(lane.heading)
    return np.nan


#: Lane boxes per road network, built on first use; dropped with the network.
_BOXES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def closest_lane_index(
    network: RoadNetwork,
    position: np.ndarray,
    heading: float,
    current: LaneIndex | None,
) -> LaneIndex:
    """``network.get_closest_lane_index(position, heading)``, searching only the lanes that
    can beat ``current`` (the vehicle's lane index before this step; None: search all).

    ``position`` ``[2]`` m, ``heading`` rad. The lane boxes are built once per network and
    rebuilt when its lane count changes: a network is not edited otherwise once vehicles
    drive on it (highway-env builds it at reset)."""
    boxes = _BOXES.get(network)
    if boxes is None or boxes.size != _lane_count(network):  # new, or a lane was added
        boxes = _BOXES[network] = _LaneBoxes(network)
    if not isinstance(current, tuple) or current not in boxes.known:
        return network.get_closest_lane_index(position, heading)
    bound = network.get_lane(current).distance_with_heading(position, heading)
    b = boxes.boxes
    gap = np.hypot(
        np.maximum(np.maximum(b[:, 0] - position[0], position[0] - b[:, 2]), 0.0),
        np.maximum(np.maximum(b[:, 1] - position[1], position[1] - b[:, 3]), 0.0),
    )
    best, best_index = np.inf, None
    # A straight lane's heading term is known without its coordinates: it adds to the bound.
    turn = np.abs((heading - boxes.headings + np.pi) % (2 * np.pi) - np.pi)
    gap = gap + np.where(np.isnan(turn), 0.0, turn)
    # The slack keeps a lane that ties with the current one despite rounding in ``gap``.
    for k in np.flatnonzero(gap <= bound + 1e-9):  # in network order, as highway-env searches
        d = boxes.lanes[k].distance_with_heading(position, heading)
        if d < best:  # strict: the first of equal distances wins, as with np.argmin
            best, best_index = d, boxes.indexes[k]
    return best_index


def _lane_count(network) -> int:
    return sum(len(lanes) for to_dict in network.graph.values() for lanes in to_dict.values())
