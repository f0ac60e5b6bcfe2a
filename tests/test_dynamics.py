"""The differentiable unicycle: hand-computed motion, bounds, gradients, and its inverse."""

from __future__ import annotations

import math

import pytest
import torch

from counterscene_env.dynamics import (
    ACC_MAX,
    ACC_MIN,
    actions_from_states,
    course_angles,
    max_yaw_rate,
    unicycle_rollout,
)

DT = 0.1
D = torch.float64


def _state(x=0.0, y=0.0, yaw=0.0, v=0.0):
    return torch.tensor([x, y, yaw, v], dtype=D)


def _actions(acc, rate, steps):
    return torch.tensor([[acc, rate]] * steps, dtype=D)


@pytest.mark.parametrize("yaw", [0.0, math.pi / 3, -2.5])
def test_constant_speed_is_a_straight_line(yaw):
    out = unicycle_rollout(_state(5.0, -2.0, yaw, 10.0), _actions(0.0, 0.0, 20), DT)
    assert out.shape == (20, 4)
    k = torch.arange(1, 21, dtype=D)
    torch.testing.assert_close(out[:, 0], 5.0 + 10.0 * k * DT * math.cos(yaw))
    torch.testing.assert_close(out[:, 1], -2.0 + 10.0 * k * DT * math.sin(yaw))
    torch.testing.assert_close(out[:, 2], torch.full((20,), yaw, dtype=D))
    torch.testing.assert_close(out[:, 3], torch.full((20,), 10.0, dtype=D))


def test_constant_acceleration_from_rest_is_semi_implicit():
    a = 2.0
    out = unicycle_rollout(_state(), _actions(a, 0.0, 30), DT)
    k = torch.arange(1, 31, dtype=D)
    torch.testing.assert_close(out[:, 3], a * k * DT)
    # x_k = dt * sum_{j=1..k} v_j = dt * sum a j dt = a dt^2 k (k + 1) / 2 (not a t^2 / 2).
    torch.testing.assert_close(out[:, 0], a * DT**2 * k * (k + 1) / 2)
    assert out[0, 0].item() == pytest.approx(a * DT * DT)  # the first step already moves
    torch.testing.assert_close(out[:, 1], torch.zeros(30, dtype=D))


def test_constant_yaw_rate_turn():
    yaw0, v, w, n = 0.4, 10.0, 0.3, 40
    assert w < float(max_yaw_rate(torch.tensor(v)))  # not clipped
    out = unicycle_rollout(_state(1.0, 2.0, yaw0, v), _actions(0.0, w, n), DT)
    k = torch.arange(1, n + 1, dtype=D)
    yaw = yaw0 + w * k * DT
    torch.testing.assert_close(out[:, 2], yaw)
    torch.testing.assert_close(out[:, 0], 1.0 + DT * v * torch.cumsum(torch.cos(yaw), 0))
    torch.testing.assert_close(out[:, 1], 2.0 + DT * v * torch.cumsum(torch.sin(yaw), 0))
    # Equal chords turning by equal angles: the points lie on one circle of radius
    # chord / (2 sin(w dt / 2)), whose centre is equidistant from three of them.
    pts = torch.cat([torch.tensor([[1.0, 2.0]], dtype=D), out[:, :2]])
    chord, turn = v * DT, w * DT
    radius = chord / (2 * math.sin(turn / 2))
    a, b, c = pts[0], pts[1], pts[2]
    # Circumcentre of a, b, c.
    d = 2 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
    ux = ((a @ a) * (b[1] - c[1]) + (b @ b) * (c[1] - a[1]) + (c @ c) * (a[1] - b[1])) / d
    uy = ((a @ a) * (c[0] - b[0]) + (b @ b) * (a[0] - c[0]) + (c @ c) * (b[0] - a[0])) / d
    dist = (pts - torch.stack([ux, uy])).norm(dim=-1)
    torch.testing.assert_close(dist, torch.full_like(dist, radius))


def test_acceleration_is_clipped():
    up = unicycle_rollout(_state(v=5.0), _actions(100.0, 0.0, 3), DT)
    torch.testing.assert_close(up[:, 3], 5.0 + ACC_MAX * DT * torch.arange(1, 4, dtype=D))
    assert ACC_MAX == 8.0 and ACC_MIN == -10.0
    down = unicycle_rollout(_state(v=5.0), _actions(-100.0, 0.0, 3), DT)
    torch.testing.assert_close(down[:, 3], 5.0 + ACC_MIN * DT * torch.arange(1, 4, dtype=D))
    free = unicycle_rollout(_state(v=5.0), _actions(100.0, 0.0, 3), DT, bound=False)
    torch.testing.assert_close(free[:, 3], 5.0 + 100.0 * DT * torch.arange(1, 4, dtype=D))


