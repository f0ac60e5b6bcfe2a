"""The closed loop: determinism, batching, validity, ego control, selection and bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from conftest import make_scene

from counterscene_env import geometry
from counterscene_env.sim import ClosedLoop, MotionSource, SimConfig
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.window import make_window

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHORT = SimConfig(duration=1.5, num_samples=2)


@pytest.fixture(scope="module")
def model():
    return load_model()


def run(model, scenes, seeds, config=SHORT, actions=None):
    loop = ClosedLoop(model, config)
    loop.reset(scenes, seeds)
    a = np.zeros((len(scenes), 2)) if actions is None else actions
    infos = []
    while not loop.done.all():
        infos.append(loop.step(a))
    return loop, infos


def test_same_seed_and_actions_give_the_same_episode(model, generated):
    scene = generated["intersection"]
    a, _ = run(model, [scene], [7])
    b, _ = run(model, [scene], [7])
    c, _ = run(model, [scene], [8])
    sa, sb, sc = a.scene(0), b.scene(0), c.scene(0)
    assert np.array_equal(sa.positions, sb.positions) and np.array_equal(sa.yaws, sb.yaws)
    assert not np.allclose(sa.positions, sc.positions)  # the seed does matter


def test_an_episode_does_not_depend_on_its_batch(model, generated):
    alone, _ = run(model, [generated["merge"]], [3])
    batched, _ = run(model, [generated["merge"], generated["roundabout"]], [3, 4])
    np.testing.assert_allclose(alone.scene(0).positions, batched.scene(0).positions, atol=1e-3)


def test_history_is_the_log_and_validity_follows_it(model, generated):
    scene = generated["intersection"]
    loop, _ = run(model, [scene], [0])
    sim = loop.scene(0)
    c = scene.current_index
    assert sim.num_steps == c + 1 + round(SHORT.duration / scene.dt)
    assert np.array_equal(sim.positions[:, : c + 1], scene.positions[:, : c + 1])
    assert np.array_equal(sim.valid, scene.valid[:, : sim.num_steps])
    assert np.isfinite(sim.positions[sim.valid]).all()
    # Traffic moved by the model: not a copy of the log.
    others = np.arange(scene.num_agents) != scene.ego_index
    moved = sim.valid[others, c + 1 :] & scene.valid[others, c + 1 : sim.num_steps]
    diff = sim.positions[others, c + 1 :] - scene.positions[others, c + 1 : sim.num_steps]
    assert np.abs(diff[moved]).max() > 0.01


def test_an_agent_entering_on_top_of_the_ego_waits_until_its_place_is_clear(model):
    # The log: the ego drives east at 10 m/s from x = 50; row 1 appears 2 s later at x = 58,
    # 12 m behind where the logged ego is by then, and follows at 10 m/s. The simulated ego
    # brakes to a stop near x = 60, so row 1's logged entry lands on it.
    c, T = 30, 90
    t = np.arange(T) * 0.1 - c * 0.1
    ego = np.stack([50 + 10.0 * t, np.zeros(T)], -1)
    late = np.stack([58 + 10.0 * (t - 2.0), np.zeros(T)], -1)
    # Far off, two parked cars the log itself has overlapping, one of them entering then:
    # an overlap of the log's own holds no one back.
    parked, joins = np.tile([200.0, 4.0], (T, 1)), np.tile([202.0, 4.0], (T, 1))
    valid = np.ones((4, T), bool)
    valid[1, : c + 20] = False
    valid[3, : c + 20] = False
    speeds = np.array([np.full(T, 10.0), np.full(T, 10.0), np.zeros(T), np.zeros(T)])
    positions = np.stack([ego, late, parked, joins])
    scene = make_scene(positions, speeds=speeds, valid=valid, current_index=c)
    loop = ClosedLoop(model, SimConfig(duration=4.0, num_samples=2))
    loop.reset([scene], [0])
    infos = []
    while not loop.done.all():
        infos.append(loop.step(np.array([[-5.0, 0.0]])))
    sim = loop.scene(0)
    entry = c + 20
    assert geometry.boxes_overlap(  # where the log would put it, the ego stands
        scene.positions[1, entry],
        0.0,
        scene.extents[1],
        sim.positions[0, entry],
        0.0,
        scene.extents[0],
    )
    assert not any(i[0]["collision"] for i in infos)
    first = int(np.flatnonzero(sim.valid[1])[0])
    assert first > entry  # it waited...
    assert np.array_equal(
        sim.positions[1, first], scene.positions[1, first]
    )  # ...then came in as logged
    assert (loop.motion_source(0)[1, entry:first] == MotionSource.NONE).all()
    assert np.array_equal(sim.valid[3], scene.valid[3, : sim.num_steps])


def test_ego_follows_its_actions_through_the_bicycle_model(model, generated):
    scene = generated["highway"]
    e, c = scene.ego_index, scene.current_index
    loop, infos = run(model, [scene], [0], actions=np.array([[-4.0, 0.0]]))
    sim = loop.scene(0)
    v0 = scene.speeds[e, c]
    assert sim.speeds[e, -1] == pytest.approx(v0 - 4.0 * SHORT.duration, abs=1e-6)
    assert all(i[0]["hard_braking"] for i in infos)  # -4 m/s^2 < -3 m/s^2
    assert infos[-1][0]["ego_acceleration"] == pytest.approx(-4.0)


def test_written_ego_states_replay_the_log(model, generated):
    scene = generated["roundabout"]
    e = scene.ego_index
    loop = ClosedLoop(model, SHORT)
    loop.reset([scene], [0])
    while not loop.done.all():
        t1 = loop.state(0).t + 1
        state = [*scene.positions[e, t1], scene.yaws[e, t1], scene.speeds[e, t1]]
        loop.step(ego_states=np.array([state]))
    sim = loop.scene(0)
    assert np.allclose(sim.positions[e], scene.positions[e, : sim.num_steps])


def test_step_info_is_plain_and_complete(model, generated):
    _, infos = run(model, [generated["intersection"]], [0])
    info = infos[0][0]
    for key in (
        "collision",
        "collided_with",
        "hard_braking",
        "ego_acceleration",
        "adversary",
        "conflict_type",
        "danger_score",
        "conflict_point",
        "arrival_steps",
        "adversary_distance",
        "min_ttc",
        "off_road",
        "fallback",
    ):
        assert key in info
    assert isinstance(info["collision"], bool) and isinstance(info["ego_acceleration"], float)
    json.dumps(info)  # plain Python values only


def crossing_scene(T=100):
    """Ego east along y = 0 at 10 m/s; row 1 crosses north on x = 30 and yields: it reaches
    the crossing at index 38, 0.8 s after the ego (index 30). Row 2 parks far away."""
    t = np.arange(T) * 0.1
    ego = np.stack([-0.0 + 10 * t, np.zeros(T)], -1)
    cross_y = np.where(t < 3.8, -30 + 30 * np.minimum(t, 3.8) / 3.8, 10 * (t - 3.8))
    cross = np.stack([np.full(T, 30.0), cross_y], -1)
    parked = np.tile([200.0, 8.0], (T, 1))
    pos = np.stack([ego, cross, parked])
    yaws = np.array([np.zeros(T), np.full(T, np.pi / 2), np.zeros(T)])
    speeds = np.array([np.full(T, 10.0), np.gradient(cross_y, 0.1), np.zeros(T)])
    return make_scene(pos, yaws=yaws, speeds=speeds, current_index=0)


def test_the_planted_critical_agent_is_selected_on_the_log(model):
    loop = ClosedLoop(model, SimConfig(duration=9.0))
    infos = loop.reset([crossing_scene()], [0])
    sel = loop.selection(0)
    assert sel.conflict.agent == 1
    assert (sel.conflict.type, sel.conflict.tier) == ("intersection", 1)
    assert (sel.conflict.ego_step, sel.conflict.adversary_step) == (30, 38)
    assert infos[0]["adversary"] == "a1" and infos[0]["arrival_steps"] == [30, 38]
    assert infos[0]["fallback"] is None


def test_no_candidate_falls_back_and_says_why(model):
    T = 40
    pos = np.stack([np.stack([np.arange(T) * 1.0, np.zeros(T)], -1)])
    scene = make_scene(pos, speeds=np.full((1, T), 10.0), current_index=0)
    _, infos = run(model, [scene], [0], SimConfig(duration=1.0))
    assert infos[-1][0]["adversary"] is None
    assert "candidate" in infos[-1][0]["fallback"]


def test_unguided_runs_still_name_the_adversary(model):
    # Guidance off: the same agent is selected (for comparable metrics), just not guided.
    off = ClosedLoop(model, SimConfig(duration=9.0, guidance="none"))
    infos = off.reset([crossing_scene()], [0])
    assert off.selection(0).conflict.agent == 1 and infos[0]["adversary"] == "a1"


def test_the_adversary_is_kept_in_the_model_window(model):
    scene = crossing_scene()
    window = make_window(scene, 0, model.window_config(), include=(2,))  # 200 m away
    assert list(window["rows"][:3]) == [0, 2, 1]
    assert list(make_window(scene, 0, model.window_config())["rows"][:3]) == [0, 1, -1]


def test_bad_input_is_refused_with_a_clear_error(model, generated):
    loop = ClosedLoop(model, SHORT)
    with pytest.raises(RuntimeError, match="reset"):
        loop.step(np.zeros((1, 2)))
    loop.reset([generated["merge"]], [0])
    with pytest.raises(ValueError, match=r"actions must have shape \(1, 2\)"):
        loop.step(np.zeros(2))
    with pytest.raises(ValueError, match="NaN"):
        loop.step(np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match="actions or ego_states"):
        loop.step()
    first = loop.episodes[0]
    for seeds, selection, words in (
        ([2**64], None, r"seeds\[0\] must be <= "),  # the torch generator takes 64 bits
        ([-1], None, r"seeds\[0\] must be >= 0"),
        ([0], [2**64], r"selection_seeds\[0\]"),
    ):
        with pytest.raises(ValueError, match=words):
            loop.reset([generated["merge"]], seeds, selection_seeds=selection)
    with pytest.raises(ValueError, match="selection_seed must be <="):
        loop.start(1, generated["merge"], 0, selection_seed=2**64)
    # None of the refused calls moved anything (no replan, no step, the same episode).
    assert loop.episodes == [first] and first.replans == 0
    assert loop.state(0).t == generated["merge"].current_index
    with pytest.raises(ValueError, match="unknown selector"):
        SimConfig(selector="closest")
    with pytest.raises(ValueError, match="unknown guidance preset"):
        SimConfig(guidance="max")
    with pytest.raises(ValueError, match="unknown simulation keys"):
        SimConfig.from_mapping({"replan": 3})


def test_model_source_reselects_at_every_replan(model, generated):
    scene = generated["merge"]
    loop = ClosedLoop(model, SimConfig(duration=1.0, num_samples=2, selection_source="model"))
    infos = loop.reset([scene], [0])
    assert infos[0]["fallback"] == "not selected yet"  # nothing is mined from the log
    sources = []
    while not loop.done.all():
        info = loop.step(np.zeros((1, 2)))[0]
        sources.append((info["replanned"], info["fallback"]))
    assert [r for r, _ in sources].count(True) == 2  # steps 0 and 5 of 10
    assert sources[0][1] != "not selected yet"  # mined on the model's own sample
    # The episode names the adversary of every step, for the metrics to count them all.
    ep = loop.episodes[0]
    assert len(ep.adversary_ids()) == loop.scene(0).num_steps - scene.current_index - 1
    assert ep.adversary_ids()[-1] == info["adversary"]


def test_several_egos_each_follow_their_actions_with_their_own_adversary(model, generated):
    """Two egos: [B, E, 2] actions drive each through its own bicycle; each has its own
    adversary, never the other ego; infos(b) has one dict per ego."""
    scene = generated["merge"]
    e0 = scene.ego_index
    t = scene.current_index
    others = [r for r in range(scene.num_agents) if r != e0 and scene.valid[r, t]]
    e1 = others[0]
    loop = ClosedLoop(model, SHORT)
    loop.reset([scene], [0], egos=[[e0, e1]])
    with pytest.raises(ValueError, match=r"actions must have shape \(1, 2, 2\)"):
        loop.step(np.zeros((1, 2)))
    speeds = scene.speeds[[e0, e1], t]
    for _ in range(5):
        loop.step(np.array([[[2.0, 0.0], [-2.0, 0.0]]]))
    infos = loop.infos(0)
    assert len(infos) == 2
    v = loop.state(0).speeds[[e0, e1]]
    assert v[0] == pytest.approx(speeds[0] + 1.0, abs=1e-6)  # +2 m/s^2 for 0.5 s
    assert v[1] == pytest.approx(max(speeds[1] - 1.0, 0.0), abs=1e-6)
    ids = {str(scene.agent_ids[e0]), str(scene.agent_ids[e1])}
    adversaries = [i["adversary"] for i in infos if i["adversary"] is not None]
    assert not ids & set(adversaries)
    assert len(adversaries) == len(set(adversaries))


def rear_scene(T=90, c=30):
    """Ego east on y = 0 at 3 m/s from x = 60; row 1 follows in the same lane at 10 m/s from
    x = 30 and, in the log, drives straight through it (a planted rear-end conflict)."""
    t = np.arange(T) * 0.1 - c * 0.1
    ego = np.stack([60 + 3.0 * t, np.zeros(T)], -1)
    follower = np.stack([30 + 10.0 * t, np.zeros(T)], -1)
    speeds = np.array([np.full(T, 3.0), np.full(T, 10.0)])
    return make_scene(np.stack([ego, follower]), speeds=speeds, current_index=c)


@pytest.mark.parametrize("guidance", ["none", "full"])
def test_traffic_yields_to_the_ego_but_a_guided_adversary_does_not(model, guidance):
    def gap_and_held(**kw):
        config = SimConfig(duration=5.0, num_samples=2, strict_gates=False, guidance=guidance)
        loop = ClosedLoop(model, dataclasses.replace(config, **kw))
        infos = loop.reset([rear_scene()], [0])
        assert infos[0]["adversary"] == "a1" and infos[0]["conflict_type"] == "rear_approach"
        while not loop.done.all():
            loop.step(np.zeros((1, 2)))  # the ego keeps its 3 m/s
        sim, held = loop.scene(0), loop.motion_source(0)[1] == MotionSource.YIELD
        gap = np.abs(sim.positions[0, 30:, 0] - sim.positions[1, 30:, 0]).min()
        return gap, held.any()

    gap, held = gap_and_held()
    if guidance == "none":  # the selected agent is ordinary traffic: it brakes in time
        assert held and gap > 4.5
        # Followed to the letter, the world model's plans drive it into the ego (4 m boxes).
        gap, held = gap_and_held(traffic_yields=False)
        assert gap < 4.0 and not held
    else:  # its safety margins are what the guidance removes: it never yields
        assert not held and gap < 4.0


@pytest.mark.parametrize("guidance", ["none", "full"])
def test_the_final_guidance_step_moves_only_a_guided_adversary(model, guidance):
    def adversary_path(final):
        config = SimConfig(
            duration=5.0,
            num_samples=2,
            strict_gates=False,
            guidance=guidance,
            final_step_guidance=final,
        )
        loop = ClosedLoop(model, config)
        assert loop.guidance.final_step_size == (0.3 if final else 0.0)
        assert loop.reset([rear_scene()], [0])[0]["adversary"] == "a1"
        while not loop.done.all():
            loop.step(np.zeros((1, 2)))
        return loop.scene(0).positions[1, 31:]

    with_step, without = adversary_path(True), adversary_path(False)
    if guidance == "none":  # nothing to guide: the switch changes nothing
        assert np.array_equal(with_step, without)
    else:
        assert not np.allclose(with_step, without, atol=1e-3)


@pytest.mark.parametrize("guidance", ["none", "full"])
def test_lane_keeping_lets_only_a_guided_adversary_keep_to_any_lane(model, guidance, monkeypatch):
    """The guided adversary's counterfactual crosses into the ego's lane, so lane keeping
    exempts it from the lanes' direction (``any_way``); unguided, it is ordinary traffic."""
    seen = []
    sample = type(model).sample

    def spy(self, batch, *args, any_way=None, **kwargs):
        seen.append(None if any_way is None else any_way.clone())
        return sample(self, batch, *args, any_way=any_way, **kwargs)

    monkeypatch.setattr(type(model), "sample", spy)
    loop = ClosedLoop(model, SimConfig(duration=9.0, guidance=guidance))
    assert loop.reset([crossing_scene()], [0])[0]["adversary"] == "a1"
    for _ in range(10):  # two more replans
        loop.step(np.zeros((1, 2)))
    assert seen and all(m is not None for m in seen)
    rows = [m.nonzero().tolist() for m in seen]  # [window, agent slot] pairs exempted
    if guidance == "none":
        assert all(r == [] for r in rows)
    else:  # one agent, the adversary's slot, in every replan
        assert all(len(r) == 1 for r in rows)


