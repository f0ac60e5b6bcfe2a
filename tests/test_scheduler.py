"""The cosine schedule: timesteps, forward process, posterior, guidance hook, seeding."""

from __future__ import annotations

import math

import pytest
import torch

from counterscene_env.world_model.scheduler import CosineScheduler

K = 100


def _x0_and_noise(seed=0, shape=(3, 4, 13, 2)):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=g), torch.randn(shape, generator=g)


def test_alphas_cumprod_strictly_decreasing_in_unit_interval():
    s = CosineScheduler(K)
    abar = s.alphas_cumprod
    assert abar.shape == (K,)
    assert (abar > 0).all() and (abar <= 1).all()
    assert (abar[1:] < abar[:-1]).all()
    assert abar[0] > 0.99 and abar[-1] < 1e-3  # almost clean at 0, almost pure noise at K-1
    assert (s.betas > 0).all() and (s.betas <= 0.999).all()


@pytest.mark.parametrize("n", [2, 3, 7, 10, 33, 99, 100])
def test_set_timesteps_strictly_decreasing_from_k_minus_1_to_0(n):
    s = CosineScheduler(K)
    ts = s.set_timesteps(n)
    assert ts.dtype == torch.long and len(ts) == n
    assert ts[0] == K - 1 and ts[-1] == 0
    assert (ts[1:] < ts[:-1]).all()
    assert torch.equal(s.timesteps, ts)
    assert s.previous_timestep(int(ts[0])) == (int(ts[1]))
    assert s.previous_timestep(0) == -1
    if n == K:
        assert ts.tolist() == list(range(K - 1, -1, -1))


def test_one_inference_step_goes_from_pure_noise_straight_to_clean():
    s = CosineScheduler(K)
    assert s.set_timesteps(1).tolist() == [K - 1]
    assert s.previous_timestep(K - 1) == -1
    x0, noise = _x0_and_noise()
    x0 = x0.clamp(-5, 5)
    out = s.step(x0, K - 1, noise)
    assert out.sigma == 0.0
    assert torch.equal(out.prev_sample, out.pred_original_sample)
    torch.testing.assert_close(out.prev_sample, x0)


@pytest.mark.parametrize("n", [0, -1, K + 1])
def test_set_timesteps_rejects_out_of_range(n):
    with pytest.raises(ValueError, match="num_inference_steps"):
        CosineScheduler(K).set_timesteps(n)


def test_rejects_unknown_prediction():
    with pytest.raises(ValueError, match="prediction"):
        CosineScheduler(K, prediction="v")


def test_add_noise_is_the_forward_process():
    s = CosineScheduler(K)
    x0, noise = _x0_and_noise()
    t = torch.tensor([0, 50, 99])
    xt = s.add_noise(x0, noise, t)
    for i, ti in enumerate(t.tolist()):
        abar = float(s.alphas_cumprod[ti])
        torch.testing.assert_close(xt[i], math.sqrt(abar) * x0[i] + math.sqrt(1 - abar) * noise[i])


def test_x0_prediction_perfect_model_recovers_the_sample():
    s = CosineScheduler(K, prediction="x0", clip_sample=5.0)
    x0, noise = _x0_and_noise()
    x0 = x0.clamp(-5, 5)
    s.set_timesteps(10)
    t = 44
    xt = s.add_noise(x0, noise, torch.full((3,), t))
    assert torch.equal(s.predict_original(x0, t, xt), x0)
    out = s.step(x0, 0, s.add_noise(x0, noise, torch.zeros(3, dtype=torch.long)))
    assert out.sigma == 0.0
    assert torch.equal(out.prev_sample, x0) and torch.equal(out.mean, x0)


def test_clip_sample_clips_the_predicted_x0():
    s = CosineScheduler(K, prediction="x0", clip_sample=1.5)
    x0 = torch.tensor([-4.0, -1.0, 0.5, 3.0])
    assert s.predict_original(x0, 10, torch.zeros(4)).tolist() == [-1.5, -1.0, 0.5, 1.5]
    s = CosineScheduler(K, prediction="x0", clip_sample=0.0)
    assert torch.equal(s.predict_original(x0, 10, torch.zeros(4)), x0)


@pytest.mark.parametrize("t", [0, 10, 60, 98])
def test_epsilon_prediction_with_true_noise_recovers_x0(t):
    s = CosineScheduler(K, prediction="epsilon", clip_sample=0.0)
    x0, noise = _x0_and_noise(shape=(2, 5, 2))
    x0, noise = x0.double(), noise.double()
    xt = s.add_noise(x0, noise, torch.full((2,), t))
    torch.testing.assert_close(s.predict_original(noise, t, xt), x0)


