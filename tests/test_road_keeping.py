"""Road keeping: a step that would leave the road is moved sideways onto the agent's lane."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import make_scene

from counterscene_env.sim import road_keeping
from counterscene_env.sim.road_keeping import EDGE_MARGIN

# One eastbound lane 4 m wide along y = 0, and one westbound along y = 10.
LINES = np.array(
    [[[0.0, 0.0], [50.0, 0.0], [100.0, 0.0]], [[100.0, 10.0], [50.0, 10.0], [0.0, 10.0]]]
)
PIECES = road_keeping.lane_pieces(LINES, np.array([4.0, 4.0]))


def test_a_point_over_the_edge_moves_sideways_just_inside_its_lane():
    moved = road_keeping.keep_on_lane(np.array([30.0, 3.5]), 0.1, PIECES)
    np.testing.assert_allclose(moved, [30.0, 2.0 - EDGE_MARGIN])  # progress along x kept
    inside = np.array([30.0, 1.0])
    assert road_keeping.keep_on_lane(inside, 0.0, PIECES) is inside


def test_only_a_lane_going_the_agents_way_counts():
    # 6 m off the eastbound lane, 4 m off the westbound one: an eastbound car goes back to
    # its own lane, a westbound one to the other.
    point = np.array([30.0, 6.0])
    np.testing.assert_allclose(road_keeping.keep_on_lane(point, 0.0, PIECES)[1], 2.0 - EDGE_MARGIN)
    np.testing.assert_allclose(
        road_keeping.keep_on_lane(point, math.pi, PIECES)[1], 8.0 + EDGE_MARGIN
    )
    # Northbound: no lane goes that way.
    assert road_keeping.keep_on_lane(point, math.pi / 2, PIECES) is None


def test_a_lane_going_the_agents_way_but_far_away_is_no_correction():
    # 25 m north of the westbound lane, heading west: the nearest lane going that way lies
    # beyond MAX_SHIFT. A correction there would teleport the car (a turning car at a junction
    # did: 25 m in one step); it is left to leave the road instead.
    far = np.array([30.0, 10.0 + 2.0 + road_keeping.MAX_SHIFT + 1.0])
    assert road_keeping.keep_on_lane(far, math.pi, PIECES) is None
    near = np.array([30.0, 10.0 + 2.0 + road_keeping.MAX_SHIFT - 1.0])
    np.testing.assert_allclose(road_keeping.keep_on_lane(near, math.pi, PIECES), [30, 11.7])


@pytest.mark.usefixtures("one_torch_thread")
@pytest.mark.parametrize("keep", [True, False])
def test_traffic_drifting_off_the_road_is_kept_on_it(keep):
    from counterscene_env.sim import ClosedLoop, MotionSource, SimConfig
    from counterscene_env.world_model.checkpoint import load_model

    # Row 1 is 150 m ahead of the ego (beyond the model's view, so it replays its log), and
    # its log drifts left at 0.6 m/s over the edge of the two-lane road (y in [-2, 6]).
    T, c = 80, 30
    t = np.arange(T) * 0.1
    ego = np.stack([10 * t, np.zeros(T)], -1)
    drift = np.stack([150 + 10 * t, 4 + 0.6 * np.clip(t - 3, 0, None)], -1)
    yaws = np.array([np.zeros(T), np.where(t < 3, 0.0, math.atan2(0.6, 10))])
    scene = make_scene(
        np.stack([ego, drift]), yaws=yaws, speeds=np.full((2, T), 10.0), current_index=c
    )
    loop = ClosedLoop(load_model(), SimConfig(duration=4.5, num_samples=1, road_keeping=keep))
    loop.reset([scene], [0])
    while not loop.done.all():
        loop.step(np.zeros((1, 2)))
    sim, source = loop.scene(0), loop.motion_source(0)[1, c + 1 :]
    y = sim.positions[1, c + 1 :, 1]
    if keep:
        # It drifts as logged while on the road; the step over the edge puts it back inside
        # its lane, and there it stays.
        assert y.max() < 6.0 and y[-1] == pytest.approx(4 + 2 - EDGE_MARGIN)
        assert (source == MotionSource.KEEP).any()
        # Still moving on at its speed, not stopped at the edge.
        assert sim.positions[1, -1, 0] - sim.positions[1, c, 0] > 40.0
    else:
        assert y.max() > 6.0 and not (source == MotionSource.KEEP).any()
