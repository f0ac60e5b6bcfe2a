"""Re-simulate one episode of a stress run from its seeds, keeping every step for drawing.

The closed loop is deterministic given the scenes and seeds of a batch (``sim.ClosedLoop``:
each episode has its own generators), and a stress run records both (``scene_seed`` or the
episode index, and ``seed``; with candidate rollouts, the ``rollout`` kept). An episode is
replayed in its batch (:func:`batch_of`) exactly as ``stress.run_batch`` runs it, and the
replay's metrics are checked against the record.

Planners ``sb3:PATH.zip`` run through ``CounterScene-v0`` (``stress.run_policy_episodes``)
and are not replayed here.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from counterscene_env import metrics
from counterscene_env.config import Scenario
from counterscene_env.planners import make_planner
from counterscene_env.report.rundir import Run
from counterscene_env.scene.core import Scene
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.stress import SB3_PREFIX
from counterscene_env.stress.batch import play_batch
from counterscene_env.stress.log import PYTHON_PLANNER_PREFIX
from counterscene_env.stress.rollouts import rollout_seed
from counterscene_env.world_model.model import WorldModel

#: Record fields a replay must reproduce for its video to be the recorded episode.
CHECKED_FIELDS = ("cr", "cr_ego_adversary", "min_ttc", "adversary_id")


@dataclass(frozen=True)
class Frame:
    """One step of a replayed episode.

    Attributes:
        time: s since the episode's start ("now" of the scene).
        positions: ``[N, 2]`` m; yaws ``[N]`` rad; valid ``[N]`` bool.
        plan: ``[F', 2]`` m, the adversary's current plan from its next step on (None: no
            adversary, or not planned yet).
        info: the loop's step info of the ego (``ClosedLoop.step``: ``collision``,
            ``hard_braking``, ``ego_acceleration`` m/s^2, ``ego_speed`` m/s,
            ``conflict_point`` [x, y] m, ``adversary``, ``conflict_type``, ...).
    """

    time: float
    positions: np.ndarray
    yaws: np.ndarray
    valid: np.ndarray
    plan: np.ndarray | None
    info: dict


@dataclass(frozen=True)
class Replay:
    """A replayed episode.

    Attributes:
        record: the run's record of the episode.
        scene: the factual scene (road, extents, ids).
        ego, adversary: scene rows (adversary None: fallback, no adversary).
        frames: one per step, from "now" to the episode's end.
        mismatches: fields of :data:`CHECKED_FIELDS` whose replayed value differs from the
            record (empty: the replay is the recorded episode).
    """

    record: dict
    scene: Scene
    ego: int
    adversary: int | None
    frames: list[Frame]
    mismatches: tuple[str, ...]


def can_replay(run: Run) -> str | None:
    """Why the run's episodes cannot be replayed here (None: they can)."""
    planner = str(run.identity.get("planner", ""))
    if planner.startswith(PYTHON_PLANNER_PREFIX):
        return (
            f"planner {planner[len(PYTHON_PLANNER_PREFIX) :]!r} was given from Python, and no "
            "command can rebuild it to re-simulate its episodes"
        )
    if planner.startswith(SB3_PREFIX):
        return (
            f"planner {planner} runs through CounterScene-v0 and its episodes are not "
            "re-simulated for videos"
        )
    if "scenario" not in run.identity:
        return f"{run.directory / 'run.json'} has no 'scenario'"
    return None


def batch_of(run: Run, episode: int) -> range:
    """The episodes run in one batch with ``episode`` (``stress.chunks``: ``batch``
    consecutive episodes from a multiple of ``batch``, the last batch shorter). A batched
    world-model call's floating-point results can depend on the batch's other rows, so an
    episode is replayed in its batch."""
    size = int(run.identity.get("batch", 1))
    first = episode - episode % size
    return range(first, min(first + size, len(run.records)))


def group_by_batch(run: Run, episodes: Sequence[int]) -> dict[range, list[int]]:
    """``episodes`` grouped by their batch (:func:`batch_of`), batches in the order of their
    first episode in ``episodes``."""
    out: dict[range, list[int]] = {}
    for e in episodes:
        out.setdefault(batch_of(run, e), []).append(e)
    return out


