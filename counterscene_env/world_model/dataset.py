"""Training windows: a torch ``Dataset`` over scenes, each item one model window.

Items are :func:`counterscene_env.world_model.window.make_window` windows (the key table is in
``world_model/window.py``) as tensors, plus ``scene_index``: the row of the scene in the
dataset. Windows are all ``t0`` in ``[history_steps - 1, T - min_future_steps - 1]`` (step
``stride``) at which the ego is valid. ``min_future_steps`` defaults to the window's
``future_steps`` (every window has its whole future); a smaller value admits windows near the
end of short real logs, whose missing future frames are invalid and masked out of the loss
(``future_valid``). NGSIM recordings run 7 s at the median: with full 5.2 s futures only about
15 of 84 give a window at all.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from counterscene_env.scene.core import Scene
from counterscene_env.scene.datagen import MANIFEST, shard_paths
from counterscene_env.scene.shards import load_scenes
from counterscene_env.world_model.window import WindowConfig, lane_segments, make_window


class SceneWindowDataset(Dataset):
    """Windows over scenes from shard files or dataset directories (see module docstring).

    Args:
        sources: dataset directories (with ``manifest.json``), shard files, or ``Scene`` objects.
        config: window sizes.
        min_future_steps: future frames a window needs inside the log (None: all
            ``future_steps``; at least 1).

    Raises:
        ValueError: ``min_future_steps`` outside ``[1, future_steps]``.
    """

    def __init__(
        self,
        sources: Sequence[str | os.PathLike | Scene] | str | os.PathLike,
        config: WindowConfig | None = None,
        min_future_steps: int | None = None,
    ) -> None:
        self.config = config or WindowConfig()
        need = self.config.future_steps if min_future_steps is None else int(min_future_steps)
        if not 1 <= need <= self.config.future_steps:
            raise ValueError(
                f"min_future_steps must be in [1, {self.config.future_steps}], got {need}"
            )
        self.scenes: list[Scene] = load_sources(sources)
        c = self.config
        self._segments = [
            lane_segments(s, c.lane_segment_length, c.lane_points) for s in self.scenes
        ]
        self.index: list[tuple[int, int]] = []
        for i, s in enumerate(self.scenes):
            first, last = c.history_steps - 1, s.num_steps - need - 1
            self.index += [
                (i, t) for t in range(first, last + 1, c.stride) if s.valid[s.ego_index, t]
            ]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        i, t0 = self.index[item]
        return {k: torch.from_numpy(np.asarray(v)) for k, v in self.window(i, t0).items()}

    def window(self, scene_index: int, t0: int) -> dict[str, np.ndarray]:
        """The window of one scene at one step, as numpy arrays (see the module docstring)."""
        window = make_window(self.scenes[scene_index], t0, self.config, self._segments[scene_index])
        window["scene_index"] = np.int64(scene_index)
        return window


def load_sources(
    sources: Sequence[str | os.PathLike | Scene] | str | os.PathLike,
) -> list[Scene]:
    """Scenes from dataset directories (with ``manifest.json``), shard files or ``Scene``s."""
    if isinstance(sources, (str, os.PathLike)):
        sources = [sources]
    scenes: list[Scene] = []
    for src in sources:
        if isinstance(src, Scene):
            scenes.append(src)
        elif (Path(src) / MANIFEST).is_file():
            for shard in shard_paths(src):
                scenes.extend(load_scenes(shard))
        else:
            scenes.extend(load_scenes(src))
    return scenes
