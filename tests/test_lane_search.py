"""Imported maps answer highway-env's lane queries exactly as highway-env does, faster
(``scene/lane_search.py``): the closest lane, the Frenet projection and the segment lookup."""

from __future__ import annotations

import numpy as np
import pytest
from highway_env.road.lane import PolyLaneFixedWidth
from highway_env.road.road import RoadNetwork
from hypothesis import given, settings
from hypothesis import strategies as st

from counterscene_env.scene.lane_search import IndexedRoadNetwork, PolylineSpline
from counterscene_env.scene.road import RoadMap
from counterscene_env.scene.road_json import network_from_json, network_to_json


def _lines() -> list[np.ndarray]:
    """Lanes with what makes the search hard: a straight road in pieces (shared tangent
    lines), the opposite direction on top of it, a quarter turn, a U-turn, a short stub, and
    points 1 m apart (samples that fall exactly on the query grid)."""
    turn = np.linspace(0, np.pi / 2, 12)
    u = np.linspace(-np.pi / 2, np.pi / 2, 20)
    return [
        np.array([[0.0, 0.0], [30.0, 0.0]]),
        np.array([[30.0, 0.0], [60.0, 0.0]]),
        np.array([[60.0, 0.0], [0.0, 0.0]]),
        np.array([[0.0, 3.5], [60.0, 3.5]]),
        np.c_[60 + 15 * np.sin(turn), 15 - 15 * np.cos(turn)],
        np.c_[-10 + 8 * np.cos(u), 8 + 8 * np.sin(u)][::-1],
        np.array([[20.0, -6.0], [21.5, -6.0]]),
        np.c_[np.arange(0.0, 12.0), np.full(12, -10.0)],
    ]


@pytest.fixture(scope="module")
def maps() -> tuple[RoadNetwork, RoadNetwork]:
    """The imported network, and highway-env's own from the same centre lines."""
    lines = _lines()
    road = RoadMap.from_centerlines(lines, [3.5] * len(lines))
    stock = RoadNetwork()
    for start, to in road.network.graph.items():
        for end, lanes in to.items():
            for lane in lanes:
                stock.add_lane(start, end, PolyLaneFixedWidth(lane.source_points.tolist()))
    return road.network, stock


def test_imported_maps_use_the_fast_lanes(maps):
    network, _ = maps
    assert isinstance(network, IndexedRoadNetwork)
    lanes = [lane for to in network.graph.values() for ls in to.values() for lane in ls]
    assert all(isinstance(lane.curve, PolylineSpline) for lane in lanes)
    again = network_from_json(network_to_json(network))
    assert isinstance(again, IndexedRoadNetwork)
    assert all(
        isinstance(lane.curve, PolylineSpline)
        for to in again.graph.values()
        for ls in to.values()
        for lane in ls
    )


coordinate = st.one_of(
    st.floats(-40, 100, allow_nan=False),
    st.integers(-40, 100).map(float),  # on the 1 m sample grid: projections exactly 0
)


@settings(max_examples=300, deadline=None)
@given(
    x=coordinate,
    y=st.one_of(st.floats(-30, 40, allow_nan=False), st.integers(-30, 40).map(float)),
    heading=st.one_of(st.none(), st.floats(-np.pi, np.pi), st.sampled_from([0.0, np.pi])),
)
def test_same_answers_as_highway_env(maps, x, y, heading):
    network, stock = maps
    point = np.array([x, y])
    index = network.get_closest_lane_index(point, heading)
    assert index == stock.get_closest_lane_index(point, heading)
    for (_, to), (_, stock_to) in zip(network.graph.items(), stock.graph.items(), strict=True):
        for end, lanes in to.items():
            for fast, slow in zip(lanes, stock_to[end], strict=True):
                s, r = fast.local_coordinates(point)
                assert (s, r) == slow.local_coordinates(point)  # bit for bit
                assert fast.heading_at(s) == slow.heading_at(s)
                assert fast.position(s, r).tolist() == slow.position(s, r).tolist()


def test_segment_lookup_at_and_between_samples(maps):
    """The sample a longitudinal position falls in, at the samples themselves too (where a
    wrong comparison would pick the sample before), beyond both ends, and for NaN."""
    network, stock = maps
    for (_, to), (_, stock_to) in zip(network.graph.items(), stock.graph.items(), strict=True):
        for end, lanes in to.items():
            for fast, slow in zip(lanes, stock_to[end], strict=True):
                s = slow.curve.s_samples
                for lon in [*s, *(s + 0.5), -1.0, s[-1] + 3.0, float("nan")]:
                    got = fast.curve._get_idx_segment_for_lon(lon)
                    assert got == slow.curve._get_idx_segment_for_lon(lon), (end, lon)


def test_a_lane_added_later_is_searched(maps):
    network = network_from_json(network_to_json(maps[0]))
    point = np.array([200.0, 200.0])
    before = network.get_closest_lane_index(point)
    far = RoadMap.from_centerlines([np.array([[190.0, 200.0], [210.0, 200.0]])], [3.5])
    (lane,) = [ln for to in far.network.graph.values() for ls in to.values() for ln in ls]
    network.add_lane("far_a", "far_b", lane)
    assert before != ("far_a", "far_b", 0)
    assert network.get_closest_lane_index(point) == ("far_a", "far_b", 0)
