"""Open-loop evaluation of a world model (``counterscene evaluate-model``).

For each scene, at its "now" step (``current_index``, 3 s of history), the model predicts every
agent it sees (the ego and its nearest vehicles, ``num_agents`` within ``agent_radius``) over its
horizon, ``num_samples`` samples in one batched call. Against the log's future:

- ``ade[h]``: mean displacement [m] over steps 1..h of the *first* sample, averaged over agents
  with at least one valid frame in that range; ``fde[h]``: displacement at step h, over agents
  valid at step h. ``h`` is 1 s, 2 s, 3 s and the full horizon (``"full"``).
- ``min_ade_6[h]``, ``min_fde_6[h]``: the same, per agent the best of the samples (marginal,
  as in motion-forecasting benchmarks).
- ``offroad_rate``: fraction of predicted centre positions (all samples, valid agents, all
  horizon steps) outside the drivable area.

The constant-velocity baseline moves each agent along its current course at its current speed.
The log's own off-road rate over the same agent-steps is reported as ``log_offroad_rate`` (real
maps leave parked cars off the lanes).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import shapely
import torch
from torch.utils.data import default_collate

from counterscene_env.geometry import from_frame, points_in_area
from counterscene_env.scene.core import Scene
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.model import WorldModel


def horizons(model: WorldModel) -> dict[str, int]:
    """Horizon name -> step count: ``"1s"``, ``"2s"``, ``"3s"`` (those within the model's
    horizon) and ``"full"``."""
    steps = {f"{s}s": round(s / model.config.dt) for s in (1, 2, 3)}
    out = {k: v for k, v in steps.items() if v <= model.config.future_steps}
    out["full"] = model.config.future_steps
    return out


class _Accumulator:
    """Sums per horizon of displacement statistics (agent-weighted)."""

    def __init__(self, hz: dict[str, int]) -> None:
        self.hz = hz
        self.sums = {k: {h: [0.0, 0] for h in hz} for k in ("ade", "fde", "min_ade", "min_fde")}
        self.off = [0, 0]
        self.log_off = [0, 0]

    def add(self, err: np.ndarray, ok: np.ndarray) -> None:
        """``err [S, A, F]`` m for ``A`` agents, ``ok [A, F]`` bool."""
        for h, n in self.hz.items():
            o = ok[:, :n]
            has = o.any(-1)
            ade = (err[:, :, :n] * o).sum(-1) / np.maximum(o.sum(-1), 1)  # [S, A]
            self._acc("ade", h, ade[0, has])
            self._acc("min_ade", h, ade[:, has].min(0))
            end = ok[:, n - 1]
            self._acc("fde", h, err[0, end, n - 1])
            self._acc("min_fde", h, err[:, end, n - 1].min(0))

    def _acc(self, key: str, h: str, values: np.ndarray) -> None:
        self.sums[key][h][0] += float(values.sum())
        self.sums[key][h][1] += int(values.size)

    def result(self, key: str) -> dict[str, float | None]:
        return {h: (s / n if n else None) for h, (s, n) in self.sums[key].items()}


def evaluate_model(
    model: WorldModel,
    scenes: Iterable[Scene],
    num_samples: int = 6,
    seed: int = 0,
    chunk: int = 8,
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate ``model`` open loop on ``scenes`` (module docstring); returns the JSON summary."""
    scenes = list(scenes)
    model = model.eval()
    ds = SceneWindowDataset(scenes, model.window_config())
    hz = horizons(model)
    ours, cv = _Accumulator(hz), _Accumulator(hz)
    g = torch.Generator().manual_seed(seed)
    areas = [s.road.drivable_area for s in scenes]
    for a in areas:
        shapely.prepare(a)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(scenes), desc="evaluate", unit="scene", dynamic_ncols=True)
    agents = 0
    for lo in range(0, len(scenes), chunk):
        idx = range(lo, min(lo + chunk, len(scenes)))
        items = [ds.window(i, scenes[i].current_index) for i in idx]
        batch = default_collate(
            [{k: torch.from_numpy(np.asarray(v)) for k, v in w.items()} for w in items]
        )
        agents += _score_chunk(model, batch, [areas[i] for i in idx], num_samples, g, ours, cv)
        if bar is not None:
            bar.update(len(idx))
    if bar is not None:
        bar.close()
    return _summary(model, len(scenes), agents, num_samples, ours, cv)


