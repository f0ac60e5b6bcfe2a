"""The world model on a tiny network: seeding, shapes, padding, overfitting, rollout, samplers."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import make_scene
from torch.utils.data import default_collate

from counterscene_env.dynamics import unicycle_rollout
from counterscene_env.world_model.config import preset
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.features import local_map
from counterscene_env.world_model.loss import training_loss
from counterscene_env.world_model.map_guidance import off_lane_loss
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import Normalization
from counterscene_env.world_model.train import action_statistics

TINY = preset("default").replace(
    d_model=32, num_heads=2, num_blocks=1, num_agents=4, num_lanes=8, sampling_steps=3
)
AGENT_KEYS = ("history", "history_valid", "future", "future_valid", "extents", "agent_valid")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _model(config=TINY, seed=0, normalization=None) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(config, normalization).eval()


def _batch(model: WorldModel, scenes, rows=None) -> dict[str, torch.Tensor]:
    ds = SceneWindowDataset(list(scenes), model.window_config())
    rows = range(len(ds)) if rows is None else rows
    return default_collate([ds[i] for i in rows])


def _straight_scene(speeds=(10.0, 12.0), lanes=(0.0, 4.0), starts=(0.0, -15.0), T=90, valid=None):
    """Cars driving along +x at constant speed (one window at t0 = 30 for the default sizes)."""
    t = np.arange(T) * 0.1
    n = len(speeds)
    pos = np.zeros((n, T, 2))
    for i, (v, y, x0) in enumerate(zip(speeds, lanes, starts, strict=True)):
        pos[i, :, 0] = 20.0 + x0 + v * t
        pos[i, :, 1] = y
    spd = np.tile(np.asarray(speeds, float)[:, None], (1, T))
    return make_scene(pos, speeds=spd, valid=valid)


@pytest.fixture(scope="module")
def tiny():
    return _model()


@pytest.fixture(scope="module")
def scene_batch(tiny, generated):
    """One window of each generated scenario (some with padding agent slots)."""
    scenes = list(generated.values())
    ds = SceneWindowDataset(scenes, tiny.window_config())
    first = {}
    for row, (s, _, _) in enumerate(ds.index):
        first.setdefault(s, row)
    return default_collate([ds[r] for r in first.values()])


def test_window_config_matches_the_model(tiny):
    w = tiny.window_config()
    c = tiny.config
    assert (w.history_steps, w.future_steps, w.num_agents, w.num_lanes) == (31, 52, 4, 8)
    assert (w.lane_points, w.agent_radius) == (c.lane_points, c.agent_radius)


@pytest.mark.parametrize("local_lanes", [0, 3])
def test_the_map_memory_of_a_sampling_call_changes_nothing(local_lanes, generated):
    """A sampling call projects the lane tokens' keys and values once (``Denoiser.remember``)
    instead of at every step: the network's output is the same, bit for bit."""
    model = _model(TINY.replace(local_lanes=local_lanes))
    batch = _batch(model, generated.values())
    ctx = model.context(batch).repeat(2)
    x = torch.randn(ctx.agent.shape[0], ctx.agent.shape[1], model.config.action_tokens, 2)
    t = torch.full((x.shape[0],), 7)
    with torch.no_grad():
        kept = model.denoiser.remember(ctx)
        assert kept.memory is not None and len(kept.memory) == model.config.num_blocks
        assert torch.equal(model.denoiser(x, t, ctx), model.denoiser(x, t, kept))


def test_same_seed_same_sample_different_seed_different(tiny, scene_batch):
    def draw(seed):
        return tiny.sample(scene_batch, 2, torch.Generator().manual_seed(seed))

    a, b, c = draw(0), draw(0), draw(1)
    assert torch.equal(a.trajectory, b.trajectory) and torch.equal(a.actions, b.actions)
    mask = a.valid[:, None].expand(-1, 2, -1)
    assert not torch.allclose(a.trajectory[mask], c.trajectory[mask])
    # The two samples of one scene differ from each other too.
    assert not torch.allclose(a.normalized[:, 0], a.normalized[:, 1])


def test_a_warm_start_runs_only_its_last_steps(tiny, scene_batch):
    calls = []
    handle = tiny.denoiser.register_forward_hook(lambda *_: calls.append(1))
    B, K = scene_batch["history"].shape[:2]
    init = torch.zeros(B, K, TINY.action_tokens, 2)

    def draw(**kw):
        calls.clear()
        pred = tiny.sample(scene_batch, 2, torch.Generator().manual_seed(0), steps=10, **kw)
        return pred, len(calls)

    try:
        cold, n_cold = draw()
        warm, n_warm = draw(init=init, init_steps=3)
        full, n_full = draw(init=init, init_steps=10)  # not below the step count: a full sample
    finally:
        handle.remove()
    assert (n_cold, n_warm, n_full) == (10, 3, 10)
    assert torch.equal(full.trajectory, cold.trajectory)
    assert torch.isfinite(warm.trajectory).all()
    with pytest.raises(ValueError, match="init must be"):
        tiny.sample(scene_batch, 1, torch.Generator(), init=init[:, :1], init_steps=3)
    # Started near the init, a few steps stay nearer to it than a sample from pure noise.
    mask = warm.valid[:, None].expand(-1, 2, -1)
    assert warm.normalized[mask].abs().mean() < cold.normalized[mask].abs().mean()


def test_output_shapes_and_finite_with_padding(tiny, scene_batch):
    B, S, K, F = scene_batch["history"].shape[0], 3, 4, 52
    assert (~scene_batch["agent_valid"]).any(), "want at least one padding slot in the batch"
    pred = tiny.sample(scene_batch, S, torch.Generator().manual_seed(0))
    assert pred.actions.shape == (B, S, K, F, 2)
    assert pred.trajectory.shape == (B, S, K, F, 4)
    assert pred.normalized.shape == (B, S, K, TINY.action_tokens, 2)
    assert torch.equal(pred.valid, tiny.agent_mask(scene_batch))
    for t in (pred.actions, pred.trajectory, pred.normalized):
        assert torch.isfinite(t).all()
    # Padding agents get zero physical actions.
    pad = ~pred.valid[:, None].expand(B, S, K)
    torch.testing.assert_close(pred.actions[pad], torch.zeros_like(pred.actions[pad]))
    # The trajectory is the rollout of the returned actions from the current state.
    state = tiny.current_state(scene_batch)[:, None].expand(B, S, K, 4)
    c = tiny.config
    rolled = unicycle_rollout(state, pred.actions, c.dt, True, c.yaw_gain, c.lateral_limit)
    torch.testing.assert_close(pred.trajectory, rolled)


