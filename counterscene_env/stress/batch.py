"""Playing one batch of episodes in a closed loop to its end, each ego driven by its planner
(:func:`play_batch`), and the episodes' records (:func:`run_batch`, :func:`record`): the
step every stress runner (``stress/episodes.py``), the report's replay and the
``tools/`` diagnostics share.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from counterscene_env import metrics
from counterscene_env.planners import Planner
from counterscene_env.scene.core import Scene
from counterscene_env.scene.prefetch import one_thread_if, recording
from counterscene_env.sim import ClosedLoop


def run_batch(
    loop: ClosedLoop,
    scenes: Sequence[Scene],
    seeds: Sequence[int],
    planners: Sequence[Planner],
    first: int = 0,
    selection_seeds: Sequence[int | None] | None = None,
) -> list[dict]:
    """Run B episodes together to their end (episode indices ``first ..``; selection seeds
    as ``ClosedLoop.reset``); one record each."""
    start = time.perf_counter()
    play_batch(loop, scenes, seeds, planners, selection_seeds=selection_seeds)
    share = (time.perf_counter() - start) / len(scenes)
    return [record(loop, b, scene, seeds[b], share, first + b) for b, scene in enumerate(scenes)]


def play_batch(
    loop: ClosedLoop,
    scenes: Sequence[Scene],
    seeds: Sequence[int],
    planners: Sequence[Planner],
    after: Callable[[list[bool]], None] | None = None,
    selection_seeds: Sequence[int | None] | None = None,
) -> None:
    """Reset ``loop`` and the planners on B scenes and seeds (selection seeds as
    ``ClosedLoop.reset``), and step them to their end, each ego driven by its planner.
    ``after(moved)``, if given, runs after the reset (every episode moved to "now") and
    after every step (the ``[B]`` episodes that took it): a report's replay draws its frames
    there."""
    loop.reset(scenes, seeds, selection_seeds=selection_seeds)
    for planner, scene, seed in zip(planners, scenes, seeds, strict=True):
        planner.reset(scene, seed)
    B = len(scenes)
    if after is not None:
        after([True] * B)
    while not loop.done.all():
        stepped = [not ep.done for ep in loop.episodes]
        actions = np.zeros((B, 2))
        states = np.full((B, 4), np.nan)
        for b, planner in enumerate(planners):
            if not stepped[b]:
                continue
            state = loop.state(b)
            if planner.replays_log:
                states[b] = planner.next_state(state)
            else:
                actions[b] = _checked_action(planner, planner.act(state))
        with one_thread_if(recording()):  # a scene recorded in the background holds a core
            loop.step(actions, states)
        if after is not None:
            after(stepped)


def _checked_action(planner: Planner, action: object) -> np.ndarray:
    """A planner's action as ``[2]`` floats: a scalar or another shape would be broadcast
    into both controls (an acceleration read as a steering angle too), so it is refused."""
    a = np.asarray(action, dtype=float) if action is not None else np.empty(0)
    if a.shape != (2,):
        raise ValueError(
            f"planner {getattr(planner, 'name', planner)!r}: act() must return "
            f"[acceleration m/s^2, steering rad] of shape (2,), got {action!r}"
        )
    return a


def record(loop: ClosedLoop, b: int, scene: Scene, seed: int, seconds: float, index: int) -> dict:
    """Episode ``index``'s record: its metrics (:func:`metrics.evaluate_scene` of batch row
    ``b``, over every adversary the episode had), selection, seeds and timing [s]. The
    selection fields (``adversary_type``, ``adversary_tier``, ``danger_score``,
    ``fallback``) are the last selection's: with ``selection_source="model"``, the last
    replan's, which may have found none."""
    ep = loop.episodes[b]
    sim = loop.scene(b)
    factual = scene.time_slice(0, sim.num_steps)
    rec = metrics.evaluate_scene(sim, factual, adversary=ep.adversary_ids())
    conflict = ep.conflict
    scene_seed = scene.metadata.get("seed")
    rec.update(
        episode=int(index),
        seed=int(seed),
        scene_seed=None if scene_seed is None else int(scene_seed),
        adversary_type=None if conflict is None else conflict.subtype,
        adversary_tier=None if conflict is None else conflict.tier,
        danger_score=None if conflict is None else float(conflict.score),
        fallback=ep.selection.fallback,
        replans=ep.replans,
        replan_seconds=ep.replan_seconds,
        seconds=seconds,
    )
    return rec
