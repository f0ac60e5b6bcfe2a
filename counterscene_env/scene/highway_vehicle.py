"""The vehicle that drives recorded highway-env traffic: :class:`ForwardIDMVehicle`.

highway-env's IDM/MOBIL vehicle with two changes, neither of which alters what it does:

- its speed never goes below 0 (the stock class lets a car that brakes to a stop roll
  backwards, at up to -40 m/s); this one is a behaviour fix and is why the class exists;
- two of its per-frame searches are made cheaper with the same results
  (docs/history/performance.md, item 4 of "What changed in the second fast-replans
  session"; the lane search alone was 39 % of recording a scene):

  1. **The closest lane.** After every integration step highway-env computes
     ``distance_with_heading`` to every lane of the network (``RoadNetwork.
     get_closest_lane_index``). That distance is never below the point's Euclidean distance
     to the lane's centre line (``|lateral|`` plus the overshoot past either end bounds it
     from above) plus, for a straight lane, the heading difference; so a lane whose bounding
     box (plus heading difference) is farther than the vehicle's current lane cannot be the
     closest. The remaining lanes are searched with
     highway-env's own function in the network's order, so ties go as they always did.
     During a recording the updates of a frame wait until every vehicle has moved
     (:func:`defer_lane_updates`), and the boxes' bounds for all of them are one array
     operation (:func:`update_lanes`).
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
        """highway-env's update (closest lane, history), with the pruned lane search; on a
        road that ``defer_lane_updates`` marks, put off to ``update_lanes``."""
        if self.road:
            pending = _PENDING.get(self.road)
            if pending is not None:
                pending.append(self)
                return
            self.lane_index = closest_lane_index(
                self.road.network, self.position, self.heading, self.lane_index
            )
            self._lane_updated()

    def _lane_updated(self) -> None:
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

#: Roads whose vehicles' lane updates wait for ``update_lanes`` (``defer_lane_updates``).
_PENDING: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def defer_lane_updates(road) -> None:
    """From now on, a :class:`ForwardIDMVehicle` on ``road`` that has moved leaves its lane
    update to :func:`update_lanes`, which does every vehicle's of a frame at once.

    ``Road.step`` moves every vehicle (each then updates its lane) and checks collisions,
    which read no lanes; nothing reads a lane until the next frame's ``Road.act``. So the
    updates may wait until all vehicles have moved, and the lane boxes' part of the search
    is then one array operation for the frame instead of one per vehicle (docs/performance.md).
    """
    _PENDING.setdefault(road, [])


def update_lanes(road) -> None:
    """The lane updates put off since the last call (:func:`defer_lane_updates`): each
    vehicle's ``closest_lane_index`` from the lane it was on, the same result as when it
    moved."""
    pending = _PENDING.get(road)
    if not pending:
        return
    network = road.network
    boxes = _lane_boxes(network)
    position = np.array([v.position for v in pending], dtype=float).reshape(-1, 2)
    heading = np.array([v.heading for v in pending], dtype=float)
    gaps = _box_gaps(boxes, position, heading)  # [V, L]
    for v, gap in zip(pending, gaps, strict=True):
        v.lane_index = _search(network, boxes, v.position, v.heading, v.lane_index, gap)
        v._lane_updated()
    pending.clear()


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
    boxes = _lane_boxes(network)
    gap = _box_gaps(boxes, np.asarray(position, dtype=float)[None], np.array([heading]))[0]
    return _search(network, boxes, position, heading, current, gap)


def _lane_boxes(network) -> _LaneBoxes:
    boxes = _BOXES.get(network)
    if boxes is None or boxes.size != _lane_count(network):  # new, or a lane was added
        boxes = _BOXES[network] = _LaneBoxes(network)
    return boxes


def _box_gaps(boxes: _LaneBoxes, position: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``[V, L]`` lower bounds [m + rad] of ``distance_with_heading`` from each of ``V``
    poses (``position [V, 2]`` m, ``heading [V]`` rad) to each lane: the distance to the
    lane's box, plus the heading difference for a straight lane."""
    b = boxes.boxes[None]  # [1, L, 4]
    x, y = position[:, 0, None], position[:, 1, None]  # [V, 1]
    gap = np.hypot(
        np.maximum(np.maximum(b[..., 0] - x, x - b[..., 2]), 0.0),
        np.maximum(np.maximum(b[..., 1] - y, y - b[..., 3]), 0.0),
    )
    # A straight lane's heading term is known without its coordinates: it adds to the bound.
    turn = np.abs((heading[:, None] - boxes.headings + np.pi) % (2 * np.pi) - np.pi)
    return gap + np.where(np.isnan(turn), 0.0, turn)


def _search(network, boxes: _LaneBoxes, position, heading, current, gap: np.ndarray) -> LaneIndex:
    """The closest lane, given every lane's lower bound ``gap [L]`` (``_box_gaps``)."""
    if not isinstance(current, tuple) or current not in boxes.known:
        return network.get_closest_lane_index(position, heading)
    bound = network.get_lane(current).distance_with_heading(position, heading)
    best, best_index = np.inf, None
    # The slack keeps a lane that ties with the current one despite rounding in ``gap``.
    for k in np.flatnonzero(gap <= bound + 1e-9):  # in network order, as highway-env searches
        d = boxes.lanes[k].distance_with_heading(position, heading)
        if d < best:  # strict: the first of equal distances wins, as with np.argmin
            best, best_index = d, boxes.indexes[k]
    return best_index


def _lane_count(network) -> int:
    return sum(len(lanes) for to_dict in network.graph.values() for lanes in to_dict.values())
