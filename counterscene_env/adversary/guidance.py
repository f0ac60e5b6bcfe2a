"""Counterfactual guidance: remove the adversary's spatial and temporal safety margins.

Paper: "Counterfactual Guidance" and appendix "Progressive Guidance Configuration"
(Algorithm 2); docs/design.md, "Counterfactual guidance". At every denoising step but the last, the posterior mean of the
adversary's action rows takes a step down the gradient of

    L = m(p) [lambda_s (||x_e(tau_e^) - c|| + ||x_a(tau_a^) - c||)
              + lambda_t ||x_e(tau_e^) - x_a(tau_a^)||]
        + lambda_j (mean ||j_e|| + mean ||j_a||)
        + w_map * mean(off-lane distance of the adversary ^ 2)

where x are rolled-out positions (the world model's unicycle), c the mined conflict point,
(tau_e^, tau_a^) the arrival steps after compression, j the third finite difference of the
positions (jerk, m/s^3) and m(p) the stage multiplier on the progress p (these schedules and
weights: ``adversary/schedules.py``).

What the public code gets wrong and we do not (docs/design.md, "Where we depart"): the update reaches the adversary
only through a *gradient mask* (everyone else's rows are detached before the rollout, and the
gradient is masked again), never by writing into a slice of a detached copy, which silently
does nothing. The ego's predicted row is a reference only: its rows are detached too.

The step is sign-like, as one Adam step of learning rate ``step_size`` from a fresh state
(``lr * g / (|g| + eps)``, in normalised action units), clipped to +-sigma_t so guidance never
moves a sample further than the noise of that step would (the public code does; docs/design.md).
At the last step, which adds no noise, the paper's *final-step guidance* (its implementation
table: Adam, lr 0.3, one step) moves the finished sample by one unclipped step of
``final_step_size``. The clipped steps alone barely move the plan: the denoiser redraws what
the early, noisy steps changed, and the late steps' sigma_t is small (docs/history/closed_loop.md,
"Why the guidance did not bite harder").

Shapes: N = scenes x samples, K window agents, Ta action tokens, F future steps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from counterscene_env.adversary.conflicts import Conflict
from counterscene_env.adversary.schedules import (
    COMPRESSION_START,
    base_weights,
    jerk,
    stage_multiplier,
)
from counterscene_env.config import GuidancePreset, GuidanceProgress, from_mapping
from counterscene_env.world_model.map_guidance import ON_LANE_TOLERANCE, lane_excess

#: Adam's epsilon: the sign-like step is ``lr * g / (|g| + ADAM_EPS)``.
ADAM_EPS = 1e-8


@dataclass(frozen=True)
class GuidanceConfig:
    """Which parts of the counterfactual guidance are on (paper ablation, Table 4).

    Attributes:
        enabled: False is the unguided world model (preset ``none``).
        progressive: PG, the stage multiplier m(p); off: m = 1.
        conflict_aware: CW, base weights by conflict type; off: the generic weights.
        adaptive: ATC, arrival-time compression for p >= 0.5; off: the mined arrival steps.
        jerk: JR, the jerk regulariser; off: lambda_j = 0.
        map_weight: weight of the adversary's off-lane term (paper: 2.0, not scaled by m(p)).
        step_size: learning rate of the sign-like step, normalised action units (0.3).
        inner_steps: gradient steps per denoising step (their sum is clipped to +-sigma_t).
        progress: what p measures: ``"denoising"`` (the paper's main text, 1 - t / K: every
            replan's last steps are its late stage, compressing the arrival gap fully) or
            ``"rollout"`` (closed-loop step / horizon, the appendix and the public code: no
            compression before half the episode; our default before 26 Nov 2026).
        clip_scale: the step is clipped to +-``clip_scale`` sigma_t (our reference: 1).
        final_step_size: the paper's final-step guidance (implementation table: Adam, lr 0.3,
            1 step): at the last denoising step, which adds no noise and whose mean is the
            finished sample, one sign-like step of this size, not clipped (sigma is 0
            there); normalised action units. 0: none, the guidance ends at the last noisy
            step (our reference before 25 Nov 2026; docs/history/closed_loop.md, "Why the
            guidance did not bite harder").
        evaluate_on: where the loss gradient is taken: the posterior ``"mean"`` (ours) or
            the predicted clean actions ``"x0"``; the step goes to the mean either way.
    """

    enabled: bool = True
    progressive: bool = True
    conflict_aware: bool = True
    adaptive: bool = True
    jerk: bool = True
    map_weight: float = 2.0
    step_size: float = 0.3
    inner_steps: int = 1
    progress: str = GuidanceProgress.DENOISING.value
    clip_scale: float = 1.0
    final_step_size: float = 0.3
    evaluate_on: str = "mean"

    def __post_init__(self) -> None:
        object.__setattr__(self, "progress", GuidanceProgress.parse(self.progress, "progress"))
        if self.inner_steps < 1:
            raise ValueError(f"inner_steps must be >= 1, got {self.inner_steps}")
        sizes = (self.step_size, self.map_weight, self.clip_scale, self.final_step_size)
        if min(sizes) < 0:
            raise ValueError("step_size, map_weight, clip_scale and final_step_size must be >= 0")
        if self.evaluate_on not in ("mean", "x0"):
            raise ValueError(f"evaluate_on must be 'mean' or 'x0', got {self.evaluate_on!r}")

    @classmethod
    def from_mapping(cls, values: Mapping) -> GuidanceConfig:
        """Build from a dict; unknown keys raise and name the valid ones."""
        return from_mapping(cls, values, "guidance")


#: The paper's ablation rows (Table 4) plus the unguided world model.
#: Keyed by :class:`~counterscene_env.config.GuidancePreset` (its members are these strings).
PRESETS: dict[str, GuidanceConfig] = {
    GuidancePreset.FULL: GuidanceConfig(),
    GuidancePreset.NO_JERK: GuidanceConfig(jerk=False),
    GuidancePreset.NO_CONFLICT_AWARE: GuidanceConfig(conflict_aware=False),
    GuidancePreset.NO_PROGRESSIVE: GuidanceConfig(progressive=False),
    GuidancePreset.NO_ADAPTIVE: GuidanceConfig(adaptive=False),
    # "retains only the basic spatial and temporal guidance objectives"
    GuidancePreset.MINIMAL: GuidanceConfig(
        progressive=False, conflict_aware=False, adaptive=False, jerk=False
    ),
    GuidancePreset.NONE: GuidanceConfig(enabled=False),
}


def guidance_preset(name: str) -> GuidanceConfig:
    """The named preset (:data:`PRESETS`); an unknown name raises and lists the valid ones."""
    return PRESETS[GuidancePreset.parse(name, "guidance")]


# ---------------------------------------------------------------------- per replan targets
@dataclass
class GuidanceTargets:
    """What the guidance needs of B scenes at one replan, in each scene's window frame.

    Attributes:
        adversary_row: ``[B]`` long, the adversary's window row (-1: no adversary).
        conflict_point: ``[B, 2]`` m, c in the window frame.
        ego_step: ``[B]`` float, tau_e as an absolute episode step.
        adversary_step: ``[B]`` float, tau_a as an absolute episode step.
        now: ``[B]`` float, the replan step (trajectory index 0 is step ``now + 1``).
        rollout_progress: ``[B]`` float, closed-loop progress t / H in [0, 1].
        weights: ``[B, 3]`` (lambda_s, lambda_t, lambda_j).
    """

    adversary_row: torch.Tensor
    conflict_point: torch.Tensor
    ego_step: torch.Tensor
    adversary_step: torch.Tensor
    now: torch.Tensor
    rollout_progress: torch.Tensor
    weights: torch.Tensor

    def repeat(self, n: int) -> GuidanceTargets:
        """Each scene repeated ``n`` times (scene-major, like ``repeat_interleave``)."""
        return GuidanceTargets(
            **{
                f.name: getattr(self, f.name).repeat_interleave(n, 0)
                for f in dataclasses.fields(self)
            }
        )


def make_targets(
    conflicts: list[Conflict | None],
    rows: list[int],
    origins: np.ndarray,
    now: list[int],
    progress: list[float],
    config: GuidanceConfig,
) -> GuidanceTargets:
    """:class:`GuidanceTargets` of B scenes.

    Args:
        conflicts: each scene's conflict (world frame, absolute steps), or None.
        rows: each scene's adversary window row (-1 when it has none or it is not in the window).
        origins: ``[B, 3]`` window frames (world x, y m, yaw rad).
        now: the replan step of each scene.
        progress: closed-loop progress of each scene.
        config: the preset (for the conflict-aware weights).
    """
    B = len(conflicts)
    point = np.zeros((B, 2))
    steps = np.zeros((B, 2))
    weights = np.zeros((B, 3))
    adv = np.full(B, -1)
    for b, (conflict, row) in enumerate(zip(conflicts, rows, strict=True)):
        if conflict is None or row < 0:
            continue
        adv[b] = row
        x, y, yaw = origins[b]
        c, s = np.cos(yaw), np.sin(yaw)
        d = conflict.conflict_point - np.array([x, y])
        point[b] = [c * d[0] + s * d[1], -s * d[0] + c * d[1]]
        steps[b] = conflict.ego_step, conflict.adversary_step
        weights[b] = base_weights(conflict, config.conflict_aware)
    f32 = torch.float32
    return GuidanceTargets(
        adversary_row=torch.as_tensor(adv, dtype=torch.long),
        conflict_point=torch.as_tensor(point, dtype=f32),
        ego_step=torch.as_tensor(steps[:, 0], dtype=f32),
        adversary_step=torch.as_tensor(steps[:, 1], dtype=f32),
        now=torch.as_tensor(np.asarray(now, float), dtype=f32),
        rollout_progress=torch.as_tensor(np.asarray(progress, float), dtype=f32),
        weights=torch.as_tensor(weights, dtype=f32),
    )


def _schedule(
    targets: GuidanceTargets, config: GuidanceConfig, p: torch.Tensor, horizon: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """m(p) ``[N]`` and the window indices ``[N]`` of tau_e^ and tau_a^."""
    mult = (
        torch.tensor([stage_multiplier(float(q)) for q in p])
        if config.progressive
        else torch.ones_like(p)
    )
    te, ta = targets.ego_step, targets.adversary_step
    if config.adaptive:  # schedules.compressed_arrivals, row-wise
        gap = (te - ta).abs() * (1 - p)
        late = p >= COMPRESSION_START
        te, ta = (
            torch.where(late & (te > ta), ta + gap, te),
            torch.where(late & (ta >= te), te + gap, ta),
        )
    # Absolute step -> index into this window's trajectory (index 0 is step now + 1).
    je = (te.round() - targets.now - 1).clamp(0, horizon - 1).long()
    ja = (ta.round() - targets.now - 1).clamp(0, horizon - 1).long()
    return mult, je, ja


def guidance_loss(
    ego_path: torch.Tensor,
    adversary_path: torch.Tensor,
    targets: GuidanceTargets,
    config: GuidanceConfig,
    dt: float,
    p: torch.Tensor | None = None,
    lanes: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    on_lane: torch.Tensor | None = None,
) -> torch.Tensor:
    """The counterfactual loss ``[N]`` (module docstring).

    Args:
        ego_path, adversary_path: ``[N, F, 2]`` m rolled-out positions (window frame); index
            j is step ``now + 1 + j``.
        targets: per row (already repeated for samples); rows without an adversary get 0.
        config: the preset.
        dt: step [s] (for the jerk).
        p: progress ``[N]`` overriding the rollout progress (the ``denoising`` option).
        lanes: (points ``[N, M, P, 2]``, valid ``[N, M]``, widths ``[N, M]``) of the window map,
            for the off-lane term; ``on_lane [N]`` keeps it to adversaries that start on a lane.
    """
    N, F, _ = adversary_path.shape
    p = targets.rollout_progress if p is None else p
    mult, je, ja = _schedule(targets, config, p, F)
    n = torch.arange(N)
    x_e, x_a = ego_path[n, je], adversary_path[n, ja]
    c = targets.conflict_point
    spatial = (x_e - c).norm(dim=-1) + (x_a - c).norm(dim=-1)
    sync = (x_e - x_a).norm(dim=-1)
    lam_s, lam_t, lam_j = targets.weights.unbind(-1)
    loss = mult * (lam_s * spatial + lam_t * sync)
    if config.jerk:
        loss = loss + lam_j * (jerk(ego_path, dt) + jerk(adversary_path, dt))
    if lanes is not None and config.map_weight > 0:
        off = lane_excess(adversary_path[:, None], *lanes)[:, 0]  # [N, F] m
        term = (off**2).mean(-1)
        if on_lane is not None:
            term = torch.where(on_lane, term, 0.0)
        loss = loss + config.map_weight * term
    return torch.where(targets.adversary_row >= 0, loss, 0.0)


def pair_paths(
    model, normalized: torch.Tensor, state: torch.Tensor, targets: GuidanceTargets
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rolled-out ego and adversary positions ``[N, F, 2]`` m from action tokens
    ``[N, K, Ta, 2]`` (normalised) and current states ``[N, K, 4]``: only these two rows are
    rolled out (the loss reads nothing else)."""
    n = torch.arange(normalized.shape[0])
    rows = torch.stack(
        [torch.zeros_like(targets.adversary_row), targets.adversary_row.clamp(min=0)], 1
    )
    xy = model.rollout(normalized[n[:, None], rows], state[n[:, None], rows])[..., :2]
    return xy[:, 0], xy[:, 1]


def make_guidance_hook(
    model,
    batch: dict[str, torch.Tensor],
    targets: GuidanceTargets,
    num_samples: int,
    config: GuidanceConfig,
):
    """The ``guidance(mean, sigma, t, x0) -> mean`` hook for ``WorldModel.sample``.

    Args:
        model: the world model (its rollout maps normalised actions to positions).
        batch: the B windows being sampled.
        targets: per scene (B rows); repeated here for the samples.
        num_samples: S; the hook sees ``B * S`` rows, scene-major.
        config: the preset.
    """
    S = num_samples
    tg = targets.repeat(S)
    state = model.current_state(batch).repeat_interleave(S, 0)  # [N, K, 4]
    lanes = tuple(batch[k].repeat_interleave(S, 0) for k in ("map", "map_valid", "map_widths"))
    N, K = state.shape[:2]
    has = tg.adversary_row >= 0
    adv_mask = torch.zeros(N, K, dtype=torch.bool)
    adv_mask[has, tg.adversary_row[has]] = True
    with torch.no_grad():
        adv_now = state[torch.arange(N), tg.adversary_row.clamp(min=0), :2]
        on_lane = lane_excess(adv_now[:, None, None], *lanes)[:, 0, 0] <= ON_LANE_TOLERANCE
    mask = adv_mask[..., None, None]
    K_train = model.config.num_train_timesteps
    dt = model.config.dt

    def sign_step(x: torch.Tensor, size: float, p: torch.Tensor | None) -> torch.Tensor:
        """``-size * g / (|g| + eps)`` on the adversary's rows, g the loss gradient at ``x``."""
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            # The gradient mask: every row but the adversary's is detached before the
            # rollout, so the loss cannot move the ego or any other agent.
            x_in = torch.where(mask, x, x.detach())
            ego_path, adv_path = pair_paths(model, x_in, state, tg)
            loss = guidance_loss(ego_path, adv_path, tg, config, dt, p, lanes, on_lane)
            (grad,) = torch.autograd.grad(loss.sum(), x)
        grad = torch.where(mask, grad, 0.0)
        return -size * grad / (grad.abs() + ADAM_EPS)

    def hook(mean: torch.Tensor, sigma: float, t: int, x0: torch.Tensor) -> torch.Tensor:
        if not has.any():
            return mean
        p = None
        if config.progress == GuidanceProgress.DENOISING:
            p = torch.full((N,), 1.0 - t / K_train)
        if sigma <= 0:
            # The last step adds no noise: its mean is the finished sample. The paper's
            # final-step guidance takes one step of its own size there, unclipped.
            if config.final_step_size <= 0:
                return mean
            return mean + sign_step(mean, config.final_step_size, p)
        limit = config.clip_scale * sigma
        if limit <= 0:
            return mean
        base = x0 if config.evaluate_on == "x0" else mean
        delta = torch.zeros_like(mean)
        for _ in range(config.inner_steps):
            step = sign_step(base + delta, config.step_size, p)
            delta = (delta + step).clamp(-limit, limit)
        return mean + delta

    hook.on_lane = on_lane  # for best-of-N scoring with the same off-lane switch
    hook.lanes = lanes
    hook.state = state
    hook.targets = tg
    hook.mask = mask  # [N, K, 1, 1] the adversary's rows: the only ones the guidance moves
    return hook


def sample_losses(model, hook, normalized: torch.Tensor, config: GuidanceConfig) -> torch.Tensor:
    """``[B, S]`` guidance loss of each final sample, from the action tokens
    ``[B, S, K, Ta, 2]`` (normalised) of a sampling call guided by ``hook`` (best-of-N)."""
    B, S = normalized.shape[:2]
    flat = normalized.reshape(B * S, *normalized.shape[2:])
    with torch.no_grad():
        ego_path, adv_path = pair_paths(model, flat, hook.state, hook.targets)
        loss = guidance_loss(
            ego_path,
            adv_path,
            hook.targets,
            config,
            model.config.dt,
            None,
            hook.lanes,
            hook.on_lane,
        )
    return loss.reshape(B, S)