def _score_chunk(
    model: WorldModel,
    batch: dict[str, torch.Tensor],
    areas: list,
    num_samples: int,
    g: torch.Generator,
    ours: _Accumulator,
    cv: _Accumulator,
) -> int:
    """Sample a batch of B scenes; add model and constant-velocity errors; return agents scored."""
    F = model.config.future_steps
    with torch.no_grad():
        prediction = model.sample(batch, num_samples, g)
        pred = prediction.trajectory.numpy()  # [B, S, K, F, 4]
        agent_ok = prediction.valid.numpy()  # [B, K]
        state = model.current_state(batch).numpy()  # [B, K, 4]
    t = (np.arange(1, F + 1) * model.config.dt)[None, :, None]
    heading = np.stack([np.cos(state[..., 2]), np.sin(state[..., 2])], -1)
    cv_xy = state[:, :, None, :2] + (state[:, :, None, 3:4] * t) * heading[:, :, None, :]
    future = batch["future"].numpy()
    valid = batch["future_valid"].numpy() & agent_ok[..., None]
    agents = 0
    for b, area in enumerate(areas):
        keep = agent_ok[b]
        if not keep.any():
            continue
        agents += int(keep.sum())
        ok = valid[b][keep]  # [A, F]
        gt = future[b][keep, :, :2]
        p = pred[b][:, keep, :, :2]  # [S, A, F, 2]
        c = cv_xy[b][keep][None]
        origin = batch["origin"][b].numpy()
        _score_scene(area, origin, ok, gt, p, c, ours, cv)
    return agents


def _score_scene(
    area,
    origin: np.ndarray,
    ok: np.ndarray,
    gt: np.ndarray,
    p: np.ndarray,
    c: np.ndarray,
    ours: _Accumulator,
    cv: _Accumulator,
) -> None:
    """Add one scene's errors [m] and off-road counts (``p [S, A, F, 2]``, ``ok [A, F]``)."""
    ours.add(np.linalg.norm(p - gt, axis=-1), ok)
    cv.add(np.linalg.norm(c - gt, axis=-1), ok)
    for acc, xy in ((ours, p), (cv, c)):
        inside = points_in_area(area, from_frame(xy, origin))  # [S, A, F]
        mask = np.broadcast_to(ok, inside.shape)
        acc.off[0] += int((~inside & mask).sum())
        acc.off[1] += int(mask.sum())
    log_in = points_in_area(area, from_frame(gt, origin))
    ours.log_off[0] += int((~log_in & ok).sum())
    ours.log_off[1] += int(ok.sum())


def _rate(pair: list[int]) -> float | None:
    """``pair[0] / pair[1]``, or None if the denominator is 0."""
    return pair[0] / pair[1] if pair[1] else None


def _summary(
    model: WorldModel,
    scenes: int,
    agents: int,
    num_samples: int,
    ours: _Accumulator,
    cv: _Accumulator,
) -> dict[str, Any]:
    """The JSON summary of :func:`evaluate_model` from its accumulated sums."""
    return {
        "scenes": scenes,
        "agents": agents,
        "samples": num_samples,
        "horizon_s": model.config.horizon,
        "lane_steering": model.config.lane_steering,
        "model": {
            "ade": ours.result("ade"),
            "fde": ours.result("fde"),
            "min_ade_6": ours.result("min_ade"),
            "min_fde_6": ours.result("min_fde"),
            "offroad_rate": _rate(ours.off),
        },
        "constant_velocity": {
            "ade": cv.result("ade"),
            "fde": cv.result("fde"),
            "offroad_rate": _rate(cv.off),
        },
        "log_offroad_rate": _rate(ours.log_off),
    }
