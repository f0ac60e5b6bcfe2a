"""A highway-env road network as JSON, and back: how a road crosses to a shard file or to
another process (``scene/shards.py``; ``RoadMap`` pickles through it, since highway-env's
spline lanes hold closures that do not pickle).
"""

from __future__ import annotations

import json

import numpy as np
from highway_env.road.lane import (
    AbstractLane,
    CircularLane,
    LineType,
    PolyLane,
    PolyLaneFixedWidth,
    SineLane,
    StraightLane,
)
from highway_env.road.road import RoadNetwork

from counterscene_env.scene.lane_search import IndexedRoadNetwork, fast_poly_lane

# Lane classes a serialised network may name. A name outside this table is refused: unlike
# highway-env's own ``lane_from_config`` we never import a class path read from a file.
_LANE_CLASSES: dict[str, type[AbstractLane]] = {
    cls.__name__: cls
    for cls in (StraightLane, SineLane, CircularLane, PolyLaneFixedWidth, PolyLane)
}


def network_to_json(network: RoadNetwork) -> str:
    """Serialise a network to JSON (lane class names and their constructor arguments)."""
    lanes = []
    for _from, to_dict in network.graph.items():
        for _to, lane_list in to_dict.items():
            for lane in lane_list:
                cfg = lane.to_config()["config"]
                if isinstance(lane, PolyLaneFixedWidth) and hasattr(lane, "source_points"):
                    # highway-env's to_config writes the spline's 1 m resampling, which loses
                    # the lane's end and cannot rebuild a lane shorter than 2 m: keep the source.
                    cfg["lane_points"] = lane.source_points.tolist()
                if isinstance(lane, PolyLane):
                    cfg = {
                        "lane_points": cfg["lane_points"],
                        "left_boundary_points": [
                            p.position.tolist() for p in lane.left_boundary.poses
                        ],
                        "right_boundary_points": [
                            p.position.tolist() for p in lane.right_boundary.poses
                        ],
                        **{
                            k: cfg[k]
                            for k in ("line_types", "forbidden", "speed_limit", "priority")
                        },
                    }
                lanes.append(
                    {"from": _from, "to": _to, "class": type(lane).__name__, "config": cfg}
                )
    return json.dumps(lanes, default=_json_default)


def network_from_json(text: str) -> RoadNetwork:
    """Rebuild a network written by :func:`network_to_json`; unknown lane classes are refused."""
    network = IndexedRoadNetwork()
    for entry in json.loads(text):
        name = entry.get("class")
        if name not in _LANE_CLASSES:
            raise ValueError(f"unknown lane class {name!r}; allowed: {sorted(_LANE_CLASSES)}")
        cfg = dict(entry["config"])
        for key in ("start", "end", "center"):
            if key in cfg:
                cfg[key] = np.asarray(cfg[key], dtype=np.float64)
        if cfg.get("line_types") is not None:
            cfg["line_types"] = tuple(cfg["line_types"])
        if name == "PolyLaneFixedWidth":
            lane = poly_lane(np.asarray(cfg.pop("lane_points"), dtype=np.float64), **cfg)
        else:
            lane = _LANE_CLASSES[name](**cfg)
        network.add_lane(entry["from"], entry["to"], lane)
    return network


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"cannot serialise {type(obj).__name__}")


def poly_lane(points: np.ndarray, width: float, **kwargs) -> PolyLaneFixedWidth:
    """A ``PolyLaneFixedWidth`` that remembers its source points ``[P, 2]`` m for serialising.

    Without ``line_types`` its edges are striped (highway-env's default for its other lanes;
    its renderer cannot draw a lane whose ``line_types`` is None).
    """
    if kwargs.get("line_types") is None:
        kwargs["line_types"] = (LineType.STRIPED, LineType.STRIPED)
    lane = fast_poly_lane(PolyLaneFixedWidth(points.tolist(), width=width, **kwargs))
    lane.source_points = np.asarray(points, dtype=np.float64)
    return lane
