"""Counterfactual guidance: schedules, weights, presets, and the gradient mask."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from counterscene_env.adversary.guidance import (
    PRESETS,
    GuidanceConfig,
    guidance_loss,
    guidance_preset,
    make_guidance_hook,
    make_targets,
    pair_paths,
)
from counterscene_env.adversary.schedules import (
    base_weights,
    compressed_arrivals,
    jerk,
    stage_multiplier,
)
from counterscene_env.adversary.selection import (
    FOLLOWING,
    INTERSECTION,
    LEAD_BRAKING,
    REAR_APPROACH,
    Conflict,
)
from counterscene_env.world_model.bench import synthetic_batch
from counterscene_env.world_model.checkpoint import load_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def conflict(subtype=INTERSECTION, score=0.5, agent=3, point=(20.0, 0.0), steps=(40, 50)):
    kind = INTERSECTION if subtype == INTERSECTION else FOLLOWING
    return Conflict(
        agent=agent,
        conflict_point=np.array(point),
        ego_step=steps[0],
        adversary_step=steps[1],
        min_distance=2.0,
        arrival_gap=abs(steps[0] - steps[1]) * 0.1,
        relative_speed=5.0,
        type=kind,
        subtype=subtype,
        score=score,
        tier=1,
        weight=-100.0,
    )


@pytest.mark.parametrize(
    ("p", "m"),
    [(0.0, 0.2), (0.299, 0.2), (0.3, 0.2), (0.5, 0.85), (0.7, 1.5), (0.85, 2.25), (1.0, 3.0)],
)
def test_stage_multiplier_break_points(p, m):
    assert stage_multiplier(p) == pytest.approx(m)


def test_stage_multiplier_is_continuous_and_non_decreasing():
    ps = np.linspace(0, 1, 1001)
    ms = np.array([stage_multiplier(p) for p in ps])
    assert (np.diff(ms) >= -1e-12).all()
    assert np.abs(np.diff(ms)).max() < 0.01  # no jumps at 0.3 or 0.7


@pytest.mark.parametrize(
    ("tau_e", "tau_a", "p", "expected"),
    [
        (40, 50, 0.0, (40, 50)),
        (40, 50, 0.49, (40, 50)),  # compression starts at p = 0.5
        (40, 50, 0.5, (40, 45)),  # the later (adversary) moves to earlier + gap (1 - p)
        (40, 50, 0.8, (40, 42)),
        (40, 50, 1.0, (40, 40)),
        (50, 40, 0.5, (45, 40)),  # the ego is later: its target moves instead
        (50, 40, 1.0, (40, 40)),
        (45, 45, 0.9, (45, 45)),
    ],
)
def test_compression_schedule(tau_e, tau_a, p, expected):
    assert compressed_arrivals(tau_e, tau_a, p) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("subtype", "score", "weights"),
    [
        (INTERSECTION, 0.5, (1.0, 0.75, 0.3)),
        (INTERSECTION, 0.05, (0.3, 0.2, 0.3)),  # floors
        (REAR_APPROACH, 0.5, (0.75, 0.5, 0.5)),
        (LEAD_BRAKING, 0.5, (1.25, 0.4, 0.8)),
        (LEAD_BRAKING, 0.1, (0.3, 0.2, 0.8)),
    ],
)
def test_conflict_aware_base_weights(subtype, score, weights):
    assert base_weights(conflict(subtype, score)) == pytest.approx(weights)


def test_without_conflict_awareness_every_type_gets_the_generic_weights():
    for subtype in (INTERSECTION, REAR_APPROACH, LEAD_BRAKING):
        assert base_weights(conflict(subtype, 0.5), False) == pytest.approx((0.75, 0.5, 0.5))


def test_presets_switch_the_ablated_parts():
    assert PRESETS["full"] == GuidanceConfig()
    assert not PRESETS["no_jerk"].jerk
    assert not PRESETS["no_conflict_aware"].conflict_aware
    assert not PRESETS["no_progressive"].progressive
    assert not PRESETS["no_adaptive"].adaptive
    m = PRESETS["minimal"]
    assert not (m.jerk or m.conflict_aware or m.progressive or m.adaptive) and m.enabled
    assert not PRESETS["none"].enabled
    with pytest.raises(ValueError, match=r"unknown guidance preset 'fancy'.*full"):
        guidance_preset("fancy")
    with pytest.raises(ValueError, match="unknown guidance keys"):
        GuidanceConfig.from_mapping({"jerk": False, "strength": 2})


def test_jerk_of_constant_acceleration_is_zero_and_of_a_kink_is_not():
    t = torch.arange(20, dtype=torch.float64) * 0.1
    smooth = torch.stack([0.5 * 2.0 * t**2, torch.zeros_like(t)], -1)
    assert float(jerk(smooth, 0.1)) == pytest.approx(0.0, abs=1e-4)
    kink = smooth.clone()
    kink[10:, 1] += torch.arange(10, dtype=torch.float64) * 0.1
    assert float(jerk(kink, 0.1)) > 1.0


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.fixture(scope="module")
def batch(model):
    return synthetic_batch(model, torch.Generator().manual_seed(0))


def targets_for(batch, row, cfg=None, progress=0.8):
    # Conflict 20 m ahead of the ego, on the adversary's row; origin = world frame.
    return make_targets(
        [conflict(agent=row, steps=(20, 25))],
        [row],
        np.zeros((1, 3)),
        [0],
        [progress],
        cfg or GuidanceConfig(),
    )


def test_one_guided_step_moves_only_the_adversary_rows(model, batch):
    row, S = 5, 3
    hook = make_guidance_hook(model, batch, targets_for(batch, row), S, GuidanceConfig())
    K, Ta = model.config.num_agents, model.config.action_tokens
    mean = torch.randn((S, K, Ta, 2), generator=torch.Generator().manual_seed(1))
    sigma = 0.5
    out = hook(mean, sigma, 50, mean)
    moved = (out - mean).abs().amax(dim=(-1, -2))  # [S, K]
    assert (moved[:, row] > 0).all()  # the adversary moves in every sample ...
    others = torch.ones(K, dtype=torch.bool)
    others[row] = False
    assert (moved[:, others] == 0).all()  # ... and nobody else, the ego included
    assert moved.max() <= sigma + 1e-6  # clipped to +-sigma_t


def test_the_guided_step_lowers_the_counterfactual_loss(model, batch):
    row, S = 5, 4
    cfg = GuidanceConfig()
    tg = targets_for(batch, row, cfg)
    hook = make_guidance_hook(model, batch, tg, S, cfg)
    mean = torch.randn(
        (S, model.config.num_agents, model.config.action_tokens, 2),
        generator=torch.Generator().manual_seed(2),
    )
    state = model.current_state(batch).repeat_interleave(S, 0)

    def loss(x):
        ego, adv = pair_paths(model, x, state, tg.repeat(S))
        return guidance_loss(ego, adv, tg.repeat(S), cfg, model.config.dt)

    before, after = loss(mean), loss(hook(mean, 0.2, 50, mean))
    assert (after < before).all()


def test_no_adversary_leaves_the_mean_alone(model, batch):
    S, K, Ta = 2, model.config.num_agents, model.config.action_tokens
    mean = torch.randn((S, K, Ta, 2), generator=torch.Generator().manual_seed(3))
    none = make_targets([None], [-1], np.zeros((1, 3)), [0], [0.8], GuidanceConfig())
    hook = make_guidance_hook(model, batch, none, S, GuidanceConfig())
    assert torch.equal(hook(mean, 0.5, 50, mean), mean)
    assert torch.equal(hook(mean, 0.0, 0, mean), mean)


def test_the_final_step_moves_the_finished_adversary_plan_by_its_own_size(model, batch):
    # The last denoising step adds no noise (sigma = 0): the paper's final-step guidance moves
    # the adversary's rows of the finished sample by one unclipped step, and nobody else.
    row, S, K, Ta = 5, 2, model.config.num_agents, model.config.action_tokens
    mean = torch.randn((S, K, Ta, 2), generator=torch.Generator().manual_seed(3))
    cfg = GuidanceConfig()
    hook = make_guidance_hook(model, batch, targets_for(batch, row, cfg), S, cfg)
    moved = (hook(mean, 0.0, 0, mean) - mean).abs()
    assert torch.allclose(moved[:, row], torch.full_like(moved[:, row], cfg.final_step_size))
    others = torch.ones(K, dtype=torch.bool)
    others[row] = False
    assert (moved[:, others] == 0).all()
    off = GuidanceConfig(final_step_size=0.0)
    hook = make_guidance_hook(model, batch, targets_for(batch, row, off), S, off)
    assert torch.equal(hook(mean, 0.0, 0, mean), mean)  # off: the guidance ends before


def test_conflict_point_is_moved_into_the_window_frame():
    # Window at world (100, 50) facing +y: a point 10 m ahead of it is (10, 0) in the window.
    tg = make_targets(
        [conflict(point=(100.0, 60.0))],
        [2],
        np.array([[100.0, 50.0, np.pi / 2]]),
        [0],
        [0.5],
        GuidanceConfig(),
    )
    assert tg.conflict_point[0].tolist() == pytest.approx([10.0, 0.0], abs=1e-5)
