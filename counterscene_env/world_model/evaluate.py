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
  horizon steps) off the road by the road's own test (``RoadMap.off_road``): outside the
  drivable area and inside the map's extent (a real map is a crop; beyond it nothing is known).

The constant-velocity baseline moves each agent along its current course at its current speed.
The log's own off-road rate over the same agent-steps is reported as ``log_offroad_rate`` (real
maps leave parked cars off the lanes).

Every figure is also split by the agent's speed "now" (``by_speed``, bin edges
``speed_bins_m_s``): ``"parked"`` below :data:`PARKED_SPEED`, ``"slow"`` from there to
:data:`MOVING_SPEED`, ``"moving"`` from there on. Parked cars are easy for constant velocity and
a large share of real logs, so the pooled figure alone hides how moving traffic is predicted.

Short logs: future frames beyond the log are invalid and simply not scored, and history before
the log's first frame is padded by the window. A scene whose log ends at its "now" step has
nothing to compare against: it is skipped and counted (``skipped_scenes``; ``scenes`` counts
the scenes scored).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
from torch.utils.data import default_collate

from counterscene_env.geometry import from_frame
from counterscene_env.metrics.realism import PARKED_SPEED  # the one "parked" speed, m/s
from counterscene_env.scene.core import Scene
from counterscene_env.scene.road import RoadMap
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.model import WorldModel

#: Speed "now" from which an agent counts as moving, m/s; between the two it is "slow"
#: (creeping in a queue, pulling out, stopping).
MOVING_SPEED = 3.0

#: Edges of the speed bins, m/s; a bin holds ``[lower edge, upper edge)``.
SPEED_BIN_EDGES = (PARKED_SPEED, MOVING_SPEED)

#: Names of the speed bins, slowest first (``SPEED_BIN_EDGES`` separates them).
SPEED_BINS = ("parked", "slow", "moving")


def horizons(model: WorldModel) -> dict[str, int]:
    """Horizon name -> step count: ``"1s"``, ``"2s"``, ``"3s"`` (those within the model's
    horizon) and ``"full"``."""
    steps = {f"{s}s": round(s / model.config.dt) for s in (1, 2, 3)}
    out = {k: v for k, v in steps.items() if v <= model.config.future_steps}
    out["full"] = model.config.future_steps
    return out


def speed_bins(speed: np.ndarray) -> np.ndarray:
    """Index into :data:`SPEED_BINS` of each speed ``[...]`` m/s -> ``[...]`` int.

    The sign is ignored: the state's speed is signed along the heading, and a car reversing at
    5 m/s is moving.
    """
    return np.digitize(np.abs(speed), SPEED_BIN_EDGES)


class _Accumulator:
    """Sums per horizon of displacement statistics (agent-weighted) and off-road counts."""

    def __init__(self, hz: dict[str, int]) -> None:
        self.hz = hz
        self.sums = {k: {h: [0.0, 0] for h in hz} for k in ("ade", "fde", "min_ade", "min_fde")}
        self.off = [0, 0]

    def add(self, err: np.ndarray, ok: np.ndarray, off: np.ndarray) -> None:
        """Add ``A`` agents: ``err [S, A, F]`` m, ``ok [A, F]`` bool, ``off [S, A, F]`` bool."""
        for h, n in self.hz.items():
            o = ok[:, :n]
            has = o.any(-1)
            ade = (err[:, :, :n] * o).sum(-1) / np.maximum(o.sum(-1), 1)  # [S, A]
            self._acc("ade", h, ade[0, has])
            self._acc("min_ade", h, ade[:, has].min(0))
            end = ok[:, n - 1]
            self._acc("fde", h, err[0, end, n - 1])
            self._acc("min_fde", h, err[:, end, n - 1].min(0))
        mask = np.broadcast_to(ok, off.shape)
        self.off[0] += int((off & mask).sum())
        self.off[1] += int(mask.sum())

    def _acc(self, key: str, h: str, values: np.ndarray) -> None:
        self.sums[key][h][0] += float(values.sum())
        self.sums[key][h][1] += int(values.size)

    def result(self, key: str) -> dict[str, float | None]:
        return {h: (s / n if n else None) for h, (s, n) in self.sums[key].items()}


class _Group:
    """The sums of one set of agents (all of them, or one speed bin): model, constant velocity
    and the log's off-road counts."""

    def __init__(self, hz: dict[str, int]) -> None:
        self.agents = 0
        self.ours, self.cv = _Accumulator(hz), _Accumulator(hz)
        self.log_off = [0, 0]