def test_agent_seen_only_now_and_padding_slots(tiny):
    # Agent 1 appears at the "now" frame (t0 = 30): its whole history before it is invalid.
    valid = np.ones((3, 90), bool)
    valid[1, :30] = False
    scene = _straight_scene((10.0, 12.0, 8.0), (0.0, 4.0, 0.0), (0.0, -10.0, 15.0), valid=valid)
    batch = _batch(tiny, [scene])
    assert batch["agent_valid"][0].tolist() == [True, True, True, False]
    hv = batch["history_valid"][0]
    row = int(np.flatnonzero(hv.sum(-1).numpy() == 1)[0])
    assert hv[row, -1] and not hv[row, :-1].any()
    pred = tiny.sample(batch, 2, torch.Generator().manual_seed(0))
    assert pred.valid[0].tolist() == [True, True, True, False]
    assert torch.isfinite(pred.trajectory).all() and torch.isfinite(pred.actions).all()
    # Its features and loss are finite as well.
    losses = training_loss(tiny, batch, torch.Generator().manual_seed(0))
    assert all(torch.isfinite(v) for v in losses.values())


def test_agent_valid_but_absent_now_is_padding(tiny):
    batch = _batch(tiny, [_straight_scene()])
    batch["history_valid"][0, 1, -1] = False
    assert tiny.agent_mask(batch)[0].tolist() == [True, False, False, False]


def test_padding_contents_do_not_change_valid_predictions(tiny):
    batch = _batch(tiny, [_straight_scene()])
    assert batch["agent_valid"][0].tolist() == [True, True, False, False]
    garbage = {k: v.clone() for k, v in batch.items()}
    g = torch.Generator().manual_seed(5)
    for k in ("history", "future", "extents"):
        garbage[k][:, 2:] = torch.randn(garbage[k][:, 2:].shape, generator=g) * 30
    garbage["history_valid"][:, 2:] = True
    garbage["future_valid"][:, 2:] = True
    a = tiny.sample(batch, 2, torch.Generator().manual_seed(0))
    b = tiny.sample(garbage, 2, torch.Generator().manual_seed(0))
    torch.testing.assert_close(b.trajectory[:, :, :2], a.trajectory[:, :, :2], rtol=0, atol=1e-5)
    torch.testing.assert_close(b.normalized[:, :, :2], a.normalized[:, :, :2], rtol=0, atol=1e-6)


def test_an_extra_padding_slot_does_not_change_the_denoiser_output(tiny):
    batch = _batch(tiny, [_straight_scene((10.0, 12.0, 8.0), (0.0, 4.0, 0.0), (0.0, -10.0, 15.0))])
    batch = {k: v[:, :3] if k in AGENT_KEYS else v for k, v in batch.items()}
    assert batch["agent_valid"].all()
    # The same scene with a fourth, padding slot holding a plausible-looking but invalid agent.
    wider = {}
    for k, v in batch.items():
        if k in AGENT_KEYS:
            extra = v[:, :1].clone()
            if k == "agent_valid":
                extra[:] = False
            elif k == "history":
                extra[..., 0] += 3.0  # 3 m ahead of the ego: would matter if attended
            wider[k] = torch.cat([v, extra], dim=1)
        else:
            wider[k] = v
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, 4, TINY.action_tokens, 2, generator=g)
    t = torch.tensor([40])
    with torch.no_grad():
        narrow_out = tiny.denoiser(x[:, :3], t, tiny.context(batch))
        wide_out = tiny.denoiser(x, t, tiny.context(wider))
        # Control: the same fourth agent marked valid does change the others' output.
        wider["agent_valid"][:, 3] = True
        seen_out = tiny.denoiser(x, t, tiny.context(wider))
    torch.testing.assert_close(wide_out[:, :3], narrow_out, rtol=0, atol=1e-5)
    assert not torch.allclose(seen_out[:, :3], narrow_out, atol=1e-4)


@pytest.mark.slow
def test_tiny_model_overfits_one_batch(generated):
    probe = _model()
    batch = _batch(probe, [generated["merge"]], rows=[0])
    model = _model(normalization=action_statistics(probe, batch))

    def fixed_noise_loss():
        # Same diffusion steps and noise every time: only the weights change the loss.
        model.eval()
        with torch.no_grad():
            return float(training_loss(model, batch, torch.Generator().manual_seed(123))["loss"])

    before = fixed_noise_loss()
    steps = 200
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    decay = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1 - i / steps)
    model.train()
    for _ in range(steps):
        loss = training_loss(model, batch, torch.Generator().manual_seed(123))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        decay.step()
    after = fixed_noise_loss()
    assert np.isfinite(before) and np.isfinite(after)
    assert after < before / 10, (before, after)


@pytest.mark.parametrize("curve_radius", [None, 60.0])
def test_target_actions_roll_out_to_the_log(tiny, curve_radius):
    T, v = 90, 10.0
    t = np.arange(T) * 0.1
    if curve_radius is None:
        scene = _straight_scene((10.0, 13.0, 7.0), (0.0, 4.0, 4.0), (0.0, -20.0, 10.0))
    else:  # constant-speed left turn on a 60 m circle
        ang = v * t / curve_radius
        pos = np.stack([curve_radius * np.sin(ang), curve_radius * (1 - np.cos(ang))], -1)
        scene = make_scene(pos[None], yaws=ang[None], speeds=np.full((1, T), v))
    batch = _batch(tiny, [scene])
    actions, ok = tiny.target_actions(batch)
    assert actions.shape == (1, 4, TINY.action_tokens, 2)
    valid = tiny.agent_mask(batch)
    assert ok[valid].all() and not ok[~valid].any()
    expected_rate = 0.0 if curve_radius is None else v / curve_radius
    torch.testing.assert_close(
        actions[valid][..., 1],
        torch.full_like(actions[valid][..., 1], expected_rate),
        atol=1e-3,
        rtol=0,
    )
    torch.testing.assert_close(
        actions[valid][..., 0], torch.zeros_like(actions[valid][..., 0]), atol=1e-3, rtol=0
    )
    traj = tiny.rollout(tiny.normalize(actions), tiny.current_state(batch))
    err = (traj[..., :2] - batch["future"][..., :2]).norm(dim=-1)[valid]
    assert err.max() < 0.03, err.max()
    speed_err = (traj[..., 3] - batch["future"][..., 3]).abs()[valid]
    assert speed_err.max() < 1e-3


