"""``python -m src.bench <subcommand> [args]``.

Subcommands are registered in :data:`SUBCOMMANDS` (name -> ``main(argv) -> exit code``):
``rasterizer`` (a full run writes ``sweeps/results/bench/rasterizer.json`` and ``.png``) and
``training``. Modules are imported lazily so one subcommand's imports don't slow down another.

``OMP_WAIT_POLICY`` defaults to ``PASSIVE`` with a short spin (``GOMP_SPINCOUNT=1000``), set at the
top of this module before torch loads (``src/kernels/threads.py``; export ``OMP_WAIT_POLICY=ACTIVE`` to
override): on a shared, oversubscribed machine OpenMP threads that
spin at barriers while their partner is descheduled made 2-thread renders 10-20x slower.
"""

from __future__ import annotations

from src.kernels.threads import configure_openmp

configure_openmp()  # before anything loads torch's OpenMP runtime (src/kernels/threads.py)

import importlib
import sys
from collections.abc import Callable


def _lazy(module: str, func: str = "main") -> Callable[[list[str]], int]:
    def run(argv: list[str]) -> int:
        return getattr(importlib.import_module(module), func)(argv)

    return run


SUBCOMMANDS: dict[str, Callable[[list[str]], int]] = {
    "rasterizer": _lazy("src.bench.rasterizer"),
    "training": _lazy("src.bench.training"),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in SUBCOMMANDS:
        names = ", ".join(SUBCOMMANDS)
        print(f"usage: python -m src.bench {{{names}}} [args]   (each subcommand has --help)")
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return int(SUBCOMMANDS[argv[0]](argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
