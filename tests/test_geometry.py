"""Oriented-box geometry: corners, SAT overlap, drivable area, TTC and box distance."""

import math

import numpy as np
import pytest
import shapely

from counterscene_env import geometry
from counterscene_env.ttc import time_to_collision

CAR = (4.0, 2.0)  # length, width in m
R2 = math.sqrt(2.0)


def overlap2(c1, y1, c2, y2, ext1=CAR, ext2=CAR):
    """Overlap of two boxes through the public pairwise function."""
    ov = geometry.pairwise_overlap(
        np.array([c1, c2], float), np.array([y1, y2]), np.array([ext1, ext2]), np.ones(2, bool)
    )
    assert ov[0, 1] == ov[1, 0]
    return bool(ov[0, 1])


# ---------------------------------------------------------------------- corners
def test_box_corners_of_a_known_box_counter_clockwise():
    corners = geometry.box_corners(np.array([1.0, 2.0]), np.array(math.pi / 2), np.array(CAR))
    expected = [[2.0, 4.0], [0.0, 4.0], [0.0, 0.0], [2.0, 0.0]]
    np.testing.assert_allclose(corners, expected, atol=1e-12)
    x, y = corners[:, 0], corners[:, 1]
    shoelace = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    assert shoelace == pytest.approx(8.0)  # positive: counter-clockwise, area 4 x 2


def test_box_corners_batched_shape():
    c = geometry.box_corners(np.zeros((3, 5, 2)), np.zeros((3, 5)), np.ones((3, 1, 2)))
    assert c.shape == (3, 5, 4, 2)


# ---------------------------------------------------------------------- overlap
def test_corner_touching_face_is_not_overlap_but_slightly_closer_is():
    # A 4x2 box at 45 deg reaches 3/sqrt(2) m in x; its rear-left corner is at
    # (-3/sqrt2, -1/sqrt2) from its centre, so this centre puts that corner exactly on the
    # front face x = 2 of an axis-aligned box at the origin.
    cx, cy = 2.0 + 3.0 / R2, 1.0 / R2
    q = math.pi / 4
    assert not overlap2((0, 0), 0.0, (cx, cy), q)
    assert overlap2((0, 0), 0.0, (cx - 0.01, cy), q)
    assert not overlap2((0, 0), 0.0, (cx + 0.01, cy), q)


def test_rotated_side_by_side_boxes_separated_although_bounding_boxes_overlap():
    # Two 45-deg boxes side by side: their axis-aligned bounding boxes overlap widely, only the
    # rotated axes separate them. Widths sum to 2 m along the shared normal.
    q = math.pi / 4
    normal = np.array([-math.sin(q), math.cos(q)])
    assert not overlap2((0, 0), q, tuple(2.1 * normal), q)
    assert not overlap2((0, 0), q, tuple(2.0 * normal), q)  # edge contact
    assert overlap2((0, 0), q, tuple(1.9 * normal), q)


def test_cross_same_centre_and_far_apart():
    assert overlap2((0, 0), 0.0, (0, 0), math.pi / 2)  # a cross
    assert overlap2((5, 5), 1.0, (5, 5), 1.0)  # identical boxes
    assert not overlap2((0, 0), 0.3, (30, -20), 2.0)
    # A 90-deg box inside the arm of a long cross bar: 10x1 bar, 2x0.5 box rotated 90 deg.
    assert overlap2((0, 0), 0.0, (4.0, 0.0), math.pi / 2, ext1=(10.0, 1.0), ext2=(2.0, 0.5))