def test_ddpm_and_ddim_samplers_run_their_steps(tiny):
    batch = _batch(tiny, [_straight_scene()])
    for sampler, expected in (("ddim", TINY.sampling_steps), ("ddpm", TINY.num_train_timesteps)):
        seen = []

        def hook(mean, sigma, t, x0, seen=seen):
            seen.append((t, sigma, tuple(mean.shape)))
            return mean

        pred = tiny.sample(
            batch, 2, torch.Generator().manual_seed(0), sampler=sampler, guidance=hook
        )
        assert torch.isfinite(pred.trajectory).all()
        assert len(seen) == expected
        assert seen[0][0] == TINY.num_train_timesteps - 1 and seen[-1][0] == 0
        assert seen[-1][1] == 0.0 and all(s > 0 for _, s, _ in seen[:-1])
        assert seen[0][2] == (2, 4, TINY.action_tokens, 2)
    # Explicit steps and eta for the strided sampler.
    pred = tiny.sample(batch, 1, torch.Generator().manual_seed(0), steps=5, eta=0.0)
    assert torch.isfinite(pred.trajectory).all()
    with pytest.raises(ValueError, match="sampler"):
        tiny.sample(batch, 1, sampler="euler")


def test_guidance_moves_the_samples(tiny):
    batch = _batch(tiny, [_straight_scene()])
    push = tiny.normalize(torch.tensor([3.0, 0.0]))  # +3 m/s^2 in normalised units

    def accelerate(mean, sigma, t, x0):
        return torch.full_like(mean, 0.0) + push

    # Final-step lane keeping off: the hook alone decides the actions.
    plain = tiny.sample(batch, 1, torch.Generator().manual_seed(0), lane_steering=0)
    guided = tiny.sample(
        batch, 1, torch.Generator().manual_seed(0), guidance=accelerate, lane_steering=0
    )
    valid = guided.valid[0]
    torch.testing.assert_close(
        guided.actions[0, 0][valid], torch.tensor([3.0, 0.0]).expand_as(guided.actions[0, 0][valid])
    )
    assert not torch.allclose(plain.trajectory, guided.trajectory)


def test_epsilon_prediction_trains_and_samples(generated):
    model = _model(TINY.replace(prediction="epsilon"))
    batch = _batch(model, [generated["highway"]], rows=[0, 1])
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in model.parameters()]
    losses = training_loss(model, batch, torch.Generator().manual_seed(0))
    assert set(losses) == {"loss", "action", "position", "yaw", "speed", "off_lane", "overlap"}
    assert all(torch.isfinite(v) for v in losses.values())
    opt.zero_grad()
    losses["loss"].backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(gr).all() for gr in grads)
    opt.step()
    assert any(not torch.equal(a, b) for a, b in zip(before, model.parameters(), strict=True))
    model.eval()
    pred = model.sample(batch, 2, torch.Generator().manual_seed(0))
    assert pred.trajectory.shape == (2, 2, 4, 52, 4)
    assert torch.isfinite(pred.trajectory).all()


def test_normalization_round_trip(tiny):
    model = _model(normalization=Normalization((0.5, -0.1), (2.0, 0.3)))
    a = torch.tensor([[1.0, 0.2], [-3.0, -0.5]])
    torch.testing.assert_close(
        model.normalize(a), (a - torch.tensor([0.5, -0.1])) / torch.tensor([2.0, 0.3])
    )
    torch.testing.assert_close(model.denormalize(model.normalize(a)), a)


@pytest.mark.parametrize("name", ["default", "paper"])
def test_presets_build_and_sample(name):
    """Both presets run on a full scene window (every agent and lane slot filled)."""
    from counterscene_env.world_model.bench import synthetic_batch

    model = _model(preset(name))
    cfg = model.config
    batch = synthetic_batch(model, torch.Generator().manual_seed(0))
    pred = model.sample(batch, 2, torch.Generator().manual_seed(0), sampler="ddim", steps=2)
    assert pred.trajectory.shape == (1, 2, cfg.num_agents, cfg.future_steps, 4)
    assert torch.isfinite(pred.trajectory).all()


def test_paper_preset_has_the_reference_constants():
    cfg = preset("paper")
    assert (cfg.history_steps, cfg.future_steps, cfg.num_agents, cfg.agent_radius) == (
        31,
        52,
        21,
        50.0,
    )
    assert (cfg.d_model, cfg.num_heads, cfg.num_train_timesteps, cfg.sampler) == (
        128,
        16,
        100,
        "ddpm",
    )
    assert cfg.history_tokens + cfg.action_tokens == 83


@pytest.mark.slow
def test_map_guidance_pulls_samples_toward_the_lanes(tiny, scene_batch):
    """With the same noise, map-guided samples end up no further off the lanes, and closer
    for at least one scene, than unguided ones (an untrained model drifts off freely)."""
    from counterscene_env.world_model.map_guidance import lane_excess

    b = scene_batch

    def off(step):
        pred = tiny.sample(b, 2, torch.Generator().manual_seed(3), map_guidance=step)
        xy = pred.trajectory[..., :2].flatten(0, 1)
        ex = lane_excess(
            xy,
            b["map"].repeat_interleave(2, 0),
            b["map_valid"].repeat_interleave(2, 0),
            b["map_widths"].repeat_interleave(2, 0),
        )
        return (ex**2).mean()

    assert off(1.0) < off(0.0)


