"""Adversary selection: the paper's conflict mining on hand-built tracks, and the baselines.

Tracks are built from per-step displacements that are exact in binary floating point (1.0,
0.5, 1.25 m per 0.1 s step ...), so the closest encounters are exact zeros and the expected
steps, speeds and scores can be computed by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from counterscene_env.adversary.selection import (
    FOLLOWING,
    INTERSECTION,
    LEAD_BRAKING,
    METHODS,
    REAR_APPROACH,
    Conflict,
    encounter,
    mine_conflicts,
    reachable,
    required_acceleration,
    select_adversary,
)
from counterscene_env.adversary.tracks import check_tracks

DT = 0.1
T = 60
STEPS = np.arange(T, dtype=float)


def track(x, y) -> np.ndarray:
    """``[T, 2]`` from per-step x and y (arrays or constants)."""
    x = np.broadcast_to(np.asarray(x, dtype=float), (T,))
    y = np.broadcast_to(np.asarray(y, dtype=float), (T,))
    return np.stack([x, y], axis=-1)


def ego_track() -> np.ndarray:
    """The ego: east along y = 0 at 10 m/s from the origin (x = index, m)."""
    return track(STEPS, 0.0)


def yielding_crosser() -> np.ndarray:
    """North along x = 20 at 10 m/s, then 5 m/s from index 10: at (20, 0) at index 30.

    The ego is there at index 20, so the crosser yields 1.0 s.
    """
    y = np.where(STEPS <= 10, -20.0 + STEPS, -10.0 + 0.5 * (STEPS - 10))
    return track(20.0, y)


def stack(*tracks) -> tuple[np.ndarray, np.ndarray]:
    """``positions [N, T, 2]`` and an all-True ``valid [N, T]``."""
    positions = np.stack(tracks)
    return positions, np.ones(positions.shape[:2], dtype=bool)


def crossing_scene() -> tuple[np.ndarray, np.ndarray]:
    """Ego, the yielding crosser, a distant parallel car (y = 100) and a car parked at (30, 4)."""
    return stack(ego_track(), yielding_crosser(), track(STEPS, 100.0), track(30.0, 4.0))


def by_agent(conflicts: list[Conflict]) -> dict[int, Conflict]:
    return {c.agent: c for c in conflicts}


# ---------------------------------------------------------------- the planted crossing


@pytest.mark.parametrize("ego_row", [0, 2])
def test_causal_picks_the_yielding_crosser_with_hand_computed_conflict(ego_row):
    positions, valid = crossing_scene()
    order = [1, 2, 0, 3] if ego_row == 2 else [0, 1, 2, 3]  # new row k holds old row order[k]
    positions, valid = positions[order], valid[order]
    crosser = order.index(1)

    sel = select_adversary("causal", positions, valid, ego_row, dt=DT, start_step=31)

    assert sel.fallback is None
    assert sel.num_candidates == 3
    c = sel.conflict
    assert c.agent == crosser
    assert (c.type, c.subtype, c.tier) == (INTERSECTION, INTERSECTION, 1)
    # The ego is at (20, 0) at index 20, the crosser at index 30; absolute = 31 + index.
    assert (c.ego_step, c.adversary_step) == (51, 61)
    np.testing.assert_allclose(c.conflict_point, [20.0, 0.0], atol=1e-9)
    assert c.min_distance == pytest.approx(0.0, abs=1e-9)
    assert c.arrival_gap == pytest.approx(1.0)
    v_rel = math.hypot(10.0, 5.0)  # ego (10, 0) m/s, crosser (0, 5) m/s
    assert c.relative_speed == pytest.approx(v_rel)
    assert c.score == pytest.approx(v_rel / (1.0 + 0.5))
    assert c.weight == pytest.approx(-80.0 - 40.0)  # score > 1 saturates


def test_mine_conflicts_lists_every_candidate_with_tiers_strict_or_not():
    positions, valid = crossing_scene()
    paper = by_agent(mine_conflicts(positions, valid, 0, dt=DT))
    strict = by_agent(mine_conflicts(positions, valid, 0, dt=DT, strict=True))
    assert sorted(paper) == sorted(strict) == [1, 2, 3]
    # Distant parallel car: following, 100 m away, no tier either way.
    assert (paper[2].type, paper[2].tier, strict[2].tier) == (FOLLOWING, None, None)
    # Parked car: no direction -> intersection; the ego passes it at index 30, it is "there"
    # from index 0: gap 3.0 s, v_rel 10 m/s. Tier 1 for the paper; strict rejects it.
    parked = paper[3]
    assert parked.type == INTERSECTION
    assert (parked.ego_step, parked.adversary_step) == (30, 0)
    assert parked.score == pytest.approx(10.0 / 3.5)
    assert parked.tier == 1 and strict[3].tier is None
    assert paper[1].tier == strict[1].tier == 1


def test_eligible_mask_removes_candidates():
    positions, valid = crossing_scene()
    eligible = np.array([True, False, True, True])
    sel = select_adversary("causal", positions, valid, 0, eligible=eligible, dt=DT)
    assert sel.conflict is None
    assert sel.num_candidates == 2
    assert "tier" in sel.fallback and "2 candidates" in sel.fallback


# ---------------------------------------------------------------- formulas by hand


def test_following_score_relative_speed_and_weight_by_hand():
    # A faster car (11.25 m/s) in the next lane (y = 3) starting 4 m behind: at index 8 it is
    # at x = 5, where the ego is at index 5. d_min 3 m, v_rel 1.25 m/s.
    positions, valid = stack(ego_track(), track(-4.0 + 1.125 * STEPS, 3.0))
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.type, c.subtype) == (FOLLOWING, REAR_APPROACH)
    assert (c.ego_step, c.adversary_step) == (5, 8)
    assert c.min_distance == pytest.approx(3.0)
    np.testing.assert_allclose(c.conflict_point, [5.0, 1.5])  # midpoint of (5, 0) and (5, 3)
    assert c.arrival_gap == pytest.approx(0.3)
    assert c.relative_speed == pytest.approx(1.25)
    assert c.score == pytest.approx(1.25 / (3.0 + 1.0))
    assert c.weight == pytest.approx(-60.0 - 30.0 * 0.3125)  # unsaturated: s < 1
    assert c.tier == 2


def test_relative_speed_uses_forward_difference_at_index_zero():
    # The encounter is at the ego's first step: no p_e(tau_e - 1), so its forward difference
    # (10, 0) m/s is used, not a zero velocity (which would give v_rel = 5).
    crosser = track(0.0, -5.0 + 0.5 * STEPS)  # at (0, 0) at index 10, 5 m/s north
    positions, valid = stack(ego_track(), crosser)
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.ego_step, c.adversary_step) == (0, 10)
    assert c.relative_speed == pytest.approx(math.hypot(10.0, 5.0))


def test_relative_speed_uses_forward_difference_after_an_invalid_step_with_nan():
    # The crosser reaches (20, 0) at index 30 at 5 m/s and leaves at 10 m/s; index 29 is
    # invalid (NaN), so its velocity at 30 is the forward difference (0, 10) m/s.
    y = np.where(STEPS <= 30, -15.0 + 0.5 * STEPS, STEPS - 30.0)
    crosser = track(20.0, y)
    positions, valid = stack(ego_track(), crosser)
    positions[1, 29] = np.nan
    valid[1, 29] = False
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert c.adversary_step == 30
    assert c.relative_speed == pytest.approx(math.hypot(10.0, 10.0))
    assert c.score == pytest.approx(math.hypot(10.0, 10.0) / (1.0 + 0.5))


def test_isolated_valid_step_has_zero_velocity():
    positions, valid = stack(ego_track(), yielding_crosser())
    valid[1, 1::2] = False  # the crosser is seen only at even steps (index 30 included)
    positions[1, 1::2] = np.nan
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert c.adversary_step == 30
    assert c.relative_speed == pytest.approx(10.0)  # the ego's speed alone


def test_ties_go_to_the_first_pair_in_row_major_order():
    # A car parked on the ego's path at (20, 0): every one of its steps is at distance 0 from
    # the ego's index 20; the earliest (index 0) is chosen.
    positions, valid = stack(ego_track(), track(20.0, 0.0))
    c = encounter(positions, valid, 0, 1, dt=DT, start_step=7)
    assert (c.ego_step, c.adversary_step) == (27, 7)


# ---------------------------------------------------------------- types and tiers


@pytest.mark.parametrize("heading", [1.0, -1.0], ids=["east", "west"])
@pytest.mark.parametrize(
    ("start", "subtype"), [(-8.0, REAR_APPROACH), (8.0, LEAD_BRAKING)], ids=["behind", "ahead"]
)
def test_following_subtype_is_order_along_the_ego_direction(heading, start, subtype):
    # Same lane, same direction; "behind" is relative to the ego's travel, not to +x.
    positions, valid = stack(ego_track(), track(start + 1.25 * STEPS, 0.0))
    positions[..., 0] *= heading
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.type, c.subtype) == (FOLLOWING, subtype)


def test_opposite_direction_is_an_intersection():
    positions, valid = stack(ego_track(), track(80.0 - STEPS, 3.0))
    assert encounter(positions, valid, 0, 1, dt=DT).type == INTERSECTION


@pytest.mark.parametrize(("step", "tier"), [(1.0, None), (1.0625, 2)], ids=["pacing", "closing"])
def test_tiers_need_a_minimum_score(step, tier):
    # A car 3 m to the side starting 4 m behind: pacing the ego (v_rel 0, score 0) is no
    # conflict; closing at 0.625 m/s (score 0.156 >= 0.05) is a rear approach.
    positions, valid = stack(ego_track(), track(-4.0 + step * STEPS, 3.0))
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.subtype, c.min_distance) == (REAR_APPROACH, pytest.approx(3.0))
    assert c.tier == tier


@pytest.mark.parametrize(("arrival", "tier"), [(54, 1), (55, None)], ids=["4.9s", "5.0s"])
def test_intersection_tier_needs_an_arrival_gap_below_five_seconds(arrival, tier):
    # The ego is at (5, 0) at index 5; the crosser on x = 5 gets there at `arrival`.
    positions, valid = stack(ego_track(), track(5.0, 0.5 * (STEPS - arrival)))
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.type, c.ego_step, c.adversary_step) == (INTERSECTION, 5, arrival)
    assert c.tier == tier


@pytest.mark.parametrize(
    ("start", "step", "offset", "subtype", "tier"),
    [
        (-4.0, 1.25, 9.5, REAR_APPROACH, 2),
        (-4.0, 1.25, 10.0, REAR_APPROACH, None),
        (8.0, 0.5, 11.5, LEAD_BRAKING, 3),
        (8.0, 0.5, 12.0, LEAD_BRAKING, None),
    ],
)
def test_following_tiers_need_a_small_min_distance(start, step, offset, subtype, tier):
    # A parallel car `offset` m to the side, closing in from behind or being closed on.
    positions, valid = stack(ego_track(), track(start + step * STEPS, offset))
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.subtype, c.min_distance) == (subtype, pytest.approx(offset))
    assert c.score >= 0.05
    assert c.tier == tier


@pytest.mark.parametrize(("dy", "kind"), [(0.5, FOLLOWING), (1.0, INTERSECTION)])
def test_type_threshold_is_direction_cosine_point_eight(dy, kind):
    # Directions (1, 0.5) -> cos 0.894 (a merge: following); (1, 1) -> cos 0.707 (crossing).
    positions, valid = stack(ego_track(), track(10.0 + STEPS, -20.0 + dy * STEPS))
    assert encounter(positions, valid, 0, 1, dt=DT).type == kind


def test_intersection_tier_beats_a_higher_scoring_rear_approach():
    # Row 2 closes in from behind at 25 m/s: v_rel 15 m/s at d_min 0 -> score 15 > 7.45.
    fast_rear = track(-10.0 + 2.5 * STEPS, 0.0)
    positions, valid = stack(ego_track(), yielding_crosser(), fast_rear)
    mined = by_agent(mine_conflicts(positions, valid, 0, dt=DT, strict=True))
    assert (mined[2].subtype, mined[2].tier) == (REAR_APPROACH, 2)
    assert mined[2].score == pytest.approx(15.0)
    assert mined[2].score > mined[1].score
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 1


def test_rear_approach_tier_beats_a_higher_scoring_lead_braking():
    rear = track(-3.0 + 1.25 * STEPS, 0.0)  # 12.5 m/s from behind: score 2.5 / 1
    lead = track(8.0 + 0.5 * STEPS, 0.0)  # 5 m/s ahead: score 5 / 1
    positions, valid = stack(ego_track(), rear, lead)
    mined = by_agent(mine_conflicts(positions, valid, 0, dt=DT, strict=True))
    assert (mined[1].subtype, mined[1].tier) == (REAR_APPROACH, 2)
    assert (mined[2].subtype, mined[2].tier) == (LEAD_BRAKING, 3)
    assert (mined[1].score, mined[2].score) == (pytest.approx(2.5), pytest.approx(5.0))
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 1


@pytest.mark.parametrize("swap", [False, True])
def test_within_a_tier_the_higher_score_wins(swap):
    on_time = track(40.0, -40.0 + STEPS)  # at (40, 0) with the ego: gap 0, score 28.3
    cars = [yielding_crosser(), on_time]
    if swap:
        cars.reverse()
    positions, valid = stack(ego_track(), *cars)
    sel = select_adversary("causal", positions, valid, 0, dt=DT)
    assert sel.conflict.agent == (1 if swap else 2)
    assert sel.conflict.score == pytest.approx(math.hypot(10.0, 10.0) / 0.5)


def test_yielders_first_ranks_a_crosser_that_passes_before_the_ego_last():
    # Row 1 crosses (40, 0) 1 s before the ego: a tier-1 conflict, which the paper's ranking
    # puts ahead of any tier-2 one; yielders_first ranks it after every other conflict.
    early = track(40.0, -30.0 + STEPS)  # at (40, 0) at index 30, the ego at index 40
    rear = track(-3.0 + 1.25 * STEPS, 0.0)  # tier 2: closes in from behind
    positions, valid = stack(ego_track(), early, rear)
    mined = by_agent(mine_conflicts(positions, valid, 0, dt=DT, strict=True))
    assert (mined[1].subtype, mined[1].tier) == (INTERSECTION, 1)
    assert mined[1].adversary_step < mined[1].ego_step
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 1
    picked = select_adversary("causal", positions, valid, 0, dt=DT, yielders_first=True)
    assert picked.conflict.agent == 2
    # A crosser that yields (arrives after the ego) keeps its tier-1 rank.
    positions, valid = stack(ego_track(), early, rear, yielding_crosser())
    picked = select_adversary("causal", positions, valid, 0, dt=DT, yielders_first=True)
    assert picked.conflict.agent == 3
    # Only passers-by: yielders_first still picks one of them.
    positions, valid = stack(ego_track(), early)
    picked = select_adversary("causal", positions, valid, 0, dt=DT, yielders_first=True)
    assert picked.conflict.agent == 1


def late_sprinter() -> np.ndarray:
    """North along x = 20: 5 m/s for 2 s, then 30 m/s: at (20, 0) at index 30, 1 s after the
    ego. Only its logged sprint gets it there: from 5 m/s it needs 15 m/s^2 over the 2 s
    until the ego arrives (2 (40 - 5 x 2) / 2^2)."""
    y = np.where(STEPS <= 20, -40.0 + 0.5 * STEPS, -30.0 + 3.0 * (STEPS - 20))
    return track(20.0, y)


def test_required_acceleration_is_what_takes_the_candidate_there_by_the_ego_arrival():
    positions, valid = stack(ego_track(), yielding_crosser(), late_sprinter())
    tracks = check_tracks(positions, valid, 0, speeds=None, dt=DT, min_joint_steps=5)
    mined = by_agent(mine_conflicts(positions, valid, 0, dt=DT))
    # The yielding crosser covers its 20 m in the ego's 2 s at its present 10 m/s.
    assert required_acceleration(tracks, mined[1], 0) == pytest.approx(0.0, abs=1e-9)
    assert reachable(tracks, mined[1], 0)
    assert required_acceleration(tracks, mined[2], 0) == pytest.approx(15.0)
    assert not reachable(tracks, mined[2], 0)
    # A follower on the ego's own line meets the ego's present place: 5 m in 0.2 s from
    # 12.5 m/s (its encounter is the ego's position at index 2).
    rear = track(-3.0 + 1.25 * STEPS, 0.0)
    positions, valid = stack(ego_track(), rear)
    tracks = check_tracks(positions, valid, 0, speeds=None, dt=DT, min_joint_steps=5)
    (conflict,) = mine_conflicts(positions, valid, 0, dt=DT)
    assert (conflict.ego_step, conflict.adversary_step) == (2, 4)
    assert required_acceleration(tracks, conflict, 0) == pytest.approx(125.0)


def test_reachable_first_ranks_a_conflict_the_candidate_cannot_make_last():
    positions, valid = stack(ego_track(), late_sprinter(), yielding_crosser())
    mined = by_agent(mine_conflicts(positions, valid, 0, dt=DT, strict=True))
    assert mined[1].tier == mined[2].tier == 1
    assert mined[1].score > mined[2].score  # the paper takes the sprinter
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 1
    picked = select_adversary("causal", positions, valid, 0, dt=DT, reachable_first=True)
    assert picked.conflict.agent == 2
    # Nothing reachable: the best unreachable conflict is still the adversary.
    positions, valid = stack(ego_track(), late_sprinter())
    picked = select_adversary("causal", positions, valid, 0, dt=DT, reachable_first=True)
    assert picked.conflict.agent == 1


def test_equal_tier_and_score_go_to_the_lower_row():
    positions, valid = stack(
        ego_track(), track(STEPS, 100.0), yielding_crosser(), yielding_crosser()
    )
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 2


def test_nothing_tiered_falls_back_with_a_reason():
    positions, valid = stack(ego_track(), track(STEPS, 100.0))  # far parallel car only
    sel = select_adversary("causal", positions, valid, 0, dt=DT)
    assert sel.conflict is None
    assert sel.num_candidates == 1
    assert "tier rules" in sel.fallback and "1 candidates" in sel.fallback


# ---------------------------------------------------------------- strict gates


def parked_in_path() -> tuple[np.ndarray, np.ndarray]:
    """A car parked at (20, 0), seen from index 15: only the moving gate can reject it.

    The ego reaches it at index 20: gap 0.5 s, d_min 0, not at the last step.
    """
    positions, valid = stack(ego_track(), track(20.0, 0.0))
    positions[1, :15] = np.nan
    valid[1, :15] = False
    return positions, valid


def test_parked_car_on_collision_course_needs_strict_off():
    positions, valid = parked_in_path()
    paper = select_adversary("causal", positions, valid, 0, dt=DT, strict=False)
    assert paper.conflict.agent == 1 and paper.conflict.tier == 1
    strict = select_adversary("causal", positions, valid, 0, dt=DT, strict=True)
    assert strict.conflict is None and "strict" in strict.fallback


def test_moving_gate_reads_given_speeds():
    positions, valid = parked_in_path()
    speeds = np.full(valid.shape, 5.0)  # e.g. a log whose positions are frozen but speeds not
    sel = select_adversary("causal", positions, valid, 0, speeds=speeds, dt=DT)
    assert sel.conflict.agent == 1


@pytest.mark.parametrize(("horizon", "picked"), [(50, False), (60, True)])
def test_encounter_on_the_last_step_is_rejected_under_strict(horizon, picked):
    # Crosser on x = 49 reaching y = 0 at index 49, with the ego: the last index when T = 50.
    positions, valid = stack(ego_track(), track(49.0, STEPS - 49.0))
    positions, valid = positions[:, :horizon], valid[:, :horizon]
    strict = select_adversary("causal", positions, valid, 0, dt=DT)
    assert (strict.conflict is not None) == picked
    paper = select_adversary("causal", positions, valid, 0, dt=DT, strict=False)
    assert paper.conflict.agent == 1 and paper.conflict.ego_step == 49


@pytest.mark.parametrize(
    ("ego_x", "cross_index"), [(40.0, 49), (49.0, 40)], ids=["adversary-last", "ego-last"]
)
def test_encounter_with_either_end_on_the_last_step_is_rejected_under_strict(ego_x, cross_index):
    # T = 50. The crosser on x = ego_x reaches y = 0 at cross_index; the ego is at x = ego_x
    # at index ego_x. One of the two ends is the last index, the gap is 0.9 s either way.
    positions, valid = stack(ego_track(), track(ego_x, STEPS - cross_index))
    positions, valid = positions[:, :50], valid[:, :50]
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert {c.ego_step, c.adversary_step} == {40, 49} and c.tier == 1
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict is None


@pytest.mark.parametrize(("stop", "picked"), [(16.0, False), (14.0, True)])
def test_min_distance_gate_under_strict(stop, picked):
    # Crosser heading north on x = 20 stops `stop` m short of the ego's path.
    positions, valid = stack(ego_track(), track(20.0, np.minimum(-40.0 + STEPS, -stop)))
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert c.min_distance == pytest.approx(stop) and c.tier == 1
    assert c.arrival_gap < 1.5
    strict = select_adversary("causal", positions, valid, 0, dt=DT)
    assert (strict.conflict is not None) == picked
    assert select_adversary("causal", positions, valid, 0, dt=DT, strict=False).conflict.agent == 1


@pytest.mark.parametrize(("step", "gap"), [(0.5, 2.0), (0.4, 3.0)])
def test_a_crossing_needs_only_the_tier_one_arrival_gap_under_strict(step, gap):
    # Same geometry as the planted crossing, but the crosser arrives 2 s (3 s) after the ego:
    # the strict gates keep a crossing that the guidance's arrival-time compression can
    # close; only tier 1's own gap (< 5 s) applies.
    late = track(20.0, -20.0 + step * STEPS)  # at (20, 0) at index 40 (50)
    positions, valid = stack(ego_track(), late)
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert c.arrival_gap == pytest.approx(gap) and c.tier == 1
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 1


def test_a_follower_closing_in_is_no_late_arrival_under_strict():
    # 30 m behind the ego at 20 m/s: it reaches the ego's start 1.5 s later (its headway) and
    # the ego itself at index 30. The gap gate is for crossing conflicts only.
    positions, valid = stack(ego_track(), track(-30.0 + 2.0 * STEPS, 0.0))
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.subtype, c.tier, c.ego_step, c.adversary_step) == (REAR_APPROACH, 2, 0, 15)
    assert c.arrival_gap == pytest.approx(1.5)
    assert select_adversary("causal", positions, valid, 0, dt=DT).conflict.agent == 1


# ---------------------------------------------------------------- validity


def test_four_jointly_valid_steps_is_not_a_candidate_five_is():
    positions, valid = stack(ego_track(), yielding_crosser())
    valid[1] = False
    valid[1, 26:36] = True  # the crosser is seen for 10 steps around the crossing ...
    valid[0, 26:32] = False  # ... but the ego only for the last 4 of them
    positions[~valid] = np.nan
    assert mine_conflicts(positions, valid, 0, dt=DT) == []
    sel = select_adversary("causal", positions, valid, 0, dt=DT)
    assert sel.conflict is None and sel.num_candidates == 0
    assert ">= 5 jointly valid" in sel.fallback

    valid[0, 31] = True
    positions[0, 31] = [31.0, 0.0]
    assert [c.agent for c in mine_conflicts(positions, valid, 0, dt=DT)] == [1]


def test_nan_at_a_valid_step_raises():
    positions, valid = crossing_scene()
    positions[3, 12, 1] = np.nan
    with pytest.raises(ValueError, match=r"positions is not finite.*agent 3, step 12"):
        select_adversary("causal", positions, valid, 0)
    with pytest.raises(ValueError, match="positions is not finite"):
        encounter(positions, valid, 0, 1)
    positions, valid = crossing_scene()
    speeds = np.ones(valid.shape)
    speeds[1, 5] = np.inf
    with pytest.raises(ValueError, match="speeds is not finite"):
        mine_conflicts(positions, valid, 0, speeds=speeds)


# ---------------------------------------------------------------- baselines


def parallel_scene() -> tuple[np.ndarray, np.ndarray]:
    """Ego plus: next lane 6.1 m away (row 1), 30 m ahead (row 2), 8 m behind (row 3), and a
    car parked 3 m away (row 4); all moving cars drive east at 10 m/s."""
    return stack(
        ego_track(),
        track(5.0 + STEPS, 3.5),
        track(30.0 + STEPS, 0.0),
        track(-8.0 + STEPS, 0.0),
        track(0.0, -3.0),
    )


def test_distance_picks_the_nearest_mover():
    positions, valid = parallel_scene()
    sel = select_adversary("distance", positions, valid, 0, dt=DT)
    assert sel.conflict.agent == 1 and sel.num_candidates == 4
    # Its conflict is still mined (following, far apart: no tier, but returned anyway).
    assert sel.conflict.type == FOLLOWING
    # Without the moving gate the parked car is nearest.
    assert (
        select_adversary("distance", positions, valid, 0, dt=DT, strict=False).conflict.agent == 4
    )


def test_distance_is_measured_at_the_first_jointly_valid_step():
    # The ego appears at index 10 (x = 10). A car driving west at 25 m/s is 40 m from the
    # ego's (unseen) start but 5.1 m from it at index 10, nearer than row 1 (6.1 m).
    positions, valid = parallel_scene()
    valid[0, :10] = False
    positions[0, :10] = np.nan
    positions[2] = track(40.0 - 2.5 * STEPS, 1.0)
    assert select_adversary("distance", positions, valid, 0, dt=DT).conflict.agent == 2


def test_ttc_picks_the_collision_course_over_a_nearer_car_moving_away():
    away = track(3.0 + 1.5 * STEPS, 4.0)  # 5 m away, 15 m/s east in the next lane
    crosser = track(20.0, -20.0 + STEPS)  # 28 m away, meets the ego at (20, 0) in 2 s
    positions, valid = stack(ego_track(), away, crosser)
    sel = select_adversary("ttc", positions, valid, 0, dt=DT)
    assert sel.conflict.agent == 2
    assert select_adversary("distance", positions, valid, 0, dt=DT).conflict.agent == 1
    # The chosen agent's conflict is the mined encounter.
    mined = encounter(positions, valid, 0, 2, dt=DT)
    assert (sel.conflict.ego_step, sel.conflict.adversary_step) == (
        mined.ego_step,
        mined.adversary_step,
    )
    assert (sel.conflict.score, sel.conflict.tier, sel.conflict.weight) == (
        mined.score,
        mined.tier,
        mined.weight,
    )
    np.testing.assert_array_equal(sel.conflict.conflict_point, mined.conflict_point)


def test_ttc_uses_the_given_boxes():
    # A car in the next lane (y = 3) drifting towards the ego at 1 m/s: with the default
    # 2.0 m wide boxes the 1 m clearance closes in ~1 s, before the crosser (~1.7 s) arrives.
    # With 0.2 m wide boxes it needs ~2.8 s, so the crosser has the smaller TTC.
    side = track(STEPS, 3.0 - 0.1 * STEPS)
    crosser = track(20.0, -20.0 + STEPS)
    positions, valid = stack(ego_track(), side, crosser)
    assert select_adversary("ttc", positions, valid, 0, dt=DT).conflict.agent == 1
    yaws = np.zeros(valid.shape)
    yaws[2] = np.pi / 2
    narrow = np.array([[4.5, 0.2], [4.5, 0.2], [4.5, 2.0]])
    sel = select_adversary("ttc", positions, valid, 0, extents=narrow, yaws=yaws, dt=DT)
    assert sel.conflict.agent == 2


def test_ttc_reads_the_given_yaws():
    # A car pacing the ego 3 m to the side: heading east its box clears the ego's by 1 m
    # (TTC inf), turned across the lane (yaw pi/2) it overlaps it already (TTC 0).
    side = track(STEPS, 3.0)
    crosser = track(20.0, -20.0 + STEPS)
    positions, valid = stack(ego_track(), side, crosser)
    assert select_adversary("ttc", positions, valid, 0, dt=DT).conflict.agent == 2
    yaws = np.zeros(valid.shape)
    yaws[1:] = np.pi / 2
    assert select_adversary("ttc", positions, valid, 0, yaws=yaws, dt=DT).conflict.agent == 1


def test_ttc_without_any_collision_falls_back_to_distance():
    positions, valid = stack(
        ego_track(), track(30.0 + 1.5 * STEPS, 4.0), track(3.0 + 1.5 * STEPS, -4.0)
    )
    assert select_adversary("ttc", positions, valid, 0, dt=DT).conflict.agent == 2


def test_random_is_reproducible_and_covers_the_moving_pool():
    positions, valid = parallel_scene()

    def pick(seed):
        rng = np.random.default_rng(seed)
        return select_adversary("random", positions, valid, 0, dt=DT, rng=rng).conflict.agent

    assert [pick(7) for _ in range(5)] == [pick(7)] * 5
    assert {pick(seed) for seed in range(40)} == {1, 2, 3}  # never the ego or the parked car


@pytest.mark.parametrize("method", METHODS)
def test_no_candidate_gives_no_conflict_and_a_reason(method):
    positions, valid = stack(ego_track(), yielding_crosser())
    valid[1, 3:] = False  # 3 valid steps
    positions[1, 3:] = np.nan
    sel = select_adversary(method, positions, valid, 0, dt=DT, rng=np.random.default_rng(0))
    assert (sel.method, sel.conflict, sel.num_candidates) == (method, None, 0)
    assert "jointly valid" in sel.fallback


@pytest.mark.parametrize("method", ["random", "distance", "ttc"])
def test_baselines_without_a_mover_give_no_conflict_under_strict(method):
    positions, valid = stack(ego_track(), track(30.0, 4.0))
    sel = select_adversary(method, positions, valid, 0, dt=DT, rng=np.random.default_rng(0))
    assert sel.conflict is None and "moving" in sel.fallback and sel.num_candidates == 1


# ---------------------------------------------------------------- bad input


def test_bad_input_is_a_clear_value_error():
    positions, valid = crossing_scene()
    with pytest.raises(ValueError, match=r"unknown .*'closest'.*causal"):
        select_adversary("closest", positions, valid, 0)
    with pytest.raises(ValueError, match="needs rng"):
        select_adversary("random", positions, valid, 0)
    with pytest.raises(ValueError, match=r"valid must be \[N, T\]"):
        select_adversary("causal", positions, valid[:, :-1], 0)
    with pytest.raises(ValueError, match=r"positions must be \[N, T, 2\]"):
        mine_conflicts(positions[..., :1], valid, 0)
    with pytest.raises(ValueError, match="speeds must be"):
        mine_conflicts(positions, valid, 0, speeds=np.ones((4, 3)))
    with pytest.raises(ValueError, match="eligible must be"):
        select_adversary("causal", positions, valid, 0, eligible=np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match="extents must be"):
        select_adversary("ttc", positions, valid, 0, extents=np.ones((4, 3)))
    with pytest.raises(ValueError, match="ego index 4 out of range for 4 agents"):
        select_adversary("causal", positions, valid, 4)
    with pytest.raises(ValueError, match="agent 0 is the ego"):
        encounter(positions, valid, 0, 0)


def test_a_pair_closest_right_now_is_rejected_under_strict():
    # A car beside the ego at index 0 that turns away: the closest encounter is "now" for
    # both, so no conflict lies ahead; the paper's rule still tiers it (intersection, gap 0).
    diverging = np.stack([STEPS * 0.7, 3.0 + STEPS * 0.7], -1)
    positions, valid = stack(ego_track(), diverging)
    c = encounter(positions, valid, 0, 1, dt=DT)
    assert (c.ego_step, c.adversary_step, c.tier) == (0, 0, 1)
    assert select_adversary("causal", positions, valid, 0, dt=DT, strict=False).conflict.agent == 1
    strict = select_adversary("causal", positions, valid, 0, dt=DT)
    assert strict.conflict is None and "strict" in strict.fallback
