"""The road of a ScenarioNet scenario: its ``map_features`` as a :class:`RoadMap`.

One job: turn the map features of a ScenarioNet file (nuScenes, Waymo, nuPlan, Argoverse 2,
Lyft, as ScenarioNet's converters write them) into lanes, their links and a drivable area.
docs/scenes.md ("Real maps") shows the area over the logs it was checked on.

Lanes
-----
Lanes are the ``LANE_*`` features except ``LANE_BIKE_LANE``. Each becomes a highway-env
``PolyLaneFixedWidth`` lane via :meth:`RoadMap.from_centerlines`. Width: the ``width`` field
where present and positive (an array is reduced to the median of its per-point total,
left + right), else the lane polygon's area over the centre-line length, else 3.5 m; the first
two are clipped to [2.5, 6] m. Connectivity: ``exit_lanes`` (and the reverse of
``entry_lanes``) where the file carries them; the nuScenes files carry neither, but their lanes
and lane connectors meet at bit-identical end points, so without those fields a lane's
successors are the lanes starting within :data:`CONNECT_TOLERANCE` of its end. A polyline with
fewer than two points has no direction and is not a lane.

Drivable area
-------------
The union of every surface the format marks as drivable:

1. Lane surfaces: the lane polygon where the file has one (nuScenes), else the centre line
   buffered by half the lane width (Waymo, nuScenes lane connectors).
2. Drivable-area outlines: ScenarioNet's nuScenes and nuPlan converters write the boundary
   rings of the map's drivable area (nuScenes ``drivable_area``; nuPlan road blocks and
   intersections) as closed ``ROAD_LINE_SOLID_SINGLE_WHITE`` polylines named ``boundary_*``;
   its Argoverse 2 converter writes the drivable areas' outlines as the same lines cut into
   20-point pieces. The pieces are merged end to end, and the area the closed rings enclose is
   filled even-odd (a ring inside a ring is an island). This adds the road beyond the lanes:
   kerbside, turn pockets, junction floors, the entries of car parks.
3. Road edges (Waymo ``ROAD_EDGE_BOUNDARY`` / ``ROAD_EDGE_MEDIAN``, and the ``BOUNDARY_LINE``
   of other converters): the paved strip between the outermost lane and the kerb, where cars
   pull over and pass parked ones. A road edge is an open polyline, so the strip is built per
   edge: the one-sided buffer of width :data:`EDGE_REACH` on the side where the lanes are
   (the side whose buffer overlaps the lane surfaces more; the format's own orientation is
   not relied on), clipped to the lane surfaces grown by the same reach. An edge with no lane
   within reach adds nothing.
4. ``DRIVEWAY`` polygons (Waymo) and any feature polygon of a type in :data:`SURFACE_TYPES`
   (intersections, car parks and drivable areas where a converter writes them).

The map's extent (:attr:`RoadMap.extent`) is the convex hull of every map feature point: a
ScenarioNet map is a crop around the log (the nuScenes crops end a few tens of metres from the
ego's path), and a car driving on beyond the crop is not off the road, it is off the map.

Interior holes smaller than :data:`HOLE_FILL_AREA` (50 m^2) are then filled: in the nuScenes
files the ~520 holes under 10 m^2 (and most up to ~40 m^2) are slivers between the lane
polygons and the buffered connectors inside junctions, which traffic crosses; larger holes are
medians, blocks and parking-lot islands, which stay off the area. Parking lots that a map does
not carry stay off the area: we never invent road from the log.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import shapely

from counterscene_env.scene.core import SceneError
from counterscene_env.scene.road import RoadMap, fill_small_holes

DEFAULT_LANE_WIDTH = 3.5  # [m] lanes with neither a width field nor a polygon
LANE_WIDTH_RANGE = (2.5, 6.0)  # [m] clip for widths read or estimated from the file
CONNECT_TOLERANCE = 0.1  # [m] end-to-start gap under which two lanes are joined
HOLE_FILL_AREA = 50.0  # [m^2] interior holes of the drivable area below this are filled
#: [m] how far from a road edge, on the lanes' side, the paved strip may reach.
EDGE_REACH = 6.0
#: A ring closes when its ends are this close, m.
RING_CLOSURE = 0.05
#: Road edges: open kerb lines between road and not-road.
EDGE_TYPES = ("ROAD_EDGE_BOUNDARY", "ROAD_EDGE_MEDIAN", "ROAD_EDGE_SIDEWALK", "BOUNDARY_LINE")
#: Feature types whose ``polygon`` (or closed ``polyline``) is itself drivable surface.
SURFACE_TYPES = ("DRIVEWAY", "INTERSECTION", "CARPARK_AREA", "DRIVABLE_AREA", "ROAD_SEGMENT")
#: Drivable-area outlines as ScenarioNet's converters write them (module docstring, item 2).
OUTLINE_TYPE = "ROAD_LINE_SOLID_SINGLE_WHITE"
OUTLINE_PREFIX = "boundary_"


class MapError(SceneError):
    """A map feature is malformed; the message names the feature and the field."""


@dataclass
class _Features:
    """The map features sorted by use (lists align per lane)."""

    keys: list[str] = field(default_factory=list)
    lines: list[np.ndarray] = field(default_factory=list)
    polygons: list[np.ndarray | None] = field(default_factory=list)
    widths: list[float] = field(default_factory=list)
    exits: list[list[str]] = field(default_factory=list)
    entries: list[list[str]] = field(default_factory=list)
    has_links: bool = False
    surfaces: list[shapely.Geometry] = field(default_factory=list)
    outlines: list[np.ndarray] = field(default_factory=list)
    edges: list[np.ndarray] = field(default_factory=list)
    extent_points: list[np.ndarray] = field(default_factory=list)


def road_from_features(features: Mapping[Any, Any], source: str) -> tuple[RoadMap, dict]:
    """Build the road of a ScenarioNet scenario (module docstring).

    Args:
        features: the file's ``map_features`` dict (id -> feature dict).
        source: the file name, for error messages.

    Returns:
        The road map and a summary ``{"lanes", "outline_rings", "road_edges", "surfaces"}``
        (counts).

    Raises:
        MapError: a feature of a used type has a malformed polyline or polygon.
    """
    feats = _sort_features(features, source)
    if feats.has_links:
        successors = _successors_from_links(feats.keys, feats.exits, feats.entries)
    else:
        successors = _successors_from_geometry(feats.lines)
    road = RoadMap.from_centerlines(
        feats.lines, feats.widths, polygons=feats.polygons, successors=successors
    )
    lanes = road.drivable_area
    parts = [lanes, *feats.surfaces]
    rings = _closed_rings(feats.outlines)
    if rings:
        parts.append(_even_odd_fill(rings))
    if feats.edges and not lanes.is_empty:
        parts.append(_kerb_strips(feats.edges, lanes, EDGE_REACH))
    area = fill_small_holes(shapely.union_all(parts), HOLE_FILL_AREA)
    points = np.concatenate([np.zeros((0, 2)), *feats.extent_points])
    extent = shapely.MultiPoint(points).convex_hull if len(points) >= 3 else None
    if extent is not None and extent.geom_type != "Polygon":
        extent = None  # collinear points describe no region
    summary = {
        "lanes": len(road.lane_centerlines),
        "outline_rings": len(rings),
        "road_edges": len(feats.edges),
        "surfaces": len(feats.surfaces),
    }
    road = RoadMap(
        road.network, area, road.lane_centerlines, road.lane_widths, extent, road.lane_priorities
    )
    return road, summary


def _sort_features(features: Mapping[Any, Any], source: str) -> _Features:
    """Read each feature the road uses into :class:`_Features`; skip the others. Every
    feature's points (any type) also mark the map's extent."""
    feats = _Features()
    for key, feat in features.items():
        if not isinstance(feat, Mapping):
            raise MapError(f"{source}: map_features[{key!r}] is not a dict")
        ftype = str(feat.get("type", ""))
        where = f"{source}: map_features[{key!r}]"
        line = _points(feat.get("polyline"), f"{where}.polyline", allow_none=True)
        poly = _points(feat.get("polygon"), f"{where}.polygon", allow_none=True)
        feats.extent_points += [p for p in (line, poly) if p is not None]
        if ftype.startswith("LANE") and ftype != "LANE_BIKE_LANE":
            if line is None:
                raise MapError(f"{where}.polyline: missing")
            _add_lane(feats, str(key), feat, line, poly, where)
        elif ftype in SURFACE_TYPES:
            ring = line if poly is None else poly
            if ring is not None and len(ring) >= 3:
                feats.surfaces.append(shapely.make_valid(shapely.Polygon(ring)))
        elif line is not None and len(line) >= 2:
            if ftype in EDGE_TYPES:
                feats.edges.append(line)
            elif ftype == OUTLINE_TYPE and str(key).startswith(OUTLINE_PREFIX):
                feats.outlines.append(line)
    return feats


def _add_lane(
    feats: _Features,
    key: str,
    feat: Mapping[str, Any],
    line: np.ndarray,
    poly: np.ndarray | None,
    where: str,
) -> None:
    """One lane: centre line ``[P, 2]`` m, optional polygon, width and links."""
    if len(line) < 2:
        return  # a single point has no direction: not a lane
    if poly is not None and len(poly) < 3:
        poly = None
    feats.keys.append(key)
    feats.lines.append(line)
    feats.polygons.append(poly)
    feats.widths.append(_lane_width(feat.get("width"), line, poly, f"{where}.width"))
    for field_name, store in (("exit_lanes", feats.exits), ("entry_lanes", feats.entries)):
        links = feat.get(field_name)
        feats.has_links |= links is not None
        store.append([] if links is None else [str(x) for x in np.asarray(links).reshape(-1)])


def _points(value: Any, where: str, allow_none: bool = False) -> np.ndarray | None:
    """A ``(P, 2|3)`` point list as ``[P, 2]`` float64 m (the third column, z, dropped).

    A single point may come as a flat ``(2|3,)`` array; points with a non-finite coordinate are
    dropped (a lane keeps its other points).
    """
    if value is None:
        if allow_none:
            return None
        raise MapError(f"{where}: missing")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MapError(f"{where}: not a numeric array ({exc})") from None
    if arr.ndim == 1 and arr.shape[0] in (2, 3):
        arr = arr[None]
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise MapError(f"{where}: expected shape (P, 2|3), got {arr.shape}")
    arr = arr[:, :2]
    return arr[np.isfinite(arr).all(axis=1)]


def _closed_rings(lines: list[np.ndarray]) -> list[np.ndarray]:
    """The closed rings ``[P, 2]`` m that ``lines`` form, pieces merged end to end."""
    rings, pieces = [], []
    for line in lines:
        closed = len(line) >= 4 and float(np.linalg.norm(line[0] - line[-1])) <= RING_CLOSURE
        (rings if closed else pieces).append(line)
    if pieces:
        merged = shapely.line_merge(shapely.MultiLineString(pieces))
        for part in getattr(merged, "geoms", [merged]):
            coords = shapely.get_coordinates(part)
            if len(coords) >= 4 and np.linalg.norm(coords[0] - coords[-1]) <= RING_CLOSURE:
                rings.append(coords)
    return rings


def _lane_width(value: Any, line: np.ndarray, poly: np.ndarray | None, where: str) -> float:
    """Lane width, m: the ``width`` field, else polygon area / centre-line length, else 3.5."""
    lo, hi = LANE_WIDTH_RANGE
    if value is not None:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise MapError(f"{where}: not numeric ({exc})") from None
        if arr.ndim == 2:  # per point (left, right) half widths
            arr = arr.sum(axis=1)
        arr = arr.reshape(-1)
        arr = arr[np.isfinite(arr)]
        if arr.size and float(np.median(arr)) > 0:
            return float(np.clip(np.median(arr), lo, hi))
    if poly is not None:
        length = float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())
        area = float(shapely.make_valid(shapely.Polygon(poly)).area)
        if length > 1e-6 and area > 0:
            return float(np.clip(area / length, lo, hi))
    return DEFAULT_LANE_WIDTH


def _successors_from_links(
    keys: list[str], exits: list[list[str]], entries: list[list[str]]
) -> list[list[int]]:
    """Successor lane indices from ``exit_lanes`` and (reversed) ``entry_lanes`` ids."""
    index = {k: i for i, k in enumerate(keys)}
    succ: list[set[int]] = [set() for _ in keys]
    for i, (ex, en) in enumerate(zip(exits, entries, strict=True)):
        for other in ex:
            j = index.get(other)
            if j is not None and j != i:
                succ[i].add(j)
        for other in en:
            j = index.get(other)
            if j is not None and j != i:
                succ[j].add(i)
    return [sorted(s) for s in succ]


def _successors_from_geometry(lines: list[np.ndarray]) -> list[list[int]]:
    """Lane j continues lane i where j starts within CONNECT_TOLERANCE of i's end."""
    if not lines:
        return []
    starts = shapely.points(np.array([line[0] for line in lines]))
    ends = shapely.points(np.array([line[-1] for line in lines]))
    tree = shapely.STRtree(starts)
    src, dst = tree.query(ends, predicate="dwithin", distance=CONNECT_TOLERANCE)
    succ: list[list[int]] = [[] for _ in lines]
    for i, j in zip(src.tolist(), dst.tolist(), strict=True):
        if i != j:
            succ[i].append(j)
    return [sorted(s) for s in succ]


def _even_odd_fill(rings: list[np.ndarray]) -> shapely.Geometry:
    """The area inside an odd number of the closed ``rings`` ([P, 2] m each)."""
    area = shapely.Polygon()
    for ring in rings:
        area = shapely.symmetric_difference(area, shapely.make_valid(shapely.Polygon(ring)))
    return area


def _kerb_strips(
    edges: list[np.ndarray], lanes: shapely.Geometry, reach: float
) -> shapely.Geometry:
    """The strips between each road edge and the lanes (module docstring, item 3)."""
    near = lanes.buffer(reach)
    shapely.prepare(near)
    strips = []
    for edge in edges:
        line = shapely.LineString(edge)
        if line.length < 1e-6 or not near.intersects(line):
            continue
        sides = [line.buffer(d, single_sided=True) for d in (reach, -reach)]
        overlap = [shapely.intersection(s, lanes).area for s in sides]
        if max(overlap) <= 0.0:
            continue
        strips.append(shapely.intersection(sides[int(np.argmax(overlap))], near))
    return shapely.union_all(strips) if strips else shapely.Polygon()
