"""Causal Interaction Graph edge features against hand-computed encounters."""

from __future__ import annotations

import math

import pytest
import torch

from counterscene_env.world_model.cig import (
    COLLISION_RADIUS,
    DIST_CAP,
    HORIZON,
    NUM_EDGE_FEATURES,
    SPEED_CAP,
    edge_features,
)

DP, DV, TTC, TTI, DINT, VINT = range(NUM_EDGE_FEATURES)
D = torch.float64


def _edges(positions, velocities, valid=None, **kw):
    p = torch.tensor(positions, dtype=D)
    v = torch.tensor(velocities, dtype=D)
    ok = torch.ones(p.shape[:-1], dtype=torch.bool) if valid is None else torch.tensor(valid)
    return edge_features(p, v, ok, **kw)


def test_crossing_collision_course_by_hand():
    # A from the west, B from the south, both at 10 m/s: they meet at the origin at t = 2 s.
    e = _edges([[-20.0, 0.0], [0.0, -20.0]], [[10.0, 0.0], [0.0, 10.0]])
    assert e.shape == (2, 2, NUM_EDGE_FEATURES)
    closing = 10 * math.sqrt(2)  # |v_B - v_A|
    ttc = 2 - COLLISION_RADIUS / closing
    expected = torch.tensor(
        [
            0.0,  # 28.3 m apart: beyond the 20 m cap
            closing / SPEED_CAP,
            1 - ttc / HORIZON,
            1 - 2.0 / HORIZON,
            1.0,  # closest approach 0 m
            closing / SPEED_CAP,  # heading straight at each other in the relative frame
        ],
        dtype=D,
    )
    assert DIST_CAP == 20.0 and SPEED_CAP == 20.0 and HORIZON == 5.2
    torch.testing.assert_close(e[0, 1], expected)
    torch.testing.assert_close(e[1, 0], expected)  # symmetric encounter
    assert (e[0, 0] == 0).all() and (e[1, 1] == 0).all()


def test_tti_is_directed():
    # A reaches the crossing point (origin) in 1 s, B in 3 s.
    e = _edges([[-10.0, 0.0], [0.0, -30.0]], [[10.0, 0.0], [0.0, 10.0]])
    assert e[0, 1, TTI].item() == pytest.approx(1 - 1.0 / HORIZON)
    assert e[1, 0, TTI].item() == pytest.approx(1 - 3.0 / HORIZON)
    # Everything else is symmetric.
    others = [DP, DV, TTC, DINT, VINT]
    torch.testing.assert_close(e[0, 1, others], e[1, 0, others])
    # B reaches the crossing 2 s after A. Relative position (10 - 10 t, -30 + 10 t): closest at
    # t = 2 s, 14.1 m apart, so no collision.
    assert e[0, 1, TTC].item() == 0.0
    assert e[0, 1, DINT].item() == pytest.approx(1 - math.sqrt(200) / DIST_CAP)


def test_parallel_cars_in_adjacent_lanes_never_intersect():
    # Same speed, 4 m apart laterally, 5 m apart longitudinally.
    e = _edges([[0.0, 0.0], [5.0, 4.0]], [[10.0, 0.0], [10.0, 0.0]])
    assert e[0, 1, TTI].item() == 0.0 and e[1, 0, TTI].item() == 0.0
    assert e[0, 1, TTC].item() == 0.0  # they keep their 6.4 m gap
    assert e[0, 1, DV].item() == 0.0 and e[0, 1, VINT].item() == 0.0
    gap = math.hypot(5.0, 4.0)
    assert e[0, 1, DP].item() == pytest.approx(1 - gap / DIST_CAP)
    assert e[0, 1, DINT].item() == pytest.approx(1 - gap / DIST_CAP)
    # Paths crossing behind one of the cars do not count either: B drives away from the crossing.
    e = _edges([[-20.0, 0.0], [0.0, -20.0]], [[10.0, 0.0], [0.0, -10.0]])
    assert e[0, 1, TTI].item() == 0.0 and e[1, 0, TTI].item() == 0.0