@pytest.mark.parametrize("lanes_count", [0, 3, 48])
def test_lane_excess_is_the_exact_distance_outside_the_nearest_lane_strip(lanes_count, monkeypatch):
    """The off-lane distance (guidance, realism cost, training loss) searches only the nearest
    lane pieces, yet equals the point-to-centre-line distance less half the width, over all
    lanes (shapely, float64), and its values and gradients are those of the search over every
    segment: on-lane, off-lane and far-off points, maps with fewer lanes than it searches, and
    a map without lanes (1e3 m everywhere)."""
    import shapely

    from counterscene_env.world_model import map_guidance

    g = torch.Generator().manual_seed(7)
    N, P, A, T = 2, 10, 5, 16
    M = max(lanes_count, 1)
    start = torch.rand(N, M, 1, 2, generator=g) * 100 - 50
    turn = torch.cumsum(torch.randn(N, M, P, 1, generator=g) * 0.1, 2)
    heading = torch.rand(N, M, 1, 1, generator=g) * 6.3 + turn
    lanes = start + torch.cumsum(2.2 * torch.cat([heading.cos(), heading.sin()], -1), 2)
    valid = torch.rand(N, M, generator=g) > 0.2 if lanes_count else torch.zeros(N, M, dtype=bool)
    widths = 3.0 + torch.rand(N, M, generator=g)
    near = lanes[:, torch.arange(A) % M][..., torch.arange(T) % P, :]  # [N, A, T, 2]
    points = near + torch.randn(N, A, T, 2, generator=g) * 4
    points[:, 0] *= 5  # far from most lanes
    points.requires_grad_(True)
    got = map_guidance.lane_excess(points, lanes, valid, widths)
    (grad,) = torch.autograd.grad(got.sum(), points)
    for n in range(N):
        strips = [
            (shapely.LineString(lanes[n, m].double().numpy()), float(widths[n, m]) / 2)
            for m in range(M)
            if valid[n, m]
        ]
        for a in range(A):
            for t in range(T):
                p = shapely.Point(points[n, a, t].detach().double().numpy())
                want = min((max(line.distance(p) - h, 0.0) for line, h in strips), default=1e3)
                assert float(got[n, a, t].detach()) == pytest.approx(want, abs=1e-4)
    # With the cars' courses: each segment going against a course counts WRONG_WAY_PENALTY m
    # farther (the brute force over every segment, numpy), and the search stays exact.
    course = torch.rand(N, A, T, generator=g) * 6.3
    way = map_guidance.lane_excess(points, lanes, valid, widths, course)
    (way_grad,) = torch.autograd.grad(way.sum(), points)
    a_, b_ = lanes[:, :, :-1].double().numpy(), lanes[:, :, 1:].double().numpy()
    for n in range(N):
        for a in range(A):
            for t in range(T):
                p = points[n, a, t].detach().double().numpy()
                h = np.array([np.cos(float(course[n, a, t])), np.sin(float(course[n, a, t]))])
                best = 1e3
                for m in range(M):
                    if not valid[n, m]:
                        continue
                    ab = b_[n, m] - a_[n, m]
                    u = np.clip(((p - a_[n, m]) * ab).sum(-1) / (ab**2).sum(-1), 0, 1)
                    d = np.linalg.norm(p - (a_[n, m] + u[:, None] * ab), axis=-1)
                    extra = np.where(ab @ h > 0, 0.0, map_guidance.WRONG_WAY_PENALTY)
                    best = min(
                        best, float(np.maximum(d - widths[n, m].item() / 2 + extra, 0).min())
                    )
                assert float(way[n, a, t].detach()) == pytest.approx(best, abs=1e-4)
    assert (way >= got - 1e-6).all()  # the penalty only adds
    monkeypatch.setattr(map_guidance, "NEAREST_PIECES", 10**6)  # every segment
    x = points.detach().requires_grad_(True)
    every = map_guidance.lane_excess(x, lanes, valid, widths)
    assert torch.equal(got, every)
    assert torch.equal(grad, torch.autograd.grad(every.sum(), x)[0])
    x = points.detach().requires_grad_(True)
    every = map_guidance.lane_excess(x, lanes, valid, widths, course)
    assert torch.equal(way, every)
    assert torch.equal(way_grad, torch.autograd.grad(every.sum(), x)[0])


def test_lane_steering_turns_a_drifting_car_back_onto_the_road():
    """Final-step lane keeping: a plan that curves off the road is steered back onto a lane by
    its yaw rates alone; a car that is off every lane now is left alone."""
    from counterscene_env.world_model.lane_steering import steer_onto_lanes
    from counterscene_env.world_model.map_guidance import lane_excess

    # The shipped model's action scales (yaw rate: 0.3 rad/s per normalised unit).
    tiny = _model(normalization=Normalization((0.0, 0.0), (1.4, 0.3)))

    # Cars on the lanes y = 0 and y = 4 (road y in [-2, 6]) and one parked on the verge at
    # y = -12; every plan turns left at 0.15 rad/s, which leaves the road within 3 s.
    batch = _batch(tiny, [_straight_scene((10.0, 12.0, 0.0), (0.0, 4.0, -12.0), (0, -15, 30))])
    c = tiny.config
    plan = torch.zeros(1, c.num_agents, c.action_tokens, 2)
    plan[..., 0], plan[..., 1] = 0.5, 0.15  # m/s^2, rad/s
    x = tiny.normalize(plan)
    state = tiny.current_state(batch)
    lanes = (batch["map"], batch["map_valid"], batch["map_widths"])

    def off(tokens):  # [K] mean distance [m] outside every lane strip over the horizon
        return lane_excess(tiny.rollout(tokens, state)[..., :2], *lanes)[0].mean(-1)

    assert (off(x)[:2] > 3.0).all()
    steered = steer_onto_lanes(tiny, batch, x, 40)
    assert (off(steered)[:2] < 0.05).all()
    assert torch.equal(steered[..., 0], x[..., 0])  # acceleration is never touched
    assert torch.equal(steered[0, 2:], x[0, 2:])  # the parked car and padding: unchanged
    assert steer_onto_lanes(tiny, batch, x, 0) is x


def test_lane_steering_leaves_plans_that_run_past_the_end_of_the_map_alone():
    """A real map is a crop: a car driving straight on toward the map's edge is not off its
    lane once it is past the last lane's end, so lane keeping does not turn it round toward
    the lane end (it did, on NGSIM's short map sections)."""
    from conftest import straight_road

    from counterscene_env.world_model.lane_steering import steer_onto_lanes

    tiny = _model(normalization=Normalization((0.0, 0.0), (1.4, 0.3)))
    # The road ends at x = 70 m (20 m ahead of the ego, at the window's origin); the cars are
    # at x = 50 and 38 now and drive on along +x, 40 m past the end by the horizon.
    scene = _straight_scene((10.0, 12.0), (0.0, 4.0), (0.0, -15.0))
    batch = _batch(tiny, [scene.replace(road=straight_road(2, 70.0))])
    c = tiny.config
    plan = torch.zeros(1, c.num_agents, c.action_tokens, 2)
    # m/s^2 and rad/s: drifting 0.4 m to the left by the road's end, well inside the lane
    plan[..., 0], plan[..., 1] = 0.5, 0.02
    x = tiny.normalize(plan)
    assert (tiny.rollout(x, tiny.current_state(batch))[0, :2, -1, 0] > 55).all()
    assert torch.equal(steer_onto_lanes(tiny, batch, x, 40), x)
    # Drifting off the side of the same road is still corrected.
    plan[..., 1] = 0.3  # rad/s
    drifting = tiny.normalize(plan)
    assert not torch.equal(steer_onto_lanes(tiny, batch, drifting, 40), drifting)


