"""The closed loop: the world model drives traffic, an external policy drives the ego, and the
causally selected adversary is steered by counterfactual guidance (docs/design.md, "Data
flow").

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
  step the adversary's rows alone are nudged by the guidance; of ``num_samples`` samples the
  one with the lowest guidance loss plus realism cost (``sim/realism.py``) is kept. The ego's
  predicted row is only the guidance's reference: the ego follows its policy.
- **Who moves how.** An agent exists at a step when the log says so (agents leave and enter
  as recorded; one that would enter on top of another waits until its logged pose is clear,
  ``sim/motion.py``). An agent in the model's window follows its current plan; one that was
  never planned (outside the window: beyond ``agent_radius`` or the K nearest) replays the
  log, and so does one that just entered; one the model planned before but no longer sees
  continues as a highway-env IDM lane follower (its stale open-loop plan would drift off the
  road); one whose plan ran out keeps its speed and course.
- **Reflexes of the ordinary traffic** (not the egos). An agent about to run into another
  brakes along its path instead (``sim/yielding.py``; a guided adversary yields to everyone
  but the egos, ``adversary_yields_to_others``: its margins toward them are what the guidance
  removes), and a step that would leave the road is moved sideways onto the lane
  (``sim/road_keeping.py``). The steps are in ``sim/motion.py``, the replans in
  ``sim/replan.py``.
- **Every step records** ego collisions (oriented boxes), off-road, the ego's signed
  longitudinal acceleration and hard braking, the smallest constant-velocity TTC, and the
  adversary's distance (``sim/step_info.py``); :meth:`ClosedLoop.scene` returns the
  simulated :class:`Scene` for :mod:`counterscene_env.metrics`.

Randomness: each episode has its own ``torch.Generator`` and ``numpy`` Generator, both seeded
from its seed at :meth:`ClosedLoop.reset`, so an episode does not depend on which other
episodes share its batch; same seed and actions give the same episode on CPU.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.adversary.guidance import guidance_preset
from counterscene_env.adversary.selection import Selection
from counterscene_env.config import check_seed
from counterscene_env.scene.core import Scene
from counterscene_env.sim import road_keeping
from counterscene_env.sim.adversaries import select_on_log
from counterscene_env.sim.config import SimConfig
from counterscene_env.sim.memory import check_replan_memory
from counterscene_env.sim.motion import advance
from counterscene_env.sim.replan import Replanner
from counterscene_env.sim.state import Episode, WorldState
from counterscene_env.sim.step_info import ego_step_info
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.window import lane_segments


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
        config = config or SimConfig()
        config.check_model(model.config.num_train_timesteps)  # before anything changes
        self.model = model.eval()
        self.config = config
        preset = guidance_preset(self.config.guidance)
        self.guidance = dataclasses.replace(
            preset,
            progress=self.config.guidance_progress,
            final_step_size=preset.final_step_size if self.config.final_step_guidance else 0.0,
        )
        self.replanner = Replanner(self.model, self.config, self.guidance)
        #: The episodes of the current batch (public records, read-only outside ``sim/``).
        self.episodes: list[Episode] = []

    # ------------------------------------------------------------------ episode control
    def reset(
        self,
        scenes: Sequence[Scene],
        seeds: Sequence[int],
        egos: Sequence[Sequence[int]] | None = None,
        selection_seeds: Sequence[int | None] | None = None,
    ) -> list[dict]:
        """Start one episode per scene.

        Args:
            scenes: the factual scenes.
            seeds: one seed per episode (its torch and numpy generators), an int in
                [0, ``config.MAX_SEED``].
            egos: per scene, the agent rows driven by external policies (default: the
                scene's ego alone). Every episode of a batch has the same number of egos; the
                first one becomes the scene's ego (the frame of its model window).
            selection_seeds: per episode, the seed of a ``random`` selector's choice, or
                None (the default): the episode's own numpy generator chooses. Candidate
                rollouts of one episode share it (``stress/rollouts.py``).

        Returns:
            Each episode's first ego's info dict at step ``now`` (:meth:`infos` has all).
        """
        if len(scenes) != len(seeds):
            raise ValueError(f"{len(scenes)} scenes but {len(seeds)} seeds")
        if not scenes:
            raise ValueError("reset needs at least one scene")
        if egos is None:
            egos = [[s.ego_index] for s in scenes]
        if selection_seeds is None:
            selection_seeds = [None] * len(scenes)
        if len(selection_seeds) != len(scenes):
            raise ValueError(f"{len(scenes)} scenes but {len(selection_seeds)} selection seeds")
        if len(egos) != len(scenes) or len({len(e) for e in egos}) != 1:
            raise ValueError("egos needs one list per scene, all of the same length")
        for b, (seed, chooser) in enumerate(zip(seeds, selection_seeds, strict=True)):
            check_seed(f"seeds[{b}]", seed)
            if chooser is not None:
                check_seed(f"selection_seeds[{b}]", chooser)
        c = self.config
        windows = len(scenes) * max(c.max_windows, len(egos[0]))
        check_replan_memory(self.model.config, c.num_samples, windows, c.memory_limit_gb)
        self.episodes = [
            self._start(s, int(seed), [int(r) for r in rows], chooser)
            for s, seed, rows, chooser in zip(scenes, seeds, egos, selection_seeds, strict=True)
        ]
        for ep in self.episodes:
            ep.records.append([ego_step_info(ep, k, replanned=False) for k in range(len(ep.egos))])
        return [ep.records[-1][0] for ep in self.episodes]

    def start(
        self,
        b: int,
        scene: Scene,
        seed: int,
        egos: Sequence[int] | None = None,
        selection_seed: int | None = None,
    ) -> dict:
        """Start a fresh episode in slot ``b`` while the others go on (a vector env's
        autoreset); ``b == len(episodes)`` adds a slot. Same arguments as :meth:`reset` for one
        episode; it must have as many egos as the others.

        Returns:
            The new episode's first ego's info dict at step ``now``.
        """
        if not 0 <= b <= len(self.episodes):
            raise ValueError(f"slot {b} out of range: the loop has {len(self.episodes)} episodes")
        egos = [scene.ego_index] if egos is None else [int(r) for r in egos]
        others = [ep for k, ep in enumerate(self.episodes) if k != b]
        if others and len(egos) != len(others[0].egos):
            raise ValueError(f"{len(egos)} egos, but the other episodes have {len(others[0].egos)}")
        check_seed("seed", seed)
        if selection_seed is not None:
            check_seed("selection_seed", selection_seed)
        c = self.config
        windows = (len(others) + 1) * max(c.max_windows, len(egos))
        check_replan_memory(self.model.config, c.num_samples, windows, c.memory_limit_gb)
        ep = self._start(scene, int(seed), egos, selection_seed)
        ep.records.append([ego_step_info(ep, k, replanned=False) for k in range(len(ep.egos))])
        if b == len(self.episodes):
            self.episodes.append(ep)
        else:
            self.episodes[b] = ep
        return ep.records[-1][0]

    @property
    def num_egos(self) -> int:
        """Egos per episode."""
        return len(self.episodes[0].egos) if self.episodes else 1

    def _start(
        self, scene: Scene, seed: int, egos: list[int], selection_seed: int | None = None
    ) -> Episode:
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
        # A selection seed that is the episode's own leaves the episode exactly as without
        # one (candidate 0 of candidate rollouts is the plain run).
        own = selection_seed is None or int(selection_seed) == seed
        chooser = rng if own else np.random.default_rng(int(selection_seed))
        c = self.replanner.window_config
        ep = Episode(
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
            pieces=road_keeping.lane_pieces(segments.points, segments.widths),
            generator=torch.Generator().manual_seed(seed),
            rng=rng,
            selection_rng=chooser,
            selections=[Selection(self.config.selector, None, "not selected yet", 0)] * len(egos),
            plan_positions=np.zeros((N, F, 2)),
            plan_yaws=np.zeros((N, F)),
            plan_speeds=np.zeros((N, F)),
            plan_start=np.zeros(N, np.int64),
            plan_tokens=np.zeros((N, self.model.config.action_tokens, 2), np.float32),
            tokens_start=np.full(N, -1, np.int64),
            planned=np.zeros(N, bool),
            progress=np.full(N, np.nan),
        )
        # The adversary is selected (and kept in the model's window) with guidance off too, so
        # an unguided run reports the same agent's collisions and clearance as a guided one.
        if self.config.selection_source == "log":
            select_on_log(ep, self.config)
        return ep

    @property
    def done(self) -> np.ndarray:
        """``[B]`` bool: episodes that reached their last step."""
        return np.array([ep.done for ep in self.episodes], bool)

    def state(self, b: int) -> WorldState:
        """What episode ``b`` looks like at its current step."""
        return self.episodes[b].state()

    def step(
        self,
        actions: np.ndarray | None = None,
        ego_states: np.ndarray | None = None,
        only: Sequence[bool] | np.ndarray | None = None,
    ) -> list[dict]:
        """Advance every unfinished episode by one step (those of ``only``, if given).

        Args:
            actions: ``[B, 2]`` ego actions, (acceleration m/s^2, steering rad), through the
                highway-env bicycle model; ``[B, E, 2]`` with E egos per episode.
            ego_states: ``[B, 4]`` (x m, y m, yaw rad, speed m/s) written as the ego's next
                state instead (log replay, or an ego stepped by the caller); ``[B, E, 4]``
                with E egos. A row of NaN uses ``actions`` for that ego.
            only: ``[B]`` bool: the episodes to advance (a vector env whose other episodes
                have ended their policy step); their rows alone need actions or states.

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
        if only is None:
            only = np.ones(B, bool)
        only = np.asarray(only, bool)
        if only.shape != (B,):
            raise ValueError(f"only must have shape ({B},), got {only.shape}")
        active = [b for b, ep in enumerate(self.episodes) if only[b] and not ep.done]
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
            self.replanner([self.episodes[b] for b in due])
        for b in active:
            ep = self.episodes[b]
            ep_actions = None if actions is None else actions[b]
            advance(ep, ep_actions, states[b], self.config, self.guidance.enabled)
            ep.records.append([ego_step_info(ep, k, replanned=b in due) for k in range(E)])
        return [ep.records[-1][0] for ep in self.episodes]

    def infos(self, b: int) -> list[dict]:
        """Episode ``b``'s latest info dict of every ego (in ``egos`` order)."""
        return list(self.episodes[b].records[-1])

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
        :class:`MotionSource`)."""
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