def test_rear_end_ttc_and_closing_speed():
    # Follower at 20 m/s, 20 m behind a leader at 10 m/s in the same lane: TTC = (20 - R) / 10.
    e = _edges([[0.0, 0.0], [20.0, 0.0]], [[20.0, 0.0], [10.0, 0.0]])
    ttc = (20.0 - COLLISION_RADIUS) / 10.0
    assert e[0, 1, TTC].item() == pytest.approx(1 - ttc / HORIZON)
    assert e[0, 1, VINT].item() == pytest.approx(10.0 / SPEED_CAP)
    assert e[0, 1, DINT].item() == pytest.approx(1.0)  # they would pass through each other
    # Already overlapping: TTC 0 -> score 1.
    e = _edges([[0.0, 0.0], [2.0, 0.0]], [[10.0, 0.0], [10.0, 0.0]])
    assert e[0, 1, TTC].item() == pytest.approx(1.0)
    # Opening gap: no closing speed, no collision.
    e = _edges([[0.0, 0.0], [10.0, 0.0]], [[10.0, 0.0], [20.0, 0.0]])
    assert e[0, 1, VINT].item() == 0.0 and e[0, 1, TTC].item() == 0.0


def test_invalid_agents_and_diagonal_are_zero():
    g = torch.Generator().manual_seed(0)
    p = torch.randn(5, 2, generator=g, dtype=D) * 8
    v = torch.randn(5, 2, generator=g, dtype=D) * 6
    valid = torch.tensor([True, False, True, True, False])
    e = edge_features(p, v, valid)
    assert (e[1] == 0).all() and (e[:, 1] == 0).all()
    assert (e[4] == 0).all() and (e[:, 4] == 0).all()
    assert (e[torch.arange(5), torch.arange(5)] == 0).all()
    # The valid pairs are unaffected by what the invalid agents hold.
    p2, v2 = p.clone(), v.clone()
    p2[1], v2[4] = torch.tensor([0.3, 0.1]), torch.tensor([-50.0, 20.0])
    torch.testing.assert_close(edge_features(p2, v2, valid), e)
    assert (e[0, 2] != 0).any()


def test_values_in_unit_interval_and_batch_dims():
    g = torch.Generator().manual_seed(1)
    p = torch.randn(2, 3, 6, 2, generator=g) * 15
    v = torch.randn(2, 3, 6, 2, generator=g) * 10
    valid = torch.rand(2, 3, 6, generator=g) > 0.2
    e = edge_features(p, v, valid)
    assert e.shape == (2, 3, 6, 6, NUM_EDGE_FEATURES)
    assert torch.isfinite(e).all() and (e >= 0).all() and (e <= 1).all()
    assert (e > 0).any()
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(e[i, j], edge_features(p[i, j], v[i, j], valid[i, j]))
    # Coincident agents standing still (zero relative motion, zero distance) stay finite.
    e = edge_features(torch.zeros(2, 2), torch.zeros(2, 2), torch.ones(2, dtype=torch.bool))
    assert torch.isfinite(e).all() and (e >= 0).all() and (e <= 1).all()


def test_horizon_caps_ttc_and_tti():
    # The same crossing, but with a 1.5 s horizon: TTC (1.79 s) and TTI (2 s) fall outside it.
    e = _edges([[-20.0, 0.0], [0.0, -20.0]], [[10.0, 0.0], [0.0, 10.0]], horizon=1.5)
    assert e[0, 1, TTC].item() == 0.0 and e[0, 1, TTI].item() == 0.0
    # The closest approach is then taken at 1.5 s: relative position (5, -5).
    assert e[0, 1, DINT].item() == pytest.approx(1 - math.sqrt(50) / DIST_CAP)
