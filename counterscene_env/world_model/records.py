"""The records the world model hands to its callers: the action statistics stored with the
weights (:class:`Normalization`), a sampling call's output (:class:`Prediction`) and the
guidance hook's signature (:data:`GuidanceHook`). ``model.py`` produces them; the closed loop,
checkpoints and training read them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

#: ``guidance(mean, sigma, t, x0) -> mean``: edits the posterior mean ``[B*S, K, Ta, 2]``
#: (normalised actions) at one denoising step; see :meth:`CosineScheduler.step`.
GuidanceHook = Callable[[torch.Tensor, float, int, torch.Tensor], torch.Tensor]


@dataclass
class Normalization:
    """Per-channel statistics of the actions (acceleration [m/s^2], yaw rate [rad/s])."""

    action_mean: tuple[float, float] = (0.0, 0.0)
    action_std: tuple[float, float] = (1.0, 0.1)

    def to_dict(self) -> dict[str, list[float]]:
        return {"action_mean": list(self.action_mean), "action_std": list(self.action_std)}


@dataclass
class Prediction:
    """Output of :meth:`WorldModel.sample` (S samples per scene).

    Attributes:
        actions: ``[B, S, K, F, 2]`` acceleration [m/s^2], yaw rate [rad/s] per future step.
        trajectory: ``[B, S, K, F, 4]`` x [m], y [m], yaw [rad], speed [m/s], ego frame.
        normalized: ``[B, S, K, Ta, 2]`` the sampled action tokens, normalised.
        valid: ``[B, K]`` agents the prediction is meaningful for.
    """

    actions: torch.Tensor
    trajectory: torch.Tensor
    normalized: torch.Tensor
    valid: torch.Tensor
