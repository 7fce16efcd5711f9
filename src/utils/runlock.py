"""One writer per run directory: an advisory lock file ``<run>/.lock`` held for the whole run; and
:func:`exclusive`, a waiting lock for work that one process at a time may do (a first stage, a build).

``fcntl.flock`` locks are released by the kernel when their holder exits, also after ``kill -9``, so a
killed run never leaves a stale lock and its directory can be resumed. The file itself stays (it
holds the pid and host of the last holder, for the refusal message).
"""

from __future__ import annotations

import fcntl
import os
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType

LOCK_NAME = ".lock"


class RunDirLocked(RuntimeError):
    """Another process is writing to this run directory."""


class RunLock:
    """Context manager holding ``<run_dir>/.lock`` exclusively; raises :class:`RunDirLocked` if it is taken."""

    def __init__(self, run_dir: Path | str) -> None:
        self.path = Path(run_dir) / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        """Take the lock without waiting (RunDirLocked naming the holder if another process has it)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise RunDirLocked(
                f"{self.path.parent} is in use by a running job ({holder}); wait for it to finish or choose "
                "another output directory (hydra.run.dir=...)") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Release the lock (the file stays)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.release()


@contextmanager
def exclusive(path: Path | str) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``path`` (created with its parents if missing), waiting for its holder.

    Released on exit, and by the kernel if the holder dies (also ``kill -9``), so it never goes stale.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