def test_invalid_nan_agent_does_not_disable_other_checks():
    centers = np.array([[0.0, 0.0], [1.0, 0.0], [np.nan, np.nan], [1.5, 0.5]])
    yaws = np.array([0.0, 0.0, np.nan, 0.0])
    extents = np.array([CAR, CAR, [np.nan, np.nan], CAR])
    valid = np.array([True, True, False, False])  # agent 3 overlaps but is invalid
    ov = geometry.pairwise_overlap(centers, yaws, extents, valid)
    assert ov[0, 1] and ov[1, 0]
    assert not ov[2].any() and not ov[:, 2].any()
    assert not ov[3].any() and not ov[:, 3].any()
    assert not ov.diagonal().any()
    # Flagged valid but NaN: still dropped alone.
    ov = geometry.pairwise_overlap(centers, yaws, extents, np.ones(4, bool))
    assert ov[0, 1] and ov[0, 3] and ov[1, 3] and not ov[2].any()


def test_overlaps_over_time_matches_elementwise_check():
    rng = np.random.default_rng(0)
    n, t = 12, 7
    pos = rng.uniform(-8, 8, (n, t, 2))
    yaw = rng.uniform(-np.pi, np.pi, (n, t))
    ext = rng.uniform(1, 5, (n, 2))
    valid = rng.random((n, t)) > 0.2
    out = geometry.overlaps_over_time(pos, yaw, ext, valid)
    assert out.shape == (t, n, n)
    for k in range(t):
        ref = geometry.boxes_overlap(
            pos[:, None, k], yaw[:, None, k], ext[:, None], pos[None, :, k], yaw[None, :, k], ext
        )
        ref &= valid[:, None, k] & valid[None, :, k] & ~np.eye(n, dtype=bool)
        np.testing.assert_array_equal(out[k], ref)
        np.testing.assert_array_equal(
            out[k], geometry.pairwise_overlap(pos[:, k], yaw[:, k], ext, valid[:, k])
        )
    assert 0 < out.sum() < out.size / 4  # some overlap, many do not: the check is not vacuous


def test_sat_agrees_with_shapely_on_random_boxes():
    rng = np.random.default_rng(1)
    m = 2000
    ca, cb = rng.uniform(-4, 4, (m, 2)), rng.uniform(-4, 4, (m, 2))
    ya, yb = rng.uniform(-np.pi, np.pi, m), rng.uniform(-np.pi, np.pi, m)
    ea, eb = rng.uniform(0.5, 5, (m, 2)), rng.uniform(0.5, 5, (m, 2))
    ours = geometry.boxes_overlap(ca, ya, ea, cb, yb, eb)
    pa = shapely.polygons(geometry.box_corners(ca, ya, ea))
    pb = shapely.polygons(geometry.box_corners(cb, yb, eb))
    ref = shapely.area(shapely.intersection(pa, pb)) > 1e-9
    assert 0.2 < ours.mean() < 0.8
    np.testing.assert_array_equal(ours, ref)


# ---------------------------------------------------------------------- drivable area
def test_points_in_area_polygon_with_hole():
    area = shapely.Polygon(
        [(0, 0), (10, 0), (10, 10), (0, 10)], holes=[[(3, 3), (7, 3), (7, 7), (3, 7)]]
    )
    shapely.prepare(area)
    pts = np.array([[[1.0, 1.0], [5.0, 5.0], [10.0, 5.0]], [[12.0, 5.0], [np.nan, 1.0], [3, 5]]])
    inside = geometry.points_in_area(area, pts)
    assert inside.shape == (2, 3)
    # ring, hole, outer boundary | outside, NaN, hole boundary
    np.testing.assert_array_equal(inside, [[True, False, True], [False, False, True]])


def test_points_in_empty_area_all_outside():
    assert not geometry.points_in_area(shapely.Polygon(), np.zeros((4, 2))).any()


# ---------------------------------------------------------------------- time to collision
def head_on(gap_between_fronts, speed=10.0):
    x_b = gap_between_fronts + CAR[0]
    pos = np.array([[0.0, 0.0], [x_b, 0.0]])
    vel = np.array([[speed, 0.0], [-speed, 0.0]])
    yaws = np.array([0.0, math.pi])
    return pos, vel, yaws, np.array([CAR, CAR]), np.ones(2, bool)


