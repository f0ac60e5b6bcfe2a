"""The road a scene drives on: a highway-env ``RoadNetwork`` plus what the rest of us need from it.

Roads are (docs/design.md, "highway-env is the substrate") highway-env networks (its Straight/Sine/Circular lanes for generated
scenarios, ``PolyLaneFixedWidth`` lanes built from centre lines for imported maps), so that the
ego can be driven and observed through highway-env. From a network we derive the two views the
metrics and the world model read: lane centre polylines (``[P, 2]`` m, about 1 m apart) and a
drivable area (a shapely geometry, the union of the lane surfaces).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from highway_env.road.lane import (
    AbstractLane,
    SineLane,
    StraightLane,
)
from highway_env.road.road import RoadNetwork

from counterscene_env.geometry import arc_length, points_in_area
from counterscene_env.scene.lane_search import IndexedRoadNetwork
from counterscene_env.scene.road_json import network_from_json, network_to_json, poly_lane

#: Spacing of the sampled centre lines and lane-surface outlines, m.
SAMPLE_SPACING = 1.0

#: Radius of the morphological closing (grow, then shrink) applied to the union of lane
#: surfaces of a generated road, m. highway-env lanes meet at junctions with wedge-shaped gaps
#: (roundabout ring to entries and exits, turn lanes at the intersection) that its vehicles
#: legally drive across; the closing paves gaps narrower than twice this and rounds concave
#: corners like a kerb radius, but leaves straight road edges where they are.
JUNCTION_FILL = 4.0

#: Shortest lane highway-env's ``PolyLaneFixedWidth`` spline accepts, m.
MIN_LANE_LENGTH = 1.0


@dataclass(eq=False)
class RoadMap:
    """A road network with its centre lines and drivable area.

    Attributes:
        network: the highway-env ``RoadNetwork`` (lanes the ego's vehicle model follows).
        drivable_area: shapely (Multi)Polygon, m, world frame.
        lane_centerlines: list of ``[P, 2]`` float64 arrays, m, in driving direction.
        lane_widths: ``[L]`` float64, m, one per centre line.
        extent: shapely (Multi)Polygon, m: the region the map describes (a real map is a crop
            of a city; beyond it nothing is known, road or not). None: the whole plane.
        lane_priorities: ``[L]`` float64, the right of way of each centre line's lane
            (highway-env's lane ``priority``: at a crossing the lower one gives way; its
            intersection has 0-3). 0 where the map gives none (imported maps). None: read
            from the network's lanes (:func:`priorities_from_network`).
    """

    network: RoadNetwork
    drivable_area: shapely.Geometry
    lane_centerlines: list[np.ndarray]
    lane_widths: np.ndarray
    extent: shapely.Geometry | None = None
    lane_priorities: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.lane_centerlines = [np.asarray(c, dtype=np.float64) for c in self.lane_centerlines]
        self.lane_widths = np.asarray(self.lane_widths, dtype=np.float64).reshape(-1)
        if len(self.lane_centerlines) != len(self.lane_widths):
            raise ValueError(
                f"{len(self.lane_centerlines)} centre lines but {len(self.lane_widths)} widths"
            )
        for i, c in enumerate(self.lane_centerlines):
            if c.ndim != 2 or c.shape[1] != 2 or len(c) < 2:
                raise ValueError(f"lane centre line {i} must be [P>=2, 2], got {c.shape}")
            if not np.isfinite(c).all():
                raise ValueError(f"lane centre line {i} has non-finite coordinates (NaN or inf)")
        bad = ~(np.isfinite(self.lane_widths) & (self.lane_widths > 0))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"lane width {i} must be finite and > 0 m, got {self.lane_widths[i]}")
        self._set_priorities()
        if not isinstance(self.drivable_area, shapely.Polygon | shapely.MultiPolygon):
            raise ValueError(
                "drivable_area must be a shapely Polygon or MultiPolygon, got "
                f"{type(self.drivable_area).__name__}"
            )
        if self.extent is not None and not isinstance(
            self.extent, shapely.Polygon | shapely.MultiPolygon
        ):
            raise ValueError(f"extent must be a shapely Polygon or None, got {type(self.extent)}")
        # Point-in-area queries are the hot path of ORR: prepare the geometry once.
        shapely.prepare(self.drivable_area)
        if self.extent is not None:
            shapely.prepare(self.extent)

    def _set_priorities(self) -> None:
        """Check ``lane_priorities``, or read them from the network where None."""
        if self.lane_priorities is None:
            self.lane_priorities = priorities_from_network(self.network, self.lane_centerlines)
        self.lane_priorities = np.asarray(self.lane_priorities, dtype=np.float64).reshape(-1)
        if len(self.lane_priorities) != len(self.lane_widths):
            raise ValueError(
                f"{len(self.lane_centerlines)} centre lines but "
                f"{len(self.lane_priorities)} lane priorities"
            )
        if not np.isfinite(self.lane_priorities).all():
            raise ValueError("lane_priorities must be finite")

    def __getstate__(self) -> dict:
        # highway-env's spline lanes (PolyLane*) hold closures, which do not pickle: a map
        # crosses to another process (``stress --workers``) as its serialised network, rebuilt
        # lane for lane from the same source points (network_to_json).
        return {**self.__dict__, "network": network_to_json(self.network)}

    def __setstate__(self, state: dict) -> None:
        # A map pickled before ``lane_priorities`` existed reads them from its network.
        self.__dict__.update(
            {"lane_priorities": None, **state, "network": network_from_json(state["network"])}
        )
        self._set_priorities()
        shapely.prepare(self.drivable_area)
        if self.extent is not None:
            shapely.prepare(self.extent)

    def off_road(self, points: np.ndarray, judged: np.ndarray | None = None) -> np.ndarray:
        """Whether points are off the road: outside the drivable area, inside the map's extent.

        The one definition of "off-road" (ORR, the step info, road keeping): a point beyond the
        map's crop is not judged (docs/scenes.md, "Real maps").

        Args:
            points: ``[..., 2]`` m, world frame.
            judged: ``[...]`` bool, :meth:`judged` of the same points where a caller has it
                already (an off-road rate needs both); None: computed here.

        Returns:
            ``[...]`` bool; False for non-finite points.
        """
        points = np.asarray(points, dtype=np.float64)
        if judged is None:
            judged = self.judged(points)
        return ~points_in_area(self.drivable_area, points) & judged

    def judged(self, points: np.ndarray) -> np.ndarray:
        """Whether :meth:`off_road` can judge points: finite and inside the map's extent (a
        real map is a crop; beyond it the map says nothing). An off-road *rate* counts only
        judged points, on top of the line and under it.

        Args:
            points: ``[..., 2]`` m, world frame.

        Returns:
            ``[...]`` bool.
        """
        points = np.asarray(points, dtype=np.float64)
        ok = np.isfinite(points).all(-1)
        if self.extent is not None:
            ok &= points_in_area(self.extent, points)
        return ok

    @classmethod
    def from_network(
        cls,
        network: RoadNetwork,
        bounds: tuple[float, float, float, float] | None = None,
    ) -> RoadMap:
        """Derive centre lines and drivable area from a highway-env network.

        Args:
            network: any highway-env network (all lane classes that implement ``position``).
            bounds: optional ``(xmin, ymin, xmax, ymax)`` m; centre lines and area are clipped
                to it (highway-env's straight highway lanes are kilometres long).
        """
        box = None if bounds is None else shapely.box(*bounds)
        centerlines, widths, priorities, surfaces = [], [], [], []
        for lane in network.lanes_list():
            s = _lane_samples(lane)
            width = float(lane.width_at(0.0))
            center = np.array([lane.position(si, 0.0) for si in s])
            left = np.array([lane.position(si, lane.width_at(si) / 2) for si in s])
            right = np.array([lane.position(si, -lane.width_at(si) / 2) for si in s])
            surface = shapely.make_valid(shapely.Polygon(np.concatenate([left, right[::-1]])))
            if box is not None:
                surface = surface.intersection(box)
            if not surface.is_empty:
                surfaces.append(surface)
            for piece in _clip_polyline(center, box):
                centerlines.append(piece)
                widths.append(width)
                priorities.append(float(getattr(lane, "priority", 0)))
        area = shapely.union_all(surfaces) if surfaces else shapely.Polygon()
        # Closing (grow then shrink) paves junction gaps, keeps the outer road edge in place.
        area = area.buffer(JUNCTION_FILL).buffer(-JUNCTION_FILL)
        if box is not None:
            area = area.intersection(box)
        return cls(network, area, centerlines, np.array(widths), None, np.array(priorities))

    @classmethod
    def from_centerlines(
        cls,
        centerlines: Sequence[np.ndarray],
        widths: Sequence[float],
        polygons: Sequence[np.ndarray | None] | None = None,
        successors: Sequence[Sequence[int]] | None = None,
        extra_area: shapely.Geometry | None = None,
    ) -> RoadMap:
        """Build a map from lane centre lines (real logs).

        Each centre line becomes a ``PolyLaneFixedWidth`` lane of the network. Lanes are joined
        where ``successors[i]`` lists the lanes that continue lane i (the end node of lane i is
        the start node of each successor), so highway-env's route planning works across them.

        Args:
            centerlines: ``[P_i, 2]`` m arrays in driving direction.
            widths: lane widths, m.
            polygons: optional lane surface outlines ``[Q_i, 2]`` m; where absent the surface is
                the centre line buffered by half its width.
            successors: optional lane indices that continue each lane.
            extra_area: optional further drivable surface (e.g. intersections) to union in.
        """
        n = len(centerlines)
        polygons = polygons if polygons is not None else [None] * n
        successors = successors if successors is not None else [[] for _ in range(n)]
        if not (len(widths) == len(polygons) == len(successors) == n):
            raise ValueError("centerlines, widths, polygons and successors must align")
        lines = [_dedupe(np.asarray(line, dtype=np.float64)[:, :2]) for line in centerlines]
        # highway-env's spline needs a lane of at least 1 m; shorter ones (map crops, stubs)
        # keep their surface in the drivable area but are not lanes of the network. They are
        # dropped before nodes are named, so no link runs through them.
        usable = [arc_length(line)[-1] >= MIN_LANE_LENGTH for line in lines]
        links = [
            [j for j in succ if 0 <= j < n and usable[j]] if usable[i] else []
            for i, succ in enumerate(successors)
        ]
        start, end = _lane_nodes(n, links)
        network = IndexedRoadNetwork()
        kept_lines, kept_widths, surfaces = [], [], []
        for i, (line, width, poly) in enumerate(zip(lines, widths, polygons, strict=True)):
            if poly is not None and len(poly) >= 3:
                surfaces.append(shapely.make_valid(shapely.Polygon(np.asarray(poly)[:, :2])))
            elif len(line) >= 2:
                surfaces.append(shapely.LineString(line).buffer(width / 2, cap_style="flat"))
            if not usable[i]:
                continue
            network.add_lane(start[i], end[i], poly_lane(line, float(width)))
            kept_lines.append(line)
            kept_widths.append(float(width))
        if extra_area is not None:
            surfaces.append(extra_area)
        area = shapely.union_all(surfaces).buffer(0.01) if surfaces else shapely.Polygon()
        return cls(
            network, area, kept_lines, np.array(kept_widths), None, np.zeros(len(kept_lines))
        )


# ---------------------------------------------------------------------- helpers
def fill_small_holes(area: shapely.Geometry, max_hole: float) -> shapely.Geometry:
    """``area`` with every interior ring enclosing less than ``max_hole`` m^2 filled (slivers
    between lane surfaces that traffic crosses); an area with no polygon comes back empty."""
    parts = []
    for poly in getattr(area, "geoms", [area]):
        if poly.geom_type != "Polygon" or poly.is_empty:
            continue
        holes = [r for r in poly.interiors if shapely.Polygon(r).area >= max_hole]
        parts.append(shapely.Polygon(poly.exterior, holes))
    return shapely.union_all(parts) if parts else shapely.Polygon()


def priorities_from_network(network: RoadNetwork, centerlines: Sequence[np.ndarray]) -> np.ndarray:
    """``[L]`` the priority of the network lane each centre line was drawn from.

    For maps stored before ``RoadMap.lane_priorities`` existed. Each line goes to the lane
    whose sampled centre passes nearest its points on average (lines are drawn from their
    lane's samples, :meth:`RoadMap.from_network`, so the right lane is at about 0 m; lanes
    that share a start, such as an intersection's turns, part within a few metres). A
    network whose lanes are all of priority 0 (every imported map) gives zeros at once.
    """
    lanes = network.lanes_list()
    priority = np.array([float(getattr(lane, "priority", 0)) for lane in lanes])
    if not priority.any():
        return np.zeros(len(centerlines))
    samples = [
        np.array([lane.position(s, 0.0) for s in np.linspace(0.0, lane.length, 50)])
        for lane in lanes
    ]
    out = np.zeros(len(centerlines))
    for i, line in enumerate(centerlines):
        points = line[:: max(1, len(line) // 10)]
        cost = [
            np.linalg.norm(points[:, None] - s[None], axis=-1).min(axis=1).mean() for s in samples
        ]
        out[i] = priority[int(np.argmin(cost))]
    return out


def _lane_samples(lane: AbstractLane) -> np.ndarray:
    """Longitudinal sample positions along a lane, m: both ends, about SAMPLE_SPACING apart."""
    if isinstance(lane, StraightLane) and not isinstance(lane, SineLane):
        return np.array([0.0, lane.length])  # straight: the ends say everything
    n = max(2, int(np.ceil(lane.length / SAMPLE_SPACING)) + 1)
    return np.linspace(0.0, lane.length, n)


def _clip_polyline(points: np.ndarray, box: shapely.Geometry | None) -> list[np.ndarray]:
    """Clip a polyline to a box and resample each piece at about SAMPLE_SPACING."""
    line = shapely.LineString(points)
    if box is not None:
        line = line.intersection(box)
    pieces = list(getattr(line, "geoms", [line]))
    out = []
    for piece in pieces:
        if piece.is_empty or piece.geom_type != "LineString" or piece.length < 1e-6:
            continue
        n = max(2, int(np.ceil(piece.length / SAMPLE_SPACING)) + 1)
        pts = shapely.line_interpolate_point(piece, np.linspace(0.0, piece.length, n))
        out.append(shapely.get_coordinates(pts))
    return out


def _dedupe(points: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicate points (highway-env's spline divides by segment length)."""
    if len(points) < 2:
        return points
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-6])
    return points[keep]


def _lane_nodes(n: int, successors: Sequence[Sequence[int]]) -> tuple[list[str], list[str]]:
    """Node names so that lane i ends where each of its successors starts (union-find)."""
    parent = list(range(2 * n))  # node 2i: start of lane i, 2i+1: end of lane i

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, succ in enumerate(successors):
        for j in succ:
            if 0 <= j < n:
                parent[find(2 * i + 1)] = find(2 * j)
    start = [f"n{find(2 * i)}" for i in range(n)]
    end = [f"n{find(2 * i + 1)}" for i in range(n)]
    return start, end
