"""Scene metrics on tiny hand-made scenes with known answers."""

import dataclasses
import json
import math

import conftest
import numpy as np
import pytest
from highway_env.road.road import RoadNetwork

from counterscene_env import metrics
from counterscene_env.scene import RoadMap

DT = 0.1
HIST = 3  # history steps; current_index = HIST - 1, the rollout starts at step HIST
CAR = (4.0, 2.0)


@pytest.fixture(scope="module")
def road():
    # Two 4 m lanes along +x from x = 0 to 200 m: drivable for y in [-2, 6].
    return RoadMap.from_network(RoadNetwork.straight_road_network(2, length=200))


def make_scene(road, positions, yaws=None, speeds=None, valid=None, types=None, ids=None):
    n = np.asarray(positions).shape[0]
    kw = {"agent_types": np.array(types)} if types is not None else {}
    if ids is not None:
        kw["agent_ids"] = np.array(ids)
    return conftest.make_scene(
        positions,
        yaws,
        speeds,
        np.array([CAR] * n),
        valid,
        road=road,
        dt=DT,
        scenario_id="test",
        current_index=HIST - 1,
        **kw,
    )


def crash_scene(road, steps=HIST + 100):
    """Ego at 10 m/s along y = 0 (x = t m at step t) into a stopped car at x = 30.5 m.

    The boxes first overlap when the ego's front (x_t + 2) passes the obstacle's rear (28.5):
    at step 27, rollout step 24, i.e. 2.5 s into the rollout (the third second).
    A third car cruises alongside in the other lane and never touches anyone.
    """
    t = np.arange(steps, dtype=float)
    pos = np.zeros((3, steps, 2))
    pos[0, :, 0] = t
    pos[1, :, 0] = 30.5
    pos[2, :, 0], pos[2, :, 1] = t + 5.0, 4.0
    speeds = np.stack([np.full(steps, 10.0), np.zeros(steps), np.full(steps, 10.0)])
    return make_scene(road, pos, speeds=speeds, ids=["ego", "obstacle", "neighbour"])


# ---------------------------------------------------------------------- CR
def test_crash_at_known_step_per_second_cr(road):
    scene = crash_scene(road)
    hits = metrics.ego_collision_steps(scene)
    assert hits.shape == (100,)
    assert np.flatnonzero(hits)[0] == 24
    res = metrics.evaluate_scene(scene, adversary="obstacle")
    assert [res["per_second"][str(h)]["CR"] for h in range(1, 11)] == [0.0, 0.0] + [1.0] * 8
    assert res["cr"] == 1.0 and res["cr_all_agents"] == 1.0 and res["cr_non_ego"] == 0.0
    assert res["cr_ego_adversary"] == 1.0
    assert res["min_ttc"] == 0.0 and res["min_clearance_adversary"] == 0.0
    assert metrics.ego_collided(scene, 2.4) is False and metrics.ego_collided(scene, 2.5)
    other = metrics.evaluate_scene(scene, adversary=2)
    assert other["cr_ego_adversary"] == 0.0 and other["adversary_id"] == "neighbour"
    with pytest.raises(ValueError, match="nobody"):
        metrics.evaluate_scene(scene, adversary="nobody")


def test_adversary_per_step_counts_every_adversary_from_its_choice(road):
    """A closed loop that re-selects at its replans (``selection_source="model"``) hands
    one adversary per step: a contact with any agent that was the adversary counts, from
    the step it was chosen on, and the record names them all."""
    scene = crash_scene(road)  # the ego meets "obstacle" (row 1) at rollout step 24
    T = metrics.rollout_steps(scene)
    chosen_early = ["neighbour"] * 10 + ["obstacle"] * 10 + ["neighbour"] * (T - 20)
    res = metrics.evaluate_scene(scene, adversary=chosen_early)
    assert res["cr_ego_adversary"] == 1.0  # the former adversary hit the ego
    assert res["adversary_ids"] == ["neighbour", "obstacle"]
    assert res["adversary_id"] == "neighbour"  # the latest one
    assert [res["per_second"][str(h)]["CR_adv"] for h in (2, 3)] == [0.0, 1.0]
    assert res["min_clearance_adversary"] == 0.0
    chosen_late = [None] * 60 + ["obstacle"] * (T - 60)  # only after the ego drove through
    late = metrics.evaluate_scene(scene, adversary=chosen_late)
    assert late["cr_ego_adversary"] == 0.0 and late["adversary_ids"] == ["obstacle"]
    never = metrics.evaluate_scene(scene, adversary=[None] * T)
    assert math.isnan(never["cr_ego_adversary"]) and never["adversary_id"] is None
    assert metrics.evaluate_scene(scene, adversary=["obstacle"] * T) == metrics.evaluate_scene(
        scene, adversary="obstacle"
    ) | {"adversary_ids": ["obstacle"]}
    with pytest.raises(ValueError, match="adversary: one entry per rollout step"):
        metrics.evaluate_scene(scene, adversary=["obstacle"] * (T - 1))


