"""Which training windows each step of ``counterscene train`` draws.

Both orders are seeded by ``(seed, step)`` or ``(seed, epoch)`` alone, so a resumed run draws
the same batches as an uninterrupted one (docs/world_model.md, "Training").
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import torch


def weighted_batches(
    sources: torch.Tensor, weights: Sequence[float], batch_size: int, seed: int, start_step: int
) -> Iterator[torch.Tensor]:
    """Row indices of each step, drawn with replacement so that source ``j`` (``sources [N]``
    int) fills ``weights[j] / sum(weights)`` of a batch on average; step ``k``'s draw is seeded
    by ``(seed, k)``, so a resumed run sees the same batches."""
    counts = torch.bincount(sources, minlength=len(weights)).double()
    w = torch.tensor(weights, dtype=torch.float64)
    p = (w / counts.clamp(min=1))[sources]  # per window; an empty source gets nothing
    if not p.sum() > 0:
        raise ValueError("data_weights: every dataset with a positive weight has no windows")

    def draws() -> Iterator[torch.Tensor]:
        step = start_step
        while True:
            g = torch.Generator().manual_seed(seed * 100003 + step)
            yield torch.multinomial(p, batch_size, replacement=True, generator=g)
            step += 1

    return draws()


def batches(n: int, batch_size: int, seed: int, start_step: int) -> Iterator[torch.Tensor]:
    """Row indices of each step: epoch ``e`` is a permutation seeded by ``(seed, e)``, so a
    resumed run sees the same batches as an uninterrupted one."""
    per_epoch = max(1, n // batch_size)
    step = start_step
    while True:
        epoch, i = divmod(step, per_epoch)
        perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed * 100003 + epoch))
        yield perm[i * batch_size : (i + 1) * batch_size]
        step += 1
