"""The windows an open-loop evaluation scores (``evaluate.py``, and the measuring scripts in
``tools/``): which "now" steps of each scene, and their batches in a model's window layout.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch
from torch.utils.data import default_collate

from counterscene_env.scene.core import Scene
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.model import WorldModel


def start_steps(scene: Scene, history_steps: int, every: int | None, future: int) -> list[int]:
    """The "now" steps scored in ``scene``: its ``current_index`` (``every`` None), or every
    ``every`` steps from ``history_steps - 1`` while ``future`` logged steps follow, where the
    ego is valid."""
    if every is None:
        return [scene.current_index]
    last = scene.num_steps - 1 - future
    ego = scene.valid[scene.ego_index]
    return [t for t in range(history_steps - 1, last + 1, every) if ego[t]]


def window_jobs(
    scenes: list[Scene], history_steps: int, every: int | None, future: int
) -> list[tuple[int, int]]:
    """``(scene row, now step)`` of every scored window (``start_steps``), scene by scene; a
    log that ends at "now" has no future to score (and no frame to predict from to)."""
    return [
        (k, t)
        for k, s in enumerate(scenes)
        for t in start_steps(s, history_steps, every, future)
        if t + 1 < s.num_steps
    ]


def window_batches(
    model: WorldModel, scenes: list[Scene], jobs: list[tuple[int, int]], chunk: int = 8
) -> Iterator[tuple[list[tuple[int, int]], dict[str, torch.Tensor]]]:
    """The windows ``jobs`` (``(scene row, now step)`` of ``scenes``, in ``model``'s window
    layout), ``chunk`` at a time: ``(the chunk's jobs, their batch)``."""
    ds = SceneWindowDataset(scenes, model.window_config())
    for lo in range(0, len(jobs), chunk):
        part = jobs[lo : lo + chunk]
        items = [ds.window(k, t) for k, t in part]
        yield (
            part,
            default_collate(
                [{key: torch.from_numpy(np.asarray(v)) for key, v in w.items()} for w in items]
            ),
        )