def test_rollout_cut_before_crash_ttc_and_clearance(road):
    scene = crash_scene(road, steps=HIST + 20)  # last step 22: ego front at 24, gap 4.5 m
    res = metrics.evaluate_scene(scene, adversary="obstacle")
    assert res["cr"] == 0.0 and res["per_second"]["10"]["CR"] == 0.0
    assert res["min_clearance_adversary"] == pytest.approx(4.5)
    # Closing 4.5 m at 10 m/s: contact at 0.45 s, first 0.1 s sample after it is 0.5 s.
    assert res["min_ttc"] == pytest.approx(0.5)
    assert math.isnan(res["per_second"]["3"]["FDE"])  # no factual given


def test_invalid_intruder_and_history_overlap_do_not_count(road):
    steps = HIST + 20
    pos = np.zeros((2, steps, 2))  # both parked at the origin, on top of each other
    valid = np.ones((2, steps), bool)
    valid[1, HIST:] = False  # the intruder exists only in the history
    scene = make_scene(road, pos, valid=valid)
    assert not metrics.ego_collision_steps(scene).any()
    assert metrics.evaluate_scene(scene)["cr_all_agents"] == 0.0
    valid[1, HIST + 5] = True  # one rollout step, within the first second
    res = metrics.evaluate_scene(make_scene(road, pos, valid=valid))
    assert res["per_second"]["1"]["CR"] == 1.0 and res["cr_non_ego"] == 0.0


def test_non_ego_collision_counts_only_in_all_agent_rates(road):
    steps = HIST + 10
    pos = np.zeros((3, steps, 2))
    pos[0, :, 1] = 4.0  # ego alone in the other lane
    pos[2, :, 0] = 3.0  # agents 1 and 2 overlap by 1 m
    res = metrics.evaluate_scene(make_scene(road, pos))
    assert res["cr"] == 0.0 and res["cr_non_ego"] == 1.0 and res["cr_all_agents"] == 1.0
    assert math.isinf(res["min_ttc"])


def test_new_vehicle_collisions_are_the_rollouts_non_ego_overlaps_the_log_does_not_have(road):
    """Row 2 runs into row 1 in the rollout only; rows 1 and 3 overlap throughout, in the log
    too, and the ego (row 0) overlaps row 3. Only (1, 2) is new, from rollout step 5."""
    from counterscene_env.metrics.safety import new_vehicle_collisions

    steps = HIST + 10
    pos = np.zeros((4, steps, 2))
    pos[0, :, 0] = 20.0  # the ego, on row 3
    pos[3, :, 0] = 20.0 + 3.0  # row 3, overlapping the ego and ...
    pos[1, :, 0] = 20.0 + 6.0  # ... row 1 (boxes 4 m long, 3 m apart)
    pos[2, :, 0] = 40.0  # row 2, clear of everyone in the log
    log = make_scene(road, pos)
    sim_pos = pos.copy()
    # In the rollout it closes in at 20 m/s and stops 2 m from row 1, from rollout step 5 on.
    sim_pos[2, HIST:, 0] = np.maximum(28.0, 40.0 - 2.0 * np.arange(1, 11))
    assert new_vehicle_collisions(make_scene(road, sim_pos), log) == [(1, 2, 5)]
    assert new_vehicle_collisions(log, log) == []


