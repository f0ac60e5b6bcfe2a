"""Exact, fast lane lookups on imported maps: the closest lane and the Frenet projection.

A real log's map (nuScenes, Waymo, CommonRoad) becomes hundreds of highway-env
``PolyLaneFixedWidth`` lanes (``scene/road.py``). highway-env then spends most of a real-log
episode in two searches written as Python loops (docs/performance.md, "Real maps"):

- ``RoadNetwork.get_closest_lane_index`` computes ``distance_with_heading`` to every lane of
  the network, after every step of every vehicle;
- ``LinearSpline2D.cartesian_to_frenet`` (every lane distance, every neighbour search) walks
  the lane's 1 m samples backwards until the point lies ahead of one, and
  ``_get_idx_segment_for_lon`` (every lane heading) scans all samples with ``np.argwhere``.

The classes here give **the same results, bit for bit**, with array operations:

- :class:`PolylineSpline`: the sample the walk would stop at is found with one vectorised
  projection; the coordinates are then computed by highway-env's own code on that sample.
  Where a projection lies within ``TOL`` of zero (rounding could make the two disagree about
  it) the walk itself runs.
- :class:`IndexedRoadNetwork`: a lower bound of every polyline lane's distance, all lanes in
  one array operation (the same walk, vectorised, over every candidate sample the rounding
  allows), then the exact distance on the lanes whose bound does not exceed the best exact
  distance found; ties go to the first lane in network order, as ``np.argmin`` does.
"""

from __future__ import annotations

import bisect

import numpy as np
from highway_env.road.lane import PolyLaneFixedWidth
from highway_env.road.road import LaneIndex, RoadNetwork
from highway_env.road.spline import LinearSpline2D

#: Projections [m] this close to zero are treated as either sign (floating-point rounding of
#: the vectorised and the scalar arithmetic differs by about 1e-12 m at map coordinates).
TOL = 1e-6


class PolylineSpline(LinearSpline2D):
    """highway-env's ``LinearSpline2D`` with the same Frenet projection and segment lookup,
    vectorised (module docstring). Build with :meth:`of`."""

    @classmethod
    def of(cls, spline: LinearSpline2D) -> PolylineSpline:
        """The same curve (its attributes shared, nothing recomputed), with the sample arrays
        the fast paths read: positions, tangents and normals ``[n, 2]``, sample positions
        ``[n]`` m."""
        fast = cls.__new__(cls)
        fast.__dict__.update(spline.__dict__)
        fast._arrays()
        return fast

    def _arrays(self) -> None:
        self.origins = np.array([pose.position for pose in self.poses], dtype=float)
        self.tangents = np.array([pose.normal for pose in self.poses], dtype=float)
        self.normals = np.array([pose.orthonormal for pose in self.poses], dtype=float)
        self.sample_list = [float(s) for s in self.s_samples]

    def stop_index(self, position: np.ndarray) -> int | None:
        """The sample ``cartesian_to_frenet`` stops at: the last one from index 1 on with the
        point at or ahead of it (projection >= 0), else 0; None where rounding could decide."""
        (ox, oy), (tx, ty) = self.origins.T, self.tangents.T
        p = (float(position[0]) - ox) * tx + (float(position[1]) - oy) * ty  # [n] m
        ahead = p >= TOL
        ahead[0] = False  # sample 0 is the fallback whatever its sign
        k = len(p) - 1 - int(ahead[::-1].argmax())
        last = k if ahead[k] else 0
        # A later sample whose projection rounding could make >= 0 might be the stop instead.
        if last + 1 < len(p) and np.abs(p[last + 1 :]).min() < TOL:
            return None
        return last

    def cartesian_to_frenet(self, position) -> tuple[float, float]:
        """highway-env's projection (longitudinal, lateral) [m], from the sample it stops at."""
        i = self.stop_index(position)
        if i is None or len(self.poses) == 1:
            return super().cartesian_to_frenet(position)
        pose = self.poses[i]
        projection = pose.project_onto_normal(position)
        lon = projection if i == 0 else self.s_samples[i] + projection
        return lon, pose.project_onto_orthonormal(position)

    def _get_idx_segment_for_lon(self, lon: float) -> int:
        # The first sample past ``lon`` (np.argwhere(lon < s)[0]) is bisect_right's insertion
        # point: pure comparisons, so the same index, NaN included (no sample compares).
        first = bisect.bisect_right(self.sample_list, lon)
        if first == len(self.sample_list):
            return len(self.sample_list) - 1
        return max(first - 1, 0)


def fast_poly_lane(lane: PolyLaneFixedWidth) -> PolyLaneFixedWidth:
    """``lane`` with its curve made a :class:`PolylineSpline` (same class, same geometry)."""
    if not isinstance(lane.curve, PolylineSpline):
        lane.curve = PolylineSpline.of(lane.curve)
    return lane


