"""The diffusion world model: denoiser with the Causal Interaction Graph, scheduler, training,
checkpoints and the shipped default (see ``docs/world_model.md``).

- :class:`WorldModel` samples every agent's future actions and rolls them out (``model.py``).
- :func:`load_model` / :func:`save_model` read and write ``model.safetensors`` + ``config.json``.
- :class:`ModelConfig` and :func:`preset` (``"default"`` for CPU, ``"paper"``) size the network.
"""

from counterscene_env.world_model.checkpoint import (
    DEFAULT_MODEL_DIR,
    CheckpointError,
    load_model,
    save_model,
)
from counterscene_env.world_model.config import PRESETS, ModelConfig, preset
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import Normalization, Prediction
from counterscene_env.world_model.scheduler import CosineScheduler, SchedulerOutput

__all__ = [
    "DEFAULT_MODEL_DIR",
    "PRESETS",
    "CheckpointError",
    "CosineScheduler",
    "ModelConfig",
    "Normalization",
    "Prediction",
    "SchedulerOutput",
    "WorldModel",
    "load_model",
    "preset",
    "save_model",
]
