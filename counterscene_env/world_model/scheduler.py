"""Cosine noise schedule with DDPM (all K steps) and strided DDIM-style sampling.

The API follows diffusers' schedulers: :meth:`CosineScheduler.set_timesteps` picks the steps,
:meth:`CosineScheduler.step` takes the network output at one step and returns the next sample
together with the predicted clean sample, the posterior mean and its standard deviation, the two
quantities the counterfactual guidance edits (docs/design.md, "Counterfactual guidance").

Notation (paper, "Diffusion Generation"): ``abar_k = prod_{i<=k} (1 - beta_i)``,

    x_k = sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps,           eps ~ N(0, I)        (forward)

and for a jump from step t down to step s < t (s = -1 means "clean", abar_{-1} = 1), with
``alpha_{t|s} = abar_t / abar_s`` and ``beta_{t|s} = 1 - alpha_{t|s}``, the posterior

    q(x_s | x_t, x_0) = N(mu, sigma^2),
    mu      = sqrt(abar_s) beta_{t|s} / (1 - abar_t) x_0 + sqrt(alpha_{t|s}) (1 - abar_s) / (1 - abar_t) x_t
    sigma^2 = beta_{t|s} (1 - abar_s) / (1 - abar_t).

With s = t - 1 this is DDPM's ancestral step; with strides it is DDIM with eta = 1. For eta < 1
the DDIM update keeps a fraction of the predicted noise deterministic (Song et al., eq. 12).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class SchedulerOutput:
    """Result of one reverse step (all ``[...]`` like the sample).

    Attributes:
        prev_sample: x_s, the sample at the next (less noisy) step.
        pred_original_sample: the predicted clean sample x_0 (after clipping).
        mean: the posterior mean mu that ``prev_sample`` was drawn around.
        sigma: the standard deviation of that draw (0 at the last step).
    """

    prev_sample: torch.Tensor
    pred_original_sample: torch.Tensor
    mean: torch.Tensor
    sigma: float


class CosineScheduler:
    """Cosine schedule (Nichol & Dhariwal 2021) over ``num_train_timesteps`` steps.

    Args:
        num_train_timesteps: K (paper: 100).
        prediction: ``"x0"`` (the network predicts the clean sample) or ``"epsilon"``.
        clip_sample: clip predicted x_0 to +-this; 0 disables.
        s: the cosine schedule's offset.
    """

    def __init__(
        self,
        num_train_timesteps: int = 100,
        prediction: str = "x0",
        clip_sample: float = 5.0,
        s: float = 0.008,
    ) -> None:
        if prediction not in ("x0", "epsilon"):
            raise ValueError("prediction must be 'x0' or 'epsilon'")
        self.num_train_timesteps = num_train_timesteps
        self.prediction = prediction
        self.clip_sample = clip_sample
        # abar(t) = f(t) / f(0), f(t) = cos^2(((t / K) + s) / (1 + s) pi / 2); betas clipped at
        # 0.999 so the last step is not a pure-noise singularity.
        k = torch.arange(num_train_timesteps + 1, dtype=torch.float64)
        f = torch.cos(((k / num_train_timesteps) + s) / (1 + s) * math.pi / 2) ** 2
        betas = (1 - f[1:] / f[:-1]).clamp(max=0.999)
        self.betas = betas
        self.alphas_cumprod = torch.cumprod(1 - betas, 0)
        self.timesteps = torch.arange(num_train_timesteps - 1, -1, -1)

    def set_timesteps(self, num_inference_steps: int) -> torch.Tensor:
        """Choose the reverse steps: ``num_inference_steps`` steps from K-1 down to 0.

        Returns the strictly decreasing integer steps (also kept as ``self.timesteps``).
        """
        K = self.num_train_timesteps
        if not 1 <= num_inference_steps <= K:
            raise ValueError(f"num_inference_steps must be in [1, {K}], got {num_inference_steps}")
        # Evenly spaced, always including K-1 (start from noise) and 0 (end clean).
        steps = torch.linspace(K - 1, 0, num_inference_steps).round().long()
        self.timesteps = torch.unique_consecutive(steps)
        return self.timesteps

    def previous_timestep(self, t: int) -> int:
        """The step after ``t`` in the current ``timesteps`` (-1 after the last)."""
        ts = self.timesteps.tolist()
        i = ts.index(int(t))
        return ts[i + 1] if i + 1 < len(ts) else -1

    def _abar(self, t: int) -> float:
        return 1.0 if t < 0 else float(self.alphas_cumprod[t])

    def add_noise(
        self, original: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor
    ) -> torch.Tensor:
        """Forward process: ``x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps``.

        ``timesteps`` is ``[B]``; ``original`` and ``noise`` are ``[B, ...]``.
        """
        abar = self.alphas_cumprod.to(original.device)[timesteps].to(original.dtype)
        abar = abar.reshape(-1, *([1] * (original.dim() - 1)))
        return abar.sqrt() * original + (1 - abar).sqrt() * noise

    def predict_original(
        self, model_output: torch.Tensor, t: int, sample: torch.Tensor
    ) -> torch.Tensor:
        """x_0 from the network output at step ``t`` (clipped if ``clip_sample``)."""
        if self.prediction == "x0":
            x0 = model_output
        else:
            # Invert the forward process: x_0 = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t).
            abar = self._abar(t)
            x0 = (sample - math.sqrt(1 - abar) * model_output) / math.sqrt(abar)
        if self.clip_sample > 0:
            x0 = x0.clamp(-self.clip_sample, self.clip_sample)
        return x0

    def posterior(
        self, x0: torch.Tensor, t: int, sample: torch.Tensor, eta: float = 1.0
    ) -> tuple[torch.Tensor, float]:
        """Mean and standard deviation of x_s given x_t = ``sample`` and x_0 (module docstring).

        ``eta = 1`` is the DDPM posterior; ``eta < 1`` the DDIM generalisation, whose mean
        moves toward the deterministic DDIM update and whose sigma shrinks by ``eta``.
        """
        s = self.previous_timestep(t)
        abar_t, abar_s = self._abar(t), self._abar(s)
        beta_ts = 1 - abar_t / abar_s
        var = beta_ts * (1 - abar_s) / (1 - abar_t)
        sigma = eta * math.sqrt(max(var, 0.0))
        # DDIM (Song et al. eq. 12): x_s = sqrt(abar_s) x0 + sqrt(1 - abar_s - sigma^2) eps_hat
        # + sigma z. With sigma^2 = var this equals the DDPM posterior mean above.
        eps_hat = (sample - math.sqrt(abar_t) * x0) / math.sqrt(1 - abar_t)
        mean = math.sqrt(abar_s) * x0 + math.sqrt(max(1 - abar_s - sigma**2, 0.0)) * eps_hat
        return mean, sigma

    def step(
        self,
        model_output: torch.Tensor,
        t: int,
        sample: torch.Tensor,
        generator: torch.Generator | None = None,
        eta: float = 1.0,
        guidance=None,
        noise: torch.Tensor | None = None,
    ) -> SchedulerOutput:
        """One reverse step from ``t`` to the next step in ``timesteps``.

        Args:
            model_output: network output at step ``t`` (x_0 or eps, as ``prediction``).
            t: the current step.
            sample: x_t.
            generator: source of the step's noise (required whenever sigma > 0).
            eta: DDIM noise scale (1 = ancestral).
            guidance: optional ``callable(mean, sigma, t, x0) -> mean`` that may move the
                posterior mean before the noise is added (the counterfactual guidance hook).
            noise: the step's standard normal noise, shaped like ``sample``, instead of drawing
                it from ``generator`` (diffusers' ``variance_noise``; lets a batch of scenes
                draw from one generator each).
        """
        x0 = self.predict_original(model_output, t, sample)
        mean, sigma = self.posterior(x0, t, sample, eta)
        if guidance is not None:
            mean = guidance(mean, sigma, t, x0)
        if sigma > 0:
            if noise is None:
                noise = torch.randn(
                    sample.shape, generator=generator, device=sample.device, dtype=sample.dtype
                )
            prev = mean + sigma * noise
        else:
            prev = mean
        return SchedulerOutput(prev, x0, mean, sigma)