def test_non_ego_cr_new_leaves_out_the_pairs_that_overlap_in_the_log_too(road):
    """The log's own overlapping pair (rows 1 and 3) is a non-ego collision, not a new one;
    row 2 running into row 1 in the rollout is both. The log's rows may come in any order:
    agents pair up by id."""
    steps = HIST + 10
    pos = np.zeros((4, steps, 2))
    pos[0, :, 1] = 10.0  # the ego, clear of everyone
    pos[3, :, 0] = 3.0  # rows 1 and 3 overlap throughout, in the log too
    pos[2, :, 0] = 20.0
    ids = ["ego", "a", "b", "c"]
    order = [2, 0, 3, 1]  # the log's rows, shuffled
    log = make_scene(road, pos[order], ids=[ids[i] for i in order])
    log = log.replace(ego_index=1)
    own = metrics.evaluate_scene(make_scene(road, pos, ids=ids), log)
    assert own["cr_non_ego"] == 1.0 and own["cr_non_ego_new"] == 0.0
    assert math.isnan(metrics.evaluate_scene(make_scene(road, pos, ids=ids))["cr_non_ego_new"])
    sim_pos = pos.copy()
    sim_pos[2, HIST:, 0] = np.maximum(2.0, 20.0 - 3.0 * np.arange(1, 11))  # into row 1
    new = metrics.evaluate_scene(make_scene(road, sim_pos, ids=ids), log)
    assert new["cr_non_ego"] == 1.0 and new["cr_non_ego_new"] == 1.0
    assert new["cr"] == 0.0


# ---------------------------------------------------------------------- HBR
def straight_motion(v0, acc, yaw, steps=HIST + 30):
    """Positions, yaws and speeds of a car along heading ``yaw`` with constant acceleration."""
    tau = np.arange(steps) * DT
    s = v0 * tau + 0.5 * acc * tau**2
    pos = np.stack([100 + s * math.cos(yaw), s * math.sin(yaw)], -1)
    return pos, np.full(steps, yaw), v0 + acc * tau


def single_car(road, v0, acc, yaw):
    pos, yaws, speeds = straight_motion(v0, acc, yaw)
    return make_scene(road, pos[None], yaws=yaws[None], speeds=speeds[None])


def test_eastbound_braking_flagged_by_signed_hbr_not_by_paper_formula(road):
    scene = single_car(road, 20.0, -5.0, 0.0)
    acc, valid = metrics.longitudinal_acceleration(scene)
    np.testing.assert_allclose(acc[valid], -5.0, atol=1e-6)
    assert metrics.hbr_ego(scene) == 1.0
    assert metrics.hbr_ego(scene, source="speed") == 1.0
    assert metrics.hbr_all(scene) == 1.0
    assert metrics.hbr_paper(scene) == 0.0  # ||a|| cos(0) = +5: the paper misses it
    assert metrics.evaluate_scene(scene)["per_second"]["1"]["HBR"] == 1.0


def test_ego_peak_deceleration_is_its_strongest_braking_whatever_the_heading(road):
    # 20 m/s braking at 5 m/s^2 for 3 s, westbound: the signed deceleration, not |a| cos psi.
    assert metrics.evaluate_scene(single_car(road, 20.0, -5.0, math.pi))[
        "ego_peak_deceleration"
    ] == pytest.approx(5.0, abs=1e-6)
    # A car that only speeds up never braked.
    assert metrics.evaluate_scene(single_car(road, 10.0, 2.0, 0.0))["ego_peak_deceleration"] == 0.0


def test_westbound_accelerating_car_flagged_only_by_paper_formula(road):
    scene = single_car(road, 10.0, 5.0, math.pi)
    assert metrics.hbr_ego(scene) == 0.0
    assert metrics.hbr_ego(scene, source="speed") == 0.0
    assert metrics.hbr_paper(scene) == 1.0  # ||a|| cos(pi) = -5 < -3: a false alarm
    res = metrics.evaluate_scene(scene)
    assert res["hbr_ego"] == 0.0 and res["hbr_paper"] == 1.0


def test_hbr_all_fraction_ignores_invalid_and_non_vehicles(road):
    brake, yb, _ = straight_motion(20.0, -5.0, 0.0)
    cruise, yc, _ = straight_motion(20.0, 0.0, 0.0)
    lane = np.array([0.0, 4.0])  # m, one lane to the left
    pos = np.stack([brake, cruise + lane, brake + 2 * lane, brake + 3 * lane])
    yaws = np.stack([yb, yc, yb, yb])
    valid = np.ones(pos.shape[:2], bool)
    valid[2, HIST:] = False  # an invalid vehicle (braking if it were scored)
    scene = make_scene(
        road, pos, yaws=yaws, valid=valid, types=["vehicle", "vehicle", "vehicle", "pedestrian"]
    )
    assert metrics.hbr_all(scene) == pytest.approx(0.5)
    assert metrics.evaluate_scene(scene)["hbr_all"] == pytest.approx(0.5)