@pytest.mark.parametrize(("horizon", "steps"), [(None, None), (2.0, 20)])
def test_the_sample_choice_reads_as_much_of_each_plan_as_asked(model, monkeypatch, horizon, steps):
    """The realism cost of the choice among samples reads the whole plan by default (a
    crossing must be seen while braking can still avoid it), or ``realism_horizon`` s."""
    from counterscene_env.sim import replan

    seen = []
    cost = replan.plan_cost

    def spy(*args):
        seen.append(args[-1])
        return cost(*args)

    monkeypatch.setattr(replan, "plan_cost", spy)
    loop = ClosedLoop(model, SimConfig(duration=1.0, realism_horizon=horizon))
    loop.reset([crossing_scene()], [0])
    for _ in range(5):
        loop.step(np.zeros((1, 2)))
    assert seen and all(s == steps for s in seen)


def platoon_scene(T=90, c=30):
    """:func:`rear_scene` with a third car at 3 m/s from x = 45, between the follower (row 1,
    the adversary) and the ego (row 0): the follower cannot reach the ego without hitting it."""
    base = rear_scene(T, c)
    t = np.arange(T) * 0.1 - c * 0.1
    third = np.stack([45 + 3.0 * t, np.zeros(T)], -1)
    positions = np.concatenate([base.positions, third[None]])
    speeds = np.concatenate([base.speeds, np.full((1, T), 3.0)])
    return make_scene(positions, speeds=speeds, current_index=c)


