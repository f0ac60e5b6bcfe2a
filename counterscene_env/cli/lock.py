"""One command at a time per output directory.

Two commands writing one ``--out`` (two ``stress`` runs, or ``generate`` with two seeds) would
interleave their records and leave a directory that neither owns: the second is refused at
once. The lock is an advisory ``flock`` on a file in the system's temporary directory, named
after the directory's real path, so nothing is written into the user's tree (a refused call
leaves it as it was) and the lock goes with the process that holds it, however it ends.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager


def lock_path(directory: str | os.PathLike) -> str:
    """The lock file of ``directory`` (which need not exist yet)."""
    key = hashlib.sha1(os.path.realpath(directory).encode()).hexdigest()[:16]
    return os.path.join(tempfile.gettempdir(), f"counterscene-{key}.lock")


@contextmanager
def out_lock(directory: str | os.PathLike, command: str) -> Iterator[None]:
    """Hold ``directory``'s lock while the body runs.

    Raises:
        RuntimeError: another process holds it (the message names its pid and command).
    """
    fd = os.open(lock_path(directory), os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            raise RuntimeError(
                f"{directory} is being written by {holder}: wait for it to finish, or use "
                "another output directory"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"counterscene {command} (pid {os.getpid()})".encode(), 0)
        yield
    finally:
        os.close(fd)  # closing releases the lock