def test_smoothing_removes_a_one_step_position_glitch(road):
    pos, yaws, speeds = straight_motion(10.0, 0.0, 0.0)
    pos[HIST + 10, 0] += 0.05  # 5 cm label jitter: second difference of -2 * 0.05 / dt^2
    scene = make_scene(road, pos[None], yaws=yaws[None], speeds=speeds[None])
    assert metrics.hbr_ego(scene) == 1.0
    assert metrics.hbr_ego(scene, smooth=0.5) == 0.0
    assert metrics.evaluate_scene(scene, smooth=0.5)["hbr_ego"] == 0.0


@pytest.mark.parametrize("source", ["position", "speed"])
def test_braking_in_the_first_rollout_step_is_hard_braking(road, source):
    """The step from "now" into the rollout is the rollout's first acceleration: an ego that
    brakes at 5 m/s^2 for that one step only is flagged, as the env's per-step
    ``info["hard_braking"]`` flags it (its samples read the speed before and after)."""
    steps = HIST + 30
    speeds = np.full(steps, 20.0)
    speeds[HIST:] = 19.5  # HIST is the first rollout step: 0.5 m/s less over 0.1 s
    x = np.concatenate([[0.0], np.cumsum(speeds[1:] * DT)])
    pos = np.stack([100 + x, np.zeros(steps)], -1)
    scene = make_scene(road, pos[None], yaws=np.zeros((1, steps)), speeds=speeds[None])
    assert scene.current_index == HIST - 1
    assert metrics.hbr_ego(scene, horizon=1.0, source=source) == 1.0
    acc, valid = metrics.longitudinal_acceleration(scene, source)
    assert valid[0, 0] and acc[0, 0] == pytest.approx(-5.0)
    if source == "position":
        rec = metrics.evaluate_scene(scene)
        assert rec["hbr_ego"] == 1.0 and rec["per_second"]["1"]["DEC"] == pytest.approx(5.0)


def test_a_steady_turn_is_no_braking_whatever_the_heading_annotation(road):
    """A car round a 12 m circle at a steady 9 m/s (6.75 m/s^2 sideways) never brakes, even
    with its heading 0.1 rad off its course (highway-env's bicycle drives at a slip angle; a
    log's heading is a box annotation). Read against the heading, the sideways acceleration
    leaked into the longitudinal one as hard braking."""
    steps, radius, speed = HIST + 30, 12.0, 9.0
    angle = np.arange(steps) * DT * speed / radius
    pos = np.stack([radius * np.cos(angle), radius * np.sin(angle)], -1) + np.array([100.0, 0.0])
    yaws = angle + np.pi / 2 + 0.1  # the course plus a slip angle
    scene = make_scene(road, pos[None], yaws=yaws[None], speeds=np.full((1, steps), speed))
    acc, valid = metrics.longitudinal_acceleration(scene)
    assert valid[0].all() and np.abs(acc[0]).max() < 0.05
    assert metrics.hbr_ego(scene) == 0.0 and metrics.evaluate_scene(scene)["hbr_ego"] == 0.0


@pytest.mark.parametrize("source", ["position", "speed"])
def test_braking_at_exactly_the_threshold_is_not_hard_braking(road, source):
    """HBR counts braking *below* -3 m/s^2: a planner that brakes at exactly 3 m/s^2 is not
    flagged at some steps and not at others as floats round its finite differences."""
    at = single_car(road, 25.0, -3.0, 0.3)
    acc, valid = metrics.longitudinal_acceleration(at, source)
    assert np.abs(acc[valid] + 3.0).max() < 1e-6  # -3 up to rounding, both ways
    assert metrics.hbr_ego(at, source=source) == 0.0
    assert metrics.hbr_ego(single_car(road, 25.0, -3.01, 0.3), source=source) == 1.0
    assert not metrics.is_hard_braking(-3.0 - 1e-9) and metrics.is_hard_braking(-3.001)