@pytest.mark.parametrize("manners", [True, False])
def test_a_guided_adversary_yields_to_third_parties_unless_told_not_to(model, manners):
    config = SimConfig(
        duration=5.0,
        num_samples=2,
        strict_gates=False,
        guidance="full",
        adversary_yields_to_others=manners,
    )
    loop = ClosedLoop(model, config)
    infos = loop.reset([platoon_scene()], [0])
    assert infos[0]["adversary"] == "a1"
    while not loop.done.all():
        loop.step(np.zeros((1, 2)))
    sim, held = loop.scene(0), loop.motion_source(0)[1] == MotionSource.YIELD
    gap = np.abs(sim.positions[2, 30:, 0] - sim.positions[1, 30:, 0]).min()
    if manners:  # its margins toward the ego are gone, not its manners toward the third car
        assert held.any() and gap > 4.5
    else:  # the paper's adversary: no reflexes at all, so it drives into the third car
        assert not held.any() and gap < 4.0


def test_a_warm_start_begins_from_the_previous_plan_shifted_to_now(model, generated):
    config = dataclasses.replace(SHORT, warm_start_steps=3, replan_every=5)
    loop = ClosedLoop(model, config)
    loop.reset([generated["intersection"]], [0])
    loop.step(np.zeros((1, 2)))  # the first replan, from pure noise
    ep = loop.episodes[0]
    made = ep.t  # the plan's first action moves its agents into step `made`
    seen = np.flatnonzero(ep.tokens_start >= 0)
    assert seen.size and (ep.tokens_start[seen] == made).all()
    for _ in range(3):
        loop.step(np.zeros((1, 2)))
    tokens = ep.plan_tokens.copy()
    window = loop.replanner.windows(ep, loop.scene(0))[0]
    init = loop.replanner.warm_start(ep, window)  # [K, Ta, 2]
    s = model.config.action_stride
    shift = ep.t + 1 - made
    for k, row in enumerate(window.rows):
        if row < 0 or ep.tokens_start[row] < 0:
            np.testing.assert_allclose(
                init[k], np.broadcast_to(loop.replanner.still, init[k].shape)
            )
            continue
        steps = np.repeat(tokens[row], s, axis=0)  # per-step actions of the previous plan
        steps = np.concatenate([steps[shift:], np.repeat(steps[-1:], shift, axis=0)])
        np.testing.assert_allclose(init[k], steps.reshape(-1, s, 2).mean(1), rtol=1e-5)


