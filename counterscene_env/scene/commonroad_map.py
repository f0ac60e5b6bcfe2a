"""The road of a CommonRoad scenario: its lanelets as a :class:`RoadMap`.

One job: lanelets -> lanes, links and drivable area. Each lanelet's centre vertices (driving
direction) become a lane of :meth:`RoadMap.from_centerlines`, its width the median distance
between its left and right vertices, its surface the left vertices + reversed right vertices,
its successors ``lanelet.successor``. Drivable area: the union of the surfaces each grown by
:data:`AREA_BUFFER` (5 cm), with holes under :data:`SLIVER_AREA` filled. Neighbouring
lanelets meet only up to rounding: the plain union of an NGSIM map has 2-170 sliver holes
between lanes; grown, US-101 has none and the urban maps keep slivers of at most 0.13 m^2
(filled) beside their 1-45 m^2 junction islands (kept: logged vehicles cross only one of them,
two in all). A CommonRoad map is the whole road of its recording: its extent is the plane.

The lanelets are read duck-typed (``lanelet_id``, ``left_vertices``, ``right_vertices``,
``center_vertices``, ``successor``, ``adj_*_same_direction``), so this module needs no
``commonroad-io`` import.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import shapely

from counterscene_env.scene.core import SceneError
from counterscene_env.scene.road import RoadMap, fill_small_holes

AREA_BUFFER = 0.05  # [m] growth of each lanelet surface before the union (closes slivers)
SLIVER_AREA = 1.0  # [m^2] holes of the drivable area smaller than this are filled


class CommonRoadError(SceneError):
    """A CommonRoad file is malformed, unsupported or too short; the message names the file."""


def road_from_lanelets(lanelets: Iterable[Any], source: str) -> tuple[RoadMap, dict]:
    """Lanelets -> RoadMap (module docstring), and facts about them for the metadata.

    Raises:
        CommonRoadError: no lanelets, or a lanelet whose bounds do not pair up.
    """
    lanelets = sorted(lanelets, key=lambda ll: ll.lanelet_id)
    if not lanelets:
        raise CommonRoadError(f"{source}: no lanelets")
    index = {ll.lanelet_id: i for i, ll in enumerate(lanelets)}
    lines, widths, polys, succ, adjacent = [], [], [], [], 0
    for ll in lanelets:
        left = np.asarray(ll.left_vertices, dtype=np.float64)[:, :2]
        right = np.asarray(ll.right_vertices, dtype=np.float64)[:, :2]
        if left.shape != right.shape or len(left) < 2:
            raise CommonRoadError(
                f"{source}: lanelet {ll.lanelet_id} has left/right bounds of {len(left)} and "
                f"{len(right)} points (need the same number, at least 2)"
            )
        lines.append(np.asarray(ll.center_vertices, dtype=np.float64)[:, :2])
        widths.append(float(np.median(np.linalg.norm(left - right, axis=1))))
        polys.append(np.concatenate([left, right[::-1]]))
        succ.append([index[s] for s in ll.successor if s in index])
        adjacent += bool(ll.adj_left_same_direction) + bool(ll.adj_right_same_direction)
    road = RoadMap.from_centerlines(lines, widths, polygons=polys, successors=succ)
    area = shapely.union_all(
        [shapely.make_valid(shapely.Polygon(p)).buffer(AREA_BUFFER) for p in polys]
    )
    facts = {
        "num_lanelets": len(lanelets),
        "lanelets_without_successor": sum(1 for s in succ if not s),
        "adjacent_same_direction_links": int(adjacent),
    }
    area = fill_small_holes(area, SLIVER_AREA)
    road = RoadMap(
        road.network, area, road.lane_centerlines, road.lane_widths, None, road.lane_priorities
    )
    return road, facts