def test_hbr_within_horizon_only(road):
    cruise, yaws, _ = straight_motion(20.0, 0.0, 0.0, steps=HIST + 50)
    tau = np.arange(30) * DT
    cruise[HIST + 20 :, 0] = cruise[HIST + 20, 0] + 20 * tau - 2.5 * tau**2  # brake from 2 s
    scene = make_scene(road, cruise[None], yaws=yaws[None])
    res = metrics.evaluate_scene(scene, horizons=(1, 2, 3))
    assert [res["per_second"][h]["HBR"] for h in ("1", "2", "3")] == [0.0, 0.0, 1.0]


# ---------------------------------------------------------------------- ORR
def test_car_leaving_the_road_known_orr(road):
    steps = HIST + 100
    x = 10 + 0.5 * np.arange(steps)
    pos = np.zeros((4, steps, 2))
    pos[:, :, 0] = x
    # The ego swerves off the road (at most 9 m a step) for the second half of the rollout.
    pos[0, HIST + 48 : HIST + 51, 1] = 5.0, 6.0, 15.0  # 6 m: the road's edge, still on it
    pos[0, HIST + 51 :, 1] = 20.0
    pos[1, :, 1] = 4.0  # on the road throughout
    pos[2, :, 1] = 50.0  # a pedestrian far off the road: not a vehicle, not scored
    pos[3, :, 1] = 50.0  # a vehicle off the road only while invalid
    valid = np.ones((4, steps), bool)
    valid[3, HIST:] = False
    types = ["vehicle", "vehicle", "pedestrian", "vehicle"]
    scene = make_scene(road, pos, valid=valid, types=types)
    assert metrics.off_road_rate(scene) == pytest.approx(0.25)
    res = metrics.evaluate_scene(scene)
    assert res["orr"] == pytest.approx(0.25)
    assert res["per_second"]["5"]["ORR"] == 0.0
    assert res["per_second"]["6"]["ORR"] == pytest.approx(10 / 120)
    assert res["per_second"]["10"]["ORR"] == pytest.approx(0.25)


def test_orr_counts_only_the_steps_inside_a_cropped_maps_extent(road):
    """A real map is a crop: a car beyond its extent is neither on nor off its roads, so the
    rate leaves those steps out of its denominator too (they counted as on the road, which
    diluted the rate of a car that drove off inside the crop)."""
    import shapely

    cropped = dataclasses.replace(road, extent=shapely.box(0.0, -30.0, 60.0, 30.0))
    steps = HIST + 100
    pos = np.zeros((2, steps, 2))
    pos[:, :, 0] = 10 + 0.5 * np.arange(steps)  # x from 10 m: leaves the crop after 50 m
    pos[0, :, 1] = 20.0  # off the road (y beyond 6 m) the whole way
    pos[1, :, 1] = 2.0  # on the road
    scene = make_scene(cropped, pos)
    inside = int((pos[0, HIST:, 0] < 60.0).sum())
    assert 0 < inside < 100
    assert metrics.off_road_rate(scene) == pytest.approx(0.5)  # inside: 1 of the 2 cars
    rec = metrics.evaluate_scene(scene, factual=scene)
    assert rec["orr"] == pytest.approx(0.5) and rec["orr_log"] == pytest.approx(0.5)
    assert metrics.off_road_rate(make_scene(road, pos)) == pytest.approx(0.5)  # no crop


def test_the_logs_own_off_road_share_is_the_reference_for_the_rollouts(road):
    # A car parked in a lot the map lacks (off the road in the log and the rollout alike), and
    # a car that the rollout drives off the road for the second half where its log stays on.
    steps = HIST + 100
    x = 10 + 0.5 * np.arange(steps)
    log = np.zeros((3, steps, 2))
    log[0, :, 0] = x  # the ego, on the road
    log[1] = 50.0, 20.0  # parked off the road
    log[2, :, 0], log[2, :, 1] = x, 4.0
    ids = ["ego", "parked", "mover"]
    factual = make_scene(road, log, ids=ids)
    sim_pos = log.copy()
    sim_pos[2, HIST + 47 : HIST + 50, 1] = 7.0, 11.0, 15.0  # off from 6 m, 4 m a step
    sim_pos[2, HIST + 50 :, 1] = 20.0
    sim = make_scene(road, sim_pos, ids=ids)
    res = metrics.evaluate_scene(sim, factual)
    assert res["orr_log"] == pytest.approx(1 / 3)  # the parked car's 100 of 300 steps
    assert res["orr"] == pytest.approx(153 / 300)
    assert res["orr_parked"] == 1.0
    assert res["orr_moving_log"] == 0.0
    assert res["orr_moving"] == pytest.approx(53 / 200)
    alone = metrics.evaluate_scene(sim)  # no log: no reference
    assert math.isnan(alone["orr_log"]) and math.isnan(alone["orr_moving_log"])
    assert alone["orr"] == res["orr"]


