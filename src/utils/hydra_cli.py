"""Hydra's own errors (an unknown experiment or group option, a mistyped key) as one line and exit code 2.

Hydra reports a config it cannot compose on stderr over several lines and exits with code 1, the
code this project keeps for runs that diverged. :func:`run_cli` holds back what is written to stderr
until the job starts (:func:`job_started`); if the process exits with an error before that, the held
text -- Hydra's message with the valid choices -- is printed as one line ``error: ...`` and the exit
code becomes 2. Once the job has started, stderr passes through unchanged.
"""

from __future__ import annotations

import io
import sys
from collections.abc import Callable
from typing import Any

#: Lines of Hydra's report that carry no information about the mistake.
_NOISE = ("Config search path:", "\tprovider=", "Set the environment variable HYDRA_FULL_ERROR")


class _HeldStderr(io.TextIOBase):
    """A stand-in for ``sys.stderr`` that keeps what is written until :meth:`release`, then passes it on."""

    def __init__(self, target) -> None:
        super().__init__()
        self.target = target
        self.held: list[str] = []
        self.released = False

    def write(self, text: str) -> int:
        if self.released:
            return self.target.write(text)
        self.held.append(text)
        return len(text)

    def flush(self) -> None:
        if self.released:
            self.target.flush()

    def release(self) -> None:
        """Write what was held and pass everything on from now on."""
        if not self.released:
            self.released = True
            self.target.write("".join(self.held))
            self.held.clear()
            self.target.flush()

    def isatty(self) -> bool:
        return self.target.isatty()

    def fileno(self) -> int:
        return self.target.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return getattr(self.target, "encoding", "utf-8")


#: OS errors Hydra meets before the job starts: creating the run directory or its log file.
_OS_ERRORS = ("OSError", "PermissionError", "FileExistsError", "NotADirectoryError", "IsADirectoryError",
              "FileNotFoundError")


def _last_exception(text: str) -> str:
    """The exception line at the end of a traceback, for the run directory's OS errors with the way out."""
    last = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith(_NOISE)][-1]
    kind, _, message = last.partition(": ")
    if kind in _OS_ERRORS:
        return (f"cannot create the run directory or its log ({message}); choose a writable place with "
                "hydra.run.dir=... (paths.output_root for new runs)")
    return last


def one_line(text: str) -> str:
    """Hydra's multi-line report as one line: noise dropped, indented choices listed after their heading."""
    if "Traceback (most recent call last)" in text:
        return _last_exception(text)
    parts: list[str] = []
    for line in text.splitlines():
        if not line.strip() or line.startswith(_NOISE):
            continue
        if line.startswith(("\t", "    ")) and parts:
            sep = ": " if parts[-1].endswith(":") else ", "
            parts[-1] = parts[-1].rstrip(":") + sep + line.strip()
        else:
            parts.append(line.strip())
    return "; ".join(parts)


def job_started() -> None:
    """Called by the job's main function: stderr passes through from now on."""
    if isinstance(sys.stderr, _HeldStderr):
        sys.stderr.release()


def run_cli(main: Callable[[], Any]) -> None:
    """Run a ``@hydra.main`` function; an error exit before the job starts becomes one line and code 2."""
    real = sys.stderr
    held = _HeldStderr(real)
    sys.stderr = held
    try:
        main()
    except SystemExit as e:
        if held.released or e.code in (0, None):
            raise
        message = one_line("".join(held.held)) or f"exit code {e.code}"
        held.held.clear()
        print(f"error: {message}", file=real)
        raise SystemExit(2) from None
    finally:
        if sys.stderr is held:
            sys.stderr = real
        held.release()