def test_speed_never_goes_below_zero_and_a_stopped_car_stays_put():
    out = unicycle_rollout(_state(3.0, 0.0, 0.0, 2.0), _actions(-5.0, 0.0, 10), DT)
    # 2 m/s at -5 m/s^2: 1.5, 1.0, 0.5, 0, then floored at 0.
    expected_v = torch.tensor([1.5, 1.0, 0.5] + [0.0] * 7, dtype=D)
    torch.testing.assert_close(out[:, 3], expected_v)
    assert (out[:, 3] >= 0).all()
    torch.testing.assert_close(out[3:, 0], torch.full((7,), out[2, 0].item(), dtype=D))
    # Unbounded rollout floors the speed too (no reversing).
    free = unicycle_rollout(_state(v=1.0), _actions(-50.0, 0.0, 5), DT, bound=False)
    assert (free[:, 3] == 0).all() and (free[:, 0] == 0).all()


@pytest.mark.parametrize(
    ("speed", "limit"),
    [
        (0.0, 0.1),  # a stopped car cannot spin: the 0.1 rad/s floor
        (1.0, 0.5),  # low speed: yaw_gain * v
        (10.0, 2 * math.pi / 10.0),  # high speed: lateral_limit / v
    ],
)
def test_yaw_rate_is_clipped_to_the_speed_dependent_bound(speed, limit):
    assert float(max_yaw_rate(torch.tensor(speed))) == pytest.approx(limit)
    for sign in (1.0, -1.0):
        out = unicycle_rollout(_state(v=speed), _actions(0.0, sign * 50.0, 1), DT)
        assert out[0, 2].item() == pytest.approx(sign * limit * DT)
    free = unicycle_rollout(_state(v=speed), _actions(0.0, 50.0, 1), DT, bound=False)
    assert free[0, 2].item() == pytest.approx(50.0 * DT)


def test_yaw_rate_bound_constants_are_arguments():
    out = unicycle_rollout(
        _state(v=10.0), _actions(0.0, 50.0, 1), DT, yaw_gain=1.0, lateral_limit=25.0
    )
    assert out[0, 2].item() == pytest.approx(2.5 * DT)  # min(1.0 * 10, 25 / 10)
    out = unicycle_rollout(
        _state(v=2.0), _actions(0.0, 50.0, 1), DT, yaw_gain=1.0, lateral_limit=25.0
    )
    assert out[0, 2].item() == pytest.approx(2.0 * DT)  # min(1.0 * 2, 25 / 2)


def test_batch_dims_match_single_rollouts():
    g = torch.Generator().manual_seed(0)
    states = torch.randn(2, 3, 4, generator=g, dtype=D)
    states[..., 3] = 5 + states[..., 3].abs()
    actions = torch.randn(2, 3, 7, 2, generator=g, dtype=D)
    out = unicycle_rollout(states, actions, DT)
    assert out.shape == (2, 3, 7, 4)
    torch.testing.assert_close(out[1, 2], unicycle_rollout(states[1, 2], actions[1, 2], DT))


def test_gradients_flow_to_the_actions():
    actions = torch.tensor([[1.0, 0.2]] * 10, dtype=D, requires_grad=True)
    out = unicycle_rollout(_state(v=8.0), actions, DT)
    (out[-1, 0] + out[-1, 1]).backward()
    grad = actions.grad
    assert torch.isfinite(grad).all()
    assert (grad[:, 0].abs() > 0).all() and (grad[:, 1].abs() > 0).all()
    # Later accelerations move the end point less than earlier ones.
    assert grad[0, 0] > grad[-1, 0] > 0


def test_actions_from_states_inverts_the_rollout():
    g = torch.Generator().manual_seed(1)
    acc = torch.rand(3, 25, generator=g, dtype=D) * 4 - 2
    rate = torch.rand(3, 25, generator=g, dtype=D) * 0.8 - 0.4
    actions = torch.stack([acc, rate], -1)
    start = torch.tensor([[0.0, 0.0, 0.3, 10.0], [5.0, 1.0, 3.0, 12.0], [0, 0, -3.0, 9.0]], dtype=D)
    states = torch.cat([start[:, None], unicycle_rollout(start, actions, DT)], -2)
    torch.testing.assert_close(actions_from_states(states, DT), actions)
    # Wrapping the yaw channel (as logs do) changes nothing.
    wrapped = states.clone()
    wrapped[..., 2] = torch.atan2(torch.sin(states[..., 2]), torch.cos(states[..., 2]))
    torch.testing.assert_close(actions_from_states(wrapped, DT), actions)


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_actions_from_states_wraps_across_pi(direction):
    # A heading crossing +-pi by 0.1 rad in one step is 1 rad/s, not a 2 pi jump.
    a, b = math.pi - 0.05, -math.pi + 0.05
    yaw = torch.tensor([a, b] if direction > 0 else [b, a], dtype=D)
    states = torch.stack(
        [torch.zeros(2, dtype=D), torch.zeros(2, dtype=D), yaw, torch.tensor([4.0, 4.5], dtype=D)],
        -1,
    )
    out = actions_from_states(states, DT)
    assert out.shape == (1, 2)
    assert out[0, 0].item() == pytest.approx(5.0)
    assert out[0, 1].item() == pytest.approx(direction * 1.0)


