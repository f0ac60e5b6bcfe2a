"""The background process that records highway-env scenes, and the parent's end of its pipes.

One child per Python process, started on first use as ``python -m
counterscene_env.scene.recorder_process``: a fresh interpreter that imports this package and
nothing of the user's (``multiprocessing``'s ``spawn`` and ``forkserver`` would re-run a
script's top level without a ``__main__`` guard in the child; ``fork`` copies a process whose
torch threads may hold locks).

The protocol, pickles behind an 8-byte length on the child's stdin and stdout (the parent
only unpickles what its own child wrote):

- parent to child: ``("record", ticket, road, seed)`` (exactly this seed, ``highway.record``)
  or ``("cancel", ticket)``;
- child to parent: ``("start", ticket)`` when it begins one, then ``("done", ticket,
  answer)`` with ``answer`` ``("ok", scene)``, ``("ok", None)`` (the seed was rejected),
  ``("error", message)`` or ``("cancelled", None)`` (withdrawn before it began).

The child keeps its own queue, in order, and reads every waiting message before it begins
the next recording, so a withdrawn one is skipped. Every ticket sent gets exactly one
``done``.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import queue
import select
import struct
import subprocess
import sys
import threading
from collections import deque
from typing import IO, Any

_HEADER = struct.Struct("<Q")


def _write(stream: IO[bytes], message: Any) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _read(stream: IO[bytes]) -> Any:
    """The next message; raises ``EOFError`` when the other end is gone."""
    (size,) = _HEADER.unpack(_read_exactly(stream, _HEADER.size))
    return pickle.loads(_read_exactly(stream, size))


def _read_exactly(stream: IO[bytes], size: int) -> bytes:
    chunks, left = [], size
    while left:
        chunk = stream.read(left)
        if not chunk:
            raise EOFError("the other end of the pipe closed")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _waiting(stream: IO[bytes]) -> bool:
    """Whether a message has begun to arrive on ``stream`` (unbuffered: nothing read ahead
    where ``select`` cannot see it)."""
    return bool(select.select([stream], [], [], 0)[0])


class Recorder:
    """The parent's handle on the child (module docstring): tickets in submission order."""

    def __init__(self) -> None:
        # It runs no torch (one thread, to be sure), and finds this package where we did.
        path = os.pathsep.join(p for p in sys.path if p)
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path}
        self.child = subprocess.Popen(
            [sys.executable, "-m", "counterscene_env.scene.recorder_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
            bufsize=0,
            # Its own session: a Ctrl-C at the terminal goes to the command, which ends the
            # child by closing its pipe (a child in the terminal's group printed a traceback).
            start_new_session=True,
        )
        self.next_ticket = 0
        self.open: set[int] = set()  # sent, no ``done`` yet
        self.begun: set[int] = set()
        self.withdrawn: set[int] = set()
        self.results: dict[int, tuple[str, Any]] = {}
        self.broken = False
        self.heard = False  # any message from the child yet
        # A scene is larger than a pipe's buffer: a thread takes every answer off the pipe
        # as it comes, or the child would wait, mid-write, for the parent to look.
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        try:
            while True:
                self.inbox.put(_read(self.child.stdout))
        except (EOFError, OSError, pickle.UnpicklingError):
            self.inbox.put(None)  # the child is gone

    @property
    def busy(self) -> bool:
        """Whether recordings are queued or in progress."""
        self._collect()
        return bool(self.open) and not self.broken

    def submit(self, road: str, seed: int) -> int:
        """Queue exactly this seed's recording; its ticket."""
        ticket = self.next_ticket
        self.next_ticket += 1
        self._send(("record", ticket, road, int(seed)))
        self.open.add(ticket)
        return ticket

    def started(self, ticket: int) -> bool:
        """Whether the child has begun (or finished) this ticket."""
        self._collect()
        return ticket in self.begun or ticket in self.results

    def done(self, ticket: int) -> bool:
        self._collect()
        return ticket in self.results or self.broken

    def withdraw(self, ticket: int) -> None:
        """Forget a ticket: skipped if the child has not begun it, its answer dropped."""
        self.results.pop(ticket, None)
        if ticket in self.open:
            self.withdrawn.add(ticket)
            self._send(("cancel", ticket))

    def result(self, ticket: int) -> tuple[str, Any]:
        """Wait for a ticket's answer: ``("ok", scene or None)``, ``("error", message)``, or
        ``("broken", None)`` if the child died."""
        while ticket not in self.results and not self.broken:
            self._receive()
        return self.results.pop(ticket, ("broken", None))

    def _send(self, message: tuple) -> None:
        if self.broken:
            return
        try:
            _write(self.child.stdin, message)
        except OSError:
            self._break()

    def _collect(self) -> None:
        """Take every message already in, without waiting for more."""
        while not self.broken and not self.inbox.empty():
            self._receive()

    def _receive(self) -> None:
        message = self.inbox.get()
        if message is None:
            self._break()
            return
        self.heard = True
        if message[0] == "start":
            self.begun.add(message[1])
            return
        _, ticket, answer = message
        self.open.discard(ticket)
        self.begun.discard(ticket)
        if ticket in self.withdrawn:
            self.withdrawn.discard(ticket)
        else:
            self.results[ticket] = answer

    def _break(self) -> None:
        self.broken = True
        self.child.kill()

    @property
    def failed_to_start(self) -> bool:
        """Whether the child ended by itself before saying anything (it could not start:
        another will not either)."""
        return self.broken and not self.heard and (self.child.poll() or 0) > 0

    def close(self) -> None:
        """End the child (it finishes the recording in hand) and let go of its pipes."""
        with contextlib.suppress(OSError):
            self.child.stdin.close()
        try:
            self.child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.child.kill()
            self.child.wait()
        with contextlib.suppress(OSError):
            self.child.stdout.close()  # the reader thread has seen the end by now


def _serve() -> None:
    """The child: answer requests in order until the parent closes the pipe."""
    from counterscene_env.scene.highway import RejectedScene, record

    requests = os.fdopen(sys.stdin.fileno(), "rb", buffering=0)
    answers = sys.stdout.buffer
    sys.stdout = sys.stderr  # anything printed must not reach the pipe
    queue: deque[tuple[int, str, int]] = deque()
    cancelled: set[int] = set()
    while True:
        try:
            while not queue or _waiting(requests):  # wait only when there is nothing to do
                message = _read(requests)
                if message[0] == "cancel":
                    cancelled.add(message[1])
                else:
                    queue.append(message[1:])
        except EOFError:
            return
        ticket, road, seed = queue.popleft()
        if ticket in cancelled:
            cancelled.discard(ticket)
            answer: tuple[str, Any] = ("cancelled", None)
        else:
            _write(answers, ("start", ticket))
            try:
                answer = ("ok", record(road, seed))
            except RejectedScene:
                answer = ("ok", None)
            except Exception as exc:
                answer = ("error", f"{type(exc).__name__}: {exc}")
        try:
            _write(answers, ("done", ticket, answer))
        except OSError:  # the parent is gone
            return


if __name__ == "__main__":
    _serve()
