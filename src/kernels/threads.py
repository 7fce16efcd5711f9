"""The OpenMP threading environment, set by each entry point before torch loads its OpenMP runtime.

On shared CPUs the spinning barriers of the compiled rasterizer and of torch stall when a partner
thread is descheduled (docs/benchmarks.md), so threads wait passively after a short spin. An explicit
user setting wins.
"""

from __future__ import annotations

import os


def configure_openmp() -> None:
    """``OMP_WAIT_POLICY=PASSIVE`` and, for libgomp, ``GOMP_SPINCOUNT=1000`` unless the user set them.

    A passive wait alone costs a futex sleep and wake-up per parallel region or barrier; ~1 000 spins
    catch most of them and waste little when the partner thread is descheduled (docs/benchmarks.md).
    Has an effect only before torch is imported.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if os.environ["OMP_WAIT_POLICY"].upper() == "PASSIVE":
        os.environ.setdefault("GOMP_SPINCOUNT", "1000")
