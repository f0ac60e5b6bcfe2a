"""Replanning: model windows, one batched world-model call and the choice among samples
(paper, Algorithm 1; docs/design.md, "Data flow"). With ``selection_source="model"`` a
replan first re-selects every ego's adversary (``sim/adversaries.py``).

At a replan every due episode contributes its windows (each ego's own window first, where its
adversary is guided), all windows of all episodes go to the world model in one call, and per
window the sample with the lowest guidance loss plus realism cost is kept. The chosen sample's
rows become the agents' plans (world frame); agents the model planned before but no longer
sees are handed to the IDM lane follower (``sim/traffic.py``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from counterscene_env.adversary.guidance import (
    GuidanceConfig,
    make_guidance_hook,
    make_targets,
    sample_losses,
)
from counterscene_env.geometry import from_frame, wrap_angle
from counterscene_env.scene.core import Scene
from counterscene_env.sim.adversaries import reselect_on_model
from counterscene_env.sim.config import SimConfig
from counterscene_env.sim.realism import plan_cost
from counterscene_env.sim.state import Episode, ModelWindow
from counterscene_env.sim.traffic import IDMLaneFollower
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import GuidanceHook, Prediction
from counterscene_env.world_model.window import agent_count, collate, make_window


class Replanner:
    """Re-plans episodes with one world-model call per replan (re-selecting their
    adversaries first with ``selection_source="model"``).

    Args:
        model: the world model (in eval mode).
        config: closed-loop settings.
        guidance: the guidance preset's settings (``adversary.guidance.guidance_preset``).
    """

    def __init__(self, model: WorldModel, config: SimConfig, guidance: GuidanceConfig) -> None:
        self.model = model
        self.config = config
        self.guidance = guidance
        self.window_config = model.window_config()
        self.sample_kwargs = dict(
            sampler=config.sampler,
            steps=config.sampling_steps,
            eta=config.eta,
            map_guidance=config.map_guidance,
            lane_steering=config.lane_steering,
        )
        # Steps of each plan whose overlaps the realism cost counts (None: the whole plan).
        horizon = config.realism_horizon
        self.cost_steps = None if horizon is None else max(1, round(horizon / model.config.dt))
        # Normalised tokens of zero acceleration and yaw rate: the warm start of an agent
        # with no previous prediction (it keeps its speed and course).
        self.still = model.normalize(torch.zeros(2)).numpy()

    # ------------------------------------------------------------------ windows
    def windows(self, ep: Episode, sim: Scene) -> list[ModelWindow]:
        """The model windows of one episode at its current step.

        The first E are centred on the E egos, each with its adversary forced in; an agent
        seen by several is planned by the first (its adversary's by its own, where it is
        guided). Agents farther than ``cover_radius`` from every window centre get windows of
        their own, centred on the uncovered agent nearest the ego, up to ``max_windows``: the
        model sees the lanes and neighbours around each agent it plans, not only around the
        ego. The default is one window (``max_windows=1``): extra windows centred on other agents
        cost a model call each and were not measured to help with the shipped model. Agents
        left uncovered continue as IDM lane followers.
        """
        c, t, wc = self.config, ep.t, self.window_config
        e = sim.ego_index
        pos = sim.positions[:, t]
        movable = sim.valid[:, t] & (sim.agent_types == "vehicle")
        movable[ep.egos] = False
        adversaries = [a for a in ep.adversaries if a is not None]
        windows: list[ModelWindow] = []
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
            windows.append(ModelWindow(item, own + mine, ego=len(windows)))
            claimed[mine] = True
            near = np.linalg.norm(pos[rows] - pos[ego], axis=-1) <= c.cover_radius
            covered[rows[near]] = True
        covered[adversaries] = True  # guided in their ego's window, wherever they are
        while len(windows) < max(c.max_windows, len(ep.egos)):
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
            windows.append(ModelWindow(item, [int(r) for r in mine], ego=-1))
            covered[mine] = True
            covered[centre] = True
        return windows

    # ------------------------------------------------------------------ the replan
    def __call__(self, eps: Sequence[Episode]) -> None:
        """Re-plan every agent of the episodes ``eps`` from their simulated histories."""
        started = time.perf_counter()
        sims = [simulated_scene(ep) for ep in eps]
        if self.config.selection_source == "model":
            c = self.config
            reselect_on_model(self.model, c, self.window_config, self.sample_kwargs, eps, sims)
        # Every window of every episode in one batched call; each ego's own window first.
        owner: list[int] = []
        windows: list[ModelWindow] = []
        for i, (sim, ep) in enumerate(zip(sims, eps, strict=True)):
            for window in self.windows(ep, sim):
                owner.append(i)
                windows.append(window)
        # A warm start reads the previous prediction: episodes at their first replan sample
        # from pure noise, in a call of their own, unless ``warm_first_replan`` starts them
        # from "keep speed and course". Windows are also grouped by the agent slots they
        # fill, and each call's agent axis is cut to that (``collate(trim=True)``): padding
        # costs as much as a real agent, and a matrix product's rounding depends on the
        # sizes, so an episode's result never depends on which others share its call.
        c = self.config
        warm = [
            c.warm_start_steps > 0 and (eps[o].replans > 0 or c.warm_first_replan) for o in owner
        ]
        keys = [(w, agent_count(window.arrays)) for w, window in zip(warm, windows, strict=True)]
        chosen: dict[int, tuple] = {}
        for key in sorted(set(keys)):
            js = [j for j, k in enumerate(keys) if k == key]
            plans = self._plan([eps[owner[j]] for j in js], [windows[j] for j in js], key[0])
            chosen.update(zip(js, plans, strict=True))
        # Applied after every call and in window order: a warm start reads the plans from
        # before this replan, and where windows overlap the later window's tokens win, as
        # in one call for all windows.
        for j, window in enumerate(windows):
            _apply_plan(eps[owner[j]], window, *chosen[j])
        planned_now: dict[int, set[int]] = {}
        for o, window in zip(owner, windows, strict=True):
            planned_now.setdefault(o, set()).update(window.plan_rows)
        for i, ep in enumerate(eps):
            _hand_over(ep, planned_now.get(i, set()))
        for ep in eps:
            ep.replans += 1
            ep.replan_seconds += (time.perf_counter() - started) / len(eps)

    def _plan(
        self, eps: list[Episode], windows: list[ModelWindow], warm: bool
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Sample windows ``windows`` (of episodes ``eps``, one per window) in one call;
        ``warm``: start from the previous predictions. Returns each window's chosen sample
        ``[K, F, 4]``, its normalised tokens ``[K, Ta, 2]`` and the model's ``valid [K]``."""
        owner = list(range(len(eps)))
        init = None
        if warm:
            init = np.stack([self.warm_start(ep, w) for ep, w in zip(eps, windows, strict=True)])
        pred, best = self._sample(eps, owner, windows, init)
        traj, tokens = pred.trajectory.numpy(), pred.normalized.numpy()
        return [(traj[j, best[j]], tokens[j, best[j]], pred.valid[j]) for j in range(len(windows))]

    def warm_start(self, ep: Episode, window: ModelWindow) -> np.ndarray:
        """``[K, Ta, 2]`` normalised tokens to start window ``window``'s sampling from: each
        agent's last prediction shifted by the steps since it began (its last action held
        for the steps it did not cover), or ``still`` for an agent with none."""
        rows = window.rows
        s = self.model.config.action_stride
        known = rows >= 0
        r = np.where(known, rows, 0)
        begun = ep.tokens_start[r]
        tokens = ep.plan_tokens[r]  # [K, Ta, 2]
        K, Ta = tokens.shape[:2]
        F = Ta * s
        shift = ep.t + 1 - begun
        known &= (begun >= 0) & (shift < F)
        steps = np.repeat(tokens, s, axis=1)  # [K, F, 2] the per-step actions
        idx = np.minimum(shift[:, None] + np.arange(F), F - 1)
        shifted = np.take_along_axis(steps, idx[..., None], 1).reshape(K, Ta, s, 2).mean(2)
        return np.where(known[:, None, None], shifted, self.still).astype(np.float32)

    def _sample(
        self,
        eps: Sequence[Episode],
        owner: list[int],
        windows: list[ModelWindow],
        init: np.ndarray | None = None,
    ) -> tuple[Prediction, np.ndarray]:
        """One guided sampling call for every window (warm-started from ``init [W, K, Ta,
        2]`` when given); returns the model's prediction and the ``[W]`` index of the sample
        kept per window."""
        c, g = self.config, self.guidance
        batch = collate([w.arrays for w in windows], trim=True)
        conflicts = [
            eps[o].selections[w.ego].conflict if w.ego >= 0 else None
            for w, o in zip(windows, owner, strict=True)
        ]
        adv_rows = [
            -1 if conflict is None else w.row_of(conflict.agent)
            for w, conflict in zip(windows, conflicts, strict=True)
        ]
        S = c.num_samples
        targets = make_targets(
            conflicts,
            adv_rows,
            np.stack([w.origin for w in windows]),
            [eps[o].t for o in owner],
            [(eps[o].t - eps[o].start) / (eps[o].end - eps[o].start) for o in owner],
            g,
        )
        hook = make_guidance_hook(self.model, batch, targets, S, g) if g.enabled else None
        gens = [eps[o].generator for o in owner]
        warm = {}
        if init is not None:  # cut to the batch's trimmed agent axis
            init = torch.from_numpy(np.ascontiguousarray(init[:, : batch["agent_valid"].shape[1]]))
            warm = dict(init=init, init_steps=c.warm_start_steps)
        # Parked cars off the street are held in place (``SimConfig.hold_parked``, else the
        # model's own ``ModelConfig.hold_parked``), but
        # never the selected adversary (a car that pulls out of a driveway in the log may be
        # one), guided or not, so that a guided and an unguided row plan the same agents.
        hold = self.model.held_agents(batch, c.hold_parked)
        # The guided adversary keeps to any lane strip, whichever its way: its counterfactual
        # crosses into the ego's lane, and lane keeping must not undo the guidance
        # (docs/world_model_experiments.md, "Wrong-way driving").
        any_way = torch.zeros_like(hold)
        for j, adv in enumerate(adv_rows):
            if adv >= 0:
                hold[j, adv] = False
                any_way[j, adv] = g.enabled
        pred = self.model.sample(
            batch, S, gens, guidance=hook, **self.sample_kwargs, **warm, held=hold, any_way=any_way
        )
        ego_rows = [
            [r for r in (w.row_of(e) for e in eps[o].egos) if r >= 0]
            for w, o in zip(windows, owner, strict=True)
        ]
        best = np.zeros(len(windows), np.int64)
        if S > 1:
            best = self.choose(batch, pred, hook, adv_rows, ego_rows).numpy()
        return pred, best

    def choose(
        self,
        batch: dict[str, torch.Tensor],
        pred: Prediction,
        hook: GuidanceHook | None,
        adv_rows: list[int],
        ego_rows: list[list[int]],
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
            traj = self._egos_held(batch, pred, ego_rows)
            lanes = tuple(rep(batch[k]) for k in ("map", "map_valid", "map_widths"))
            cost += w * plan_cost(
                traj, rep(pred.valid), rep(batch["extents"]), lanes, rep(exclude), self.cost_steps
            ).reshape(W, S)
        return cost.argmin(-1)

    def _egos_held(
        self, batch: dict[str, torch.Tensor], pred: Prediction, ego_rows: list[list[int]]
    ) -> torch.Tensor:
        """``[W S, K, F, 4]`` the samples with each ego held at its current speed and course.

        The ego's future is its policy's, not the model's guess: agents are scored against
        the ego held at its current speed and course (a braking or stopped ego must not be
        run into because the model expected it to drive on)."""
        W, S = pred.trajectory.shape[:2]
        traj = pred.trajectory.reshape(W * S, *pred.trajectory.shape[2:]).clone()
        state = self.model.current_state(batch).repeat_interleave(S, 0)  # [W S, K, 4]
        steps = torch.arange(1, traj.shape[-2] + 1, dtype=traj.dtype) * self.model.config.dt
        for j, egos in enumerate(ego_rows):
            for ego in egos:
                x, y, course, v = state[j * S, ego].unbind(-1)
                path = torch.stack(
                    [x + v * steps * torch.cos(course), y + v * steps * torch.sin(course)], -1
                )
                traj[j * S : (j + 1) * S, ego, :, :2] = path
                traj[j * S : (j + 1) * S, ego, :, 2] = course
        return traj


def simulated_scene(ep: Episode) -> Scene:
    """The simulated scene of an episode up to its step ``t`` (later frames invalid)."""
    valid = ep.valid.copy()
    valid[:, ep.t + 1 :] = False
    return ep.factual.replace(positions=ep.positions, yaws=ep.yaws, speeds=ep.speeds, valid=valid)


def _apply_plan(
    ep: Episode, window: ModelWindow, chosen: np.ndarray, tokens: np.ndarray, valid
) -> None:
    """Write the chosen sample ``[K, F, 4]`` (window frame) as the plans of the window's
    ``plan_rows`` that the model could plan (``valid [K]``), and its normalised action
    tokens ``[K, Ta, 2]`` as every predicted agent's warm start. ``K`` may be below the
    window's slot count (``collate(trim=True)`` cuts its trailing padding slots)."""
    window_rows = window.rows[: len(valid)]
    seen = (window_rows >= 0) & np.asarray(valid)
    ep.plan_tokens[window_rows[seen]] = tokens[seen]
    ep.tokens_start[window_rows[seen]] = ep.t + 1
    lookup = {int(r): k for k, r in enumerate(window_rows) if r >= 0}
    rows = np.array([r for r in window.plan_rows if valid[lookup[r]]], dtype=np.int64)
    if not rows.size:
        return
    plan = chosen[np.array([lookup[r] for r in rows])]  # [A, F, 4] window frame
    ep.plan_positions[rows] = from_frame(plan[..., :2], window.origin)
    ep.plan_yaws[rows] = wrap_angle(plan[..., 2] + window.origin[2])
    ep.plan_speeds[rows] = plan[..., 3]
    ep.plan_start[rows] = ep.t + 1
    ep.planned[rows] = True
    ep.progress[rows] = 0.0


def _hand_over(ep: Episode, planned_now: set[int]) -> None:
    """Agents the model planned before but no longer sees (they left its window) continue as
    highway-env IDM lane followers rather than on a stale open-loop plan; an agent back in
    view is the model's again."""
    for r in list(ep.background):
        if r in planned_now:
            del ep.background[r]
    for r in np.flatnonzero(ep.planned & ep.valid[:, ep.t]):
        r = int(r)
        if r not in planned_now and r not in ep.background and r not in ep.egos:
            idm = IDMLaneFollower()
            idm.reset(ep.factual, int(ep.rng.integers(2**31)), agent=r, t=ep.t)
            ep.background[r] = idm