# ---------------------------------------------------------------------- ADE / FDE
def ade_pair(road):
    """A factual log and a sim whose non-ego cars are 1 m off it (the ego 5 m: not scored)."""
    steps = HIST + 100
    x = np.arange(steps, dtype=float)
    fac_pos = np.zeros((5, steps, 2))
    fac_pos[:, :, 0] = x
    fac_pos[:, :, 1] = [[0.0], [4.0], [8.0], [12.0], [16.0]]
    factual = make_scene(road, fac_pos, ids=["ego", "c1", "c2", "c3", "c4"])
    sim_pos = fac_pos.copy()
    sim_pos[:, HIST:, 1] += [[5.0], [1.0], [1.0], [1.0], [3.0]]
    valid = np.ones((5, steps), bool)
    valid[3, HIST:] = False  # c3 vanishes in the sim: ignored, not a 12 m error
    valid[4, HIST + 15 :] = False  # c4 lives for 1.5 s of the rollout, 3 m off
    # Rows permuted relative to the factual log: alignment is by id.
    order = [0, 2, 1, 4, 3]
    sim = make_scene(
        road,
        sim_pos[order],
        valid=valid[order],
        types=["vehicle", "vehicle", "vehicle", "vehicle", "vehicle"],
        ids=[factual.agent_ids[i] for i in order],
    )
    return sim, factual


def test_ade_fde_of_a_one_metre_offset(road):
    sim, factual = ade_pair(road)
    # c4 counts while valid: ADE over agents (1, 1, 3); FDE_1 at step 9 includes it.
    assert metrics.ade_fde(sim, factual, 1.0) == pytest.approx((5 / 3, 5 / 3))
    assert metrics.ade_fde(sim, factual, 2.0) == pytest.approx((5 / 3, 1.0))
    res = metrics.evaluate_scene(sim, factual)
    for h in range(2, 11):
        assert res["per_second"][str(h)]["FDE"] == pytest.approx(1.0)
    one_off = sim.select_agents([0, 1, 2])  # only the cars exactly 1 m off
    res = metrics.evaluate_scene(one_off, factual)
    for h in range(1, 11):
        assert res["per_second"][str(h)]["ADE"] == pytest.approx(1.0)
        assert res["per_second"][str(h)]["FDE"] == pytest.approx(1.0)


def test_ade_nan_without_agents_or_factual_and_missing_ids_raise(road):
    sim, factual = ade_pair(road)
    ego_only = sim.select_agents([0])
    assert all(math.isnan(v) for v in metrics.ade_fde(ego_only, factual, 3.0))
    res = metrics.evaluate_scene(sim)
    assert math.isnan(res["per_second"]["1"]["ADE"]) and math.isnan(res["per_second"]["1"]["FDE"])
    short_factual = factual.select_agents([0, 1, 2])
    with pytest.raises(ValueError, match=r"c3.*c4|c4.*c3"):
        metrics.evaluate_scene(sim, short_factual)


# ---------------------------------------------------------------------- records and aggregate
def test_a_scene_with_no_rollout_has_no_collision_rate_rather_than_zero(road):
    """ "now" at the log's last step: no step to count a collision in, so the rates are NaN
    (docs/metrics.md: nothing to measure is NaN, never 0)."""
    scene = crash_scene(road, steps=HIST)
    res = metrics.evaluate_scene(scene, adversary="obstacle")
    assert res["rollout_s"] == 0.0
    for key in ("cr", "cr_all_agents", "cr_non_ego", "cr_ego_adversary"):
        assert math.isnan(res[key]), key
    assert math.isnan(res["per_second"]["1"]["CR"]) and math.isnan(res["per_second"]["1"]["CR_adv"])


