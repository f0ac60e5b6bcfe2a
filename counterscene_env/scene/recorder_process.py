"""The background process that records highway-env scenes, and its end of the pipe.

One child per Python process, started on first use as ``python -m
counterscene_env.scene.recorder_process``: a fresh interpreter that imports this package and
nothing of the user's (``multiprocessing``'s ``spawn`` and ``forkserver`` would re-run a
script's top level without a ``__main__`` guard in the child; ``fork`` copies a process whose
torch threads may hold locks). It reads requests ``(seed list position, road, seed)`` from its
stdin and answers each, in order, on its stdout: ``("ok", scene or None)`` (None: the seed
was rejected) or ``("error", message)``. Messages are pickles behind an 8-byte length; the
parent only unpickles what its own child wrote.

The parent keeps the queue (:class:`Recorder`): one request is in the child at a time, so a
queued one can still be withdrawn, and the child is fed whenever the parent looks
(``submit``, ``done``, ``result``).
"""

from __future__ import annotations

import os
import pickle
import select
import struct
import subprocess
import sys
from collections import deque
from typing import IO, Any

_HEADER = struct.Struct("<Q")


def _write(stream: IO[bytes], message: Any) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _read(stream: IO[bytes]) -> Any:
    """The next message; raises ``EOFError`` when the other end is gone."""
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError("the other end of the pipe closed")
    (size,) = _HEADER.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the other end of the pipe closed mid-message")
    return pickle.loads(data)


class Recorder:
    """The parent's handle on the child: tickets in submission order."""

    def __init__(self) -> None:
        env = {**os.environ, "OMP_NUM_THREADS": "1"}  # it runs no torch; keep it that way
        self.child = subprocess.Popen(
            [sys.executable, "-m", "counterscene_env.scene.recorder_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self.queued: deque[tuple[int, str, int]] = deque()  # not yet sent
        self.sent: int | None = None  # the ticket in the child
        self.results: dict[int, tuple[str, Any]] = {}
        self.next_ticket = 0
        self.broken = False

    def submit(self, road: str, seed: int) -> int:
        """Queue exactly this seed's recording (``highway.record``); its ticket."""
        ticket = self.next_ticket
        self.next_ticket += 1
        self.queued.append((ticket, road, int(seed)))
        self._pump()
        return ticket

    def started(self, ticket: int) -> bool:
        """Whether the child has begun (or finished) this ticket."""
        self._pump()
        return ticket in self.results or ticket == self.sent

    def done(self, ticket: int) -> bool:
        self._pump()
        return ticket in self.results or self.broken

    def withdraw(self, ticket: int) -> None:
        """Forget a ticket: dropped if still queued, its result discarded otherwise."""
        self.queued = deque(q for q in self.queued if q[0] != ticket)
        self.results.pop(ticket, None)
        if self.sent == ticket:
            self.sent = -1 - ticket  # answered later, then dropped
        self._pump()

    def result(self, ticket: int) -> tuple[str, Any]:
        """Wait for a ticket that has started; ``("ok", scene or None)``, ``("error",
        message)``, or ``("broken", None)`` if the child died."""
        while ticket not in self.results and not self.broken:
            self._receive(block=True)
        return self.results.pop(ticket, ("broken", None))

    def _pump(self) -> None:
        """Collect a finished answer without waiting, and send the next request."""
        if self.sent is not None and not self.broken:
            ready, _, _ = select.select([self.child.stdout], [], [], 0)
            if ready:
                self._receive(block=False)
        if self.sent is None and self.queued and not self.broken:
            ticket, road, seed = self.queued.popleft()
            try:
                _write(self.child.stdin, (road, seed))
                self.sent = ticket
            except OSError:
                self._break()

    def _receive(self, block: bool) -> None:
        try:
            answer = _read(self.child.stdout)
        except (EOFError, OSError, pickle.UnpicklingError):
            self._break()
            return
        if self.sent is not None and self.sent >= 0:
            self.results[self.sent] = answer
        self.sent = None
        self._pump()

    def _break(self) -> None:
        self.broken = True
        self.queued.clear()
        self.child.kill()

    def close(self) -> None:
        try:
            self.child.stdin.close()
        except OSError:
            pass
        try:
            self.child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.child.kill()


def _serve() -> None:
    """The child: answer requests until the parent closes the pipe."""
    from counterscene_env.scene.highway import RejectedScene, record

    requests, answers = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # anything printed must not reach the pipe
    while True:
        try:
            road, seed = _read(requests)
        except EOFError:
            return
        try:
            answer: tuple[str, Any] = ("ok", record(road, seed))
        except RejectedScene:
            answer = ("ok", None)
        except Exception as exc:
            answer = ("error", f"{type(exc).__name__}: {exc}")
        try:
            _write(answers, answer)
        except OSError:  # the parent is gone
            return


if __name__ == "__main__":
    _serve()
