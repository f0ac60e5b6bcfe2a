"""The SceneTransformer-style denoiser with the Causal Interaction Graph (docs/design.md, "Denoiser and Causal
Interaction Graph").

Tokens: per agent, ``Hh`` history tokens followed by ``Ta`` noisy future-action tokens, one
sequence of ``L = Hh + Ta`` tokens of width ``d``. Every token gets its agent's embedding (current
state and size) and the diffusion-step embedding. Each block then applies, pre-norm and residual:

1. temporal self-attention along each agent's own sequence (bidirectional; optionally causal
   over the future tokens), invalid history frames masked as keys;
2. social attention across agents at each token position, with the CIG bias
   ``log(max(g_ij, 1e-4))``, ``g_ij = sigmoid(MLP(phi(e_ij)))``, added to the logits (per head),
   and padding agents masked as keys (an agent always sees itself, so no row is empty);
3. cross-attention from every agent token to the lane-polyline tokens (plus one learned "no map"
   token, so a scene without lanes is still well defined);
4. with ``local_lanes > 0``, cross-attention from each agent's tokens to its own agent-centric
   map: the lane segments nearest to it, in its own frame (plus a "no map" token). Lane
   following is a function of where the lanes are *relative to the agent*; in the scene frame
   the network has to learn that transformation for every agent, which the small CPU model did
   poorly at turns (off-road predictions, docs/world_model.md). Its output projection starts at
   zero, so a model fine-tuned from a checkpoint without it starts out identical to that one;
5. an MLP.

With ``plan_features`` each future token also gets an embedding of where its agent's plan
takes it (the unicycle rollout of the noisy actions, or of the previous step's prediction,
which the caller passes as ``plan``), and the social attention at each future token adds a
per-head bias learned from the two agents' rolled-out positions (``features.pair_features``).
Both start at zero output, so a model fine-tuned from a checkpoint without them starts out
identical to that one.

The head maps each future token to the network output ``[B, K, Ta, 2]``: clean normalised
actions (x0) or the noise (epsilon).
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import nn

from counterscene_env.world_model import features
from counterscene_env.world_model.attention import NEG, Block, Context
from counterscene_env.world_model.cig import NUM_EDGE_FEATURES
from counterscene_env.world_model.config import ModelConfig

HISTORY_FEATURES = 9  # x, y, dx, dy, cos yaw, sin yaw, speed, valid, age
AGENT_FEATURES = 9  # x, y, cos/sin heading, cos/sin course, speed, length, width
MAP_FEATURES = 5  # x, y, direction x, direction y, width
PLAN_FEATURES = 6  # x, y, cos course, sin course, speed, given (``features.plan_features``)
PAIR_FEATURES = 4  # ahead, aside, distance, contact (``features.pair_features``)


class _AgentPad:
    """Zero-pads an agent axis from ``k`` to ``full`` slots (padding: zeros, False)."""

    def __init__(self, k: int, full: int) -> None:
        self.extra = full - k

    def __call__(self, t: torch.Tensor, dim: int) -> torch.Tensor:
        shape = list(t.shape)
        shape[dim] = self.extra
        return torch.cat([t, t.new_zeros(shape)], dim)


def _mlp(i: int, d: int, o: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(i, d), nn.SiLU(), nn.Linear(d, o))


class Denoiser(nn.Module):
    """The network: ``forward(noisy_actions, timesteps, context) -> [B, K, Ta, 2]``."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.d_model
        self.history_in = _mlp(HISTORY_FEATURES, d, d)
        self.agent_in = _mlp(AGENT_FEATURES, d, d)
        self.action_in = nn.Linear(2, d)
        self.position = nn.Parameter(torch.zeros(cfg.history_tokens + cfg.action_tokens, d))
        nn.init.normal_(self.position, std=0.02)
        self.step_mlp = _mlp(d, d, d)
        self.edge_mlp = nn.Sequential(
            nn.Linear(NUM_EDGE_FEATURES, d),
            nn.SiLU(),
            nn.Linear(d, d),
            nn.SiLU(),
            nn.Linear(d, cfg.num_heads),
        )
        self.point_in = _mlp(MAP_FEATURES, d, d)
        self.lane_out = _mlp(d, d, d)
        self.no_map = nn.Parameter(torch.zeros(1, 1, d))
        if cfg.local_lanes:
            self.local_point_in = _mlp(MAP_FEATURES, d, d)
            self.local_lane_out = _mlp(d, d, d)
            self.local_no_map = nn.Parameter(torch.zeros(1, 1, 1, d))
        if cfg.lane_priority:
            # The right of way enters each point MLP's first layer as an extra input column
            # of its own, zero at the start: the model starts as the one without it.
            self.priority_in = nn.Linear(1, d, bias=False)
            nn.init.zeros_(self.priority_in.weight)
            if cfg.local_lanes:
                self.local_priority_in = nn.Linear(1, d, bias=False)
                nn.init.zeros_(self.local_priority_in.weight)
        if cfg.source_flag:
            # Recorded (1) or generated (0) enters every agent embedding through a column of
            # its own, zero at the start: the model starts as the one without it.
            self.source_in = nn.Linear(1, d, bias=False)
            nn.init.zeros_(self.source_in.weight)
        if cfg.plan_features != "none":
            self.plan_in = _mlp(PLAN_FEATURES, d, d)
            self.pair_mlp = _mlp(PAIR_FEATURES, 32, cfg.num_heads)
            for last in (self.plan_in[-1], self.pair_mlp[-1]):  # start as the model without
                nn.init.zeros_(last.weight)
                nn.init.zeros_(last.bias)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.num_blocks))
        self.norm_out = nn.LayerNorm(d)
        self.head = nn.Linear(d, 2)
        # Start the gate open (sigmoid(3) ~ 0.95): training begins as plain attention and learns
        # which edges to suppress.
        nn.init.zeros_(self.edge_mlp[-1].weight)
        nn.init.constant_(self.edge_mlp[-1].bias, 3.0)

    @staticmethod
    def _points(
        mlp: nn.Sequential, priority_in: nn.Linear | None, feat: torch.Tensor
    ) -> torch.Tensor:
        """A lane point MLP on ``feat [..., 5]`` (or ``[..., 6]``: the right of way last)."""
        if priority_in is None:
            return mlp(feat)
        hidden = mlp[0](feat[..., :MAP_FEATURES]) + priority_in(feat[..., MAP_FEATURES:])
        return mlp[2](mlp[1](hidden))

    def step_embedding(self, timesteps: torch.Tensor) -> torch.Tensor:
        """Sinusoidal embedding of the diffusion step ``[B]`` -> ``[B, d]``.

        Each distinct step is embedded once: a sampler's call has one step for all its
        scenes, so the MLP sees one row whatever the batch size. (A matrix product's rounding
        can depend on its row count when that is small, and a scene's result must not depend
        on which other scenes share its call: the vector env, docs/performance.md.)"""
        half = self.cfg.d_model // 2
        steps, index = torch.unique(timesteps, return_inverse=True)
        freq = torch.exp(-math.log(10000.0) * torch.arange(half, device=timesteps.device) / half)
        arg = steps.float()[:, None] * freq[None]
        return self.step_mlp(torch.cat([torch.sin(arg), torch.cos(arg)], -1))[index]

    def encode_context(
        self,
        history: torch.Tensor,
        history_valid: torch.Tensor,
        agent: torch.Tensor,
        agent_valid: torch.Tensor,
        edges: torch.Tensor,
        lanes: torch.Tensor,
        lanes_valid: torch.Tensor,
        graph_dropout: float = 0.0,
        generator: torch.Generator | None = None,
        local_lanes: torch.Tensor | None = None,
        local_valid: torch.Tensor | None = None,
        recorded: torch.Tensor | None = None,
    ) -> Context:
        """Embed everything that does not depend on the diffusion step.

        Args:
            history: ``[B, K, Hh, 9]`` history token features.
            history_valid: ``[B, K, Hh]`` bool.
            agent: ``[B, K, 9]`` agent features.
            agent_valid: ``[B, K]`` bool (real agent with a valid current state).
            edges: ``[B, K, K, 6]`` CIG edge features.
            lanes: ``[B, M, P, 5]`` lane point features (``[..., 6]`` with ``lane_priority``).
            lanes_valid: ``[B, M]`` bool.
            graph_dropout: probability of dropping each edge's bias (training only).
            generator: randomness of the graph dropout.
            local_lanes: ``[B, K, Ml, P, 5 or 6]`` each agent's nearest lane segments in its own
                frame (required when ``local_lanes > 0``).
            local_valid: ``[B, K, Ml]`` bool.
            recorded: ``[B]`` 1 for a recording of real driving, 0 for generated traffic
                (required with ``source_flag``).
        """
        cfg = self.cfg
        K = history.shape[1]
        if K < cfg.num_agents:  # a trimmed batch (``window.collate(trim=True)``)
            # Embed on the config's K slots, as the untrimmed batch would, and cut back: a
            # matrix product's rounding on the CPU depends on its row count,
            # and these products have B K (or B K K) rows, so a scene's context would
            # otherwise depend on how many scenes share its call (docs/performance.md).
            pad = _AgentPad(K, cfg.num_agents)
            ctx = self.encode_context(
                pad(history, 1),
                pad(history_valid, 1),
                pad(agent, 1),
                pad(agent_valid, 1),
                pad(pad(edges, 1), 2),
                lanes,
                lanes_valid,
                graph_dropout,
                generator,
                None if local_lanes is None else pad(local_lanes, 1),
                None if local_valid is None else pad(local_valid, 1),
                recorded,
            )
            return ctx.cut_agents(K)
        B, K, Hh, _ = history.shape
        hist = self.history_in(history)
        agent_emb = self.agent_in(agent)
        if cfg.source_flag:
            if recorded is None:
                raise ValueError("this model needs the windows' recorded flag")
            agent_emb = agent_emb + self.source_in(recorded.to(agent.dtype)[:, None])[:, None]

        key_ok = torch.cat([history_valid, history_valid.new_ones(B, K, cfg.action_tokens)], dim=-1)
        temporal = torch.where(key_ok, 0.0, NEG)[:, :, None, None, :]  # [B, K, 1, 1, L]
        if cfg.causal_temporal:
            L = Hh + cfg.action_tokens
            later = torch.ones(L, L, dtype=torch.bool, device=history.device).triu(1)
            later[:, :Hh] = False  # history is always visible; only future keys are causal
            temporal = temporal + torch.where(later, NEG, 0.0)

        # CIG gate (docs/design.md, "Denoiser and Causal Interaction Graph"): bias = log(max(sigmoid(MLP(phi(e_ij))), 1e-4)), per head.
        gate = torch.sigmoid(self.edge_mlp(edges))  # [B, K, K, heads]
        bias = torch.log(gate.clamp(min=1e-4))
        if graph_dropout > 0:
            drop = torch.rand(bias.shape[:-1], generator=generator, device=bias.device)
            bias = torch.where((drop < graph_dropout)[..., None], 0.0, bias)
        eye = torch.eye(K, dtype=torch.bool, device=history.device)
        key_agent = agent_valid[:, None, :] | eye  # query i may attend key j
        bias = bias + torch.where(key_agent, 0.0, NEG)[..., None]
        social = bias.permute(0, 3, 1, 2)[:, None]  # [B, 1, heads, K, K]

        # point-net: each lane point through an MLP, max-pooled over the points
        priority_in = self.priority_in if cfg.lane_priority else None
        points = self._points(self.point_in, priority_in, lanes).amax(dim=-2)
        tokens = torch.cat([self.lane_out(points), self.no_map.expand(B, 1, -1)], dim=1)
        map_ok = torch.cat([lanes_valid, lanes_valid.new_ones(B, 1)], dim=1)
        map_bias = torch.where(map_ok, 0.0, NEG)[:, None, None, :]
        if not cfg.local_lanes:
            return Context(hist, agent_emb, temporal, social, tokens, map_bias)
        if local_lanes is None or local_valid is None:
            raise ValueError("this model needs local_lanes and local_valid")
        local_priority_in = self.local_priority_in if cfg.lane_priority else None
        local = self._points(self.local_point_in, local_priority_in, local_lanes).amax(dim=-2)
        local = self.local_lane_out(local)
        local = torch.cat([local, self.local_no_map.expand(B, K, 1, -1)], dim=2)
        local_ok = torch.cat([local_valid, local_valid.new_ones(B, K, 1)], dim=2)
        local_bias = torch.where(local_ok, 0.0, NEG)[:, :, None, None, :]
        return Context(hist, agent_emb, temporal, social, tokens, map_bias, local, local_bias)

    def remember(self, ctx: Context) -> Context:
        """``ctx`` with every block's map keys and values (``MapMemory``) computed once, for
        a sampling call that runs the network several times on the same context. The result
        is the same, bit for bit: the same products of the same tensors, made once."""
        return dataclasses.replace(ctx, memory=[block.remember(ctx) for block in self.blocks])

    def forward(
        self,
        noisy_actions: torch.Tensor,
        timesteps: torch.Tensor,
        ctx: Context,
        plan: torch.Tensor | None = None,
        valid: torch.Tensor | None = None,
        given: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Network output ``[B, K, Ta, 2]`` for noisy normalised actions ``[B, K, Ta, 2]`` at
        diffusion steps ``timesteps [B]``.

        With ``plan_features``, ``plan`` is ``[B, K, Ta, 4]``, a plan rolled out to each
        token's last step (x [m], y [m], course [rad], speed [m/s]), ``valid`` ``[B, K]`` the
        agents planned and ``given`` ``[B]`` whether the plan is a real one
        (``WorldModel.denoise`` passes them)."""
        step = self.step_embedding(timesteps)[:, None, None, :]
        actions = self.action_in(noisy_actions)
        Hh = ctx.history.shape[2]
        social = None
        if self.cfg.plan_features != "none":
            if plan is None or valid is None or given is None:
                raise ValueError("this model needs the rolled-out plan and its validity")
            actions = actions + self.plan_in(features.plan_features(plan, valid, given))
            pair = self.pair_mlp(features.pair_features(plan, valid))  # [B, Ta, K, K, heads]
            pair = pair.permute(0, 1, 4, 2, 3)
            # History tokens keep the CIG bias alone: their positions are known, not planned.
            pair = torch.cat([pair.new_zeros(pair.shape[0], Hh, *pair.shape[2:]), pair], 1)
            social = ctx.social_bias + pair  # [B, L, heads, K, K]
        x = torch.cat([ctx.history, actions], dim=2)
        x = x + self.position + ctx.agent[:, :, None, :] + step
        memory = ctx.memory or [None] * len(self.blocks)
        for block, kept in zip(self.blocks, memory, strict=True):
            x = block(x, ctx, kept, social)
        return self.head(self.norm_out(x[:, :, Hh:]))