def _two_way_road(length: float = 300.0):
    """One lane each way, 4 m wide: eastbound on y = 0, westbound on y = 4."""
    from highway_env.road.lane import StraightLane
    from highway_env.road.road import RoadNetwork

    from counterscene_env.scene.road import RoadMap

    net = RoadNetwork()
    net.add_lane("a", "b", StraightLane([0.0, 0.0], [length, 0.0], width=4.0))
    net.add_lane("b", "a", StraightLane([length, 4.0], [0.0, 4.0], width=4.0))
    return RoadMap.from_network(net)


def test_a_plan_in_the_oncoming_lane_is_off_its_lanes_and_steered_back():
    """The oncoming lane is no lane to keep to: with the car's course known, a plan there is
    off its lanes by the distance to its own strip, and lane keeping brings it back."""
    from counterscene_env.world_model.lane_steering import steer_onto_lanes
    from counterscene_env.world_model.map_guidance import lane_excess

    tiny = _model(normalization=Normalization((0.0, 0.0), (1.4, 0.3)))
    # Both cars drive east: row 0 in its lane, row 1 in the westbound lane.
    scene = _straight_scene((10.0, 10.0), (0.0, 4.0), (0.0, -15.0))
    batch = _batch(tiny, [scene.replace(road=_two_way_road())])
    c = tiny.config
    x = tiny.normalize(torch.zeros(1, c.num_agents, c.action_tokens, 2))  # straight on
    state = tiny.current_state(batch)
    lanes = (batch["map"], batch["map_valid"], batch["map_widths"])

    def off(tokens, way=True):  # [2, F] m outside the lanes (going the car's way)
        traj = tiny.rollout(tokens, state)
        return lane_excess(traj[..., :2], *lanes, headings=traj[..., 2] if way else None)[0, :2]

    assert off(x, way=False).max() < 1e-6  # on a lane strip, whichever its way
    assert off(x)[0].max() < 1e-6 and off(x)[1].min() == pytest.approx(2.0, abs=0.05)
    steered = steer_onto_lanes(tiny, batch, x, 40)
    assert torch.equal(steered[0, 0], x[0, 0])  # the car in its own lane is left alone
    assert off(steered)[1, -10:].max() < 0.05 < off(x)[1, -10:].min()
    # The closed loop's guided adversary keeps to any lane strip: it is left where it is.
    any_way = torch.zeros(1, c.num_agents, dtype=torch.bool)
    any_way[0, 1] = True
    assert torch.equal(steer_onto_lanes(tiny, batch, x, 40, any_way), x)


def test_the_realism_cost_counts_a_collision_beyond_its_horizon_only_when_it_reads_that_far():
    """Two cars on one lane, the second stopped 35 m ahead of the first (10 m/s): their boxes
    meet after about 3 s. A cost that reads the whole plan counts those steps; one that reads
    2 s (``SimConfig.realism_horizon``) does not, and is then the cost of a plan that never
    meets."""
    from counterscene_env.sim.realism import plan_cost

    F = 52
    t = torch.arange(1, F + 1) * 0.1
    moving = torch.stack([10 * t, torch.zeros(F), torch.zeros(F), torch.full((F,), 10.0)], -1)
    stopped = torch.tensor([35.0, 0.0, 0.0, 0.0]).expand(F, 4)
    elsewhere = torch.tensor([35.0, 3.5, 0.0, 0.0]).expand(F, 4)  # in the next lane
    meet = torch.stack([moving, stopped])[None]  # [1, K=2, F, 4]
    apart = torch.stack([moving, elsewhere])[None]
    valid = torch.ones(1, 2, dtype=torch.bool)
    extents = torch.tensor([[[4.5, 1.9], [4.5, 1.9]]])
    xs = torch.linspace(-10, 80, 10)
    lane = lambda y: torch.stack([xs, torch.full_like(xs, y)], -1)  # noqa: E731
    lanes = (
        torch.stack([lane(0.0), lane(3.5)])[None],
        torch.ones(1, 2, dtype=torch.bool),
        torch.full((1, 2), 3.5),
    )
    whole = float(plan_cost(meet, valid, extents, lanes)[0])
    first_2s = float(plan_cost(meet, valid, extents, lanes, steps=20)[0])
    assert whole >= 5  # the steps from about 3.1 s to 3.9 s overlap (the mover runs into it)
    assert first_2s == float(plan_cost(apart, valid, extents, lanes, steps=20)[0]) == 0.0
    assert float(plan_cost(apart, valid, extents, lanes)[0]) == 0.0


def test_the_realism_cost_and_the_training_term_count_the_oncoming_lane_as_off_the_lanes():
    """The sample choice's realism cost and the training loss's off-lane term measure a car
    in the oncoming lane by the distance to its own (2 m outside its strip here); on a road
    whose lanes both go its way it is on a lane."""
    from conftest import straight_road

    from counterscene_env.sim.realism import plan_cost
    from counterscene_env.world_model.map_guidance import off_lane_loss

    tiny = _model(normalization=Normalization((0.0, 0.0), (1.4, 0.3)))
    scene = _straight_scene((10.0, 10.0), (0.0, 4.0), (0.0, -15.0))
    c = tiny.config
    x = tiny.normalize(torch.zeros(1, c.num_agents, c.action_tokens, 2))  # straight on
    for road, want in ((_two_way_road(), 2.0), (straight_road(2), 0.0)):
        batch = _batch(tiny, [scene.replace(road=road)])
        traj = tiny.rollout(x, tiny.current_state(batch))
        lanes = (batch["map"], batch["map_valid"], batch["map_widths"])
        valid = tiny.agent_mask(batch)
        # Row 1's mean squared excess (2 m or more: its first points lie near the end of the
        # window's crop of its own lane), averaged with row 0's 0 over the two cars on a lane.
        cost = float(plan_cost(traj, valid, batch["extents"], lanes, steps=20)[0])
        assert want**2 / 2 - 1e-4 <= cost < (want + 0.5) ** 2 / 2 + 1e-4
        # The training term: the log drives in its own lane (here: the same straight line
        # as the prediction, but eastward on the road's lane), the prediction in row 1.
        ok = valid[..., None].expand(traj.shape[:3])
        log_course = torch.zeros_like(traj[..., 2])  # the logs go east too
        term = off_lane_loss(tiny, batch, traj[..., :2], traj[..., :2], ok, traj[..., 2])
        if want:  # the log is in the oncoming lane too: with its course, it is not on a lane
            blind = off_lane_loss(tiny, batch, traj[..., :2], traj[..., :2], ok)
            assert float(blind) == 0.0 < float(term)
            gated = off_lane_loss(
                tiny, batch, traj[..., :2], traj[..., :2], ok, traj[..., 2], log_course
            )
            assert float(gated) == pytest.approx(0.0, abs=1e-6)
        else:
            assert float(term) == pytest.approx(0.0, abs=1e-6)


