"""The settings of one ``counterscene train`` run: :class:`TrainConfig`, checked on creation,
its learning-rate schedule, and the plain form a resumed run is compared against
(``world_model/run_dir.py`` compares it).

``world_model/train.py`` runs the loop; the CLI (``cli/model.py``) builds the config.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from counterscene_env.config import MAX_RUN_SEED, bounded, check_fields

__all__ = ["UNSIZED_FIELDS", "TrainConfig", "learning_rate", "plain_settings", "same_path"]


def same_path(path: str | os.PathLike) -> str:
    """``path`` as one spelling per file: absolute, symlinks resolved, no trailing slash
    (``data/x/``, ``./data/x`` and ``/abs/data/x`` are one dataset)."""
    return str(Path(path).resolve())


@dataclass(frozen=True)
class TrainConfig:
    """Settings of one training run.

    Attributes:
        data: dataset directories (``counterscene generate`` output) or shard files.
        out: output directory (checkpoints, the EMA model, the log).
        preset: model preset (``default`` or ``paper``).
        model_overrides: ModelConfig fields to change from the preset.
        steps: optimiser steps.
        batch_size: windows per step.
        lr: Adam learning rate (paper: 1e-4).
        ema_decay: EMA decay (paper: 0.995).
        ema_start: step from which the EMA averages; before it the EMA copies the weights
            (paper: 4000).
        lr_decay_start: from this step the learning rate falls linearly to ``lr / 10`` at
            ``steps`` (None: constant, the paper's setting). Like ``steps`` it may change when a
            run is resumed.
        grad_clip: gradient-norm clip.
        window_stride: steps between training windows of one scene.
        val_fraction: fraction of each dataset's scenes held out for validation (the last ones).
        val_windows: validation windows evaluated each time (at most).
        checkpoint_every: steps between checkpoints and validations.
        seed: seeds data order, diffusion noise and initialisation (at most
            ``config.MAX_RUN_SEED``: each step's draws are seeded by ``seed * 100003 + step``).
        device: torch device.
        init: a model directory (or ``"default"``, the shipped one) whose weights and action
            normalisation start the run (fine-tuning); None: a fresh model.
        off_lane_weight: weight of the loss's off-lane term (``loss.training_loss``); 0 leaves
            it out.
        overlap_weight: weight of the loss's overlap term (``loss.training_loss``: predicted
            boxes running into each other); 0 leaves it out.
        off_lane_by_course: the off-lane term measured against the lanes going each
            prediction's way (``loss.training_loss``); off by default.
        min_future_steps: future frames a window needs inside its log (None: the model's whole
            horizon); fewer admits the ends of short real logs, their missing frames masked.
        agent_centred: those of ``data`` whose windows centre on every vehicle in turn
            (``SceneWindowDataset(centres="agents")``: real recordings), not on the ego alone.
        data_weights: share of each ``data`` entry in every batch (normalised; windows drawn
            with replacement, seeded by the step). None: every window equally likely (one
            shuffled pass per epoch), so a source's share is its share of the windows.
        parked_cars: share of the training windows that get parked cars beside their lanes
            (``world_model/parked.py``; seeded by the step); 0: none.
        smooth_tracks: those of ``data`` whose tracks are low-pass filtered before their
            windows are cut (``scene/smoothing.py``: video-tracked recordings such as NGSIM,
            whose speeds carry measurement noise); none by default.
        smooth_sigma: the filter's standard deviation [s] for ``smooth_tracks``.
    """

    data: tuple[str, ...]
    out: str
    preset: str = "default"
    model_overrides: Mapping[str, Any] = field(default_factory=dict)
    steps: int = bounded(20000, ge=1)
    batch_size: int = bounded(32, ge=1)
    lr: float = bounded(1e-4, ge=0)
    ema_decay: float = bounded(0.995, ge=0, le=1)
    ema_start: int = bounded(4000, ge=0)
    lr_decay_start: int | None = bounded(None, ge=0)
    grad_clip: float = bounded(1.0, gt=0)
    window_stride: int = bounded(5, ge=1)
    val_fraction: float = bounded(0.05, ge=0, le=0.5)
    val_windows: int = bounded(128, ge=1)
    checkpoint_every: int = bounded(500, ge=1)
    seed: int = bounded(0, ge=0, le=MAX_RUN_SEED)
    device: str = "cpu"
    init: str | None = None
    off_lane_weight: float = bounded(0.0, ge=0)
    overlap_weight: float = bounded(0.0, ge=0)
    off_lane_by_course: bool = False
    min_future_steps: int | None = bounded(None, ge=1)
    agent_centred: tuple[str, ...] = ()
    data_weights: tuple[float, ...] | None = None
    parked_cars: float = bounded(0.0, ge=0, le=1)
    smooth_tracks: tuple[str, ...] = ()
    smooth_sigma: float = bounded(0.5, gt=0)

    def __post_init__(self) -> None:
        check_fields(self)  # every number by type and range, naming the field
        data = {same_path(d) for d in self.data}
        for key in ("agent_centred", "smooth_tracks"):
            unknown = [d for d in getattr(self, key) if same_path(d) not in data]
            if unknown:
                raise ValueError(f"{key} names datasets not in data: {unknown}")
        if self.data_weights is not None:
            w = self.data_weights
            if len(w) != len(self.data):
                raise ValueError(
                    f"data_weights has {len(w)} values for {len(self.data)} data entries"
                )
            if any(not x >= 0 for x in w) or sum(w) <= 0:
                raise ValueError(f"data_weights must be >= 0 with a positive sum, got {list(w)}")

    def marked(self, key: str, dataset: str) -> bool:
        """Whether ``dataset`` of ``data`` is among ``key``'s (``agent_centred``,
        ``smooth_tracks``), as a path: ``data/x/`` and ``data/x`` are one dataset."""
        return same_path(dataset) in {same_path(d) for d in getattr(self, key)}


# ModelConfig fields that size no tensor, so ``--init`` may change them: which lanes the window
# holds, and how the model samples.
UNSIZED_FIELDS = (
    "num_lanes",
    "map_radius",
    "lane_anchors",
    "sampler",
    "sampling_steps",
    "eta",
    "map_guidance",
    "lane_steering",
    "hold_parked",
)


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """Learning rate of optimiser step ``step + 1`` (see ``TrainConfig.lr_decay_start``)."""
    start = cfg.lr_decay_start
    if start is None or step < start or cfg.steps <= start:
        return cfg.lr
    frac = min(1.0, (step - start) / (cfg.steps - start))
    return cfg.lr * (1 - 0.9 * frac)


def plain_settings(cfg: TrainConfig) -> dict[str, Any]:
    """The run settings as plain containers (compared on resume; stored in ``last.pt``)."""
    d = dataclasses.asdict(cfg)
    d["data"] = [str(x) for x in d["data"]]
    d["agent_centred"] = [str(x) for x in d["agent_centred"]]
    if not d["agent_centred"]:
        d.pop("agent_centred")  # runs from before agent-centred windows still resume
    if d["data_weights"] is None:
        d.pop("data_weights")
    else:
        d["data_weights"] = [float(x) for x in d["data_weights"]]
    d["model_overrides"] = {k: v for k, v in sorted(dict(cfg.model_overrides).items())}
    d.pop("device")
    d.pop("out")  # a moved or copied run directory still resumes
    if d["init"] is None:
        d.pop("init")  # runs from before --init existed still resume
    if d["off_lane_weight"] == 0:
        d.pop("off_lane_weight")  # and so do runs from before the off-lane term
    if d["overlap_weight"] == 0:
        d.pop("overlap_weight")  # and before the overlap term
    if not d["off_lane_by_course"]:
        d.pop("off_lane_by_course")  # and before the off-lane term by course
    if d["parked_cars"] == 0:
        d.pop("parked_cars")  # and before parked cars
    d["smooth_tracks"] = [str(x) for x in d["smooth_tracks"]]
    if not d["smooth_tracks"]:
        d.pop("smooth_tracks")  # and before smoothed tracks
        d.pop("smooth_sigma")
    d["steps"] = None  # a longer --steps continues the same run
    d["lr_decay_start"] = None  # and so may the tail of the schedule
    return d