def test_evaluate_scene_record_is_json_and_complete(road):
    sim, factual = ade_pair(road)
    res = metrics.evaluate_scene(sim, factual, adversary="c1")
    text = json.dumps(res)
    back = json.loads(text)
    assert set(back) == {
        "scenario_id",
        "rollout_s",
        "ends_in_ego_collision",
        "adversary_id",
        "adversary_ids",
        "per_second",
        *metrics.SCENE_KEYS,
    }
    assert list(back["per_second"]) == [str(h) for h in range(1, 11)]
    assert set(back["per_second"]["4"]) == {
        *metrics.PER_SECOND_KEYS,
        *metrics.EXTRA_PER_SECOND_KEYS,
    }
    assert back["rollout_s"] == pytest.approx(10.0)
    agg = metrics.aggregate([res, back])
    assert agg["per_second"]["4"]["ADE"] == pytest.approx(res["per_second"]["4"]["ADE"])


def test_aggregate_groups_are_means_of_seconds():
    def record(offset, nan_first=False):
        per = {}
        for h in range(1, 11):
            v = math.nan if (nan_first and h == 1) else h + offset
            per[str(h)] = {"ADE": v, "FDE": 2 * v, "ORR": 0.0, "HBR": 1.0, "CR": float(h > 5)}
        return {"per_second": per, "cr": 1.0, "min_ttc": math.inf, "hbr_paper": math.nan}

    agg = metrics.aggregate([record(0), record(2, nan_first=True), record(0.0)])
    assert agg["num_scenes"] == 3
    # second 1: NaN ignored -> mean(1, 1); others: mean(h, h + 2, h)
    assert agg["per_second"]["1"]["ADE"] == pytest.approx(1.0)
    assert agg["per_second"]["2"]["ADE"] == pytest.approx(8 / 3)
    means = {h: agg["per_second"][str(h)]["ADE"] for h in range(1, 11)}
    assert agg["groups"]["1-4s"]["ADE"] == pytest.approx(np.mean([means[h] for h in (1, 2, 3, 4)]))
    assert agg["groups"]["5-7s"]["ADE"] == pytest.approx(np.mean([means[h] for h in (5, 6, 7)]))
    assert agg["groups"]["8-10s"]["ADE"] == pytest.approx(np.mean([means[h] for h in (8, 9, 10)]))
    assert agg["groups"]["5-7s"]["CR"] == pytest.approx(2 / 3)
    assert agg["overall"]["cr"] == 1.0 and math.isinf(agg["overall"]["min_ttc"])
    assert math.isnan(agg["overall"]["hbr_paper"])
    with pytest.raises(ValueError):
        metrics.aggregate([])


def test_horizons_an_episode_never_reached_have_no_value_in_the_tables():
    """An episode on a short log ends with the log; its record carries the rollout's values
    on, but the stress tables (as paper-tables) count only episodes that reached a horizon:
    one that ended at 3 s without a collision is not collision-free "at 10 s"."""
    from counterscene_env.report.tables import horizon_table, per_second_table

    def record(rollout, cr):
        per = {
            str(h): {"ADE": 1.0, "FDE": 1.0, "ORR": 0.0, "HBR": 0.0, "CR": cr} for h in range(1, 11)
        }
        return {"per_second": per, "rollout_s": rollout, "cr": cr}

    short, long = record(3.0, 0.0), record(10.0, 1.0)
    agg = metrics.aggregate([short, long])
    assert agg["per_second"]["3"]["CR"] == pytest.approx(0.5)
    assert agg["per_second"]["4"]["CR"] == 1.0 and agg["groups"]["8-10s"]["CR"] == 1.0
    assert per_second_table([short, long])["10"]["CR"].n == 1
    assert horizon_table([short, long])["8-10s"]["CR"].value == 1.0
    assert metrics.horizon_values(short, "3") and metrics.horizon_values(short, "4") == {}


