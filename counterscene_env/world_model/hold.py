"""Cars parked off the street, held in place (``ModelConfig.hold_parked``).

A vehicle stopped now whose centre lies more than ``hold_parked`` m outside every lane strip of
its window (a car in a parking lot or a driveway, off every street the map holds) is no
traffic the network was trained to plan: its training data hold parked cars only at the kerb,
at most ``world_model.parked.KERB_OFFSET[1]`` m outside a lane. On real streets the network
braked the moving cars near such cars as if they were queued traffic (docs/world_model.md,
"Cars parked off the street"). Such a car is taken out of the network's view (its slot
becomes padding: nobody attends to it, nothing plans it) and its plan is to stop over the
first action token and stay, which is what the logs' parked cars do.
"""

from __future__ import annotations

import torch

from counterscene_env.metrics.realism import PARKED_SPEED  # the one "parked" speed, m/s
from counterscene_env.world_model.map_guidance import lane_excess


def parked_off_lanes(
    batch: dict[str, torch.Tensor], state: torch.Tensor, valid: torch.Tensor, beyond: float
) -> torch.Tensor:
    """``[B, K]`` bool: the agents ``valid [B, K]`` slower than ``PARKED_SPEED`` at
    ``state [B, K, 4]`` (x m, y m, course rad, speed m/s) whose centre lies more than
    ``beyond`` m outside every lane strip of a window that has lanes (the batch's ``map``,
    ``map_valid``, ``map_widths``); ``beyond`` > 0 (``WorldModel.held_agents`` skips the
    call when the hold is off)."""
    stopped = valid & (state[..., 3].abs() < PARKED_SPEED)
    if not bool(stopped.any()):
        return stopped
    with torch.no_grad():
        outside = lane_excess(
            state[:, :, None, :2], batch["map"], batch["map_valid"], batch["map_widths"]
        )[..., 0]  # [B, K] m
    has_lanes = batch["map_valid"].any(-1, keepdim=True)  # no lanes: no street to be off
    return stopped & has_lanes & (outside > beyond)


def without(batch: dict[str, torch.Tensor], held: torch.Tensor) -> dict[str, torch.Tensor]:
    """``batch`` with the agents ``held [B, K]`` made padding for the network."""
    if not bool(held.any()):
        return batch
    return {**batch, "agent_valid": batch["agent_valid"] & ~held}


def stop_actions(state: torch.Tensor, tokens: int, stride: int, dt: float) -> torch.Tensor:
    """``[..., tokens, 2]`` physical action tokens (acceleration m/s^2, yaw rate rad/s) that
    bring agents at ``state [..., 4]`` to a stop over the first token (``stride`` steps of
    ``dt`` s) and keep them there, without turning: under ``PARKED_SPEED`` an agent rolls at
    most ``PARKED_SPEED * stride * dt / 2`` (0.1 m) before it stands."""
    actions = torch.zeros(*state.shape[:-1], tokens, 2, device=state.device)
    actions[..., 0, 0] = -state[..., 3] / (stride * dt)
    return actions