@pytest.mark.parametrize("warm_first", [False, True])
def test_the_first_replan_starts_from_noise_or_from_keeping_speed_and_course(
    warm_first, model, generated, monkeypatch
):
    """``warm_first_replan``: an episode's first replan runs only the warm start's last
    denoising steps, from every agent's "keep speed and course" tokens (noised to that level);
    off, it runs every step from pure noise. Either way the episode is deterministic."""
    config = dataclasses.replace(SHORT, warm_start_steps=3, warm_first_replan=warm_first)
    calls = []
    sample = type(model).sample

    def counting(self, batch, *args, **kwargs):
        calls.append((kwargs.get("init"), kwargs.get("init_steps", 0)))
        return sample(self, batch, *args, **kwargs)

    monkeypatch.setattr(type(model), "sample", counting)
    loop = ClosedLoop(model, config)
    loop.reset([generated["intersection"]], [0])
    loop.step(np.zeros((1, 2)))  # the first replan
    ((init, steps),) = calls
    if warm_first:
        assert steps == 3
        still = torch.from_numpy(loop.replanner.still).expand_as(init)
        assert torch.equal(init, still)
    else:
        assert init is None
    monkeypatch.undo()
    a, _ = run(model, [generated["intersection"]], [4], config)
    b, _ = run(model, [generated["intersection"]], [4], config)
    assert np.array_equal(a.scene(0).positions, b.scene(0).positions)


def test_warm_started_episodes_are_deterministic_and_differ_from_cold_ones(model, generated):
    scene = generated["merge"]
    warm = dataclasses.replace(SHORT, warm_start_steps=3)
    a, _ = run(model, [scene], [5], warm)
    b, _ = run(model, [scene], [5], warm)
    cold, _ = run(model, [scene], [5], dataclasses.replace(SHORT, warm_start_steps=0))
    assert np.array_equal(a.scene(0).positions, b.scene(0).positions)
    assert a.episodes[0].replans == cold.episodes[0].replans > 1
    assert not np.allclose(a.scene(0).positions, cold.scene(0).positions)