def _steering_cost(tiny, x, state, lanes_batch=None):
    """A ``SteeringCost`` for tokens ``x [N, K, Ta, 2]`` from states ``[N, K, 4]``, with every
    point's candidates the segments of one straight two-lane road."""
    from counterscene_env.dynamics import max_yaw_rate
    from counterscene_env.world_model.lane_steering import SteeringCost

    c = tiny.config
    traj = tiny.rollout(x, state)
    v = traj[..., 3]
    limit = max_yaw_rate(torch.cat([state[..., None, 3], v[..., :-1]], -1), c.yaw_gain, 25.0)
    R, F = v.shape[0] * v.shape[1], v.shape[2]
    # Two lanes at y = 0 and y = 4 (half-width 1.8 m), each of 3 sub-segments, turned by
    # 0.3 rad so that the off-lane direction has both an x and a y part.
    starts = torch.tensor(
        [[-50.0, 0.0], [0.0, 0.0], [50.0, 0.0], [-50.0, 4.0], [0.0, 4.0], [50.0, 4.0]]
    ).double()
    turn = torch.tensor([[np.cos(0.3), np.sin(0.3)], [-np.sin(0.3), np.cos(0.3)]]).double()
    ca = (starts @ turn).expand(R, F, 6, 2)
    cb = ca + torch.tensor([50.0, 0.0]).double() @ turn
    half = torch.full((R, F, 6), 1.8).double()
    ok = torch.ones(R, F, 6, dtype=torch.bool)
    first = torch.tensor([True, False, False, True, False, False]).expand(R, F, 6)
    last = torch.tensor([False, False, True, False, False, True]).expand(R, F, 6)
    wrong = torch.zeros(R, F, 6).double()  # every lane goes the car's way
    cands = tuple(t.numpy() for t in (ca, cb, half, ok, first, last, wrong))
    flat = lambda t: t.flatten(0, 1).double().numpy()  # noqa: E731
    return SteeringCost(
        flat(v),
        flat(limit),
        flat(state[..., :3]),
        cands,
        float(tiny.action_std[1]),
        float(tiny.action_mean[1]),
        c.action_stride,
        c.dt,
    )


def test_steering_rollout_is_the_unicycle_with_fixed_accelerations(tiny):
    """Lane keeping's closed-form rollout of yaw-rate tokens (fixed accelerations) gives the
    model's unicycle rollout."""
    g = torch.Generator().manual_seed(0)
    c = tiny.config
    x = torch.randn(3, c.num_agents, c.action_tokens, 2, generator=g)
    state = torch.rand(3, c.num_agents, 4, generator=g) * torch.tensor([50.0, 50.0, 6.0, 20.0])
    turned = x.clone()
    turned[..., 1] += torch.randn(turned.shape[:-1], generator=g)
    cost = _steering_cost(tiny, x, state)
    fx, fy, _ = cost.centres(turned[..., 1].flatten(0, 1).double().numpy())
    slow = tiny.rollout(turned, state)[..., :2].flatten(0, 1).double()
    torch.testing.assert_close(torch.from_numpy(np.stack([fx, fy], -1)), slow, rtol=0, atol=1e-3)


def test_steering_gradient_is_the_cost_s_derivative(tiny):
    """The written-out gradient of lane keeping's cost matches central finite differences."""
    g = torch.Generator().manual_seed(1)
    c = tiny.config
    x = torch.randn(2, 3, c.action_tokens, 2, generator=g) * 0.5
    # Cars on the turned lanes, heading 0.4-0.5 rad off them: each plan leaves the road.
    state = torch.tensor([[0.0, 1.0, 0.8, 12.0], [10.0, 6.0, -0.2, 8.0], [-20.0, -4.0, 0.8, 15.0]])
    state = state.expand(2, 3, 4)
    cost = _steering_cost(tiny, x, state)
    tokens = x[..., 1].flatten(0, 1).double().numpy()
    change = np.full_like(tokens, 0.1)
    value, grad = cost(tokens, change)
    assert (value > 0.5).all()  # every plan leaves the road: the lane term is active
    eps, numeric = 1e-6, np.zeros_like(tokens)
    for j in range(tokens.shape[1]):
        step = np.zeros_like(tokens)
        step[:, j] = eps
        up = cost(tokens + step, change + step, gradient=False)[0]
        down = cost(tokens - step, change - step, gradient=False)[0]
        numeric[:, j] = (up - down) / (2 * eps)
    np.testing.assert_allclose(grad, numeric, rtol=1e-4, atol=1e-6)


def test_learning_rate_schedule():
    from counterscene_env.world_model.train_config import TrainConfig, learning_rate

    flat = TrainConfig(data=("d",), out="o", steps=100, lr=1e-3)
    assert learning_rate(flat, 0) == learning_rate(flat, 99) == 1e-3
    decay = TrainConfig(data=("d",), out="o", steps=100, lr=1e-3, lr_decay_start=60)
    assert learning_rate(decay, 59) == 1e-3
    assert learning_rate(decay, 80) == pytest.approx(1e-3 * (1 - 0.9 * 0.5))
    assert learning_rate(decay, 100) == pytest.approx(1e-4)


def test_off_lane_term_counts_only_where_the_log_keeps_to_a_lane(tiny):
    # Two cars along the lanes y = 0 and y = 4 of a road drivable for y in [-2, 6].
    batch = _batch(tiny, [_straight_scene()])
    log = batch["future"][..., :2]
    ok = batch["future_valid"] & tiny.agent_mask(batch)[..., None]
    assert float(off_lane_loss(tiny, batch, log, log, ok)) == 0.0  # the log itself: nothing
    # Shifted 9 m to the left, over the first second (well inside the window's map): the
    # cars on y = 0 and y = 4 run 3 m and 7 m beyond the outer strip's edge (y = 6).
    first = ok & (torch.arange(ok.shape[-1]) < 10)
    side = log + torch.tensor([0.0, 9.0])
    assert float(off_lane_loss(tiny, batch, side, log, first)) == pytest.approx(5.0, abs=1e-3)
    # A log that itself leaves the lanes (a car on the verge) is never pulled back.
    assert float(off_lane_loss(tiny, batch, side, side, ok)) == 0.0
    # In the loss, the term adds its weight times its value (same noise, same draw).
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    plain, weighted = (
        training_loss(tiny, batch, g()),
        training_loss(tiny, batch, g(), off_lane_weight=2.0),
    )
    assert float(weighted["loss"].detach()) == pytest.approx(
        float(plain["loss"].detach()) + 2.0 * float(weighted["off_lane"]), rel=1e-5
    )


