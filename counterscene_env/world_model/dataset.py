"""Training windows: a torch ``Dataset`` over scenes, each item one model window.

Items are :func:`counterscene_env.world_model.window.make_window` windows (the key table is in
``world_model/window.py``) as tensors, plus ``scene_index``: the row of the scene in the
dataset. Windows are all ``t0`` in ``[history_steps - 1, T - min_future_steps - 1]`` (step
``stride``) at which the window's centre is valid.

Centres (``centres``): ``"ego"`` centres every window on the scene's ego (generated traffic:
the ego is an ordinary IDM car). ``"agents"`` makes every vehicle a centre in turn, wherever it
has at least :data:`MIN_CENTRE_HISTORY` valid frames up to ``t0`` and ``min_future_steps``
valid frames after it: a real recording has one logged "ego" at most, and most of its
vehicles would otherwise only ever be seen from far away, without the lanes around them.

``min_future_steps`` defaults to the window's ``future_steps`` (every window has its whole
future); a smaller value admits windows near the end of short real logs, whose missing future
frames are invalid and masked out of the loss (``future_valid``). NGSIM recordings run 7 s at
the median: with full 5.2 s futures only 15 of 84 give a window at all (docs/scenes.md).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from counterscene_env.config import WindowCentres
from counterscene_env.scene.core import Scene
from counterscene_env.scene.manifest import MANIFEST, shard_paths
from counterscene_env.scene.shards import load_scenes
from counterscene_env.world_model.window import WindowConfig, lane_segments, make_window

#: Valid frames up to and including ``t0`` a vehicle needs to centre a window (``"agents"``):
#: 1 s, so that its course and speed "now" come from a real track, not from its first frame.
MIN_CENTRE_HISTORY = 10


class SceneWindowDataset(Dataset):
    """Windows over scenes from shard files or dataset directories (see module docstring).

    Args:
        sources: dataset directories (with ``manifest.json``), shard files, or ``Scene`` objects.
        config: window sizes.
        min_future_steps: future frames a window needs inside the log (None: all
            ``future_steps``; at least 1).
        centres: ``"ego"`` or ``"agents"`` (module docstring).

    Attributes:
        index: ``(scene row, t0, centre row)`` of each item.

    Raises:
        ValueError: ``min_future_steps`` outside ``[1, future_steps]``, or an unknown
            ``centres``.
    """

    def __init__(
        self,
        sources: Sequence[str | os.PathLike | Scene] | str | os.PathLike,
        config: WindowConfig | None = None,
        min_future_steps: int | None = None,
        centres: str = WindowCentres.EGO,
    ) -> None:
        centres = WindowCentres.parse(centres)
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
        self.index: list[tuple[int, int, int]] = []
        for i, s in enumerate(self.scenes):
            first, last = c.history_steps - 1, s.num_steps - need - 1
            for t in range(first, last + 1, c.stride):
                if centres == WindowCentres.EGO:
                    if s.valid[s.ego_index, t]:
                        self.index.append((i, t, s.ego_index))
                    continue
                ok = s.valid[:, max(0, t - MIN_CENTRE_HISTORY + 1) : t + 1].all(axis=1)
                ok &= s.valid[:, t + 1 : t + 1 + need].sum(axis=1) >= need
                ok &= s.agent_types == "vehicle"
                self.index += [(i, t, int(r)) for r in np.flatnonzero(ok)]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        i, t0, centre = self.index[item]
        window = self.window(i, t0, centre)
        return {k: torch.from_numpy(np.asarray(v)) for k, v in window.items()}

    def window(self, scene_index: int, t0: int, centre: int | None = None) -> dict[str, np.ndarray]:
        """The window of one scene at one step, centred on agent row ``centre`` (None: the
        scene's ego), as numpy arrays (see the module docstring)."""
        scene = self.scenes[scene_index]
        if centre is not None and centre != scene.ego_index:
            scene = scene.replace(ego_index=int(centre))
        window = make_window(scene, t0, self.config, self._segments[scene_index])
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