def evaluate_model(
    model: WorldModel,
    scenes: Iterable[Scene],
    num_samples: int = 6,
    seed: int = 0,
    chunk: int = 8,
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate ``model`` open loop on ``scenes`` (module docstring); returns the JSON summary."""
    given = list(scenes)
    # A log that ends at "now" has no future to score (and no frame to predict from to).
    scenes = [s for s in given if s.current_index + 1 < s.num_steps]
    model = model.eval()
    ds = SceneWindowDataset(scenes, model.window_config())
    hz = horizons(model)
    groups = {name: _Group(hz) for name in ("all", *SPEED_BINS)}
    g = torch.Generator().manual_seed(seed)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(scenes), desc="evaluate", unit="scene", dynamic_ncols=True)
    for lo in range(0, len(scenes), chunk):
        idx = range(lo, min(lo + chunk, len(scenes)))
        items = [ds.window(i, scenes[i].current_index) for i in idx]
        batch = default_collate(
            [{k: torch.from_numpy(np.asarray(v)) for k, v in w.items()} for w in items]
        )
        _score_chunk(model, batch, [scenes[i].road for i in idx], num_samples, g, groups)
        if bar is not None:
            bar.update(len(idx))
    if bar is not None:
        bar.close()
    return _summary(model, len(scenes), len(given) - len(scenes), num_samples, groups)


def _score_chunk(
    model: WorldModel,
    batch: dict[str, torch.Tensor],
    roads: list[RoadMap],
    num_samples: int,
    g: torch.Generator,
    groups: dict[str, _Group],
) -> None:
    """Sample a batch of B scenes (``roads`` one per scene); add model and constant-velocity
    errors to ``groups``."""
    F = model.config.future_steps
    with torch.no_grad():
        prediction = model.sample(batch, num_samples, g)
        pred = prediction.trajectory.numpy()  # [B, S, K, F, 4]
        agent_ok = prediction.valid.numpy()  # [B, K]
        state = model.current_state(batch).numpy()  # [B, K, 4] x, y, course, speed (m/s)
    t = (np.arange(1, F + 1) * model.config.dt)[None, :, None]
    heading = np.stack([np.cos(state[..., 2]), np.sin(state[..., 2])], -1)
    cv_xy = state[:, :, None, :2] + (state[:, :, None, 3:4] * t) * heading[:, :, None, :]
    bins = speed_bins(state[..., 3])  # [B, K]
    future = batch["future"].numpy()
    valid = batch["future_valid"].numpy() & agent_ok[..., None]
    for b, road in enumerate(roads):
        keep = agent_ok[b]
        if not keep.any():
            continue
        ok = valid[b][keep]  # [A, F]
        gt = future[b][keep, :, :2]
        p = pred[b][:, keep, :, :2]  # [S, A, F, 2]
        c = cv_xy[b][keep][None]
        origin = batch["origin"][b].numpy()
        _score_scene(road, origin, ok, (gt, p, c), bins[b][keep], groups)


def _score_scene(
    road: RoadMap,
    origin: np.ndarray,
    ok: np.ndarray,
    tracks: tuple[np.ndarray, np.ndarray, np.ndarray],
    bins: np.ndarray,
    groups: dict[str, _Group],
) -> None:
    """Add one scene's errors [m] and off-road counts to ``"all"`` and each agent's speed bin.

    Args:
        road: the scene's road (world frame).
        origin: ``[3]`` the window's frame (world x m, y m, yaw rad).
        ok: ``[A, F]`` bool, the log's valid future frames of the ``A`` scored agents.
        tracks: the log ``[A, F, 2]``, the model's samples ``[S, A, F, 2]`` and constant velocity
            ``[1, A, F, 2]``, m, window frame.
        bins: ``[A]`` int, each agent's speed bin (:func:`speed_bins`).
    """
    gt, p, c = tracks
    err_p, err_c = np.linalg.norm(p - gt, axis=-1), np.linalg.norm(c - gt, axis=-1)
    # Off-road is judged once per scene for every agent; the groups then sum their subsets.
    off_p, off_c, off_log = (road.off_road(from_frame(xy, origin)) for xy in (p, c, gt))
    members = [("all", np.ones(len(ok), bool))]
    members += [(name, bins == i) for i, name in enumerate(SPEED_BINS)]
    for name, sel in members:
        if not sel.any():
            continue
        group, o = groups[name], ok[sel]
        group.agents += int(sel.sum())
        group.ours.add(err_p[:, sel], o, off_p[:, sel])
        group.cv.add(err_c[:, sel], o, off_c[:, sel])
        group.log_off[0] += int((off_log[sel] & o).sum())
        group.log_off[1] += int(o.sum())


def _rate(pair: list[int]) -> float | None:
    """``pair[0] / pair[1]``, or None if the denominator is 0."""
    return pair[0] / pair[1] if pair[1] else None


def _figures(group: _Group) -> dict[str, Any]:
    """The figures of one group of agents: ``agents``, ``model``, ``constant_velocity``,
    ``log_offroad_rate``."""
    ours, cv = group.ours, group.cv
    return {
        "agents": group.agents,
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
        "log_offroad_rate": _rate(group.log_off),
    }


def _summary(
    model: WorldModel,
    scenes: int,
    skipped: int,
    num_samples: int,
    groups: dict[str, _Group],
) -> dict[str, Any]:
    """The JSON summary of :func:`evaluate_model` from its accumulated sums: the figures of all
    agents at the top level (the layout from before the speed split), each speed bin's under
    ``by_speed``."""
    return {
        "scenes": scenes,
        "skipped_scenes": skipped,
        "samples": num_samples,
        "horizon_s": model.config.horizon,
        "lane_steering": model.config.lane_steering,
        **_figures(groups["all"]),
        "speed_bins_m_s": list(SPEED_BIN_EDGES),
        "by_speed": {name: _figures(groups[name]) for name in SPEED_BINS},
    }
