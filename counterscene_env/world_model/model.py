"""The world model: batched sampling (input features: ``features.py``; the training loss:
``loss.py``; the records it hands out: ``records.py``).

A *batch* is a dict of tensors in the layout of
:class:`counterscene_env.world_model.dataset.SceneWindowDataset` (leading batch axis ``B``): ``history
[B, K, H, 4]`` (x [m], y [m], yaw [rad], speed [m/s] in the ego frame), ``history_valid``,
``extents [B, K, 2]`` m, ``agent_valid``, ``map [B, M, P, 2]`` m, ``map_valid``, ``map_widths``,
and for training ``future [B, K, F, 4]`` and ``future_valid``. Agents are valid when
``agent_valid`` and their current (last history) frame is valid.

The diffused variable is each agent's future actions (acceleration [m/s^2], yaw rate [rad/s]),
one token per ``action_stride`` steps, normalised by the training set's mean and standard
deviation. Trajectories come from :func:`counterscene_env.dynamics.unicycle_rollout` of the
denormalised actions from the agent's current state. The rollout's yaw is the agent's course
(direction of motion, :func:`counterscene_env.dynamics.course_angles`), so predicted
trajectories carry courses in their yaw channel; the body heading is an input only.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from counterscene_env.dynamics import (
    actions_from_states,
    course_angles,
    unicycle_rollout,
)
from counterscene_env.world_model import features, hold
from counterscene_env.world_model.attention import Context
from counterscene_env.world_model.cig import edge_features
from counterscene_env.world_model.config import ModelConfig, check_sampling
from counterscene_env.world_model.denoiser import Denoiser
from counterscene_env.world_model.lane_steering import steer_onto_lanes
from counterscene_env.world_model.records import GuidanceHook, Normalization, Prediction
from counterscene_env.world_model.scheduler import CosineScheduler
from counterscene_env.world_model.window import WindowConfig, check_batch


class WorldModel(nn.Module):
    """Denoiser + cosine scheduler + normalisation (see the module docstring).

    Args:
        config: architecture and sampling defaults.
        normalization: action statistics (from the training set; stored in ``config.json``).
    """

    def __init__(self, config: ModelConfig, normalization: Normalization | None = None) -> None:
        super().__init__()
        self.config = config
        self.normalization = normalization or Normalization()
        self.preset: str | None = None  # set by load_model from config.json
        self.training_info: dict = {}  # provenance from config.json (data, steps, losses)
        self.denoiser = Denoiser(config)
        self.scheduler = CosineScheduler(
            config.num_train_timesteps, config.prediction, config.clip_sample
        )
        n = self.normalization
        self.register_buffer("action_mean", torch.tensor(n.action_mean), persistent=False)
        self.register_buffer("action_std", torch.tensor(n.action_std), persistent=False)

    # ------------------------------------------------------------------ data layout
    def window_config(self, stride: int = 10) -> WindowConfig:
        """The :class:`WindowConfig` that builds batches this model reads
        (``ModelConfig.window``)."""
        return self.config.window(stride)

    @staticmethod
    def agent_mask(batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """``[B, K]``: real agents whose current state is known."""
        return batch["agent_valid"] & batch["history_valid"][..., -1]

    def held_agents(
        self, batch: dict[str, torch.Tensor], beyond: float | None = None
    ) -> torch.Tensor:
        """``[B, K]`` bool: the agents the sampler holds in place, parked more than ``beyond``
        m off every lane (None: ``ModelConfig.hold_parked``; 0: none; ``world_model/hold.py``)."""
        valid = self.agent_mask(batch)
        beyond = self.config.hold_parked if beyond is None else beyond
        if beyond <= 0:
            return torch.zeros_like(valid)
        return hold.parked_off_lanes(batch, self.current_state(batch), valid, beyond)

    def kinematic_states(
        self, batch: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """History ``[B, K, H, 4]`` and (when the batch has one) future ``[B, K, F, 4]`` with the
        yaw channel replaced by the course (the unicycle's state)."""
        hist, hist_ok = batch["history"], batch["history_valid"]
        if "future" in batch:
            states = torch.cat([hist, batch["future"]], dim=-2)
            ok = torch.cat([hist_ok, batch["future_valid"]], dim=-1)
        else:
            states, ok = hist, hist_ok
        course = course_angles(
            states[..., :2], states[..., 2], states[..., 3], ok, dt=self.config.dt
        )
        states = torch.cat([states[..., :2], course[..., None], states[..., 3:]], dim=-1)
        H = hist.shape[-2]
        return states[..., :H, :], (states[..., H:, :] if "future" in batch else None)

    def current_state(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """``[B, K, 4]`` unicycle state at "now" (x, y, course, speed)."""
        # The course at "now" needs only the last two frames (a backward difference).
        last = {
            "history": batch["history"][..., -2:, :],
            "history_valid": batch["history_valid"][..., -2:],
        }
        return self.kinematic_states(last)[0][..., -1, :]

    def normalize(self, actions: torch.Tensor) -> torch.Tensor:
        return (actions - self.action_mean) / self.action_std

    def denormalize(self, actions: torch.Tensor) -> torch.Tensor:
        return actions * self.action_std + self.action_mean

    def rollout(self, normalized: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Trajectory ``[..., F, 4]`` of normalised action tokens ``[..., Ta, 2]`` from the
        current states ``[..., 4]`` (actions held for ``action_stride`` steps)."""
        actions = self.denormalize(normalized).repeat_interleave(self.config.action_stride, -2)
        c = self.config
        return unicycle_rollout(state, actions, c.dt, True, c.yaw_gain, c.lateral_limit)

    def denoise(
        self,
        noisy: torch.Tensor,
        timesteps: torch.Tensor,
        ctx: Context,
        state: torch.Tensor,
        valid: torch.Tensor,
        previous: torch.Tensor | None = None,
        given: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One denoiser forward: output ``[B, K, Ta, 2]`` for noisy normalised action tokens
        ``noisy [B, K, Ta, 2]`` at diffusion steps ``timesteps [B]``, for the agents ``valid
        [B, K]`` at their current states ``state [B, K, 4]``.

        With ``plan_features="noisy"`` the noisy tokens rolled out from there are an input
        too; with ``"self"`` the rollout of ``previous`` ``[B, K, Ta, 2]`` (the last step's
        clean prediction, normalised) is, in the windows ``given [B]`` marks (default: all
        when ``previous`` is passed, none otherwise); the others get zero actions rolled
        out and a flag that says there is no plan."""
        mode = self.config.plan_features
        if mode == "none":
            return self.denoiser(noisy, timesteps, ctx)
        B = noisy.shape[0]
        if mode == "noisy":
            plan, given = noisy, torch.ones(B, dtype=torch.bool, device=noisy.device)
        else:
            if given is None:
                given = torch.full((B,), previous is not None, device=noisy.device)
            plan = self.normalize(torch.zeros(2, device=noisy.device)).expand_as(noisy)
            if previous is not None:
                plan = torch.where(given[:, None, None, None], previous, plan)
        s = self.config.action_stride
        rolled = self.rollout(plan, state)[..., s - 1 :: s, :]  # each token's last step
        return self.denoiser(noisy, timesteps, ctx, rolled, valid, given)

    def target_actions(
        self,
        batch: dict[str, torch.Tensor],
        states: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Ground-truth action tokens ``[B, K, Ta, 2]`` (physical units) and their validity.

        Token j is the mean action between future steps ``j s`` and ``(j + 1) s``
        (``s = action_stride``), from the speed and course differences of the log.
        ``states`` is ``kinematic_states(batch)`` when the caller already has it.
        """
        s = self.config.action_stride
        hist, fut = states if states is not None else self.kinematic_states(batch)
        states = torch.cat([hist[..., -1:, :], fut], dim=-2)
        ok = torch.cat([self.agent_mask(batch)[..., None], batch["future_valid"]], dim=-1)
        states, ok = states[..., ::s, :], ok[..., ::s]
        actions = actions_from_states(states, self.config.dt * s)
        valid = ok[..., 1:] & ok[..., :-1]
        return torch.where(valid[..., None], actions, 0.0), valid

    def context(
        self,
        batch: dict[str, torch.Tensor],
        graph_dropout: float = 0.0,
        generator: torch.Generator | None = None,
    ) -> Context:
        """Encode history, agents, CIG edges and lanes (once per sampling call)."""
        c = self.config
        valid = self.agent_mask(batch)
        course = self.current_state(batch)[..., 2]
        hfeat, hist_ok = features.history_features(batch, valid, c.history_stride, c.history_steps)
        now = batch["history"][..., -1, :]
        afeat = features.agent_features(now, course, batch["extents"], valid)
        velocity = now[..., 3:4] * torch.stack([torch.cos(course), torch.sin(course)], -1)
        edges = edge_features(now[..., :2], velocity, valid, horizon=c.horizon)
        lfeat, lanes_ok, direction, extras = features.lane_features(batch, c.lane_priority)
        local, local_ok = (
            features.local_map(
                batch["map"],
                direction,
                extras,
                lanes_ok,
                now[..., :2],
                course,
                valid,
                c.local_lanes,
                c.local_radius,
            )
            if c.local_lanes
            else (None, None)
        )
        return self.denoiser.encode_context(
            hfeat,
            hist_ok,
            afeat,
            valid,
            edges,
            lfeat,
            lanes_ok,
            graph_dropout,
            generator,
            local,
            local_ok,
            batch.get("recorded") if c.source_flag else None,
        )

    # ------------------------------------------------------------------ sampling
    def sample(
        self,
        batch: dict[str, torch.Tensor],
        num_samples: int = 1,
        generator: torch.Generator | Sequence[torch.Generator] | None = None,
        sampler: str | None = None,
        steps: int | None = None,
        eta: float | None = None,
        guidance: GuidanceHook | None = None,
        map_guidance: float | None = None,
        lane_steering: int | None = None,
        init: torch.Tensor | None = None,
        init_steps: int = 0,
        held: torch.Tensor | None = None,
        any_way: torch.Tensor | None = None,
    ) -> Prediction:
        """Sample every agent's future, ``num_samples`` per scene, in one batched call.

        Args:
            batch: scene windows (module docstring); ``future`` is not needed.
            num_samples: S samples per scene, drawn together as a batch of ``B * S``.
            generator: the only source of randomness (initial noise and every step's noise);
                a sequence of B generators gives each scene its own, so a scene's samples do
                not depend on which other scenes share the batch. None draws from torch's
                global generator (``torch.manual_seed``), as torch's own samplers do.
            sampler: ``"ddim"`` (strided, ``steps`` steps) or ``"ddpm"`` (all K steps); default
                from the config.
            steps: strided sampler steps; default from the config.
            eta: strided sampler noise scale; default from the config.
            guidance: hook that edits the posterior mean at each step (see ``GuidanceHook``);
                it runs after the map guidance.
            map_guidance: step size of the map guidance (``map_guidance.py``); default from the
                config, 0 disables.
            lane_steering: Adam steps of final-step lane keeping on the finished samples
                (``lane_steering.steer_onto_lanes``); default from the config, 0 disables.
            init: ``[B, K, Ta, 2]`` normalised action tokens to start from instead of pure
                noise (a warm start: the previous plan, shifted to "now"). It is noised to the
                level of the sampler's last ``init_steps`` steps, ``x_t = sqrt(abar_t) init +
                sqrt(1 - abar_t) eps``, and only those steps are run (SDEdit, Meng et al.
                2022): the denoiser keeps what the previous plan got right and redraws the
                detail the new history calls for.
            init_steps: steps run from ``init``; ignored without ``init``, and a full sample
                when it is not below the sampler's step count.
            held: ``[B, K]`` bool, the agents to hold in place; default ``held_agents(batch)``
                (``ModelConfig.hold_parked``; a caller that guides an agent passes it with
                that agent cleared). A held agent is taken out of the network's view and its
                plan is ``hold.stop_actions``: it stops over the first token and stays.
            any_way: ``[B, K]`` bool, agents that lane keeping keeps on any lane strip,
                whichever its way (``steer_onto_lanes``); default none: every agent keeps to
                the lanes going its way.
        """
        c = self.config
        sampler = sampler or c.sampler
        check_sampling(sampler, num_samples, steps, eta, map_guidance, lane_steering, init_steps)
        check_batch(batch)
        if sampler == "ddpm":
            steps, eta = c.num_train_timesteps, 1.0
        steps = steps or c.sampling_steps
        eta = c.eta if eta is None else eta
        valid = self.agent_mask(batch)
        B, K = valid.shape
        device = valid.device
        held = (self.held_agents(batch) if held is None else held.to(torch.bool)) & valid
        batch = hold.without(batch, held)
        planned = self.agent_mask(batch)
        with torch.no_grad():
            ctx = self.denoiser.remember(self.context(batch).repeat(num_samples))
        state = self.current_state(batch).repeat_interleave(num_samples, 0)
        planned_rows = planned.repeat_interleave(num_samples, 0)

        step_size = c.map_guidance if map_guidance is None else map_guidance
        if step_size > 0:
            from counterscene_env.world_model.map_guidance import make_map_guidance

            on_road = make_map_guidance(self, batch, num_samples, step_size)
            hook = on_road if guidance is None else _chain(on_road, guidance)
        else:
            hook = guidance

        self.scheduler.set_timesteps(steps)
        per_scene = isinstance(generator, Sequence)
        if per_scene and len(generator) != B:
            raise ValueError(f"{len(generator)} generators for a batch of {B} scenes")

        # Noise is drawn for the config's K agents whatever the batch's K: a batch whose
        # trailing padding was cut (``window.collate(trim=True)``) draws the same numbers for
        # its real agents as the full batch, and so the same samples.
        gens = generator if per_scene else [generator]
        rows = num_samples if per_scene else B * num_samples
        draw = (rows, max(K, c.num_agents), c.action_tokens, 2)  # [S, K, Ta, 2]

        def randn() -> torch.Tensor:
            return torch.cat([torch.randn(draw, generator=g, device=device)[:, :K] for g in gens])

        # ``previous``: self-conditioning's plan, the last step's clean prediction (a warm
        # start's first step has the plan it started from).
        x, timesteps, previous = self._start(randn(), init, init_steps, num_samples)
        for t in timesteps:
            tt = torch.full((B * num_samples,), t, device=device, dtype=torch.long)
            with torch.no_grad():
                out = self.denoise(x, tt, ctx, state, planned_rows, previous)
            # The last step adds no noise; eta = 0 never does.
            noise = randn() if eta > 0 and t != timesteps[-1] else None
            result = self.scheduler.step(out, t, x, generator, eta, hook, noise)
            x, previous = result.prev_sample.detach(), result.pred_original_sample.detach()
        # Padding agents get zero physical actions: a clean, finite "keep going" plan.
        still = self.normalize(torch.zeros(2, device=device))
        x = torch.where(planned_rows[..., None, None], x, still)
        steer = c.lane_steering if lane_steering is None else lane_steering
        x = self._hold(steer_onto_lanes(self, batch, x, steer, any_way), held, state)
        with torch.no_grad():
            traj = self.rollout(x, state)
            actions = self.denormalize(x).repeat_interleave(c.action_stride, -2)
        S = num_samples
        return Prediction(
            actions=actions.reshape(B, S, *actions.shape[1:]),
            trajectory=traj.reshape(B, S, *traj.shape[1:]),
            normalized=x.reshape(B, S, *x.shape[1:]),
            valid=valid,
        )

    def _hold(self, x: torch.Tensor, held: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Samples ``x [B S, K, Ta, 2]`` with the agents ``held [B, K]`` (at ``state [B S, K,
        4]``) given ``hold.stop_actions``: they stop over the first token and stay."""
        if not bool(held.any()):
            return x
        c = self.config
        rep = held.repeat_interleave(x.shape[0] // held.shape[0], 0)[..., None, None]
        stop = hold.stop_actions(state, c.action_tokens, c.action_stride, c.dt)
        return torch.where(rep, self.normalize(stop), x)

    def _start(
        self, noise: torch.Tensor, init: torch.Tensor | None, init_steps: int, num_samples: int
    ) -> tuple[torch.Tensor, list[int], torch.Tensor | None]:
        """The first sample ``[B S, K, Ta, 2]``, the steps to run and the clean plan it
        starts from: pure ``noise``, every step and none, or ``init`` noised to the level of
        the last ``init_steps``, those steps and ``init`` (``sample``)."""
        timesteps = self.scheduler.timesteps.tolist()
        if init is None:
            return noise, timesteps, None
        B, K = noise.shape[0] // num_samples, noise.shape[1]
        if tuple(init.shape) != (B, K, self.config.action_tokens, 2):
            raise ValueError(
                f"init must be [B, K, Ta, 2] = {[B, K, self.config.action_tokens, 2]} "
                f"normalised action tokens, got {list(init.shape)}"
            )
        if not 0 < init_steps < len(timesteps):
            return noise, timesteps, None
        timesteps = timesteps[-init_steps:]
        level = torch.full((noise.shape[0],), timesteps[0], dtype=torch.long, device=noise.device)
        start = init.to(noise.dtype).repeat_interleave(num_samples, 0)
        return self.scheduler.add_noise(start, noise, level), timesteps, start


def _chain(first: GuidanceHook, second: GuidanceHook) -> GuidanceHook:
    def hook(mean: torch.Tensor, sigma: float, t: int, x0: torch.Tensor) -> torch.Tensor:
        return second(first(mean, sigma, t, x0), sigma, t, x0)

    return hook
