"""Smoothed tracks (``scene/smoothing.py``, ``counterscene train --smooth-tracks``)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from counterscene_env.scene.smoothing import smooth_tracks


def _track(T, x0, vx, vy, ax, yaw0, rate):
    """Positions ``[T, 2]``, headings and speeds of a car speeding up at ``ax`` and turning
    its heading at ``rate``: each channel is a polynomial of degree <= 2 in time."""
    t = np.arange(T) * 0.1
    pos = np.stack([x0 + vx * t + 0.5 * ax * t**2, 2.0 + vy * t], -1)
    return pos, yaw0 + rate * t, 20.0 + ax * t


@settings(max_examples=40, deadline=None)
@given(
    T=st.integers(1, 60),
    vx=st.floats(0, 30),
    vy=st.floats(-3, 3),
    ax=st.floats(-3, 3),
    yaw0=st.floats(-3, 3),
    rate=st.floats(-0.5, 0.5),
    sigma=st.floats(0.05, 2.0),
)
def test_steady_manoeuvres_come_out_unchanged(T, vx, vy, ax, yaw0, rate, sigma):
    """A car speeding up or braking at a constant rate while its heading turns at a constant
    rate is not noise: the filter leaves it where it is, ends included, whatever the width
    against the run."""
    pos, yaw, speed = _track(T, 10.0, vx, vy, ax, yaw0, rate)
    scene = make_scene(pos[None], yaws=yaw[None], speeds=speed[None])
    out = smooth_tracks(scene, sigma)
    np.testing.assert_allclose(out.positions, scene.positions, atol=1e-9)
    np.testing.assert_allclose(np.cos(out.yaws - scene.yaws), 1.0, atol=1e-12)
    np.testing.assert_allclose(out.speeds, scene.speeds, atol=1e-9)


def test_measurement_noise_is_taken_out():
    """A steady car tracked with noise: the smoothed track lies nearer the true one, its
    speeds swing less, and the headings stay continuous across +-pi."""
    rng = np.random.default_rng(0)
    T = 80
    pos, yaw, _ = _track(T, 0.0, -10.0, 0.0, 0.0, np.pi - 0.01, 0.0)  # westbound, at the seam
    noisy_pos = pos + rng.normal(0, 0.2, pos.shape)
    noisy_speed = 10.0 + rng.normal(0, 0.8, T)
    noisy_yaw = np.angle(np.exp(1j * (yaw + rng.normal(0, 0.05, T))))
    scene = make_scene(noisy_pos[None], yaws=noisy_yaw[None], speeds=noisy_speed[None])
    out = smooth_tracks(scene, 0.5)
    err = lambda p: np.linalg.norm(p[0] - pos, axis=-1).mean()  # noqa: E731
    assert err(out.positions) < 0.5 * err(scene.positions)
    assert np.diff(out.speeds[0]).std() < 0.25 * np.diff(noisy_speed).std()
    assert np.abs(np.angle(np.exp(1j * (out.yaws[0] - np.pi)))).max() < 0.05
    assert out.metadata["smoothed_sigma_s"] == 0.5


def test_runs_are_smoothed_apart_and_the_scene_is_not_touched():
    """Two runs of one agent split by missing steps: neither bleeds into the other (a jump
    between them stays a jump), the missing steps keep their values, and the input scene
    is unchanged (the filter returns a new scene)."""
    T = 40
    pos = np.zeros((1, T, 2))
    pos[0, :20, 0] = np.arange(20) * 1.0
    pos[0, 25:, 0] = 100 + np.arange(15) * 1.0
    valid = np.ones((1, T), bool)
    valid[0, 20:25] = False
    speeds = np.where(valid, 10.0, 0.0)
    scene = make_scene(pos, speeds=speeds, valid=valid)
    before = scene.positions.copy()
    out = smooth_tracks(scene, 1.0)
    np.testing.assert_allclose(out.positions, before, atol=1e-9)  # two straight runs
    np.testing.assert_array_equal(scene.positions, before)
    np.testing.assert_array_equal(out.valid, scene.valid)


def test_a_start_from_standstill_keeps_speeds_at_or_above_zero():
    T = 30
    speed = np.concatenate([np.zeros(10), np.linspace(0, 6, 20) ** 1.5])
    pos = np.stack([np.cumsum(speed) * 0.1, np.zeros(T)], -1)
    out = smooth_tracks(make_scene(pos[None], speeds=speed[None]), 0.5)
    assert out.speeds.min() >= 0.0


@pytest.mark.parametrize("sigma", [0.0, -1.0, float("nan")])
def test_a_width_not_above_zero_is_refused_by_name(sigma):
    with pytest.raises(ValueError, match="sigma"):
        smooth_tracks(make_scene(np.zeros((1, 5, 2))), sigma)
