"""What this CPU can do natively (read once from /proc/cpuinfo), and whether bfloat16 pays off on it.

A CPU flag says that bfloat16 products are *native*, not that they are *faster*: on CPUs whose
AVX512-BF16 dot-product instruction issues once per cycle where float32 FMAs issue twice (and
without AMX), oneDNN's bf16 matmuls and convolutions run at about half the float32 speed. So
``autocast_bf16: auto`` asks ``bf16_pays_off``, which times both dtypes on this machine at the shapes
training uses and takes bf16 only when it is clearly faster. The measured speed-up is kept on disk
(``speedup_cache_path``), keyed by the CPU's model and flags, the torch version and the thread count,
so every later process on the machine makes the same choice: a timing taken under a passing load
cannot make two runs of one configuration differ in precision.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

BF16_MIN_SPEEDUP = 1.25  # bf16 must beat float32 by this factor: a clear win, not timing noise
KINDS = ("matmul", "conv")  # the products timed: a field head's hidden layer, a tri-plane convolution

log = logging.getLogger(__name__)


@functools.cache
def cpu_has_native_bf16() -> bool:
    """True when this CPU multiplies bfloat16 natively (AVX512-BF16 or AMX-BF16 in /proc/cpuinfo)."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    words = set(flags.split())
    return bool(words & {"avx512_bf16", "amx_bf16"})


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ValueError(f"bf16_speedup kind must be 'matmul' or 'conv', got {kind!r}")


def best_time(fn: Callable[[], object], reps: int, warmup: int = 1) -> float:
    """Fastest of ``reps`` timed calls of ``fn`` after ``warmup`` untimed calls (seconds)."""
    for _ in range(warmup):
        fn()
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _machine_key() -> str:
    """What a measured speed-up depends on: the CPU (model name, flags), torch, the thread count."""
    import torch

    try:
        first_cpu = Path("/proc/cpuinfo").read_text().split("\n\n")[0]
    except OSError:
        first_cpu = ""
    fields = {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in first_cpu.splitlines() if ":" in line)}
    text = "|".join([fields.get("model name", ""), fields.get("flags", ""), f"torch {torch.__version__}",
                     f"threads {torch.get_num_threads()}"])
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def user_cache_dir() -> Path:
    """``${XDG_CACHE_HOME:-~/.cache}/splatfields``: the project's per-user cache (compiled kernels, timings)."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "splatfields"


def speedup_cache_path() -> Path:
    """``user_cache_dir() / "bf16_speedup.json"``: the measured speed-ups by machine key."""
    return user_cache_dir() / "bf16_speedup.json"


def _read_speedups() -> dict:
    try:
        data = json.loads(speedup_cache_path().read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _store_speedup(key: str, value: float) -> None:
    from src.utils.record import atomic_write_text

    path = speedup_cache_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps({**_read_speedups(), key: value}, indent=2, sort_keys=True) + "\n")
    except OSError as err:  # a read-only home: every process measures for itself
        log.debug("bf16 speed-up not cached (%s)", err)


def measure_bf16_speedup(kind: str, rounds: int = 4) -> float:
    """float32 time / bfloat16 time of one representative CPU product, timed now (> 1: bf16 faster).

    ``kind``: "matmul" (a field head's hidden layer, [16384, 128] x [128, 128]) or "conv" (a tri-plane
    generator convolution: 3 stacked planes of 32 channels at 80 px, 3x3, channels-last). The dtypes
    are timed in ``rounds`` interleaved rounds (best of 2 each), the fastest time of each kept, with
    the process's torch thread count: ~0.1 s per kind. Smaller products than these measure thread
    start-up more than arithmetic (on 2 threads their ratio scattered over 0.6-1.4).
    """
    import torch
    import torch.nn.functional as F

    _check_kind(kind)
    g = torch.Generator().manual_seed(0)
    work = {}
    for dt in (torch.float32, torch.bfloat16):
        if kind == "matmul":
            a = torch.randn(16384, 128, generator=g).to(dt)  # [N, width]
            w = torch.randn(128, 128, generator=g).to(dt)  # [width, width]
            work[dt] = lambda a=a, w=w: a @ w
        else:
            x = torch.randn(1, 96, 80, 80, generator=g).to(dt).contiguous(memory_format=torch.channels_last)
            w = torch.randn(96, 32, 3, 3, generator=g).to(dt).contiguous(memory_format=torch.channels_last)
            work[dt] = lambda x=x, w=w: F.conv2d(x, w, padding=1, groups=3)
    best = dict.fromkeys(work, float("inf"))
    with torch.no_grad():
        for _ in range(rounds):
            for dt, fn in work.items():
                best[dt] = min(best[dt], best_time(fn, 2))
    return best[torch.float32] / best[torch.bfloat16]


@functools.cache
def bf16_speedup(kind: str) -> float:
    """This machine's bf16 speed-up for ``kind`` (see ``measure_bf16_speedup``): read from the cache
    file when this machine key has one, else measured once and stored there."""
    _check_kind(kind)
    key = f"{_machine_key()}/{kind}"
    cached = _read_speedups().get(key)
    if isinstance(cached, int | float) and cached > 0:
        return float(cached)
    value = measure_bf16_speedup(kind)
    _store_speedup(key, value)
    log.info("%s: bfloat16 measured at %.2fx the float32 speed, kept in %s", kind, value, speedup_cache_path())
    return value


@functools.cache
def bf16_pays_off(kind: str) -> bool:
    """True when bf16 is native here AND measured at least ``BF16_MIN_SPEEDUP`` faster for ``kind``.

    The decision is logged once per kind and process.
    """
    if not cpu_has_native_bf16():
        log.info("%s products in float32: this CPU has no native bfloat16", kind)
        return False
    speedup = bf16_speedup(kind)
    chosen = speedup >= BF16_MIN_SPEEDUP
    log.info("%s products in %s: bfloat16 measured %.2fx the float32 speed (threshold %.2fx)",
             kind, "bfloat16" if chosen else "float32", speedup, BF16_MIN_SPEEDUP)
    return chosen


def resolve_autocast_bf16(value: bool | str, kind: str) -> bool:
    """The ``autocast_bf16`` config value (true, false or "auto") as a bool; "auto" = ``bf16_pays_off``."""
    if value not in (True, False, "auto"):
        raise ValueError(f"autocast_bf16 must be true, false or 'auto', got {value!r}")
    return bf16_pays_off(kind) if value == "auto" else bool(value)
