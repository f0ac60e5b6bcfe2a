"""Torch's thread count while a scene is recorded in the background (``scene/prefetch.py``).

Replans run torch's intra-op threads, two on a 2-core machine; a recording ahead holds a core
for a fifth of a second. Both at once, each thread waits for the other at every small
operation: measured on 2 cores, 41 env steps/s with two torch threads and a recording ahead,
58 with one (docs/performance.md). So while one is in progress the replans take one thread,
and torch's own choice again after.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def one_thread_if(busy: bool) -> Iterator[None]:
    """Run the body on one torch thread if ``busy``; torch's setting is restored after."""
    if not busy or torch.get_num_threads() == 1:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