def test_local_map_is_each_agents_nearest_lanes_in_its_own_frame():
    # Lane 0 runs north along x = 10, lane 1 is 100 m away, lane 2 is padding.
    lanes = torch.tensor(
        [[[10.0, 0.0], [10.0, 5.0], [10.0, 10.0]], [[110.0, 0.0], [110.0, 5.0], [110.0, 10.0]]]
    )
    lanes = torch.cat([lanes, torch.zeros(1, 3, 2)])[None]  # [1, 3, 3, 2]
    direction = torch.tensor([0.0, 1.0]).expand(1, 3, 3, 2)
    extras = torch.full((1, 3, 3, 1), 4.0 / 4.0)  # lane_features' width / 4 m
    lanes_ok = torch.tensor([[True, True, False]])
    # Agent 0 stands 5 m south of the lane's start, heading north; agent 1 is padding.
    position = torch.tensor([[[10.0, -5.0], [0.0, 0.0]]])
    course = torch.tensor([[np.pi / 2, 0.0]])
    valid = torch.tensor([[True, False]])
    feat, ok = local_map(lanes, direction, extras, lanes_ok, position, course, valid, 2, 30.0)
    assert feat.shape == (1, 2, 2, 3, 5)
    # Nearest first: lane 0, then lane 1, which is beyond local_radius.
    assert ok.tolist() == [[[True, False], [False, False]]]
    scale = 20.0  # POSITION_SCALE
    ahead = torch.tensor([[5.0, 0.0], [10.0, 0.0], [15.0, 0.0]]) / scale
    torch.testing.assert_close(feat[0, 0, 0, :, :2], ahead)  # straight ahead along its x axis
    torch.testing.assert_close(feat[0, 0, 0, :, 2:4], torch.tensor([1.0, 0.0]).expand(3, 2))
    torch.testing.assert_close(feat[0, 0, 0, :, 4], torch.ones(3))  # the width, unrotated
    assert not feat[0, 1].any() and not feat[0, 0, 1].any()  # masked entries carry zeros


def test_agent_centric_map_starts_silent_and_then_steers(scene_batch):
    """Its output projections start at zero, so a model with the agent-centric map predicts
    exactly what the same weights without it predict (the basis of fine-tuning an older
    checkpoint); once they are non-zero the agent-centric lanes change the prediction."""
    plain = _model(TINY.replace(local_lanes=0))
    local = WorldModel(TINY.replace(local_lanes=4)).eval()
    missing, unexpected = local.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(".local" in k for k in missing)

    def sample(m):
        with torch.no_grad():
            return m.sample(scene_batch, 2, torch.Generator().manual_seed(3)).trajectory

    torch.testing.assert_close(sample(local), sample(plain), rtol=0, atol=0)
    with torch.no_grad():
        for block in local.denoiser.blocks:
            block.local.out.weight.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(1))
    assert not torch.allclose(sample(local), sample(plain))


@pytest.mark.parametrize("mode", ["noisy", "self"])
def test_plan_features_start_silent_then_read_where_the_other_agents_plans_go(mode, scene_batch):
    """The plan features start at zero output, so a model with them predicts exactly what the
    same weights without them predict (a fine-tune of an older checkpoint starts there). Once
    trained they make one agent's output depend on where another agent's plan takes
    it, and the training loss reaches their weights."""
    plain = _model(TINY)
    planned = WorldModel(TINY.replace(plan_features=mode)).eval()
    missing, unexpected = planned.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing
    assert all(k.startswith(("denoiser.plan_in.", "denoiser.pair_mlp.")) for k in missing)

    def sample(m):
        with torch.no_grad():
            return m.sample(scene_batch, 2, torch.Generator().manual_seed(3)).trajectory

    torch.testing.assert_close(sample(planned), sample(plain), rtol=0, atol=0)

    # The loss reaches both new modules (their last layers start at zero, not frozen).
    planned.train()
    loss = training_loss(planned, scene_batch, torch.Generator().manual_seed(0))["loss"]
    loss.backward()
    for name in ("plan_in", "pair_mlp"):
        grad = getattr(planned.denoiser, name)[-1].weight.grad
        assert grad is not None and grad.abs().sum() > 0, name
    planned.eval()

    with torch.no_grad():
        g = torch.Generator().manual_seed(1)
        planned.denoiser.pair_mlp[-1].weight.normal_(0.0, 1.0, generator=g)
        batch = {k: v[:1] for k, v in scene_batch.items()}
        valid = planned.agent_mask(batch)
        assert int(valid.sum()) >= 2
        state = planned.current_state(batch)
        ctx = planned.context(batch)
        x = torch.randn(1, TINY.num_agents, TINY.action_tokens, 2, generator=g)
        t = torch.tensor([50])
        other = int(valid[0].nonzero()[1])
        moved = x.clone()
        moved[0, other, :, 1] += 3.0  # another agent's plan turns away
        if mode == "noisy":
            a = planned.denoise(x, t, ctx, state, valid)
            b = planned.denoise(moved, t, ctx, state, valid)
        else:  # the same noisy actions; the previous prediction of the other agent turns
            a = planned.denoise(x, t, ctx, state, valid, x)
            b = planned.denoise(x, t, ctx, state, valid, moved)
    # Agent 0's own noisy actions are the same; only where the other agent goes changed.
    assert not torch.allclose(a[0, 0], b[0, 0])
    with pytest.raises(ValueError, match="rolled-out plan"):
        planned.denoiser(x, t, ctx)


