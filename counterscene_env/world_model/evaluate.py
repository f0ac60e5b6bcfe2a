"""Open-loop evaluation of a world model (``counterscene evaluate-model``).

For each scene, at its "now" step (``current_index``, 3 s of history), or with ``every`` at
every ``every`` seconds of the log where 3 s of history and 3 s of future exist (real scenes
are few; each start time is a window), the model predicts every agent it sees (the ego and
its nearest vehicles, ``num_agents`` within ``agent_radius``) over its horizon,
``num_samples`` samples in one batched call. Against the log's future:

- ``ade[h]``: mean displacement [m] over steps 1..h of the *first* sample, averaged over agents
  with at least one valid frame in that range; ``fde[h]``: displacement at step h, over agents
  valid at step h. ``h`` is 1 s, 2 s, 3 s and the full horizon (``"full"``).
- ``min_ade_S[h]``, ``min_fde_S[h]``: the same, per agent the best of the ``S = num_samples``
  samples (marginal, as in motion-forecasting benchmarks); the key names the sample count
  (``min_ade_6`` with the default 6), since the best of more samples is a smaller figure.
- ``ade_all_samples[h]``, ``fde_all_samples[h]``: the one-sample figures averaged over all the
  samples. They estimate the same quantity as ``ade`` and ``fde`` (the error of one draw),
  with less of the draw's luck in it: a few agents sent the wrong way by one draw move the
  first sample's figure by more than its interval over scenes shows (still cars,
  docs/world_model.md).
- ``offroad_rate``: fraction of predicted centre positions (all samples, valid agents, all
  horizon steps) off the road by the road's own test (``RoadMap.off_road``): outside the
  drivable area and inside the map's extent (a real map is a crop; beyond it nothing is known,
  so such positions are out of the rate altogether, ``RoadMap.judged``).

- ``sample_overlap[h]``: the share of windows whose first sample puts two agents' boxes on
  each other within steps 1..h where the log's boxes do not overlap (``overlap.new_overlaps``):
  the joint sample's own collisions, which a closed loop without reflexes would drive into.

The constant-velocity baseline moves each agent along its current course at its current speed.
The log's own off-road rate over the same agent-steps is reported as ``log_offroad_rate`` (real
maps leave parked cars off the lanes).

Every figure is also split by the agent's speed "now" (``by_speed``, bin edges
``speed_bins_m_s``): ``"parked"`` below :data:`PARKED_SPEED`, ``"slow"`` from there to
:data:`MOVING_SPEED`, ``"moving"`` from there on. Parked cars are easy for constant velocity and
a large share of real logs, so the pooled figure alone hides how moving traffic is predicted.

Still agents (``still``): parked now and within :data:`STILL_DISPLACEMENT` of their position 3 s
later in the log; their FDE at 3 s says whether the model keeps a parked car parked.

Intervals (``ci95`` beside each figure, ``*_ci95`` beside ratios): 95 % percentile bootstrap
over scenes, :data:`BOOTSTRAP_RESAMPLES` resamples seeded by ``seed``. The windows of one scene
(and the agents of one window) are correlated, so the scene is the unit resampled, and a figure
measured in one scene only (however many windows) has no interval: ``None`` (JSON null), as
one scene has no spread to resample (``scene_bootstrap.py``). Agent counts are agent-windows.

Short logs: future frames beyond the log are invalid and simply not scored, and history before
the log's first frame is padded by the window. A scene whose log ends at its "now" step has
nothing to compare against: it is skipped and counted (``skipped_scenes``; ``scenes`` counts
the scenes scored); so is, with ``every``, a log too short for any start time.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch

from counterscene_env.geometry import from_frame
from counterscene_env.metrics.realism import PARKED_SPEED  # the one "parked" speed, m/s
from counterscene_env.scene.core import Scene
from counterscene_env.scene.road import RoadMap
from counterscene_env.world_model.eval_windows import window_batches, window_jobs
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.overlap import new_overlaps
from counterscene_env.world_model.scene_bootstrap import SceneBootstrap, SceneSums

#: Speed "now" from which an agent counts as moving, m/s; between the two it is "slow"
#: (creeping in a queue, pulling out, stopping).
MOVING_SPEED = 3.0

#: Edges of the speed bins, m/s; a bin holds ``[lower edge, upper edge)``.
SPEED_BIN_EDGES = (PARKED_SPEED, MOVING_SPEED)

#: Names of the speed bins, slowest first (``SPEED_BIN_EDGES`` separates them).
SPEED_BINS = ("parked", "slow", "moving")

#: A parked agent whose logged position 3 s later is within this of where it is now is
#: "still" [m]: the prediction should keep it there (a parked car the model sets rolling).
STILL_DISPLACEMENT = 0.1

#: Logged future a start time needs with ``every`` [s]: the 3 s figures exist at every start.
MIN_SCORED_FUTURE = 3.0

#: Scene resamples behind each 95 % interval.
BOOTSTRAP_RESAMPLES = 1000


def horizons(model: WorldModel) -> dict[str, int]:
    """Horizon name -> step count: ``"1s"``, ``"2s"``, ``"3s"`` (those within the model's
    horizon) and ``"full"``."""
    steps = {f"{s}s": round(s / model.config.dt) for s in (1, 2, 3)}
    out = {k: v for k, v in steps.items() if v <= model.config.future_steps}
    out["full"] = model.config.future_steps
    return out


def constant_velocity(
    state: np.ndarray, steps: int, dt: float, course: np.ndarray | None = None
) -> np.ndarray:
    """The baseline: ``[..., steps, 2]`` m, each agent moving on from ``state [..., 4]`` (x m,
    y m, course rad, speed m/s) at its speed along ``course [...]`` rad (default: its own)."""
    course = state[..., 2] if course is None else course
    t = np.arange(1, steps + 1) * dt  # [F] s
    heading = np.stack([np.cos(course), np.sin(course)], -1)[..., None, :]  # [..., 1, 2]
    return state[..., None, :2] + (state[..., 3, None] * t)[..., None] * heading


def speed_bins(speed: np.ndarray) -> np.ndarray:
    """Index into :data:`SPEED_BINS` of each speed ``[...]`` m/s -> ``[...]`` int.

    The sign is ignored: the state's speed is signed along the heading, and a car reversing at
    5 m/s is moving.
    """
    return np.digitize(np.abs(speed), SPEED_BIN_EDGES)


def _add_errors(
    sums: SceneSums, prefix: str, scene: int, hz: dict[str, int], err: np.ndarray, ok: np.ndarray
) -> None:
    """Add ``A`` agents' displacement errors ``err [S, A, F]`` m (valid ``ok [A, F]``) under
    ``prefix``: ADE and FDE of the first sample, their mean over the samples, and the best of
    the samples (marginal)."""
    for h, n in hz.items():
        o = ok[:, :n]
        has = o.any(-1)
        ade = (err[:, :, :n] * o).sum(-1) / np.maximum(o.sum(-1), 1)  # [S, A]
        end = ok[:, n - 1]
        sums.add(f"{prefix}/ade/{h}", scene, ade[0, has])
        sums.add(f"{prefix}/ade_all/{h}", scene, ade[:, has].mean(0))
        sums.add(f"{prefix}/min_ade/{h}", scene, ade[:, has].min(0))
        sums.add(f"{prefix}/fde/{h}", scene, err[0, end, n - 1])
        sums.add(f"{prefix}/fde_all/{h}", scene, err[:, end, n - 1].mean(0))
        sums.add(f"{prefix}/min_fde/{h}", scene, err[:, end, n - 1].min(0))


def evaluate_model(
    model: WorldModel,
    scenes: Iterable[Scene],
    num_samples: int = 6,
    seed: int = 0,
    chunk: int = 8,
    progress: bool = False,
    every: float | None = None,
    bootstrap: int = BOOTSTRAP_RESAMPLES,
) -> dict[str, Any]:
    """Evaluate ``model`` open loop on ``scenes`` (module docstring); returns the JSON summary.

    Args:
        every: score every ``every`` seconds of each log where 3 s of history and
            :data:`MIN_SCORED_FUTURE` of future exist (None: each scene's "now" only).
        bootstrap: resamples of the scenes behind each 95 % interval (0: no intervals).
    """
    given = list(scenes)
    hist = model.config.history_steps
    if every is None:
        step, need = None, 1
    else:
        step = max(1, round(every / model.config.dt))
        need = round(MIN_SCORED_FUTURE / model.config.dt)
    jobs = window_jobs(given, hist, step, need)
    keep = sorted({k for k, _ in jobs})  # scenes with a window to score
    row = {i: r for r, i in enumerate(keep)}
    scenes = [given[i] for i in keep]
    jobs = [(row[k], t) for k, t in jobs]
    model = model.eval()
    sums = SceneSums()
    agents = defaultdict(int)
    g = torch.Generator().manual_seed(seed)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="evaluate", unit="window", dynamic_ncols=True)
    for part, batch in window_batches(model, scenes, jobs, chunk):
        roads = [scenes[k].road for k, _ in part]
        _score_chunk(model, batch, roads, [k for k, _ in part], num_samples, g, sums, agents)
        if bar is not None:
            bar.update(len(part))
    if bar is not None:
        bar.close()
    return _summary(
        model,
        len(scenes),
        len(given) - len(scenes),
        len(jobs),
        every,
        num_samples,
        sums,
        agents,
        bootstrap,
        seed,
    )


def _score_chunk(
    model: WorldModel,
    batch: dict[str, torch.Tensor],
    roads: list[RoadMap],
    scene_rows: list[int],
    num_samples: int,
    g: torch.Generator,
    sums: SceneSums,
    agents: dict[str, int],
) -> None:
    """Sample a batch of B windows (``roads`` and ``scene_rows`` one per window); add model and
    constant-velocity errors to ``sums``."""
    F = model.config.future_steps
    with torch.no_grad():
        prediction = model.sample(batch, num_samples, g)
        pred = prediction.trajectory.numpy()  # [B, S, K, F, 4]
        agent_ok = prediction.valid.numpy()  # [B, K]
        state = model.current_state(batch).numpy()  # [B, K, 4] x, y, course, speed (m/s)
    cv_xy = constant_velocity(state, F, model.config.dt)  # [B, K, F, 2]
    bins = speed_bins(state[..., 3])  # [B, K]
    future = batch["future"].numpy()
    extents = batch["extents"].numpy()
    valid = batch["future_valid"].numpy() & agent_ok[..., None]
    hz = horizons(model)
    n3 = hz.get("3s", F)
    for b, road in enumerate(roads):
        keep = agent_ok[b]
        if not keep.any():
            continue
        ok = valid[b][keep]  # [A, F]
        gt = future[b][keep, :, :2]
        clash = new_overlaps(pred[b, 0][keep], future[b][keep], extents[b][keep], ok)  # [F]
        for h, n in hz.items():
            sums.count(f"windows/model/overlap/{h}", scene_rows[b], int(clash[:n].any()), 1)
        # Stopped now and still 3 s later in the log: a prediction should stay put too.
        moved = np.linalg.norm(gt[:, n3 - 1] - state[b][keep, :2], axis=-1)
        still = (bins[b][keep] == 0) & ok[:, n3 - 1] & (moved < STILL_DISPLACEMENT)
        p = pred[b][:, keep, :, :2]  # [S, A, F, 2]
        c = cv_xy[b][keep][None]
        origin = batch["origin"][b].numpy()
        _score_scene(
            road,
            origin,
            ok,
            (gt, p, c),
            bins[b][keep],
            still,
            scene_rows[b],
            hz,
            sums,
            agents,
        )


def _score_scene(
    road: RoadMap,
    origin: np.ndarray,
    ok: np.ndarray,
    tracks: tuple[np.ndarray, np.ndarray, np.ndarray],
    bins: np.ndarray,
    still: np.ndarray,
    scene: int,
    hz: dict[str, int],
    sums: SceneSums,
    agents: dict[str, int],
) -> None:
    """Add one window's errors [m] and off-road counts to ``"all"``, each agent's speed bin and
    ``"still"``.

    Args:
        road: the scene's road (world frame).
        origin: ``[3]`` the window's frame (world x m, y m, yaw rad).
        ok: ``[A, F]`` bool, the log's valid future frames of the ``A`` scored agents.
        tracks: the log ``[A, F, 2]``, the model's samples ``[S, A, F, 2]`` and constant velocity
            ``[1, A, F, 2]``, m, window frame.
        bins: ``[A]`` int, each agent's speed bin (:func:`speed_bins`).
        still: ``[A]`` bool, stopped now and still in the log 3 s later.
        scene: the scene's row (windows of one scene are resampled together).
    """
    gt, p, c = tracks
    err_p, err_c = np.linalg.norm(p - gt, axis=-1), np.linalg.norm(c - gt, axis=-1)
    # Off-road is judged once per window for every agent; the groups then sum their subsets.
    # A point beyond a cropped map's extent is neither on nor off its roads: out of the rate.
    world = [from_frame(xy, origin) for xy in (p, c, gt)]
    in_p, in_c, in_log = (road.judged(xy) for xy in world)
    off_p, off_c, off_log = (
        road.off_road(xy, seen) for xy, seen in zip(world, (in_p, in_c, in_log), strict=True)
    )
    members = [("all", np.ones(len(ok), bool)), ("still", still)]
    members += [(name, bins == i) for i, name in enumerate(SPEED_BINS)]
    for name, sel in members:
        if not sel.any():
            continue
        o = ok[sel]
        agents[name] += int(sel.sum())
        _add_errors(sums, f"{name}/model", scene, hz, err_p[:, sel], o)
        _add_errors(sums, f"{name}/cv", scene, hz, err_c[:, sel], o)
        judged = (("model", off_p, in_p), ("cv", off_c, in_c), ("log", off_log[None], in_log[None]))
        for who, off, seen in judged:
            mask = np.broadcast_to(o, off[:, sel].shape) & seen[:, sel]
            sums.count(f"{name}/{who}/off", scene, int((off[:, sel] & mask).sum()), int(mask.sum()))


def _figures(
    est: SceneBootstrap, group: str, hz: dict[str, int], agents: int, samples: int
) -> dict[str, Any]:
    """The figures of one group of agents: ``agents``, ``model``, ``constant_velocity`` (each
    with ``ci95``), the model's ADE (first sample and all samples) and min-ADE over
    ``samples`` samples (``min_ade_{samples}``) as ratios to constant velocity's, and
    ``log_offroad_rate``."""
    best_ade, best_fde = f"min_ade_{samples}", f"min_fde_{samples}"

    def block(who: str, keys: dict[str, str]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        ci: dict[str, Any] = {}
        for label, key in keys.items():
            out[label] = {h: est.value(f"{group}/{who}/{key}/{h}") for h in hz}
            ci[label] = {h: est.ci(f"{group}/{who}/{key}/{h}") for h in hz}
        out["offroad_rate"] = est.value(f"{group}/{who}/off")
        ci["offroad_rate"] = est.ci(f"{group}/{who}/off")
        out["ci95"] = ci
        return out

    ratios: dict[str, Any] = {}
    for label, key in (("ade", "ade"), ("ade_all_samples", "ade_all"), (best_ade, "min_ade")):
        pairs = {h: est.ratio(f"{group}/model/{key}/{h}", f"{group}/cv/ade/{h}") for h in hz}
        ratios[f"{label}_ratio_to_cv"] = {h: v for h, (v, _) in pairs.items()}
        ratios[f"{label}_ratio_to_cv_ci95"] = {h: c for h, (_, c) in pairs.items()}
    model_keys = {
        "ade": "ade",
        "fde": "fde",
        "ade_all_samples": "ade_all",
        "fde_all_samples": "fde_all",
        best_ade: "min_ade",
        best_fde: "min_fde",
    }
    return {
        "agents": agents,
        "model": block("model", model_keys),
        "constant_velocity": block("cv", {"ade": "ade", "fde": "fde"}),
        **ratios,
        "log_offroad_rate": est.value(f"{group}/log/off"),
        "log_offroad_rate_ci95": est.ci(f"{group}/log/off"),
    }


def _summary(
    model: WorldModel,
    scenes: int,
    skipped: int,
    windows: int,
    every: float | None,
    num_samples: int,
    sums: SceneSums,
    agents: dict[str, int],
    bootstrap: int,
    seed: int,
) -> dict[str, Any]:
    """The JSON summary of :func:`evaluate_model` from its accumulated sums: the figures of all
    agents at the top level (the layout from before the speed split), each speed bin's under
    ``by_speed``, the still agents' under ``still``. Agent counts are agent-windows."""
    est = SceneBootstrap(sums, scenes, bootstrap, seed)
    hz = horizons(model)
    return {
        "scenes": scenes,
        "skipped_scenes": skipped,
        "windows": windows,
        "every_s": every,
        "samples": num_samples,
        "horizon_s": model.config.horizon,
        "lane_steering": model.config.lane_steering,
        "hold_parked_m": model.config.hold_parked,
        "bootstrap_resamples": bootstrap,
        **_figures(est, "all", hz, agents["all"], num_samples),
        "speed_bins_m_s": list(SPEED_BIN_EDGES),
        "by_speed": {
            name: _figures(est, name, hz, agents[name], num_samples) for name in SPEED_BINS
        },
        "still_displacement_m": STILL_DISPLACEMENT,
        "still": _figures(est, "still", hz, agents["still"], num_samples),
        "sample_overlap": {h: est.value(f"windows/model/overlap/{h}") for h in hz},
        "sample_overlap_ci95": {h: est.ci(f"windows/model/overlap/{h}") for h in hz},
    }
