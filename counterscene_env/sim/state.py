"""The closed loop's records: how agents move (:class:`MotionSource`), what planners see
(:class:`WorldState`), one episode's state (:class:`Episode`) and one model window
(:class:`ModelWindow`).

These are the public records between the closed loop and its readers (stress runs, the
envs, the renderer, benchmarks): they read these fields, never the loop's private helpers.
Shapes: N agents of the scene, T steps of the log (up to the episode's end), F planned steps.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.adversary.selection import Conflict, Selection
from counterscene_env.scene.core import Scene
from counterscene_env.world_model.window import LaneSegments


class MotionSource(enum.IntEnum):
    """How an agent moved into a step (``ClosedLoop.motion_source``)."""

    NONE = 0  #: absent, or history (before the closed loop started)
    PLAN = 1  #: its world-model plan
    LOG = 2  #: its log (never planned, or it just entered)
    COAST = 3  #: constant speed and course (its plan ran out)
    EGO = 4  #: an ego's policy
    IDM = 5  #: highway-env's IDM lane follower (it left the model's view; sim/traffic.py)
    YIELD = 6  #: held back by the yielding rule on its plan's, log's or IDM's path
    KEEP = 7  #: moved onto its lane by road keeping


@dataclass(frozen=True)
class WorldState:
    """A read-only snapshot of one episode at step ``t`` (what planners see).

    Attributes:
        t: absolute step of the scene's log.
        positions: ``[N, 2]`` m; yaws ``[N]`` rad; speeds ``[N]`` m/s; valid ``[N]`` bool.
        extents: ``[N, 2]`` m (length, width).
        ego_index: the ego's row.
        scene: the factual scene (road, ids, log), shared with the loop, not copied (a copy
            per step would cost more than the step): read it, do not change it.

    The arrays are copies: a planner may change them without touching the episode.
    """

    t: int
    positions: np.ndarray
    yaws: np.ndarray
    speeds: np.ndarray
    valid: np.ndarray
    extents: np.ndarray
    ego_index: int
    scene: Scene


@dataclass
class Episode:
    """One closed-loop episode: its state and its record so far (``ClosedLoop.episodes``).

    Readers outside ``sim/`` treat it as read-only.

    Attributes:
        factual: the factual scene (its ego is the first ego).
        start, end: absolute steps of "now" (the loop's first step) and of the last step.
        t: the current absolute step.
        positions: ``[N, T, 2]`` m, the simulated states (the log's history before ``start``);
            yaws ``[N, T]`` rad; speeds ``[N, T]`` m/s.
        valid: ``[N, T]`` bool, agents present at each simulated step (as the log says, but
            an agent that would enter on top of another waits: ``sim/motion.py``).
        source: ``[N, T]`` int8, how each agent moved into each step (:class:`MotionSource`).
        egos: rows driven by external policies; ``egos[0]`` is ``factual.ego_index``.
        vehicles: one highway-env bicycle per ego.
        segments: the scene's lane segments (``world_model.window.lane_segments``), cut once.
        pieces: lane centre pieces for road keeping (``sim.road_keeping.lane_pieces``).
        generator, rng: the episode's torch and numpy generators (seeded from its seed).
        selection_rng: the generator of a ``random`` selector's choice: ``rng`` itself, or
            one of its own seeded from the episode's selection seed (``ClosedLoop.reset``).
        selections: one adversary selection per ego.
        plan_positions: ``[N, F, 2]`` m, each agent's current plan; plan_yaws ``[N, F]`` rad;
            plan_speeds ``[N, F]`` m/s.
        plan_start: ``[N]`` step of each plan's index 0.
        plan_tokens: ``[N, Ta, 2]`` each agent's last world-model prediction as normalised
            action tokens (frame-free: acceleration and yaw rate), kept for the egos too: the
            warm start of the next replan.
        tokens_start: ``[N]`` step of each ``plan_tokens`` row's first action (-1: none yet).
        planned: ``[N]`` bool, agents the world model has planned.
        progress: ``[N]`` m along the current path (plan's or log's); NaN: not started.
        replans: world-model replans so far.
        replan_seconds: this episode's share of the batched replan calls [s].
        records: per step, one info dict per ego.
        background: row -> its ``sim.traffic.IDMLaneFollower`` (agents out of the model's view).
    """

    factual: Scene
    start: int
    end: int
    t: int
    positions: np.ndarray
    yaws: np.ndarray
    speeds: np.ndarray
    valid: np.ndarray
    source: np.ndarray
    egos: list[int]
    vehicles: list[Vehicle]
    segments: LaneSegments
    pieces: tuple[np.ndarray, ...]
    generator: torch.Generator
    rng: np.random.Generator
    selection_rng: np.random.Generator
    selections: list[Selection]
    plan_positions: np.ndarray
    plan_yaws: np.ndarray
    plan_speeds: np.ndarray
    plan_start: np.ndarray
    plan_tokens: np.ndarray
    tokens_start: np.ndarray
    planned: np.ndarray
    progress: np.ndarray
    replans: int = 0
    replan_seconds: float = 0.0
    records: list[list[dict]] = field(default_factory=list)
    background: dict[int, Any] = field(default_factory=dict)

    @property
    def selection(self) -> Selection:
        """The first ego's selection."""
        return self.selections[0]

    @property
    def conflict(self) -> Conflict | None:
        """The first ego's conflict (None: no adversary)."""
        return self.selections[0].conflict

    @property
    def adversary(self) -> int | None:
        """The first ego's adversary row (None: fallback)."""
        return None if self.conflict is None else self.conflict.agent

    @property
    def adversaries(self) -> list[int | None]:
        """Each ego's adversary row (None: fallback)."""
        return [None if s.conflict is None else s.conflict.agent for s in self.selections]

    def adversary_ids(self, k: int = 0) -> list[str | None]:
        """Ego ``k``'s adversary id at each rollout step so far (index 0: step ``start + 1``;
        None: none then), as its step records say. With ``selection_source="model"`` it can
        change at every replan; ``metrics.evaluate_scene`` takes this list and counts a
        contact with any of them from the step it was chosen."""
        return [step[k]["adversary"] for step in self.records[1:]]

    @property
    def done(self) -> bool:
        """The episode reached its last step."""
        return self.t >= self.end

    def state(self) -> WorldState:
        """What the episode looks like at its current step (its arrays copies; the factual
        scene shared)."""
        t = self.t
        return WorldState(
            t=t,
            positions=self.positions[:, t].copy(),
            yaws=self.yaws[:, t].copy(),
            speeds=self.speeds[:, t].copy(),
            valid=self.valid[:, t].copy(),
            extents=self.factual.extents.copy(),
            ego_index=self.factual.ego_index,
            scene=self.factual,
        )

    def remaining_plan(self, row: int) -> np.ndarray | None:
        """``[F', 2]`` m: agent ``row``'s current plan from its next step on (None: never
        planned)."""
        if not self.planned[row]:
            return None
        return self.plan_positions[row, max(0, self.t + 1 - int(self.plan_start[row])) :].copy()


@dataclass
class ModelWindow:
    """One world-model window of an episode at a replan.

    Attributes:
        arrays: the model's input arrays (``world_model.window.make_window``: ``history``
            ``[K, H, 4]``, ``map`` ``[M, P, 2]``, ``rows``, ``origin``, ...).
        plan_rows: scene rows whose plans this window supplies.
        ego: which ego's window it is (index into ``Episode.egos``; -1: an extra window).
    """

    arrays: dict[str, Any]
    plan_rows: list[int]
    ego: int

    @property
    def rows(self) -> np.ndarray:
        """``[K]`` scene row of each window agent (-1: padding)."""
        return self.arrays["rows"]

    @property
    def origin(self) -> np.ndarray:
        """``[3]`` world x [m], y [m], yaw [rad] of the window's frame."""
        return self.arrays["origin"]

    def row_of(self, agent: int | None) -> int:
        """The window row of scene row ``agent`` (-1: not in the window, or None)."""
        if agent is None:
            return -1
        hit = np.flatnonzero(self.rows == agent)
        return int(hit[0]) if hit.size else -1
