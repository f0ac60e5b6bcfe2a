"""The world model's training loss (``counterscene train``; docs/world_model.md, "Training").

The action MSE of the denoiser's output (normalised units) plus the rolled-out prediction's
trajectory errors, and optionally an off-lane and an overlap term. Agents the sampler holds
in place (``hold.py``) are padding here too.
"""

from __future__ import annotations

import torch

from counterscene_env.dynamics import wrap_angle
from counterscene_env.world_model import hold
from counterscene_env.world_model.map_guidance import off_lane_loss
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.overlap import overlap_loss

# Trajectory terms of the training loss, added to the action MSE (normalised units): the mean
# position error [m], heading error [rad] and speed error [m/s] of the rolled-out prediction.
TRAJECTORY_WEIGHTS = {"position": 0.1, "yaw": 1.0, "speed": 0.1}


def training_loss(
    model: WorldModel,
    batch: dict[str, torch.Tensor],
    generator: torch.Generator | None = None,
    off_lane_weight: float = 0.0,
    overlap_weight: float = 0.0,
    off_lane_by_course: bool = False,
) -> dict[str, torch.Tensor]:
    """Training loss of one batch: action MSE plus rolled-out trajectory errors.

    Args:
        batch: training windows (with ``future``).
        generator: diffusion time steps, noise and graph dropout.
        off_lane_weight: weight of the off-lane term: the mean distance [m] by which the
            rolled-out prediction lies outside every window lane strip, at the action
            tokens' steps where the log lies on one (``map_guidance.off_lane_loss``). The
            position error alone weighs a turn that goes wide onto the verge no more than
            one that goes wide along the lane; the open-loop off-road rate is mostly such
            under-turns (docs/world_model.md).
        overlap_weight: weight of the overlap term: the mean depth [m] by which the
            rolled-out prediction's boxes run into each other where the log's do not
            (``overlap.overlap_loss``). Every agent's error is otherwise scored alone, so
            nothing teaches the joint sample that two cars cannot share a place.
        off_lane_by_course: measure the off-lane term against the lanes going the
            prediction's way (and the log's gate by the log's course), as lane keeping
            measures it: a lane going against a course counts
            ``map_guidance.WRONG_WAY_PENALTY`` m farther. Off by default: a 1,500-step
            fine-tune with it did not lower the network's own wrong-way driving
            (docs/world_model_experiments.md, "Wrong-way driving").

    Returns a dict with ``loss`` (to minimise) and its terms ``action``, ``position`` [m],
    ``yaw`` [rad], ``speed`` [m/s], ``off_lane`` [m], ``overlap`` [m] (detached).
    """
    c = model.config
    # Agents the sampler holds in place are no part of what the network learns either.
    batch = hold.without(batch, model.held_agents(batch))
    hist, fut = model.kinematic_states(batch)
    target, tok_ok = model.target_actions(batch, (hist, fut))
    x0 = torch.where(tok_ok[..., None], model.normalize(target), 0.0)
    B = x0.shape[0]
    device = x0.device
    t = torch.randint(0, c.num_train_timesteps, (B,), generator=generator, device=device)
    noise = torch.randn(x0.shape, generator=generator, device=device)
    noisy = model.scheduler.add_noise(x0, noise, t)
    ctx = model.context(batch, c.graph_dropout if model.training else 0.0, generator)
    state, valid = hist[..., -1, :], model.agent_mask(batch)
    previous = given = None
    if c.plan_features == "self":
        # Self-conditioning (Chen et al. 2023): half of the windows first get the network's
        # own clean prediction without a plan, and learn to refine it; the rest learn the
        # first step, which has none. No gradient flows through the first prediction.
        given = torch.rand(B, generator=generator, device=device) < 0.5
        with torch.no_grad():
            first = model.denoise(noisy, t, ctx, state, valid)
            previous = first if c.prediction == "x0" else _x0(model, noisy, first, t)
    out = model.denoise(noisy, t, ctx, state, valid, previous, given)

    if c.prediction == "x0":
        pred_x0, goal = out, x0
    else:
        pred_x0, goal = _x0(model, noisy, out, t), noise
    w = tok_ok[..., None].float()
    action = ((out - goal) ** 2 * w).sum() / (w.sum() * 2).clamp(min=1)

    traj = model.rollout(pred_x0, hist[..., -1, :])
    fut_ok = batch["future_valid"] & model.agent_mask(batch)[..., None]
    n = fut_ok.float().sum().clamp(min=1)
    pos = ((traj[..., :2] - fut[..., :2]).norm(dim=-1) * fut_ok).sum() / n
    yaw = (wrap_angle(traj[..., 2] - fut[..., 2]).abs() * fut_ok).sum() / n
    speed = ((traj[..., 3] - fut[..., 3]).abs() * fut_ok).sum() / n
    tw = TRAJECTORY_WEIGHTS
    loss = action + tw["position"] * pos + tw["yaw"] * yaw + tw["speed"] * speed
    off_lane = torch.zeros((), device=device)
    if off_lane_weight > 0:
        courses = (traj[..., 2], fut[..., 2]) if off_lane_by_course else (None, None)
        off_lane = off_lane_loss(model, batch, traj[..., :2], fut[..., :2], fut_ok, *courses)
        loss = loss + off_lane_weight * off_lane
    overlap = torch.zeros((), device=device)
    if overlap_weight > 0:
        overlap = overlap_loss(traj, fut, batch["extents"], fut_ok)
        loss = loss + overlap_weight * overlap
    return {
        "loss": loss,
        "action": action.detach(),
        "position": pos.detach(),
        "yaw": yaw.detach(),
        "speed": speed.detach(),
        "off_lane": off_lane.detach(),
        "overlap": overlap.detach(),
    }


def _x0(model: WorldModel, noisy: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The clean actions ``[B, K, Ta, 2]`` that a noise prediction ``eps`` implies at ``t``."""
    abar = model.scheduler.alphas_cumprod.to(noisy.device)[t].float().reshape(-1, 1, 1, 1)
    return (noisy - (1 - abar).sqrt() * eps) / abar.sqrt()