def test_course_is_the_displacement_direction_when_moving():
    angle = 0.7
    t = torch.arange(6, dtype=D) * DT
    pos = 5.0 * t[:, None] * torch.tensor([math.cos(angle), math.sin(angle)], dtype=D)
    heading = torch.full((6,), 0.2, dtype=D)  # body heading differs from the course (slip)
    speed = torch.full((6,), 5.0, dtype=D)
    valid = torch.ones(6, dtype=torch.bool)
    course = course_angles(pos, heading, speed, valid, dt=DT)
    assert course.shape == (6,)
    assert course[0].item() == pytest.approx(0.2)  # no previous frame: the heading
    torch.testing.assert_close(course[1:], torch.full((5,), angle, dtype=D))


def test_course_is_the_heading_when_stopped_or_unknown():
    heading = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5], dtype=D)
    # Stopped: jitter of 1 mm per frame at zero speed.
    pos = torch.tensor([[0, 0], [0.001, 0], [0.001, 0.001], [0, 0.001], [0, 0]], dtype=D)
    course = course_angles(pos, heading, torch.zeros(5, dtype=D), torch.ones(5, dtype=torch.bool))
    torch.testing.assert_close(course, heading)
    # Reported speed above min_speed but a near-zero displacement: still the heading.
    course = course_angles(
        pos, heading, torch.full((5,), 3.0, dtype=D), torch.ones(5, dtype=torch.bool)
    )
    torch.testing.assert_close(course, heading)
    # Moving, but the previous frame is missing at frame 2: heading there only.
    moving = torch.stack([torch.arange(5, dtype=D), torch.zeros(5, dtype=D)], -1)  # +x, 10 m/s
    valid = torch.tensor([True, False, True, True, True])
    course = course_angles(moving, heading, torch.full((5,), 10.0, dtype=D), valid, dt=DT)
    torch.testing.assert_close(course, torch.tensor([0.1, 0.2, 0.3, 0.0, 0.0], dtype=D))


def _stepwise_rollout(state: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The module docstring's recursion, one step at a time (the reference)."""
    x, y, yaw, v = state.unbind(-1)
    out = []
    for k in range(actions.shape[1]):
        a = actions[:, k, 0].clamp(ACC_MIN, ACC_MAX)
        limit = max_yaw_rate(v)  # the default constants, as unicycle_rollout
        w = torch.maximum(torch.minimum(actions[:, k, 1], limit), -limit)
        v = (v + a * 0.1).clamp(min=0.0)
        yaw = yaw + w * 0.1
        x, y = x + 0.1 * v * torch.cos(yaw), y + 0.1 * v * torch.sin(yaw)
        out.append(torch.stack([x, y, yaw, v], -1))
    return torch.stack(out, 1)


def test_closed_form_rollout_is_the_step_by_step_recursion():
    """The rollout is computed in closed form (cumulative sums; the speed floor as Lindley's
    recursion); it is the module docstring's recursion, step by step, with brakings to a
    stop, restarts, negative start speeds and both bounds active; and so are its gradients,
    which every guidance step follows."""
    g = torch.Generator().manual_seed(0)
    state = torch.randn(64, 4, generator=g) * torch.tensor([20.0, 20.0, 3.0, 6.0])
    actions = torch.randn(64, 52, 2, generator=g) * torch.tensor([7.0, 0.8])
    want = _stepwise_rollout(state, actions)
    got = unicycle_rollout(state, actions)
    assert (want[..., 3] == 0).any() and (state[:, 3] < 0).any()  # floors and restarts happen
    torch.testing.assert_close(got, want, rtol=0, atol=1e-4)  # m, rad, m/s: float32 sums
    weights = torch.randn(want.shape, generator=g)
    grads = []
    for rollout in (_stepwise_rollout, unicycle_rollout):
        a = actions.clone().requires_grad_(True)
        (rollout(state, a) * weights).sum().backward()
        grads.append(a.grad)
    assert grads[0].abs().max() > 1.0  # the loss does depend on the actions
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-3, atol=1e-3)