class _PoseTable:
    """Every polyline lane's samples, concatenated in network order (``IndexedRoadNetwork``)."""

    def __init__(self, network: RoadNetwork) -> None:
        self.indexes: list[LaneIndex] = []
        self.lanes: list = []
        poly: list[int] = []  # positions in ``lanes`` of the polyline lanes
        for start, to_dict in network.graph.items():
            for end, lanes in to_dict.items():
                for k, lane in enumerate(lanes):
                    if isinstance(lane, PolyLaneFixedWidth) and isinstance(
                        lane.curve, PolylineSpline
                    ):
                        poly.append(len(self.lanes))
                    self.indexes.append((start, end, k))
                    self.lanes.append(lane)
        self.size = len(self.lanes)
        self.poly = np.array(poly, dtype=int)
        curves = [self.lanes[i].curve for i in poly]
        counts = np.array([len(c.poses) for c in curves], dtype=int)
        self.starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
        if not curves:
            return
        self.owner = np.repeat(np.arange(len(curves)), counts)  # [P] lane of each sample
        self.local = np.arange(counts.sum()) - np.repeat(self.starts, counts)  # [P] its index
        self.origins = np.concatenate([c.origins for c in curves])  # [P, 2] m
        self.tangents = np.concatenate([c.tangents for c in curves])  # [P, 2]
        self.normals = np.concatenate([c.normals for c in curves])  # [P, 2]
        self.s = np.concatenate([c.s_samples for c in curves]).astype(float)  # [P] m
        self.length = np.repeat([self.lanes[i].length for i in poly], counts).astype(float)

    def bounds(self, position: np.ndarray) -> np.ndarray:
        """``[L]`` lower bounds [m] of every lane's ``distance_with_heading`` from
        ``position`` (the heading term, >= 0, left out); 0 for a lane that is no polyline."""
        out = np.zeros(self.size)
        if not len(self.poly):
            return out
        d = position - self.origins
        p = d[:, 0] * self.tangents[:, 0] + d[:, 1] * self.tangents[:, 1]  # [P] m
        r = d[:, 0] * self.normals[:, 0] + d[:, 1] * self.normals[:, 1]  # [P] m
        # Where cartesian_to_frenet can stop: from sample 1 on, at or past the last sample
        # surely ahead (p >= TOL) and not surely behind; sample 0 if none is surely ahead.
        surely_ahead = np.where((p >= TOL) & (self.local >= 1), self.local, 0)
        last = np.maximum.reduceat(surely_ahead, self.starts)[self.owner]
        may_stop = ((self.local >= 1) & (self.local >= last) & (p > -TOL)) | (
            (self.local == 0) & (last == 0)
        )
        lon = self.s + p
        dist = np.abs(r) + np.maximum(lon - self.length, 0.0) + np.maximum(-lon, 0.0)
        low = np.minimum.reduceat(np.where(may_stop, dist, np.inf), self.starts)
        out[self.poly] = low - TOL
        return out


class IndexedRoadNetwork(RoadNetwork):
    """highway-env's ``RoadNetwork`` whose ``get_closest_lane_index`` prunes polyline lanes
    by a lower bound first (module docstring); the same index as highway-env's search.
    Lanes are added with ``add_lane`` (as highway-env does), not by editing ``graph``."""

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_table"}

    def add_lane(self, _from: str, _to: str, lane) -> None:
        """highway-env's ``add_lane``; the lane table is rebuilt at the next search."""
        super().add_lane(_from, _to, lane)
        self.__dict__.pop("_table", None)

    def _pose_table(self) -> _PoseTable:
        table = self.__dict__.get("_table")
        if table is None:
            table = self._table = _PoseTable(self)
        return table

    def get_closest_lane_index(
        self, position: np.ndarray, heading: float | None = None
    ) -> LaneIndex:
        point = np.asarray(position, dtype=float)
        table = self._pose_table()
        bad_heading = heading is not None and not np.isfinite(heading)
        if not len(table.poly) or not np.all(np.isfinite(point)) or bad_heading:
            return super().get_closest_lane_index(position, heading)
        bounds = table.bounds(point)
        best, exact = np.inf, {}
        for k in np.argsort(bounds, kind="stable"):
            if bounds[k] > best:
                break
            exact[k] = table.lanes[k].distance_with_heading(position, heading)
            if np.isnan(exact[k]):  # highway-env's argmin would return the first NaN
                return super().get_closest_lane_index(position, heading)
            best = min(best, exact[k])
        return table.indexes[min(k for k, d in exact.items() if d == best)]