def batch_scenes(run: Run, episodes: range) -> list[Scene]:
    """The factual scenes of consecutive episodes, as the run drew them
    (``stress.chunks``).

    Raises:
        ValueError: a scene found is not the record's (``scenario_id`` differs: the source
            changed since the run).
        FileNotFoundError: a stored source is gone.
    """
    spec = run.identity["scenario"]
    records = [run.records[i] for i in episodes]
    if spec in Scenario.values() and all(r.get("scene_seed") is not None for r in records):
        from counterscene_env.scene.highway import generate

        # A safe seed regenerates its own scene; no need to walk the seeds before it.
        scenes = [generate(spec, int(r["scene_seed"])) for r in records]
    else:
        egos = int(run.identity.get("egos", 1))
        source = scenes_for(spec, episodes.stop, int(run.identity["seed"]), egos)
        scenes = list(itertools.islice(source, episodes.start, None))
    for scene, r in zip(scenes, records, strict=True):
        if scene.scenario_id != r["scenario_id"]:
            raise ValueError(
                f"episode {r['episode']}: the source now gives scene {scene.scenario_id!r}, "
                f"the run recorded {r['scenario_id']!r}"
            )
    return scenes


def replay_batch(model: WorldModel, run: Run, episodes: range, keep: Sequence[int]) -> list[Replay]:
    """Re-simulate the batch ``episodes`` of ``run`` step by step as ``stress.run_batch``
    runs it; one :class:`Replay` per episode of ``keep`` (in that order). A run with
    candidate rollouts (``StressConfig.rollouts``) played its batch once per candidate; an
    episode is replayed in the play of the candidate it kept (its ``rollout``).

    Raises:
        ValueError: the run cannot be replayed (:func:`can_replay`), its settings are not
            this version's, or its scenes are not found again (:func:`batch_scenes`).
    """
    reason = can_replay(run)
    if reason:
        raise ValueError(reason)
    scenes = batch_scenes(run, episodes)
    loop = ClosedLoop(model, SimConfig.from_mapping(run.sim()))
    kept = {e: int(run.records[e].get("rollout", 0)) for e in keep}  # the candidate each kept
    own = [int(run.records[i]["seed"]) for i in episodes]  # every candidate's selection seeds
    replays = {}
    for k in sorted(set(kept.values())):
        # Every episode of the batch ran candidate k together.
        seeds = [rollout_seed(s, k) for s in own]
        planners = [make_planner(str(run.identity.get("planner", "idm"))) for _ in scenes]
        rows = [episodes.index(e) for e in keep if kept[e] == k]
        frames: dict[int, list[Frame]] = {b: [] for b in rows}

        def draw(moved: list[bool], rows=rows, frames=frames) -> None:
            for b in rows:
                if moved[b]:  # a finished episode (a short log) stays on its last frame
                    frames[b].append(_frame(loop, b))

        play_batch(loop, scenes, seeds, planners, after=draw, selection_seeds=own)
        for b in rows:
            replays[b] = _replay(loop, b, scenes[b], run.records[episodes[b]], frames[b])
    return [replays[episodes.index(e)] for e in keep]


def _replay(loop: ClosedLoop, b: int, scene: Scene, record: dict, frames: list[Frame]) -> Replay:
    ep = loop.episodes[b]
    simulated = loop.scene(b)
    again = metrics.evaluate_scene(
        simulated, scene.time_slice(0, simulated.num_steps), adversary=ep.adversary_ids()
    )
    return Replay(
        record=record,
        scene=ep.factual,
        ego=ep.factual.ego_index,
        adversary=ep.adversary,
        frames=frames,
        mismatches=tuple(k for k in CHECKED_FIELDS if not _same(again.get(k), record.get(k))),
    )


def _frame(loop: ClosedLoop, b: int) -> Frame:
    ep = loop.episodes[b]
    t = ep.t
    adv = ep.adversary
    return Frame(
        time=(t - ep.start) * ep.factual.dt,
        positions=ep.positions[:, t].copy(),
        yaws=ep.yaws[:, t].copy(),
        valid=ep.valid[:, t].copy(),
        plan=None if adv is None else ep.remaining_plan(adv),
        info=loop.infos(b)[0],
    )


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        if math.isnan(a) and math.isnan(b):
            return True
        return a == b or math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9)
    return a == b
