"""The denoiser's building blocks: its context record (everything but the noisy actions,
encoded once per sampling call), multi-head attention with an additive bias, and one block of
temporal, social, map and agent-centric map attention. ``denoiser.py`` assembles them
(docs/design.md, "Denoiser and Causal Interaction Graph").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from counterscene_env.world_model.config import ModelConfig

NEG = -1e9  # additive mask value: large but finite, so no softmax ever sees a row of -inf


@dataclass
class Context:
    """What the denoiser needs besides the noisy actions; computed once per sampling call.

    Attributes:
        history: ``[B, K, Hh, d]`` embedded history tokens (before the step embedding).
        agent: ``[B, K, d]`` agent embeddings.
        temporal_bias: ``[B, K, 1, 1, L]`` additive key mask of the temporal attention.
        social_bias: ``[B, 1, heads, K, K]`` CIG log-gate plus the padding mask.
        map_tokens: ``[B, M + 1, d]`` lane tokens and the "no map" token.
        map_bias: ``[B, 1, 1, M + 1]`` additive key mask of the map attention.
        local_tokens: ``[B, K, Ml + 1, d]`` each agent's agent-centric lane tokens and the "no
            map" token (None without ``local_lanes``).
        local_bias: ``[B, K, 1, 1, Ml + 1]`` additive key mask of the agent-centric map.
        memory: every block's map keys and values (``Denoiser.remember``), or None to project
            them in each forward pass; ``cut_agents`` and ``repeat`` drop it.
    """

    history: torch.Tensor
    agent: torch.Tensor
    temporal_bias: torch.Tensor
    social_bias: torch.Tensor
    map_tokens: torch.Tensor
    map_bias: torch.Tensor
    local_tokens: torch.Tensor | None = None
    local_bias: torch.Tensor | None = None
    memory: list[MapMemory] | None = None

    def cut_agents(self, k: int) -> Context:
        """The context of the first ``k`` agent slots."""
        local = None if self.local_tokens is None else self.local_tokens[:, :k]
        local_bias = None if self.local_bias is None else self.local_bias[:, :k]
        return Context(
            self.history[:, :k],
            self.agent[:, :k],
            self.temporal_bias[:, :k],
            self.social_bias[..., :k, :k],
            self.map_tokens,
            self.map_bias,
            local,
            local_bias,
        )

    def repeat(self, n: int) -> Context:
        """Each scene ``n`` times in a row (for ``n`` samples in one batched call); the
        memory cache is dropped (``Denoiser.remember`` builds it for the repeated context)."""
        tensors = {k: v for k, v in vars(self).items() if k != "memory"}
        return Context(
            **{k: None if t is None else t.repeat_interleave(n, dim=0) for k, t in tensors.items()}
        )


@dataclass
class MapMemory:
    """One block's keys and values of the map attentions, ``(k, v)`` each ``[B', heads, Lk,
    d / heads]``: the lane tokens do not change between diffusion steps, so a sampling call
    projects them once instead of at every step (docs/performance.md)."""

    map: tuple[torch.Tensor, torch.Tensor]
    local: tuple[torch.Tensor, torch.Tensor] | None


class Attention(nn.Module):
    """Multi-head attention over the last-but-one axis with an additive bias (any batch dims)."""

    def __init__(self, d: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(d, d)
        self.kv = nn.Linear(d, 2 * d)
        self.out = nn.Linear(d, d)
        self.dropout = dropout

    def keys_values(self, memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``memory [..., Lk, d]`` -> keys and values ``[B', heads, Lk, d / heads]`` each
        (the batch dims flattened to ``B'``)."""
        lk, d = memory.shape[-2:]
        h = self.heads
        k, v = self.kv(memory).reshape(-1, lk, 2, h, d // h).permute(2, 0, 3, 1, 4)
        return k, v

    def forward(
        self,
        x: torch.Tensor,
        memory: torch.Tensor,
        bias: torch.Tensor,
        kv: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """``x [..., Lq, d]`` attends to ``memory [..., Lk, d]`` (or to its keys and values
        ``kv``, from ``keys_values``); ``bias`` broadcasts to ``[..., heads, Lq, Lk]``."""
        *batch, lq, d = x.shape
        h = self.heads
        # Flatten the batch dims to one: torch's fused CPU kernels take 4-D inputs only.
        q = self.q(x).reshape(-1, lq, h, d // h).transpose(1, 2)
        k, v = self.keys_values(memory) if kv is None else kv
        if k.shape[0] != q.shape[0]:  # memory shared by several queries' batch entries
            raise ValueError("memory batch dims must match the queries'")
        bias = bias.expand(*batch, *bias.shape[-3:]).reshape(-1, *bias.shape[-3:])
        y = F.scaled_dot_product_attention(
            q, k, v, attn_mask=bias, dropout_p=self.dropout if self.training else 0.0
        )
        return self.out(y.transpose(1, 2).reshape(*batch, lq, d))


class Block(nn.Module):
    """Temporal, social, map and (optionally) agent-centric map attention, then an MLP
    (pre-norm, residual)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        d, h, p = cfg.d_model, cfg.num_heads, cfg.dropout
        self.norms = nn.ModuleList(nn.LayerNorm(d) for _ in range(4))
        self.temporal = Attention(d, h, p)
        self.social = Attention(d, h, p)
        self.map = Attention(d, h, p)
        if cfg.local_lanes:
            self.local_norm = nn.LayerNorm(d)
            self.local = Attention(d, h, p)
            nn.init.zeros_(self.local.out.weight)
            nn.init.zeros_(self.local.out.bias)
        self.mlp = nn.Sequential(
            nn.Linear(d, cfg.mlp_ratio * d),
            nn.GELU(),
            nn.Dropout(p),
            nn.Linear(cfg.mlp_ratio * d, d),
        )

    def start_as_identity(self) -> None:
        """Zero every residual branch's last layer, so the block passes its input through
        unchanged: a block appended to a trained network (``counterscene train --init`` with
        more ``num_blocks``) leaves its predictions exactly as they were."""
        last = [self.temporal.out, self.social.out, self.map.out, self.mlp[-1]]
        if hasattr(self, "local"):
            last.append(self.local.out)
        for layer in last:
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def remember(self, ctx: Context) -> MapMemory:
        """This block's map keys and values for ``ctx`` (``MapMemory``)."""
        local = None
        if ctx.local_tokens is not None:
            local = self.local.keys_values(ctx.local_tokens)
        return MapMemory(self.map.keys_values(ctx.map_tokens), local)

    def forward(
        self,
        x: torch.Tensor,
        ctx: Context,
        memory: MapMemory | None = None,
        social: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``x``: ``[B, K, L, d]``; ``memory``: this block's ``remember(ctx)``, if kept;
        ``social``: the social bias ``[B, L, heads, K, K]`` when it varies by token
        (``plan_features``), else ``ctx.social_bias`` is used."""
        B, K, L, d = x.shape
        y = self.norms[0](x)
        x = x + self.temporal(y, y, ctx.temporal_bias)
        y = self.norms[1](x).transpose(1, 2)  # [B, L, K, d]: attend across agents per position
        bias = ctx.social_bias if social is None else social
        x = x + self.social(y, y, bias).transpose(1, 2)
        y = self.norms[2](x).reshape(B, K * L, d)
        kv = None if memory is None else memory.map
        x = x + self.map(y, ctx.map_tokens, ctx.map_bias, kv).reshape(B, K, L, d)
        if ctx.local_tokens is not None:  # each agent's L tokens attend to its own lanes
            kv = None if memory is None else memory.local
            x = x + self.local(self.local_norm(x), ctx.local_tokens, ctx.local_bias, kv)
        return x + self.mlp(self.norms[3](x))
