"""Recording the next episodes' scenes in a background process while this episode runs.

A generated road's episode starts by recording 13 s of highway-env traffic (the scene's
factual log): Python that holds one core for about 0.7 s per intersection scene, rejected
seeds included (docs/performance.md, "Where it stands"). A scene is a function of its road
and seed alone (``scene.highway.generate``), so it can be recorded anywhere and ahead of time:

- :class:`Prefetch` records the scene an env's next reset will draw (and the one after); that
  reset takes it if the draw matches, or records the scene itself if it does not (an env
  re-seeded by ``reset(seed=...)``, an episode that used the env's generator). The episode is
  the one the seed gives either way. A reset that would wait for the process records the
  scene after its own meanwhile, unless the process has begun it: both cores record.
- :func:`safe_scenes_ahead` gives a stress run's scenes in order, the next ones recorded
  while a batch runs.

The recording runs in one child process per Python process (``scene/recorder_process.py``),
shared by every env and started on first use. Not in a daemonic process (the workers of SB3's
``SubprocVecEnv`` and Gymnasium's ``AsyncVectorEnv``: their cores are spoken for) and not on
Windows (the pipe is polled with ``select``): there every scene is recorded when it is needed.
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing
import os
import warnings
from collections import deque
from collections.abc import Iterator

from counterscene_env.scene.core import Scene
from counterscene_env.scene.recorder_process import Recorder

_RECORDER: Recorder | None = None
#: Set when the child process cannot start here: every scene is then recorded in-process.
_UNAVAILABLE: list[str] = []


def available() -> bool:
    """Whether this process may record in the background (module docstring)."""
    posix = os.name == "posix"
    return posix and not multiprocessing.current_process().daemon and not _UNAVAILABLE


def _recorder() -> Recorder | None:
    """The process's recorder, (re)started if it has none or the last one died; None if one
    cannot be started here (said once, on stderr)."""
    global _RECORDER
    if _UNAVAILABLE:
        return None
    if _RECORDER is not None and _RECORDER.failed_to_start:
        _RECORDER.close()
        _give_up(f"its process exited with code {_RECORDER.child.returncode} at start")
        return None
    if _RECORDER is None or _RECORDER.broken:
        if _RECORDER is None:
            atexit.register(_close)
        else:
            _RECORDER.close()
        try:
            _RECORDER = Recorder()
        except OSError as exc:
            _give_up(f"{type(exc).__name__}: {exc}")
            return None
    return _RECORDER


def start() -> None:
    """Start the background process now if it is not running (it takes about 0.75 s to be
    ready: started before a reset records its own scene, it is ready by the next one)."""
    if available():
        _recorder()


def _give_up(why: str) -> None:
    _UNAVAILABLE.append(why)
    warnings.warn(
        f"counterscene: scenes cannot be recorded in the background ({why}); each is "
        "recorded when it is needed",
        RuntimeWarning,
        stacklevel=3,
    )


def _close() -> None:
    if _RECORDER is not None:
        _RECORDER.close()


def _max_attempts() -> int:
    """``generate``'s default number of seeds (highway-env is imported on first use only)."""
    from counterscene_env.scene.highway import MAX_ATTEMPTS

    return MAX_ATTEMPTS


def _record_here(road: str, seed: int) -> Scene | None:
    """Exactly this seed's recording in this process, or None if it is rejected."""
    from counterscene_env.scene.highway import RejectedScene, record

    try:
        return record(road, seed)
    except RejectedScene:
        return None


class Prefetch:
    """``generate(road, seed)``'s scene, recorded ahead: ``seed``, then ``seed + 1`` and on
    while they are rejected, one at a time, each sent when its predecessor's answer is seen."""

    def __init__(self, road: str, seed: int) -> None:
        self.key = (road, int(seed))
        self.recorder = _recorder()
        self.seed = int(seed)
        self.rejected: list[int] = []
        self.scene: Scene | None = None
        self.failed = self.recorder is None  # given up: the caller records the scene itself
        self.ticket = -1 if self.recorder is None else self.recorder.submit(road, self.seed)

    @property
    def running(self) -> bool:
        """Whether the scene is still being recorded (a core is busy with it)."""
        self._advance(wait=False)
        return self.scene is None and not self.failed

    @property
    def in_progress(self) -> bool:
        """Whether the background process has begun the recording and not yet finished it."""
        return self.running and self.recorder.started(self.ticket)

    def take(self, road: str, seed: int) -> Scene | None:
        """The scene if it is the one asked for and its recording has begun (waiting for it
        to end); None otherwise: the caller records it (a recording still queued behind
        other envs' would take longer to wait for)."""
        self._advance(wait=False)
        wanted = self.key == (road, int(seed)) and not self.failed
        if not wanted or (self.scene is None and not self.recorder.started(self.ticket)):
            self.cancel()
            return None
        self._advance(wait=True)
        return self.scene

    def record_here(self) -> None:
        """Record the scene in this process now, unless the background process has begun it
        (a caller that would otherwise wait for the process does this work meanwhile)."""
        self._advance(wait=False)
        if self.scene is not None or self.failed or self.recorder.started(self.ticket):
            return
        self.recorder.withdraw(self.ticket)
        while self.scene is None and not self.failed:
            self._settle(_record_here(self.key[0], self.seed))

    def cancel(self) -> None:
        """Withdraw the recording (the child drops it if it has not begun)."""
        if self.scene is None and not self.failed:
            self.recorder.withdraw(self.ticket)
        self.failed = self.scene is None

    def __del__(self) -> None:  # an env dropped without close(): its recording is not needed
        with contextlib.suppress(Exception):
            self.cancel()

    def _advance(self, wait: bool) -> None:
        while self.scene is None and not self.failed:
            if not (wait or self.recorder.done(self.ticket)):
                return
            status, scene = self.recorder.result(self.ticket)
            if status != "ok":  # the child died or failed: the caller's call shows why
                self.failed = True
            elif self._settle(scene):
                self.ticket = self.recorder.submit(self.key[0], self.seed)

    def _settle(self, scene: Scene | None) -> bool:
        """Take the current seed's recording (None: rejected); True if the next seed is to be
        recorded, as ``generate`` would try it."""
        if scene is not None:
            scene.metadata["rejected_seeds"] = self.rejected
            self.scene = scene
        elif len(self.rejected) + 1 == _max_attempts():
            self.failed = True  # generate's error, raised by the caller's own call
        else:
            self.rejected.append(self.seed)
            self.seed += 1
            return True
        return False


