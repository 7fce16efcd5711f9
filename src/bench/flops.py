"""FLOP counts and measured peaks: the arithmetic floor of a training iteration's networks.

``count_flops(fn)`` runs ``fn`` (a forward + backward) under ``torch.utils.flop_counter.FlopCounterMode``
and splits the count into convolutions (``aten.convolution`` and its backward) and matrix products
(``mm``, ``addmm``, ``bmm``, ``baddbmm``, attention, oneDNN's fused linear): the only ops priced; elementwise ops,
normalisations and the rasterizer count zero. A multiply-add is 2 FLOPs. ``tests/test_bench_training.py``
checks the counter against a hand count from layer shapes.

``measure_peaks(dtype)`` times large matrix products and 3x3 convolutions in ``dtype`` on this machine
and keeps the best throughput of each kind (GFLOP/s): the peaks that ``floor_ms`` divides by.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from src.kernels.cpu import best_time

CONV_OPS = ("convolution", "convolution_backward", "_convolution")
MATMUL_OPS = ("mm", "addmm", "bmm", "baddbmm", "_linear_pointwise", "_scaled_dot_product_flash_attention",
              "_scaled_dot_product_efficient_attention", "_scaled_dot_product_cudnn_attention")


def conv_backward_flops(grad_out_shape, x_shape, w_shape, _bias, _stride, _padding, _dilation, transposed,
                        _output_padding, _groups, output_mask, out_shape, **kwargs) -> int:
    """FLOPs of ``aten.convolution_backward`` (shapes in, as FlopCounterMode passes them), groups included.

    Each requested gradient (input: ``output_mask[0]``, weight: ``output_mask[1]``) costs as much as the
    forward product: 2 x (elements of the non-transposed output) x (w_shape[1] * kernel size), where
    ``w_shape[1]`` is already the per-group input channel count. torch's own formula prices the input
    gradient of a grouped convolution as ungrouped (``groups`` times too much).
    """
    conv_out = x_shape if transposed else grad_out_shape  # [N, C_out, *spatial] of the forward product
    per_output = 1
    for d in w_shape[1:]:
        per_output *= int(d)
    n_out = int(conv_out[0]) * int(w_shape[0] if not transposed else conv_out[1])
    for d in conv_out[2:]:
        n_out *= int(d)
    forward = 2 * n_out * per_output
    return forward * (int(bool(output_mask[0])) + int(bool(output_mask[1])))


def linear_pointwise_flops(x_shape, *args, out_shape=None, **kwargs) -> int:
    """FLOPs of oneDNN's fused linear ``mkldnn._linear_pointwise`` (both overloads): 2 x rows x in x out.

    The field heads' hidden layers run through it (``src/fields/linear_relu.py``); torch's counter
    does not price it, so without this their forward products would count zero.
    """
    rows = 1
    for d in x_shape[:-1]:
        rows *= int(d)
    return 2 * rows * int(x_shape[-1]) * int(out_shape[-1])


def count_flops(fn: Callable[[], object]) -> dict[str, int]:
    """FLOPs of running ``fn()`` once: ``{"total", "conv", "matmul"}`` (2 FLOPs per multiply-add).

    Convolution backward is priced by :func:`conv_backward_flops` (correct for grouped convolutions).
    """
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    mapping = {torch.ops.aten.convolution_backward: conv_backward_flops,
               torch.ops.mkldnn._linear_pointwise: linear_pointwise_flops}
    with FlopCounterMode(display=False, custom_mapping=mapping) as counter:
        fn()
    conv = matmul = 0
    for op, n in counter.get_flop_counts().get("Global", {}).items():
        name = getattr(op, "__name__", str(op)).split(".")[-1]
        if name in CONV_OPS:
            conv += int(n)
        else:
            matmul += int(n)  # every other priced op is a matrix product (MATMUL_OPS)
    return {"total": conv + matmul, "conv": conv, "matmul": matmul}


def device_sync(device: torch.device | str) -> Callable[[], None]:
    """Wait for the queued GPU work on a CUDA ``device`` (a no-op on the CPU), so timers see it."""
    return torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)


def _best_gflops(fn: Callable[[], object], flops: float, reps: int, sync: Callable[[], None]) -> float:
    """GFLOP/s of the fastest of ``reps`` calls of ``fn``; ``sync`` (:func:`device_sync`) waits for a
    GPU's queued work."""

    def timed() -> None:
        fn()
        sync()

    sync()
    return flops / best_time(timed, reps, warmup=2) / 1e9


@torch.no_grad()
def measure_peaks(dtype: torch.dtype = torch.float32, reps: int = 5, device: str = "cpu") -> dict[str, float]:
    """Best measured GFLOP/s of matrix products and of 3x3 convolutions in ``dtype`` on ``device``.

    Matrix products: square 1024 and 2048 (on CUDA also 4096 and 8192) and the tall-skinny
    [65536, 128] x [128, 128] of an MLP layer; convolutions: 32 -> 32 channels at 80 and 160 px and
    64 -> 64 at 128 px, NCHW and channels-last. Each kind keeps its best (fastest of ``reps``) over
    shapes and layouts.
    """
    dev = torch.device(device)
    sync = device_sync(dev)
    g = torch.Generator().manual_seed(0)
    mm = 0.0
    squares = (1024, 2048, 4096, 8192) if dev.type == "cuda" else (1024, 2048)
    for m, k, n in (*((s, s, s) for s in squares), (65536, 128, 128)):
        a = torch.randn(m, k, generator=g).to(dev, dtype)
        b = torch.randn(k, n, generator=g).to(dev, dtype)
        mm = max(mm, _best_gflops(lambda a=a, b=b: a @ b, 2.0 * m * k * n, reps, sync))
    conv = 0.0
    for c, r in ((32, 80), (32, 160), (64, 128)):
        w = torch.randn(c, c, 3, 3, generator=g).to(dev, dtype)
        for fmt in (torch.contiguous_format, torch.channels_last):
            x = torch.randn(1, c, r, r, generator=g).to(dev, dtype).contiguous(memory_format=fmt)
            wf = w.contiguous(memory_format=fmt)
            conv = max(conv, _best_gflops(lambda x=x, wf=wf: torch.nn.functional.conv2d(x, wf, padding=1),
                                          2.0 * 9 * c * c * r * r, reps, sync))
    return {"matmul_gflops": mm, "conv_gflops": conv}


def floor_ms(flops: dict[str, int], peaks: dict[str, float]) -> float:
    """Milliseconds that ``flops`` (``count_flops`` output) take at ``peaks`` (``measure_peaks`` output)."""
    return 1e3 * (flops["conv"] / (peaks["conv_gflops"] * 1e9) + flops["matmul"] / (peaks["matmul_gflops"] * 1e9))
