"""SIGINT (Ctrl-C) and SIGTERM as an orderly stop: the run records ``interrupted`` and can be resumed.

:func:`stop_on_signals` installs handlers for the duration of a run. Inside a region marked by
:func:`set_deferred` (the training loop) the first signal only sets a flag: the loop finishes its
step, writes a checkpoint and raises :class:`RunInterrupted` (see :func:`stop_requested`), so
re-running the same command resumes and reproduces the uninterrupted run. Anywhere else, or at a
second signal, :class:`RunInterrupted` is raised at once.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_state: dict = {"signal": None, "deferred": False}


class RunInterrupted(BaseException):
    """The run was stopped by a signal.

    Attributes:
        signum: the signal's number; ``name`` its name (``SIGINT``, ``SIGTERM``).
        checkpoint_iteration: iterations completed in the checkpoint written on the way out (None if none).
    """

    def __init__(self, signum: int, checkpoint_iteration: int | None = None) -> None:
        self.signum = int(signum)
        self.name = signal.Signals(signum).name
        self.checkpoint_iteration = checkpoint_iteration
        super().__init__(f"interrupted by {self.name}")


def _handler(signum: int, frame) -> None:
    first = _state["signal"] is None
    _state["signal"] = signum
    if not (first and _state["deferred"]):
        raise RunInterrupted(signum)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Handle SIGINT and SIGTERM as described in the module docstring (main thread only; else a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in _SIGNALS}
    _state.update(signal=None, deferred=False)
    for s in _SIGNALS:
        signal.signal(s, _handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _state.update(signal=None, deferred=False)


def set_deferred(on: bool) -> bool:
    """Mark the start (``on``) or end of a region -- the training loop -- that checks :func:`stop_requested`
    itself between steps; returns the previous setting."""
    before = _state["deferred"]
    _state["deferred"] = bool(on)
    return before


def stop_requested() -> int | None:
    """The number of the signal that asked the run to stop, or None."""
    return _state["signal"]