def test_lane_priority_starts_silent_then_tells_who_has_the_right_of_way(scene_batch):
    """The right of way enters at zero, so a model reading it predicts exactly what the same
    weights without it predict (a fine-tune of an older checkpoint starts there); the loss
    reaches it, and once its weights are non-zero the prediction depends on which lanes have
    the right of way."""
    assert scene_batch["map_priority"].any()  # the intersection's window carries it
    plain = _model(TINY)
    with torch.no_grad():  # as trained: the agent-centric map's attention starts at zero
        for block in plain.denoiser.blocks:
            block.local.out.weight.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(1))
    ruled = WorldModel(TINY.replace(lane_priority=True)).eval()
    missing, unexpected = ruled.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected
    assert sorted(missing) == ["denoiser.local_priority_in.weight", "denoiser.priority_in.weight"]

    def sample(m, batch=scene_batch):
        with torch.no_grad():
            return m.sample(batch, 2, torch.Generator().manual_seed(3)).trajectory

    torch.testing.assert_close(sample(ruled), sample(plain), rtol=0, atol=0)
    ruled.train()
    training_loss(ruled, scene_batch, torch.Generator().manual_seed(0))["loss"].backward()
    for name in ("priority_in", "local_priority_in"):
        grad = getattr(ruled.denoiser, name).weight.grad
        assert grad is not None and grad.abs().sum() > 0, name
    ruled.eval()
    with torch.no_grad():
        g = torch.Generator().manual_seed(1)
        ruled.denoiser.priority_in.weight.normal_(0.0, 1.0, generator=g)
        ruled.denoiser.local_priority_in.weight.normal_(0.0, 1.0, generator=g)
    swapped = dict(scene_batch, map_priority=3.0 - scene_batch["map_priority"])
    assert not torch.allclose(sample(ruled), sample(ruled, swapped))
    assert torch.equal(sample(plain), sample(plain, swapped))  # the plain model never reads it


def test_source_flag_starts_silent_then_tells_recordings_from_generated_traffic(
    scene_batch, generated
):
    """Whether a scene is a recording enters at zero, so the model reading it starts as the
    same weights without it; the loss reaches it, and once trained the samples depend on it.
    A highway-env scene's windows say generated, a scene that does not say is a recording."""
    scene = next(iter(generated.values()))
    assert scene.generated and not scene.replace(metadata={}).generated
    assert not scene_batch["recorded"].any()
    plain = _model(TINY)
    told = WorldModel(TINY.replace(source_flag=True)).eval()
    missing, unexpected = told.load_state_dict(plain.state_dict(), strict=False)
    assert (missing, unexpected) == (["denoiser.source_in.weight"], [])

    def sample(m, batch=scene_batch):
        with torch.no_grad():
            return m.sample(batch, 2, torch.Generator().manual_seed(3)).trajectory

    recorded = dict(scene_batch, recorded=torch.ones_like(scene_batch["recorded"]))
    torch.testing.assert_close(sample(told, recorded), sample(plain), rtol=0, atol=0)
    told.train()
    training_loss(told, recorded, torch.Generator().manual_seed(0))["loss"].backward()
    grad = told.denoiser.source_in.weight.grad
    assert grad is not None and grad.abs().sum() > 0
    told.eval()
    with torch.no_grad():
        told.denoiser.source_in.weight.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(1))
    assert not torch.allclose(sample(told), sample(told, recorded))
    assert torch.equal(sample(plain), sample(plain, recorded))  # the plain model never reads it
    with pytest.raises(ValueError, match="recorded flag"):
        told.context({k: v for k, v in scene_batch.items() if k != "recorded"})


def test_weighted_batches_fill_each_source_to_its_share():
    """``weighted_batches``: source shares follow the weights whatever the window counts,
    and step k's draw is the same whether the run starts at 0 or resumes at k."""
    from counterscene_env.world_model.batches import weighted_batches

    sources = torch.tensor([0] * 900 + [1] * 100)
    draws = weighted_batches(sources, (1.0, 3.0), 64, seed=0, start_step=0)
    rows = torch.cat([next(draws) for _ in range(100)])
    share = float((sources[rows] == 1).float().mean())
    assert abs(share - 0.75) < 0.03  # 6400 draws: the standard error is 0.005
    again = weighted_batches(sources, (1.0, 3.0), 64, seed=0, start_step=99)
    assert torch.equal(next(again), rows[-64:])
    # Weight only on a source without windows: refused at once, not at the first step.
    with pytest.raises(ValueError, match="positive weight has no windows"):
        weighted_batches(torch.zeros(5, dtype=torch.long), (0.0, 1.0), 4, seed=0, start_step=0)


def test_a_batch_trimmed_of_padding_samples_what_the_padded_batch_does(tiny):
    """``collate(trim=True)`` cuts the trailing padding agents: the real agents get the same
    samples (same noise, same context), cold and warm-started, at a fraction of the work."""
    from counterscene_env.world_model.window import collate, make_window

    scene = _straight_scene()
    window = make_window(scene, 30, tiny.window_config())
    full, trimmed = collate([window]), collate([window], trim=True)
    assert full["agent_valid"].shape[1] == 4 and trimmed["agent_valid"].shape[1] == 2
    init = torch.randn(1, 4, TINY.action_tokens, 2, generator=torch.Generator().manual_seed(1))
    for warm in ({}, {"init_steps": 2}):
        kw = {"init": init, **warm} if warm else {}
        kt = {"init": init[:, :2], **warm} if warm else {}
        a = tiny.sample(full, 3, [torch.Generator().manual_seed(0)], **kw)
        b = tiny.sample(trimmed, 3, [torch.Generator().manual_seed(0)], **kt)
        torch.testing.assert_close(b.normalized, a.normalized[:, :, :2], rtol=0, atol=1e-5)
        torch.testing.assert_close(b.trajectory, a.trajectory[:, :, :2], rtol=0, atol=1e-4)


def test_sample_refuses_out_of_range_settings_by_name(tiny, scene_batch):
    """``sample`` is public: a count of 0 or an eta of 5 is named, not a reshape error deep
    in torch or a silently different sampler."""
    for kwargs, kind, word in (
        ({"num_samples": 0}, ValueError, "num_samples"),
        ({"steps": 0}, ValueError, "steps"),
        ({"eta": 5.0}, ValueError, "eta"),
        ({"lane_steering": -1}, ValueError, "lane_steering"),
        ({"map_guidance": -1.0}, ValueError, "map_guidance"),
        ({"init_steps": -1}, ValueError, "init_steps"),
        ({"num_samples": 1.5}, TypeError, "num_samples"),
        ({"sampler": "euler"}, ValueError, "sampler"),
    ):
        with pytest.raises(kind, match=word):
            tiny.sample(scene_batch, **{"num_samples": 1, **kwargs})
    # The batch itself: float64 states, a NaN in a valid frame, a missing key, one window.
    bad_batches = (
        ({**scene_batch, "history": scene_batch["history"].double()}, "must be float32"),
        ({**scene_batch, "history": scene_batch["history"].clone().fill_(float("nan"))}, "NaN"),
        ({k: v for k, v in scene_batch.items() if k != "map"}, r"lacks \['map'\]"),
        ({k: v[0] for k, v in scene_batch.items()}, "unbatched"),
    )
    for batch, words in bad_batches:
        with pytest.raises(ValueError, match=words):
            tiny.sample(batch, 1)
