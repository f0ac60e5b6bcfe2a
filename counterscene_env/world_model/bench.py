"""Speed of the world model (``counterscene bench``): the figures behind the CPU
budget (docs/design.md, "CPU budget and default preset").

One *sampling call* is :meth:`WorldModel.sample` on one scene with every agent slot filled
(``num_agents`` agents, ``num_lanes`` lanes), the model's default sampler and steps. FLOPs per
denoiser forward come from :class:`torch.utils.flop_counter.FlopCounterMode` (matmuls and
attention; element-wise work is not counted, so the fraction of peak is a lower bound). The peak
is measured on this machine as the best of a few float32 2048x2048 matmuls.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import torch

from counterscene_env.world_model.model import WorldModel


def synthetic_batch(model: WorldModel, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """One full scene window: every agent and lane valid, cars spread over a few lanes."""
    c = model.config
    K, H, M, P = c.num_agents, c.history_steps, c.num_lanes, c.lane_points
    t = torch.arange(H, dtype=torch.float32) * c.dt - (H - 1) * c.dt
    speed = 8 + 4 * torch.rand(K, generator=generator)
    x0 = torch.linspace(-40, 40, K)
    y0 = (torch.arange(K) % 4).float() * 3.5
    hist = torch.stack(
        [
            x0[:, None] + speed[:, None] * t,
            y0[:, None].expand(K, H),
            torch.zeros(K, H),
            speed[:, None].expand(K, H),
        ],
        -1,
    )
    lanes = torch.stack(
        [
            torch.linspace(-60, 60, P)[None].expand(M, P),
            (torch.arange(M) % 8).float()[:, None].expand(M, P) * 3.5,
        ],
        -1,
    )
    return {
        "history": hist[None],
        "history_valid": torch.ones(1, K, H, dtype=torch.bool),
        "extents": torch.tensor([4.5, 1.9]).expand(1, K, 2).clone(),
        "agent_valid": torch.ones(1, K, dtype=torch.bool),
        "map": lanes[None],
        "map_valid": torch.ones(1, M, dtype=torch.bool),
        "map_widths": torch.full((1, M), 3.5),
        "map_priority": torch.zeros(1, M),
        "recorded": torch.zeros(1),
    }


def matmul_peak_gflops(size: int = 2048, repeats: int = 5) -> float:
    """Best float32 matmul throughput of this machine [GFLOP/s]."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * size**3 / best / 1e9


def bench_model(
    model: WorldModel, runs: int = 50, samples: int = 1, threads: int | None = None
) -> dict[str, Any]:
    """Median latency of ``runs`` sampling calls and FLOPs per denoiser forward."""

    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        return _bench(model, runs, samples)
    finally:
        torch.set_num_threads(previous)


def _bench(model: WorldModel, runs: int, samples: int) -> dict[str, Any]:
    from torch.utils.flop_counter import FlopCounterMode

    model = model.eval()
    g = torch.Generator().manual_seed(0)
    batch = synthetic_batch(model, g)
    c = model.config
    steps = c.num_train_timesteps if c.sampler == "ddpm" else c.sampling_steps

    with torch.no_grad():
        ctx = model.context(batch).repeat(samples)
        x = torch.randn(samples, c.num_agents, c.action_tokens, 2, generator=g)
        t = torch.full((samples,), c.num_train_timesteps - 1)
        state = model.current_state(batch).repeat_interleave(samples, 0)
        valid = model.agent_mask(batch).repeat_interleave(samples, 0)
        counter = FlopCounterMode(display=False)
        with counter:
            model.denoise(x, t, ctx, state, valid)
        flops = counter.get_total_flops()

    model.sample(batch, samples, g)  # warm-up
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        model.sample(batch, samples, g)
        times.append(time.perf_counter() - start)
    times.sort()
    median = statistics.median(times)
    peak = matmul_peak_gflops()
    achieved = flops * steps / median / 1e9
    return {
        "agents": c.num_agents,
        "lanes": c.num_lanes,
        "samples": samples,
        "sampler": c.sampler,
        "sampling_steps": steps,
        "threads": torch.get_num_threads(),
        "runs": runs,
        "latency_median_s": median,
        "latency_p90_s": times[min(len(times) - 1, int(0.9 * len(times)))],
        "flops_per_forward": flops,
        "flops_per_call": flops * steps,
        "achieved_gflops": achieved,
        "peak_gflops": peak,
        "peak_fraction": achieved / peak,
    }