@pytest.mark.parametrize(("n", "t"), [(K, 57), (10, 55), (3, 99)])
def test_eta_one_posterior_is_the_ddpm_closed_form(n, t):
    s = CosineScheduler(K, clip_sample=0.0)
    s.set_timesteps(n)
    prev = s.previous_timestep(t)
    assert prev >= 0
    x0, xt = _x0_and_noise(seed=3, shape=(4, 6))
    x0, xt = x0.double(), xt.double()
    abar_t, abar_s = float(s.alphas_cumprod[t]), float(s.alphas_cumprod[prev])
    alpha = abar_t / abar_s
    beta = 1 - alpha
    mu = (
        math.sqrt(abar_s) * beta / (1 - abar_t) * x0
        + math.sqrt(alpha) * (1 - abar_s) / (1 - abar_t) * xt
    )
    var = beta * (1 - abar_s) / (1 - abar_t)
    mean, sigma = s.posterior(x0, t, xt, eta=1.0)
    torch.testing.assert_close(mean, mu)
    assert sigma == pytest.approx(math.sqrt(var), rel=1e-12)
    # step() draws around that mean with that sigma.
    g = torch.Generator().manual_seed(7)
    out = s.step(x0, t, xt, generator=g, eta=1.0)
    z = torch.randn(xt.shape, generator=torch.Generator().manual_seed(7), dtype=xt.dtype)
    torch.testing.assert_close(out.mean, mu)
    torch.testing.assert_close(out.prev_sample, mu + math.sqrt(var) * z)


def test_eta_zero_is_deterministic_ddim():
    s = CosineScheduler(K, clip_sample=0.0)
    s.set_timesteps(10)
    x0, xt = _x0_and_noise(seed=4, shape=(5,))
    x0, xt = x0.double(), xt.double()
    t, prev = 55, 44
    out = s.step(x0, t, xt, generator=torch.Generator().manual_seed(1), eta=0.0)
    assert out.sigma == 0.0
    abar_t, abar_s = float(s.alphas_cumprod[t]), float(s.alphas_cumprod[prev])
    eps = (xt - math.sqrt(abar_t) * x0) / math.sqrt(1 - abar_t)
    torch.testing.assert_close(
        out.prev_sample, math.sqrt(abar_s) * x0 + math.sqrt(1 - abar_s) * eps
    )
    # Half the noise scale: sigma is exactly eta times the DDPM one.
    _, sigma_half = s.posterior(x0, t, xt, eta=0.5)
    _, sigma_one = s.posterior(x0, t, xt, eta=1.0)
    assert sigma_half == pytest.approx(0.5 * sigma_one)


def test_guidance_hook_sees_mean_and_sigma_and_its_result_is_used():
    s = CosineScheduler(K, clip_sample=0.0)
    s.set_timesteps(10)
    x0, xt = _x0_and_noise(seed=5, shape=(2, 3))
    calls = []

    def shift(mean, sigma, t, pred_x0):
        calls.append((mean.clone(), sigma, t, pred_x0.clone()))
        return mean + 0.25

    # Noisy step: same generator -> the guided sample is the unguided one shifted by 0.25.
    plain = s.step(x0, 55, xt, generator=torch.Generator().manual_seed(9))
    guided = s.step(x0, 55, xt, generator=torch.Generator().manual_seed(9), guidance=shift)
    assert plain.sigma > 0
    mean, sigma, t, pred_x0 = calls[0]
    torch.testing.assert_close(mean, plain.mean)
    assert sigma == plain.sigma and t == 55
    torch.testing.assert_close(pred_x0, x0)
    torch.testing.assert_close(guided.mean, plain.mean + 0.25)
    torch.testing.assert_close(guided.prev_sample, plain.prev_sample + 0.25)
    # Last step (sigma 0): the hook's output is the next sample exactly.
    last = s.step(x0, 0, xt, guidance=shift)
    assert calls[-1][1] == 0.0
    torch.testing.assert_close(last.prev_sample, x0 + 0.25)


def test_same_generator_seed_same_step():
    s = CosineScheduler(K)
    s.set_timesteps(10)
    x0, xt = _x0_and_noise(seed=6)

    def run(seed):
        return s.step(x0, 77, xt, generator=torch.Generator().manual_seed(seed)).prev_sample

    assert torch.equal(run(11), run(11))
    assert not torch.allclose(run(11), run(12))
