"""FLOP counts and measured peaks: the arithmetic floor of a training iteration's networks.

``count_flops(fn)`` runs ``fn`` (a forward + backward) under ``torch.utils.flop_counter.FlopCounterMode``
and splits the count into convolutions (``aten.convolution`` and its backward) and matrix products
(``mm``, ``addmm``, ``bmm``, ``baddbmm``, attention): the only ops the counter prices; elementwise ops,
normalisations and the rasterizer count zero. A multiply-add is 2 FLOPs. ``tests/test_bench_training.py``
checks the counter against a hand count from layer shapes.

``measure_peaks(dtype)`` times large matrix products and 3x3 convolutions in ``dtype`` on this machine
and keeps the best throughput of each kind (GFLOP/s): the peaks that ``floor_ms`` divides by.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

CONV_OPS = ("convolution", "convolution_backward", "_convolution")
MATMUL_OPS = ("mm", "addmm", "bmm", "baddbmm", "_scaled_dot_product_flash_attention",
              "_scaled_dot_product_efficient_attention", "_scaled_dot_product_cudnn_attention")


def count_flops(fn: Callable[[], object]) -> dict[str, int]:
    """FLOPs of running ``fn()`` once: ``{"total", "conv", "matmul"}`` (2 FLOPs per multiply-add)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        fn()
    conv = matmul = 0
    for op, n in counter.get_flop_counts().get("Global", {}).items():
        name = getattr(op, "__name__", str(op)).split(".")[-1]
        if name in CONV_OPS:
            conv += int(n)
        else:
            matmul += int(n)  # every other priced op is a matrix product (MATMUL_OPS)
    return {"total": conv + matmul, "conv": conv, "matmul": matmul}


def _best_gflops(fn: Callable[[], object], flops: float, reps: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return flops / best / 1e9


@torch.no_grad()
def measure_peaks(dtype: torch.dtype = torch.float32, reps: int = 5) -> dict[str, float]:
    """Best measured GFLOP/s of matrix products and of 3x3 convolutions in ``dtype`` (CPU).

    Matrix products: square 1024 and 2048 and the tall-skinny [65536, 128] x [128, 128] of an MLP
    layer; convolutions: 32 -> 32 channels at 80 and 160 px and 64 -> 64 at 128 px, NCHW and
    channels-last. Each kind keeps its best (fastest of ``reps``) over shapes and layouts.
    """
    g = torch.Generator().manual_seed(0)
    mm = 0.0
    for m, k, n in ((1024, 1024, 1024), (2048, 2048, 2048), (65536, 128, 128)):
        a = torch.randn(m, k, generator=g).to(dtype)
        b = torch.randn(k, n, generator=g).to(dtype)
        mm = max(mm, _best_gflops(lambda a=a, b=b: a @ b, 2.0 * m * k * n, reps))
    conv = 0.0
    for c, r in ((32, 80), (32, 160), (64, 128)):
        w = torch.randn(c, c, 3, 3, generator=g).to(dtype)
        for fmt in (torch.contiguous_format, torch.channels_last):
            x = torch.randn(1, c, r, r, generator=g).to(dtype).contiguous(memory_format=fmt)
            wf = w.contiguous(memory_format=fmt)
            conv = max(conv, _best_gflops(lambda x=x, wf=wf: torch.nn.functional.conv2d(x, wf, padding=1),
                                          2.0 * 9 * c * c * r * r, reps))
    return {"matmul_gflops": mm, "conv_gflops": conv}


def floor_ms(flops: dict[str, int], peaks: dict[str, float]) -> float:
    """Milliseconds that ``flops`` (``count_flops`` output) take at ``peaks`` (``measure_peaks`` output)."""
    return 1e3 * (flops["conv"] / (peaks["conv_gflops"] * 1e9) + flops["matmul"] / (peaks["matmul_gflops"] * 1e9))