def test_ttc_head_on_within_one_step_and_symmetric():
    ttc = time_to_collision(*head_on(45.0), horizon=10.0, step=0.1)
    true = 45.0 / 20.0  # fronts 45 m apart closing at 20 m/s: contact at 2.25 s
    assert true < ttc[0, 1] <= true + 0.1 + 1e-9
    assert ttc[0, 1] == pytest.approx(2.3)
    assert ttc[1, 0] == ttc[0, 1]
    assert np.isinf(ttc.diagonal()).all()
    exact = time_to_collision(*head_on(45.0), step=0.0)
    assert exact[0, 1] == pytest.approx(true, abs=1e-6)


def test_ttc_beyond_horizon_is_inf_and_overlapping_is_zero():
    assert np.isinf(time_to_collision(*head_on(250.0), horizon=10.0)[0, 1])
    assert time_to_collision(*head_on(-1.0))[0, 1] == 0.0


def test_ttc_parallel_cars_inf_and_invalid_agent_inf():
    pos = np.array([[0.0, 0.0], [0.0, 3.5], [20.0, 0.0]])
    vel = np.array([[10.0, 0.0], [10.0, 0.0], [np.nan, np.nan]])
    yaws = np.zeros(3)
    ext = np.array([CAR] * 3)
    valid = np.array([True, True, False])
    ttc = time_to_collision(pos, vel, yaws, ext, valid)
    assert np.isinf(ttc[0, 1])
    assert np.isinf(ttc[2]).all() and np.isinf(ttc[:, 2]).all()
    valid[2] = True  # now a (finite) stopped car ahead: ego reaches it in 1.6 s
    vel[2] = 0.0
    ttc = time_to_collision(pos, vel, yaws, ext, valid)
    assert ttc[0, 2] == pytest.approx(1.7)  # gap 16 m at 10 m/s: contact at 1.6 s, sampled > it
    assert np.isinf(ttc[0, 1])


def test_ttc_closed_form_equals_brute_force_sampling():
    rng = np.random.default_rng(2)
    n = 30
    pos = rng.uniform(-25, 25, (n, 2))
    vel = rng.uniform(-12, 12, (n, 2))
    yaws = rng.uniform(-np.pi, np.pi, n)
    ext = rng.uniform(1.5, 5.0, (n, 2))
    valid = np.ones(n, bool)
    ttc = time_to_collision(pos, vel, yaws, ext, valid, horizon=5.0, step=0.1)
    taus = 0.1 * np.arange(51)
    moved = pos[:, None] + vel[:, None] * taus[None, :, None]  # [N, K, 2]
    ov = geometry.overlaps_over_time(moved, np.repeat(yaws[:, None], 51, 1), ext, np.ones((n, 51)))
    ref = np.where(ov.any(0), taus[ov.argmax(0)], np.inf)
    np.fill_diagonal(ref, np.inf)
    assert ((ref > 0) & np.isfinite(ref)).sum() > n  # many pairs collide later, not at once
    np.testing.assert_array_equal(np.isinf(ttc), np.isinf(ref))
    finite = np.isfinite(ref)
    np.testing.assert_allclose(ttc[finite], ref[finite], atol=1e-9)


# ---------------------------------------------------------------------- distance
def test_box_distance_gap_rotated_and_overlap():
    ca = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [np.nan, 0.0]])
    cb = np.array([[7.0, 0.0], [1.0, 0.0], [0.0, 5.0], [3.0, 0.0]])
    yb = np.array([0.0, 0.0, math.pi / 2, 0.0])
    d = geometry.box_distance(ca, np.zeros(4), np.array(CAR), cb, yb, np.array(CAR))
    # gap between x=2 and x=5; overlap; 90-deg box reaching down to y = 3 above y = 1
    np.testing.assert_allclose(d[:3], [3.0, 0.0, 2.0], atol=1e-9)
    assert np.isnan(d[3])