def safe_scenes_ahead(road: str, seed: int, count: int, ahead: int) -> Iterator[Scene]:
    """The first ``count`` safe scenes of ``road`` from ``seed``, exactly those of calling
    ``generate`` from ``seed`` and then from each kept scene's seed + 1 (``scenes_for``), with
    up to ``ahead`` seeds queued for the background process before they are asked for. A seed
    asked for before the process has begun it is recorded here instead (while the process
    starts, or is busy with the one before), so both record at once.

    Raises:
        RuntimeError: ``generate``'s, when its ``MAX_ATTEMPTS`` seeds in a row are rejected.
    """
    from counterscene_env.scene.highway import MAX_ATTEMPTS, generate

    seeds = _SeedsAhead(road, seed)
    rejected: list[int] = []
    kept = 0
    try:
        while kept < count:
            # No further ahead than the scenes still wanted (a rejection asks for one more).
            seeds.queue(max(min(ahead, count - kept), 1))
            k, scene = seeds.next()
            if scene is None:
                rejected.append(k)
                if len(rejected) == MAX_ATTEMPTS:  # generate's own error, raised by it
                    generate(road, rejected[0], max_attempts=MAX_ATTEMPTS)
                continue
            scene.metadata["rejected_seeds"] = rejected
            rejected, kept = [], kept + 1
            yield scene
    finally:
        seeds.withdraw()


class _SeedsAhead:
    """Consecutive seeds of one road, each recorded by the background process or here."""

    def __init__(self, road: str, seed: int) -> None:
        self.road, self.following = road, seed
        self.recorder: Recorder | None = _recorder()
        self.pending: deque[tuple[int, int]] = deque()  # (seed, ticket)

    def queue(self, depth: int) -> None:
        """Send seeds to the process until ``depth`` are pending."""
        while self.recorder is not None and len(self.pending) < depth:
            self.pending.append((self.following, self.recorder.submit(self.road, self.following)))
            self.following += 1

    def next(self) -> tuple[int, Scene | None]:
        """The next seed and its scene (None: rejected)."""
        if not self.pending:  # no process (it died): record here
            k, self.following = self.following, self.following + 1
            return k, _record_here(self.road, k)
        k, ticket = self.pending.popleft()
        if not self.recorder.started(ticket):  # record it here meanwhile
            self.recorder.withdraw(ticket)
            return k, _record_here(self.road, k)
        status, scene = self.recorder.result(ticket)
        if status != "ok":  # from here on, every seed is recorded in this process
            self.withdraw()
            self.recorder, self.following = None, k + 1
            scene = _record_here(self.road, k)
        return k, scene

    def withdraw(self) -> None:
        if self.recorder is not None:
            for _, ticket in self.pending:
                self.recorder.withdraw(ticket)
        self.pending.clear()


def recording() -> bool:
    """Whether this process's background recorder has recordings queued or in progress."""
    return _RECORDER is not None and _RECORDER.busy


@contextlib.contextmanager
def one_thread_if(busy: bool) -> Iterator[None]:
    """Run the body on one torch thread if ``busy`` (a recording in progress), torch's
    setting again after.

    Replans run torch's intra-op threads, two on a 2-core machine; a recording holds a core.
    Both at once, each thread waits for the other at every small operation: on 2 cores, 41
    env steps/s with two torch threads and a recording ahead, 58 with one
    (docs/history/performance.md, the fourth fast-replans session). The results do not
    depend on the thread count (``tests/test_prefetch.py``)."""
    import torch

    if not busy or torch.get_num_threads() == 1:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
