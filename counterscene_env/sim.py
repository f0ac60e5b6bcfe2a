"""The closed loop: the world model drives traffic, an external policy drives the ego, and the
causally selected adversary is steered by counterfactual guidance (DESIGN 2).

One :class:`ClosedLoop` advances B episodes together, so that every replan is one batched
world-model call (scenes are windows of a common agent count K, padded). Per episode:

- **Egos.** One or more agents are driven by external policies: the scene's ego by default,
  or any rows given to :meth:`ClosedLoop.reset` (the PettingZoo env's ``ego_0 .. ego_{n-1}``).
  Each ego has its own causally selected adversary (distinct, never another ego) and its own
  model window centred on it, where its adversary is guided.
- **Start.** At the scene's ``current_index`` (3 s of history), from the log. The adversary is
  selected on the factual future (``selection_source="log"``, the paper) or re-selected at
  every replan from the world model's own unguided prediction (``"model"``).
- **Every step** (dt = 0.1 s): the ego advances by its action through a highway-env
  ``Vehicle`` (kinematic bicycle: acceleration m/s^2, steering rad), or is written from a
  given state (log replay); the other agents advance along their current plans.
- **Every ``replan_every`` steps** (and at the start): the world model re-plans everyone from
  the simulated history (the ego's real past included) in the ego's frame; at each denoising
  step the adversary's rows alone are nudged by the guidance; the sample with the lowest
  guidance loss of ``num_samples`` is kept. The ego's predicted row is only the guidance's
  reference: the ego follows its policy.
- **Who moves how.** An agent exists at a step exactly when the log says so (agents leave and
  enter as recorded). An agent in the model's window follows its current plan; one that was
  never planned (outside the window: beyond ``agent_radius`` or the K nearest) replays the
  log, and so does one that just entered; one the model planned before but no longer sees
  continues as a highway-env IDM lane follower (its stale open-loop plan would drift off the
  road); one whose plan ran out keeps its speed and course.
- **Reflexes of the ordinary traffic** (not the egos). An agent about to run into another
  brakes along its path instead (:mod:`counterscene_env.yielding`; a guided adversary never
  does: its margins are what the guidance removes), and a step that would leave the road is
  moved sideways onto the lane (:mod:`counterscene_env.road_keeping`).
- **Every step records** ego collisions (oriented boxes), off-road, the ego's signed
  longitudinal acceleration and hard braking, the smallest constant-velocity TTC, and the
  adversary's distance; :meth:`ClosedLoop.scene` returns the simulated :class:`Scene` for
  :mod:`counterscene_env.metrics`.

Randomness: each episode has its own ``torch.Generator`` and ``numpy`` Generator, both seeded
from its seed at :meth:`ClosedLoop.reset`, so an episode does not depend on which other
episodes share its batch; same seed and actions give the same episode on CPU.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env import geometry, road_keeping, yielding
from counterscene_env.adversary.guidance import (
    GuidanceConfig,
    guidance_preset,
    make_guidance_hook,
    make_targets,
    sample_losses,
)
from counterscene_env.adversary.selection import METHODS, Conflict, Selection, select_adversary
from counterscene_env.config import from_mapping
from counterscene_env.planners import IDMPlanner
from counterscene_env.scene.core import Scene
from counterscene_env.scene.dataset import lane_segments, make_window
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.realism import plan_cost

#: Hard-braking threshold on the ego's longitudinal acceleration, m/s^2 (paper: -3.0).
HARD_BRAKE = -3.0
#: How an agent moved into a step (``ClosedLoop.motion_source``): absent or history, its
#: world-model plan, its log (never planned, or just entered), constant velocity (plan ran
#: out), the ego's policy, highway-env's IDM (left the model's view), and held back by the
#: yielding rule on its plan's, log's or IDM's path (:mod:`counterscene_env.yielding`), and
#: kept on its lane by road keeping (:mod:`counterscene_env.road_keeping`).
MOTION_SOURCES = ("none", "plan", "log", "coast", "ego", "idm", "yield", "keep")
#: Horizon of the per-step TTC, s.
TTC_HORIZON = 5.0


@dataclass(frozen=True)
class SimConfig:
    """Closed-loop settings.

    Attributes:
        duration: closed-loop length after "now" [s]; capped by the log's length.
        replan_every: steps between world-model replans (5 = 0.5 s).
        num_samples: samples per replan; the one with the lowest guidance loss plus
            realism cost is kept (paper protocol: 16).
        selector: ``causal`` (the paper's conflict mining) or a baseline: ``random``,
            ``distance`` (nearest), ``ttc`` (smallest time to collision).
        selection_source: ``log`` (mined once on the factual future) or ``model`` (mined at
            every replan on the world model's unguided prediction).
        strict_gates: the strict selection gates of DESIGN 3.4 (d_min < 15 m, arrival gap
            < 1.5 s, encounter before the last step, adversary moving); off in the paper.
        guidance: a guidance preset name (``full``, ``no_jerk``, ``no_conflict_aware``,
            ``no_progressive``, ``no_adaptive``, ``minimal``, ``none``).
        sampler, sampling_steps, eta: the world model's sampler (None: the model's defaults).
        map_guidance: step size of the world model's map guidance on every agent (None: the
            model's default).
        realism_weight: weight of the realism cost (agents overlapping or off their lanes,
            ``world_model/realism.py``) in the choice among samples; 0: guidance loss only.
        cover_radius: an agent is planned from a model window only if it is within this many
            metres of the window's centre [m]; farther agents get windows of their own.
        max_windows: model windows per episode and replan (the ego's plus extra ones).
        traffic_yields: ordinary traffic slows along its planned path rather than drive into
            another agent's box (:mod:`counterscene_env.yielding`); egos and a guided
            adversary never yield. False: every plan is followed to the letter.
        road_keeping: a step that would take an agent other than an ego off the road is
            moved sideways onto its lane (:mod:`counterscene_env.road_keeping`). False: the
            plans' own off-road steps stand.
    """

    duration: float = 10.0
    replan_every: int = 5
    num_samples: int = 4
    selector: str = "causal"
    selection_source: str = "log"
    strict_gates: bool = True
    guidance: str = "full"
    sampler: str | None = None
    sampling_steps: int | None = None
    eta: float | None = None
    map_guidance: float | None = None
    realism_weight: float = 1.0
    cover_radius: float = 25.0
    max_windows: int = 1
    traffic_yields: bool = True
    road_keeping: bool = True

    def __post_init__(self) -> None:
        if not self.duration > 0:
            raise ValueError(f"duration must be > 0 s, got {self.duration}")
        if self.replan_every < 1:
            raise ValueError(f"replan_every must be >= 1 step, got {self.replan_every}")
        if self.num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {self.num_samples}")
        if self.selector not in METHODS:
            raise ValueError(f"unknown selector {self.selector!r}; valid: {list(METHODS)}")
        if self.selection_source not in ("log", "model"):
            raise ValueError(
                f"selection_source must be 'log' or 'model', got {self.selection_source!r}"
            )
        guidance_preset(self.guidance)  # raises on an unknown name

    @classmethod
    def from_mapping(cls, values: Mapping) -> SimConfig:
        """Build from a dict; unknown keys raise and name the valid ones."""
        return from_mapping(cls, values, "simulation")

    @property
    def guidance_config(self) -> GuidanceConfig:
        return guidance_preset(self.guidance)


@dataclass(frozen=True)
class WorldState:
    """A read-only snapshot of one episode at step ``t`` (what planners see).

    Attributes:
        t: absolute step of the scene's log.
        positions: ``[N, 2]`` m; yaws ``[N]`` rad; speeds ``[N]`` m/s; valid ``[N]`` bool.
        extents: ``[N, 2]`` m (length, width).
        ego_index: the ego's row.
        scene: the factual scene (road, ids, log).
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
class _Episode:
    """Mutable state of one episode (see ClosedLoop)."""

    factual: Scene
    start: int
    end: int
    t: int
    positions: np.ndarray  # [N, T, 2]
    yaws: np.ndarray  # [N, T]
    speeds: np.ndarray  # [N, T]
    valid: np.ndarray  # [N, T] simulated steps so far (log validity)
    source: np.ndarray  # [N, T] int8, how each agent moved into each step (MOTION_SOURCES)
    egos: list[int]  # rows driven by external policies; egos[0] is factual.ego_index
    vehicles: list[Vehicle]  # one highway-env bicycle per ego
    segments: tuple[np.ndarray, np.ndarray]
    pieces: tuple[np.ndarray, ...]  # lane centre pieces for road keeping
    generator: torch.Generator
    rng: np.random.Generator
    selections: list[Selection]  # one per ego
    plan_positions: np.ndarray  # [N, F, 2]
    plan_yaws: np.ndarray  # [N, F]
    plan_speeds: np.ndarray  # [N, F]
    plan_start: np.ndarray  # [N] step of plan index 0
    planned: np.ndarray  # [N] bool
    progress: np.ndarray  # [N] m along the current path (plan's or log's); NaN: not started
    replans: int = 0
    replan_seconds: float = 0.0  # this episode's share of the batched replan calls
    records: list[list[dict]] = field(default_factory=list)  # per step, one info per ego
    background: dict = field(default_factory=dict)  # row -> IDMPlanner (out of the window)

    @property
    def selection(self) -> Selection:
        """The first ego's selection."""
        return self.selections[0]

    @property
    def conflict(self) -> Conflict | None:
        return self.selections[0].conflict

    @property
    def adversary(self) -> int | None:
        return None if self.conflict is None else self.conflict.agent

    @property
    def adversaries(self) -> list[int | None]:
        """Each ego's adversary row (None: fallback)."""
        return [None if s.conflict is None else s.conflict.agent for s in self.selections]

    @property
    def done(self) -> bool:
        return self.t >= self.end


class ClosedLoop:
    """B closed-loop episodes advanced together (module docstring).

    Args:
        model: the world model (``counterscene_env.world_model.load_model()``).
        config: closed-loop settings.

    Usage::

        loop = ClosedLoop(load_model(), SimConfig(guidance="full"))
        loop.reset([scene], seeds=[0])
        while not loop.done.all():
            infos = loop.step(np.array([[0.0, 0.0]]))   # (acceleration m/s^2, steering rad)
        simulated = loop.scene(0)
    """

    def __init__(self, model: WorldModel, config: SimConfig | None = None) -> None:
        self.model = model.eval()
        self.config = config or SimConfig()
        self.guidance = self.config.guidance_config
        self.window_config = model.window_config()
        self.episodes: list[_Episode] = []

    # ------------------------------------------------------------------ episode control
    def reset(
        self,
        scenes: Sequence[Scene],
        seeds: Sequence[int],
        egos: Sequence[Sequence[int]] | None = None,
    ) -> list[dict]:
        """Start one episode per scene.

        Args:
            scenes: the factual scenes.
            seeds: one seed per episode (its torch and numpy generators).
            egos: per scene, the agent rows driven by external policies (default: the
                scene's ego alone). Every episode of a batch has the same number of egos; the
                first one becomes the scene's ego (the frame of its model window).

        Returns:
            Each episode's first ego's info dict at step ``now`` (:meth:`infos` has all).
        """
        if len(scenes) != len(seeds):
            raise ValueError(f"{len(scenes)} scenes but {len(seeds)} seeds")
        if not scenes:
            raise ValueError("reset needs at least one scene")
        if egos is None:
            egos = [[s.ego_index] for s in scenes]
        if len(egos) != len(scenes) or len({len(e) for e in egos}) != 1:
            raise ValueError("egos needs one list per scene, all of the same length")
        self.episodes = [
            self._start(s, int(seed), [int(r) for r in rows])
            for s, seed, rows in zip(scenes, seeds, egos, strict=True)
        ]
        for ep in self.episodes:
            ep.records.append([self._info(ep, k, replanned=False) for k in range(len(ep.egos))])
        return [ep.records[-1][0] for ep in self.episodes]

    @property
    def num_egos(self) -> int:
        """Egos per episode."""
        return len(self.episodes[0].egos) if self.episodes else 1

    def _start(self, scene: Scene, seed: int, egos: list[int]) -> _Episode:
        start = scene.current_index
        steps = min(round(self.config.duration / scene.dt), scene.num_steps - 1 - start)
        if steps < 1:
            raise ValueError(f"scene {scene.scenario_id!r} has no future after step {start}")
        if not egos or len(set(egos)) != len(egos):
            raise ValueError(f"egos must be distinct agent rows, got {egos}")
        for r in egos:
            if not 0 <= r < scene.num_agents:
                raise ValueError(f"ego row {r} out of range: the scene has {scene.num_agents}")
            if not scene.valid[r, start]:
                raise ValueError(
                    f"agent {scene.agent_ids[r]!r} of {scene.scenario_id!r} is not valid at "
                    f"step {start} and cannot be an ego"
                )
        scene = scene.replace(ego_index=egos[0]) if egos[0] != scene.ego_index else scene
        end = start + steps
        N, F = scene.num_agents, self.model.config.future_steps
        valid = np.zeros((N, end + 1), bool)
        valid[:, : start + 1] = scene.valid[:, : start + 1]
        road = Road(network=scene.road.network, vehicles=[], np_random=np.random.default_rng(0))
        vehicles = []
        for e in egos:
            v = Vehicle(road, scene.positions[e, start].copy(), scene.yaws[e, start], 0.0)
            v.speed = float(scene.speeds[e, start])
            v.LENGTH, v.WIDTH = (float(x) for x in scene.extents[e])  # the bicycle's wheelbase
            vehicles.append(v)
        rng = np.random.default_rng(seed)
        c = self.window_config
        ep = _Episode(
            factual=scene,
            start=start,
            end=end,
            t=start,
            positions=scene.positions[:, : end + 1].copy(),
            yaws=scene.yaws[:, : end + 1].copy(),
            speeds=scene.speeds[:, : end + 1].copy(),
            valid=valid,
            source=np.zeros((N, end + 1), np.int8),
            egos=egos,
            vehicles=vehicles,
            segments=(segments := lane_segments(scene, c.lane_segment_length, c.lane_points)),
            pieces=road_keeping.lane_pieces(*segments),
            generator=torch.Generator().manual_seed(seed),
            rng=rng,
            selections=[Selection(self.config.selector, None, "not selected yet", 0)] * len(egos),
            plan_positions=np.zeros((N, F, 2)),
            plan_yaws=np.zeros((N, F)),
            plan_speeds=np.zeros((N, F)),
            plan_start=np.zeros(N, np.int64),
            planned=np.zeros(N, bool),
            progress=np.full(N, np.nan),
        )
        # The adversary is selected (and kept in the model's window) with guidance off too, so
        # an unguided run reports the same agent's collisions and clearance as a guided one.
        if self.config.selection_source == "log":
            future = self._log_future(ep)
            for k in range(len(egos)):
                ep.selections[k] = self._select(ep, k, *future, start_step=start + 1)
        return ep

    @property
    def done(self) -> np.ndarray:
        """``[B]`` bool: episodes that reached their last step."""
        return np.array([ep.done for ep in self.episodes], bool)

    def state(self, b: int) -> WorldState:
        """What episode ``b`` looks like at its current step."""
        return self._state(self.episodes[b])

    @staticmethod
    def _state(ep: _Episode) -> WorldState:
        t = ep.t
        return WorldState(
            t=t,
            positions=ep.positions[:, t].copy(),
            yaws=ep.yaws[:, t].copy(),
            speeds=ep.speeds[:, t].copy(),
            valid=ep.valid[:, t].copy(),
            extents=ep.factual.extents,
            ego_index=ep.factual.ego_index,
            scene=ep.factual,
        )

    def step(
        self, actions: np.ndarray | None = None, ego_states: np.ndarray | None = None
    ) -> list[dict]:
        """Advance every unfinished episode by one step.

        Args:
            actions: ``[B, 2]`` ego actions, (acceleration m/s^2, steering rad), through the
                highway-env bicycle model; ``[B, E, 2]`` with E egos per episode.
            ego_states: ``[B, 4]`` (x m, y m, yaw rad, speed m/s) written as the ego's next
                state instead (log replay, or an ego stepped by the caller); ``[B, E, 4]``
                with E egos. A row of NaN uses ``actions`` for that ego.

        Returns:
            The first ego's info dict of each episode (module docstring; finished episodes
            repeat their last); :meth:`infos` gives every ego's.
        """
        B = len(self.episodes)
        if not B:
            raise RuntimeError("call reset() before step()")
        E = self.num_egos
        actions = _check_rows(actions, B, E, 2, "actions")
        ego_states = _check_rows(ego_states, B, E, 4, "ego_states", allow_nan_rows=True)
        active = [b for b, ep in enumerate(self.episodes) if not ep.done]
        # Every ego's input is checked before anything moves: a bad call changes nothing.
        states = {}
        for b in active:
            rows = [None] * E if ego_states is None else list(ego_states[b])
            rows = [None if r is not None and np.isnan(r).all() else r for r in rows]
            if actions is None and any(r is None for r in rows):
                raise ValueError("step needs actions or ego_states for every running ego")
            states[b] = rows
        due = [
            b
            for b in active
            if (self.episodes[b].t - self.episodes[b].start) % self.config.replan_every == 0
        ]
        if due:
            self._replan(due)
        for b in active:
            ep = self.episodes[b]
            self._advance(ep, None if actions is None else actions[b], states[b])
            ep.records.append([self._info(ep, k, replanned=b in due) for k in range(E)])
        return [ep.records[-1][0] for ep in self.episodes]

    def infos(self, b: int) -> list[dict]:
        """Episode ``b``'s latest info dict of every ego (in ``egos`` order)."""
        return list(self.episodes[b].records[-1])

    # ------------------------------------------------------------------ selection
    def _log_future(self, ep: _Episode) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s, lo, hi = ep.factual, ep.start + 1, ep.end + 1
        return s.positions[:, lo:hi], s.valid[:, lo:hi], s.speeds[:, lo:hi]

    def _select(
        self,
        ep: _Episode,
        k: int,
        positions: np.ndarray,
        valid: np.ndarray,
        speeds: np.ndarray,
        start_step: int,
        rows: np.ndarray | None = None,
        yaws: np.ndarray | None = None,
    ) -> Selection:
        """Select ego ``k``'s adversary on future tracks; ``rows`` maps their rows to scene rows
        (None: identity). Other egos, and the adversaries of egos before ``k``, are not
        eligible: every ego gets its own world-model adversary."""
        scene = ep.factual
        rows = np.arange(scene.num_agents) if rows is None else rows
        ego = int(np.flatnonzero(rows == ep.egos[k])[0])
        taken = set(ep.egos) | {a for a in ep.adversaries[:k] if a is not None}
        eligible = (scene.agent_types[rows] == "vehicle") & ~np.isin(rows, sorted(taken))
        sel = select_adversary(
            self.config.selector,
            positions,
            valid,
            ego,
            speeds=speeds,
            extents=scene.extents[rows],
            yaws=yaws,
            eligible=eligible,
            dt=scene.dt,
            start_step=start_step,
            strict=self.config.strict_gates,
            rng=ep.rng,
        )
        if sel.conflict is not None:  # back to scene rows
            sel = dataclasses.replace(
                sel, conflict=dataclasses.replace(sel.conflict, agent=int(rows[sel.conflict.agent]))
            )
        return sel

    # ------------------------------------------------------------------ replanning
    def _sim_scene(self, ep: _Episode) -> Scene:
        """The simulated scene up to step ``t`` (later frames invalid)."""
        valid = ep.valid.copy()
        valid[:, ep.t + 1 :] = False
        return ep.factual.replace(
            positions=ep.positions, yaws=ep.yaws, speeds=ep.speeds, valid=valid
        )

    def _windows(self, ep: _Episode, sim: Scene) -> list[dict]:
        """The model windows of one episode at its current step.

        The first E are centred on the E egos, each with its adversary forced in; an agent
        seen by several is planned by the first (its adversary's by its own, where it is
        guided). Agents farther than
        ``cover_radius`` from every window centre get windows of their own, centred on the
        uncovered agent nearest the ego, up to ``max_windows``: the model sees the lanes and
        neighbours around each agent it plans, not only around the ego. Each window's
        ``plan_rows`` are the agents whose plans it supplies. The default is one window
        (``max_windows=1``): the shipped model, trained on ego-centred windows, drives worse
        in windows centred on other agents (measured, docs/closed_loop.md).
        """
        c, t = self.config, ep.t
        wc = self.window_config
        e = sim.ego_index
        pos = sim.positions[:, t]
        movable = sim.valid[:, t] & (sim.agent_types == "vehicle")
        movable[ep.egos] = False
        adversaries = [a for a in ep.adversaries if a is not None]
        items = []
        claimed = np.zeros(sim.num_agents, bool)
        claimed[ep.egos] = True
        claimed[adversaries] = True
        covered = np.zeros(sim.num_agents, bool)
        for ego, adv in zip(ep.egos, ep.adversaries, strict=True):
            include = () if adv is None else (adv,)
            view = sim if ego == e else sim.replace(ego_index=ego)
            item = make_window(view, t, wc, ep.segments, include=include)
            rows = item["rows"][item["rows"] >= 0]
            mine = [int(r) for r in rows if not claimed[r]]
            own = [] if adv is None or adv not in rows else [adv]
            item["plan_rows"] = own + mine
            item["ego"] = len(items)  # which ego's window (-1: an extra one)
            claimed[mine] = True
            near = np.linalg.norm(pos[rows] - pos[ego], axis=-1) <= c.cover_radius
            covered[rows[near]] = True
            items.append(item)
        covered[adversaries] = True  # guided in their ego's window, wherever they are
        while len(items) < max(c.max_windows, len(ep.egos)):
            left = np.flatnonzero(movable & ~covered)
            if not left.size:
                break
            centre = int(left[np.argmin(np.linalg.norm(pos[left] - pos[e], axis=-1))])
            item = make_window(sim.replace(ego_index=centre), t, wc, ep.segments)
            rows = item["rows"][item["rows"] >= 0]
            mine = rows[
                movable[rows]
                & ~covered[rows]
                & (np.linalg.norm(pos[rows] - pos[centre], axis=-1) <= c.cover_radius)
            ]
            item["plan_rows"] = [int(r) for r in mine]
            item["ego"] = -1
            covered[mine] = True
            covered[centre] = True
            items.append(item)
        return items  # agents left uncovered continue as IDM lane followers (_replan)

    def _replan(self, due: list[int]) -> None:
        started = time.perf_counter()
        model, c, g = self.model, self.config, self.guidance
        eps = [self.episodes[b] for b in due]
        sims = [self._sim_scene(ep) for ep in eps]
        kwargs = dict(
            sampler=c.sampler, steps=c.sampling_steps, eta=c.eta, map_guidance=c.map_guidance
        )
        if c.selection_source == "model":
            # Re-select on the world model's own unguided prediction of each ego's window.
            owner, items = [], []
            for i, (sim, ep) in enumerate(zip(sims, eps, strict=True)):
                for ego in ep.egos:
                    view = sim if ego == sim.ego_index else sim.replace(ego_index=ego)
                    items.append(make_window(view, ep.t, self.window_config, ep.segments))
                    owner.append(i)
            pred = model.sample(_collate(items), 1, [eps[o].generator for o in owner], **kwargs)
            for j, (o, item) in enumerate(zip(owner, items, strict=True)):
                ep = eps[o]
                k = ep.egos.index(int(item["rows"][0]))
                ok = (item["rows"] >= 0) & pred.valid[j].numpy()
                traj = pred.trajectory[j, 0].numpy()[ok]  # [A, F, 4] window frame
                xy, yaw = _to_world(traj[..., :2], traj[..., 2], item["origin"])
                valid = np.ones(xy.shape[:2], bool)
                rows = item["rows"][ok]
                ep.selections[k] = self._select(ep, k, xy, valid, traj[..., 3], ep.t + 1, rows, yaw)

        # Every window of every episode in one batched call; each ego's own window first.
        owner, items = [], []
        for i, (sim, ep) in enumerate(zip(sims, eps, strict=True)):
            for item in self._windows(ep, sim):
                owner.append(i)
                items.append(item)
        batch = _collate(items)
        conflicts = [
            eps[o].selections[item["ego"]].conflict if item["ego"] >= 0 else None
            for item, o in zip(items, owner, strict=True)
        ]
        adv_rows = [
            -1 if conflict is None else _window_row(item["rows"], conflict.agent)
            for item, conflict in zip(items, conflicts, strict=True)
        ]
        S = c.num_samples
        targets = make_targets(
            conflicts,
            adv_rows,
            np.stack([item["origin"] for item in items]),
            [eps[o].t for o in owner],
            [(eps[o].t - eps[o].start) / (eps[o].end - eps[o].start) for o in owner],
            g,
        )
        hook = make_guidance_hook(model, batch, targets, S, g) if g.enabled else None
        gens = [eps[o].generator for o in owner]
        pred = model.sample(batch, S, gens, guidance=hook, **kwargs)

        ego_rows = [
            [r for r in (_window_row(item["rows"], e) for e in eps[o].egos) if r >= 0]
            for item, o in zip(items, owner, strict=True)
        ]
        best = np.zeros(len(items), np.int64)
        if S > 1:
            best = self._choose(batch, pred, hook, adv_rows, ego_rows).numpy()

        traj = pred.trajectory.numpy()
        for j, (o, item) in enumerate(zip(owner, items, strict=True)):
            ep = eps[o]
            lookup = {int(r): k for k, r in enumerate(item["rows"]) if r >= 0}
            rows = np.array(
                [r for r in item["plan_rows"] if pred.valid[j, lookup[r]]], dtype=np.int64
            )
            if not rows.size:
                continue
            cols = np.array([lookup[r] for r in rows])
            chosen = traj[j, best[j], cols]  # [A, F, 4] window frame
            xy, yaw = _to_world(chosen[..., :2], chosen[..., 2], item["origin"])
            ep.plan_positions[rows] = xy
            ep.plan_yaws[rows] = yaw
            ep.plan_speeds[rows] = chosen[..., 3]
            ep.plan_start[rows] = ep.t + 1
            ep.planned[rows] = True
            ep.progress[rows] = 0.0

        # Agents the model planned before but no longer sees (they left its window) continue
        # as highway-env IDM lane followers rather than on a stale open-loop plan; an agent
        # back in view is the model's again.
        planned_now: dict[int, set[int]] = {}
        for o, item in zip(owner, items, strict=True):
            planned_now.setdefault(o, set()).update(item["plan_rows"])
        for i, ep in enumerate(eps):
            now = planned_now.get(i, set())
            for r in list(ep.background):
                if r in now:
                    del ep.background[r]
            for r in np.flatnonzero(ep.planned & ep.valid[:, ep.t]):
                r = int(r)
                if r not in now and r not in ep.background and r not in ep.egos:
                    idm = IDMPlanner()
                    idm.reset(ep.factual, int(ep.rng.integers(2**31)), agent=r, t=ep.t)
                    ep.background[r] = idm
        for ep in eps:
            ep.replans += 1
            ep.replan_seconds += (time.perf_counter() - started) / len(eps)

    def _choose(
        self, batch, pred, hook, adv_rows: list[int], ego_rows: list[list[int]]
    ) -> torch.Tensor:
        """``[W]`` best sample per window: lowest guidance loss plus ``realism_weight`` times
        the realism cost of everyone but the egos (whose plans are never executed) and the
        adversary (which the guidance steers)."""
        W, S, K = pred.trajectory.shape[:3]
        cost = torch.zeros(W, S)
        if hook is not None:
            cost += sample_losses(self.model, hook, pred.normalized, self.guidance)
        w = self.config.realism_weight
        if w > 0:
            exclude = torch.zeros(W, K, dtype=torch.bool)
            for j, (adv, egos) in enumerate(zip(adv_rows, ego_rows, strict=True)):
                for row in (adv, *egos):
                    if row >= 0:
                        exclude[j, row] = True
            rep = lambda x: x.repeat_interleave(S, 0)  # noqa: E731
            traj = pred.trajectory.reshape(W * S, *pred.trajectory.shape[2:]).clone()
            # The ego's future is its policy's, not the model's guess: agents are scored
            # against the ego held at its current speed and course (a braking or stopped
            # ego must not be run into because the model expected it to drive on).
            state = rep(self.model.current_state(batch))  # [W S, K, 4] window frame
            steps = torch.arange(1, traj.shape[-2] + 1, dtype=traj.dtype) * self.model.config.dt
            for j, egos in enumerate(ego_rows):
                for ego in egos:
                    x, y, course, v = state[j * S, ego].unbind(-1)
                    path = torch.stack(
                        [x + v * steps * torch.cos(course), y + v * steps * torch.sin(course)],
                        -1,
                    )
                    traj[j * S : (j + 1) * S, ego, :, :2] = path
                    traj[j * S : (j + 1) * S, ego, :, 2] = course
            lanes = tuple(rep(batch[k]) for k in ("map", "map_valid", "map_widths"))
            cost += w * plan_cost(
                traj, rep(pred.valid), rep(batch["extents"]), lanes, rep(exclude)
            ).reshape(W, S)
        return cost.argmin(-1)

    # ------------------------------------------------------------------ one step
    def _advance(
        self, ep: _Episode, actions: np.ndarray | None, states: list[np.ndarray | None]
    ) -> None:
        t, t1 = ep.t, ep.t + 1
        log = ep.factual
        egos = ep.egos
        present = log.valid[:, t1].copy()
        present[egos] = True
        k = t1 - ep.plan_start
        F = ep.plan_positions.shape[1]
        entered = present & ~ep.valid[:, t]
        idm = np.zeros_like(present)
        idm[list(ep.background)] = True
        idm &= present & ~entered
        on_plan = ep.planned & (k >= 0) & (k < F) & present & ~idm
        replay = present & ~on_plan & ~idm & (~ep.planned | entered)
        coast = present & ~on_plan & ~replay & ~idm
        if idm.any():
            now = self._state(ep)  # everyone at step t, before anyone moves
            for r in np.flatnonzero(idm):
                x, y, yaw, speed = ep.background[int(r)].drive(now)
                ep.positions[r, t1], ep.yaws[r, t1], ep.speeds[r, t1] = (x, y), yaw, speed
        i = np.flatnonzero(on_plan)
        ep.positions[i, t1] = ep.plan_positions[i, k[i]]
        ep.yaws[i, t1] = ep.plan_yaws[i, k[i]]
        ep.speeds[i, t1] = ep.plan_speeds[i, k[i]]
        i = np.flatnonzero(replay)
        ep.positions[i, t1] = log.positions[i, t1]
        ep.yaws[i, t1] = log.yaws[i, t1]
        ep.speeds[i, t1] = log.speeds[i, t1]
        ep.progress[entered] = np.nan
        held = self._yield(ep, on_plan, k, replay & ~entered, idm)
        kept = self._keep_on_road(ep, (on_plan | replay | idm) & ep.valid[:, t])
        i = np.flatnonzero(coast)
        heading = np.stack([np.cos(ep.yaws[i, t]), np.sin(ep.yaws[i, t])], -1)
        ep.positions[i, t1] = ep.positions[i, t] + log.dt * ep.speeds[i, t, None] * heading
        ep.yaws[i, t1] = ep.yaws[i, t]
        ep.speeds[i, t1] = ep.speeds[i, t]
        ep.valid[:, t1] = present
        ep.source[:, t1] = np.select([on_plan, replay, coast, idm], [1, 2, 3, 5], 0)
        ep.source[held, t1] = 6
        ep.source[kept, t1] = 7
        ep.source[egos, t1] = 4

        # The egos: the policy's action through highway-env's bicycle, or a written state.
        for k, (e, v, state) in enumerate(zip(egos, ep.vehicles, states, strict=True)):
            if state is not None:
                v.position = np.array(state[:2], dtype=np.float64)
                v.heading, v.speed = float(state[2]), float(state[3])
            else:
                v.act({"acceleration": float(actions[k, 0]), "steering": float(actions[k, 1])})
                v.step(log.dt)
            ep.positions[e, t1] = v.position
            ep.yaws[e, t1] = v.heading
            ep.speeds[e, t1] = v.speed
        ep.t = t1

    def _yield(
        self, ep: _Episode, on_plan: np.ndarray, k: np.ndarray, replay: np.ndarray, idm: np.ndarray
    ) -> list[int]:
        """Hold back, along their paths, the agents whose next step would run into another
        agent's current box (:mod:`counterscene_env.yielding`). The path is the plan's, the
        log's for a replaying agent, and the straight line through its next point for an IDM
        one. Rows free to advance keep their exact point. Returns the rows held back."""
        if not self.config.traffic_yields:
            return []
        t, t1, dt = ep.t, ep.t + 1, ep.factual.dt
        log = ep.factual
        exempt = set(ep.egos)
        if self.guidance.enabled:
            exempt.update(a for a in ep.adversaries if a is not None)
        here = np.flatnonzero(ep.valid[:, t])
        xy, yaw, speed = ep.positions[here, t], ep.yaws[here, t], ep.speeds[here, t]
        velocity = speed[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
        extents = log.extents[here]
        held = []
        movers = np.flatnonzero((on_plan | replay | idm) & ep.valid[:, t])
        # Rows whose next pose is final: written already and not subject to yielding (a guided
        # adversary, an entering car), then each yielding row once it is done.
        settled = (on_plan | replay | idm) & ep.valid[:, t1]
        settled[movers] = False
        settled[ep.egos] = False
        for r in movers:
            path, path_yaw, due = self._path(ep, int(r), bool(on_plan[r]), int(k[r]), bool(idm[r]))
            arc = geometry.arc_length(path)
            done = ep.progress[r]
            if np.isnan(done):
                done = arc[due - 1]  # a log row's first step: on schedule
            if r in exempt:
                ep.progress[r] = arc[due]
                settled[r] = True
                continue
            lagging = done < arc[due - 1] - 1e-6 and not idm[r]  # IDM keeps its own speed
            ahead = np.flatnonzero(arc > done)
            stations = np.concatenate([ep.positions[r, t][None], path[ahead]])
            station_yaw = np.concatenate([[ep.yaws[r, t]], path_yaw[ahead]])
            station_arc = np.concatenate([[0.0], arc[ahead] - done])
            desired = arc[due] - arc[due - 1]
            # Beyond the distance this step's speed needs to stop in, a car cannot change
            # the answer (allowed_advance gives ``desired`` then): check the path up to there.
            need = max(desired, (desired / dt) ** 2 / (2 * yielding.BRAKE))
            cut = int(np.searchsorted(station_arc, need)) + 1
            stations, station_yaw, station_arc = (
                stations[:cut],
                station_yaw[:cut],
                station_arc[:cut],
            )
            other = here != r
            d_free, v_lead = yielding.free_distance(
                stations,
                station_yaw,
                station_arc,
                log.extents[r],
                xy[other],
                yaw[other],
                extents[other],
                velocity[other],
            )
            step = yielding.allowed_advance(
                d_free, v_lead, float(ep.speeds[r, t]), desired, dt, lagging
            )
            on_time = not lagging and step >= desired - 1e-9
            if on_time:  # the plan's (or log's, or IDM's) point, already written
                now_done, pose = arc[due], (ep.positions[r, t1].copy(), float(ep.yaws[r, t1]))
            else:
                now_done = min(done + step, arc[-1])
                pose = yielding.point_at(path, path_yaw, arc, now_done)
            # The last guard: never end a step inside a box we were clear of, where the others
            # are now or (those settled) will be; a plan may also turn a car on the spot,
            # which sweeps its corners without moving along the path.
            then = np.flatnonzero(settled)
            if yielding.moves_into(
                pose,
                (ep.positions[r, t], ep.yaws[r, t]),
                log.extents[r],
                np.concatenate([xy[other], ep.positions[then, t1]]),
                np.concatenate([yaw[other], ep.yaws[then, t1]]),
                np.concatenate([extents[other], log.extents[then]]),
            ):
                on_time, now_done = False, done
                pose = (ep.positions[r, t].copy(), float(ep.yaws[r, t]))
            settled[r] = True
            if on_time:
                ep.progress[r] = now_done
                continue
            ep.positions[r, t1], ep.yaws[r, t1] = pose
            ep.speeds[r, t1] = (now_done - done) / dt
            ep.progress[r] = now_done
            held.append(int(r))
        return held

    @staticmethod
    def _path(
        ep: _Episode, r: int, on_plan: bool, k: int, idm: bool
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Agent ``r``'s path for the yielding rule: points ``[P, 2]`` m, yaws ``[P]`` rad, and
        the index of the point it is due at on step ``t + 1``."""
        t, t1 = ep.t, ep.t + 1
        if idm:
            # IDM's next point, then straight on for as far as it could need to stop in.
            now, then = ep.positions[r, t], ep.positions[r, t1]
            reach = ep.speeds[r, t1] ** 2 / (2 * yielding.BRAKE) + 5.0
            on = np.arange(0.5, reach, 0.5)[:, None]
            course = np.array([math.cos(ep.yaws[r, t1]), math.sin(ep.yaws[r, t1])])
            path = np.concatenate([now[None], then[None], then + on * course])
            path_yaw = np.concatenate([[ep.yaws[r, t]], np.full(len(on) + 1, ep.yaws[r, t1])])
            ep.progress[r] = 0.0  # a fresh path every step
            return path, path_yaw, 1
        if on_plan:
            start = ep.plan_start[r] - 1  # the step the plan was made from
            path = np.concatenate([ep.positions[r, start][None], ep.plan_positions[r]])
            path_yaw = np.concatenate([[ep.yaws[r, start]], ep.plan_yaws[r]])
            return path, path_yaw, k + 1
        log = ep.factual
        first, last = _valid_run(log.valid[r], t1)  # the log's path around t1
        return log.positions[r, first:last], log.yaws[r, first:last], t1 - first

    def _keep_on_road(self, ep: _Episode, movers: np.ndarray) -> list[int]:
        """Move sideways onto their lanes the non-ego agents whose step would leave the road
        (:mod:`counterscene_env.road_keeping`); returns the rows moved. A correction that
        would put an agent into another's box stops it where it was instead."""
        if not self.config.road_keeping:
            return []
        t, t1, log = ep.t, ep.t + 1, ep.factual
        movers = movers.copy()
        movers[ep.egos] = False
        rows = np.flatnonzero(movers)
        if not rows.size:
            return []
        area = log.road.drivable_area
        leaving = geometry.points_in_area(area, ep.positions[rows, t]) & ~geometry.points_in_area(
            area, ep.positions[rows, t1]
        )
        kept = []
        for r in rows[leaving]:
            here, there = ep.positions[r, t], ep.positions[r, t1]
            step = there - here
            course = math.atan2(step[1], step[0]) if step @ step > 1e-6 else ep.yaws[r, t1]
            moved = road_keeping.keep_on_lane(there, course, ep.pieces)
            if moved is None or not geometry.points_in_area(area, moved[None])[0]:
                continue
            step = moved - here
            yaw = math.atan2(step[1], step[0]) if step @ step > 1e-4 else float(ep.yaws[r, t])
            # Everyone else where they are now and where they will be (egos not yet moved).
            others = np.flatnonzero(ep.valid[:, t] & (np.arange(log.num_agents) != r))
            ahead = np.flatnonzero(movers & ep.valid[:, t1] & (np.arange(log.num_agents) != r))
            if yielding.moves_into(
                (moved, yaw),
                (here, ep.yaws[r, t]),
                log.extents[r],
                np.concatenate([ep.positions[others, t], ep.positions[ahead, t1]]),
                np.concatenate([ep.yaws[others, t], ep.yaws[ahead, t1]]),
                np.concatenate([log.extents[others], log.extents[ahead]]),
            ):
                moved, yaw = here.copy(), float(ep.yaws[r, t])
            ep.positions[r, t1], ep.yaws[r, t1] = moved, yaw
            ep.speeds[r, t1] = float(np.linalg.norm(moved - here)) / log.dt
            kept.append(int(r))
        return kept

    # ------------------------------------------------------------------ per-step info
    def _info(self, ep: _Episode, k: int, replanned: bool) -> dict:
        """Ego ``k``'s step info (plain Python values; see the module docstring)."""
        t, log = ep.t, ep.factual
        e = ep.egos[k]
        pos, yaw, ok = ep.positions[:, t], ep.yaws[:, t], ep.valid[:, t].copy()
        ok[e] = False
        ext = log.extents
        hits = geometry.boxes_overlap(pos[e], yaw[e], ext[e], pos, yaw, ext) & ok
        hit_rows = np.flatnonzero(hits)
        vel = ep.speeds[:, t, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
        ttc = geometry.box_time_to_collision(
            pos[e], vel[e], yaw[e], ext[e], pos, vel, yaw, ext, horizon=TTC_HORIZON
        )
        ttc = np.where(ok, ttc, np.inf)
        acc = (ep.speeds[e, t] - ep.speeds[e, t - 1]) / log.dt if t > ep.start else 0.0
        conflict = ep.selections[k].conflict
        adv = None if conflict is None else conflict.agent
        adv_dist = float(np.linalg.norm(pos[adv] - pos[e])) if adv is not None and ok[adv] else None
        return {
            "step": t - ep.start,
            "time": (t - ep.start) * log.dt,
            "collision": bool(hits.any()),
            "collided_with": str(log.agent_ids[hit_rows[0]]) if hit_rows.size else None,
            "hard_braking": bool(acc < HARD_BRAKE),
            "ego_acceleration": float(acc),
            "ego_speed": float(ep.speeds[e, t]),
            "off_road": not bool(geometry.points_in_area(log.road.drivable_area, pos[e])),
            "min_ttc": float(ttc.min()) if ttc.size else math.inf,
            "adversary": None if adv is None else str(log.agent_ids[adv]),
            "conflict_type": None if conflict is None else conflict.subtype,
            "danger_score": None if conflict is None else float(conflict.score),
            "tier": None if conflict is None else conflict.tier,
            "conflict_point": None
            if conflict is None
            else [float(x) for x in conflict.conflict_point],
            "arrival_steps": None
            if conflict is None
            else [int(conflict.ego_step) - ep.start, int(conflict.adversary_step) - ep.start],
            "adversary_distance": adv_dist,
            "fallback": ep.selections[k].fallback,
            "replanned": replanned,
        }

    # ------------------------------------------------------------------ results
    def scene(self, b: int) -> Scene:
        """Episode ``b`` as a :class:`Scene`: the log's history, then the simulated steps so
        far (the rollout ends at the current step)."""
        ep = self.episodes[b]
        n = ep.t + 1
        meta = dict(ep.factual.metadata)
        meta["closed_loop"] = {
            "adversary": None if ep.adversary is None else str(ep.factual.agent_ids[ep.adversary]),
            "selector": self.config.selector,
            "guidance": self.config.guidance,
            "fallback": ep.selection.fallback,
            "replans": ep.replans,
            "egos": [str(ep.factual.agent_ids[r]) for r in ep.egos],
            "adversaries": [
                None if a is None else str(ep.factual.agent_ids[a]) for a in ep.adversaries
            ],
        }
        return ep.factual.replace(
            positions=ep.positions[:, :n],
            yaws=ep.yaws[:, :n],
            speeds=ep.speeds[:, :n],
            valid=ep.valid[:, :n],
            metadata=meta,
        )

    def selection(self, b: int, k: int = 0) -> Selection:
        """The adversary selection of ego ``k`` of episode ``b`` (the latest one with source
        ``model``)."""
        return self.episodes[b].selections[k]

    def motion_source(self, b: int) -> np.ndarray:
        """``[N, T]`` int8: how each agent moved into each step so far (index into
        :data:`MOTION_SOURCES`)."""
        ep = self.episodes[b]
        return ep.source[:, : ep.t + 1].copy()

    def plan(self, b: int, row: int) -> np.ndarray | None:
        """``[F, 2]`` m: the current plan of agent ``row`` in episode ``b`` (None if none)."""
        ep = self.episodes[b]
        return ep.plan_positions[row].copy() if ep.planned[row] else None


# ---------------------------------------------------------------------- helpers
def _check_rows(
    x: np.ndarray | None, B: int, E: int, width: int, name: str, allow_nan_rows: bool = False
) -> np.ndarray | None:
    """``x`` as ``[B, E, width]`` float64; ``[B, width]`` is accepted when ``E == 1``."""
    if x is None:
        return None
    x = np.asarray(x, dtype=np.float64)
    if E == 1 and x.shape == (B, width):
        x = x[:, None]
    if x.shape != (B, E, width):
        want = f"({B}, {width}) or ({B}, 1, {width})" if E == 1 else f"({B}, {E}, {width})"
        raise ValueError(f"{name} must have shape {want}, got {x.shape}")
    bad = ~np.isfinite(x)
    if allow_nan_rows:
        bad &= ~np.isnan(x).all(-1, keepdims=True)
    if bad.any():
        raise ValueError(f"{name} contains NaN or inf: {x.tolist()}")
    return x


def _collate(items: list[dict]) -> dict[str, torch.Tensor]:
    keys = ("history", "history_valid", "extents", "agent_valid", "map", "map_valid", "map_widths")
    return {k: torch.from_numpy(np.stack([item[k] for item in items])) for k in keys}


def _window_row(rows: np.ndarray, agent: int | None) -> int:
    if agent is None:
        return -1
    hit = np.flatnonzero(rows == agent)
    return int(hit[0]) if hit.size else -1


def _valid_run(valid: np.ndarray, t: int) -> tuple[int, int]:
    """``[first, last)``: the run of consecutive valid steps of ``valid`` ``[T]`` around ``t``."""
    gaps = np.flatnonzero(~valid)
    first = int(gaps[gaps < t].max(initial=-1)) + 1
    last = int(gaps[gaps > t].min(initial=len(valid)))
    return first, last


def _to_world(xy: np.ndarray, yaw: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Window frame -> world: rotate by the origin's yaw, translate by its position."""
    c, s = np.cos(origin[2]), np.sin(origin[2])
    x, y = xy[..., 0], xy[..., 1]
    world = np.stack([c * x - s * y + origin[0], s * x + c * y + origin[1]], -1)
    return world, (yaw + origin[2] + np.pi) % (2 * np.pi) - np.pi
