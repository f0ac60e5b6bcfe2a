"""Recording the next episode's scene in a background process while this episode runs.

A generated road's episode starts by recording 13 s of highway-env traffic (the scene's
factual log): Python that holds one core for about 0.2 s, as long as a whole episode of
random actions (docs/performance.md). The scene is a function of its road and seed alone
(``scene.highway.generate``), so it can be recorded anywhere and ahead of time: one worker
process per Python process records the scene the next reset will draw, and that reset takes
it if the draw matches, or records it itself if it does not (an env re-seeded by
``reset(seed=...)``, an episode that consumed the env's generator). Either way the episode
is the one the seed gives.

The worker is started on first use with ``forkserver`` (``spawn`` where there is none; a fork
of a process with torch's threads running is unsafe) and shared by every env of the process.
A daemonic process (the workers of SB3's ``SubprocVecEnv`` and Gymnasium's
``AsyncVectorEnv``) may not have children, and its cores are spoken for: there nothing is
recorded ahead. The scene comes back pickled from our own child process, which is trusted.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from counterscene_env.scene.core import Scene

_POOL: ProcessPoolExecutor | None = None


def available() -> bool:
    """Whether this process may record in the background (it is not daemonic)."""
    return not multiprocessing.current_process().daemon


def _pool() -> ProcessPoolExecutor:
    global _POOL
    if _POOL is None:
        methods = multiprocessing.get_all_start_methods()
        context = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
        _POOL = ProcessPoolExecutor(max_workers=1, mp_context=context)
    return _POOL


def _record(road: str, seed: int) -> Scene:
    from counterscene_env.scene.highway import generate

    return generate(road, seed)


class Prefetch:
    """One scene being recorded ahead: road ``road`` from seed ``seed`` (``generate``'s)."""

    def __init__(self, road: str, seed: int) -> None:
        self.key = (road, int(seed))
        self.future: Future = _pool().submit(_record, road, int(seed))

    @property
    def running(self) -> bool:
        """Whether the worker is still recording it (it then holds a core)."""
        return not self.future.done()

    def take(self, road: str, seed: int) -> Scene | None:
        """The scene if it is the one asked for and was recorded; None otherwise (the caller
        records it). Waits for a recording in progress only if it is the one asked for."""
        if self.key != (road, int(seed)):
            self.future.cancel()
            return None
        try:
            return self.future.result()
        except BrokenProcessPool:  # the worker died: the next prefetch starts a new one
            _discard_pool()
            return None
        except Exception:
            return None  # it again, with its own traceback)


def _discard_pool() -> None:
    global _POOL
    if _POOL is not None:
        _POOL.shutdown(wait=False, cancel_futures=True)
        _POOL = None