def test_an_episode_that_ended_in_a_collision_counts_as_collided_at_every_later_horizon():
    """``terminate_on_collision`` ends an episode at its crash: CR within 8 s is 1 for it, not
    an episode left out of the 8 s column (which biased the horizon CR toward 0). Its ADE has
    no 8 s trajectory behind it and stays out."""
    from counterscene_env.report.tables import per_second_table

    def record(rollout, cr, crashed):
        per = {str(h): {"ADE": 1.0, "FDE": 1.0, "CR": cr, "HBR": 0.0} for h in range(1, 11)}
        return {"per_second": per, "rollout_s": rollout, "ends_in_ego_collision": crashed}

    crashed, ok = record(3.0, 1.0, True), record(10.0, 0.0, False)
    assert metrics.horizon_values(crashed, "8") == {"CR": 1.0, "HBR": 0.0}
    agg = metrics.aggregate([crashed, ok])
    assert agg["per_second"]["8"]["CR"] == pytest.approx(0.5)
    assert agg["per_second"]["8"]["ADE"] == pytest.approx(1.0)  # the crashed one is left out
    table = per_second_table([crashed, ok])["10"]
    assert table["CR"].n == 2 and table["ADE"].n == 1
    ended_with_log = record(3.0, 0.0, False)
    assert metrics.horizon_values(ended_with_log, "8") == {}


def test_a_log_that_ends_in_the_collision_does_not_count_past_its_end(road):
    """A short real log ends every row's episode on it alike. A stress episode (never
    terminated) whose log runs out while the ego still overlaps the car it hit is no episode
    at later horizons: counting the crashed ones there gave the guided rows of the real-log
    tables more episodes past a short log's end than the others, all collided. Only an
    episode its termination cut short (the env's ``terminate_on_collision``) counts there."""
    scene = crash_scene(road, steps=HIST + 27)  # the log ends 2.7 s in, mid-crash (2.5 s)
    assert metrics.ego_collision_steps(scene)[-1]
    ran_out = metrics.evaluate_scene(scene)
    assert not ran_out["ends_in_ego_collision"] and ran_out["cr"] == 1.0
    assert metrics.horizon_values(ran_out, "3") == {}
    cut_short = metrics.evaluate_scene(scene, terminated=True)
    assert cut_short["ends_in_ego_collision"]
    assert metrics.horizon_values(cut_short, "3")["CR"] == 1.0
    assert metrics.horizon_values(cut_short, "8")["CR"] == 1.0
    # Terminated (off the road, say) without a collision: nothing is known past its end.
    clear = metrics.evaluate_scene(crash_scene(road, steps=HIST + 20), terminated=True)
    assert not clear["ends_in_ego_collision"]


def test_every_table_counts_an_episode_without_adversary_as_no_collision_with_one():
    """The ego-adversary CR is a rate over episodes: a selector that finds no adversary in an
    episode made no collision with one there. ``stress``'s summary, ``report``/``compare``
    and ``paper-tables`` count it as 0 alike (they disagreed: two dropped it, which scored a
    selector only on the episodes where it found an adversary). Its record keeps NaN."""
    from counterscene_env.report import paper_tables
    from counterscene_env.report.tables import EPISODE_METRICS

    def record(adversary, hit):
        per = {str(h): {"CR": hit, "CR_adv": hit} for h in range(1, 11)}
        return {
            "per_second": per,
            "rollout_s": 10.0,
            "adversary_id": adversary,
            "cr": hit,
            "cr_ego_adversary": hit,
        }

    records = [record("a1", 1.0), record(None, math.nan)]
    assert metrics.aggregate(records)["overall"]["cr_ego_adversary"] == pytest.approx(0.5)
    assert EPISODE_METRICS["cr_ego_adversary"].estimate(records).value == pytest.approx(0.5)
    assert paper_tables.episode_flags(records, "cr_ego_adversary").tolist() == [1.0, 0.0]
    assert paper_tables.per_episode(records, "CR_adv", [3])[:, 0].tolist() == [1.0, 0.0]
    assert math.isnan(records[1]["cr_ego_adversary"])
    unplayed = {**record(None, math.nan), "rollout_s": 0.0}
    assert math.isnan(metrics.rate_value(unplayed, "cr_ego_adversary", math.nan))


@pytest.mark.parametrize("n", [1, 7, 27, 50, 400])
def test_wilson_interval_of_no_and_every_event_ends_exactly_at_0_and_1(n):
    """A table prints "0 [0, 12.5]" for 0 of 27, not a rounding residue as its lower end."""
    assert metrics.wilson_interval(0, n)[0] == 0.0
    assert metrics.wilson_interval(n, n)[1] == 1.0
    lo, hi = metrics.wilson_interval(1, n)
    assert 0.0 < lo < 1 / n <= hi <= 1.0
