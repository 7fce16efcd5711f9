"""The hidden layers of one field head as one AMX-BF16 kernel (``csrc/head_chain_amx.cpp``).

A head's hidden layers form a chain of equal-width ReLU layers on its first layer's pre-activation
``x0`` [N, W]:

    h_0 = ReLU(x0),   h_l = ReLU(h_{l-1} W_lᵀ + a_l)   (l = 1..L; a_l: bias [W] or skip part [N, W])

``head_chain(x0, weights, adds)`` returns h_L (bf16 [N, W]). Its slow reference is the same chain
through ``linear_relu`` (oneDNN, one layer at a time; hand-written backward checked against autograd in
float64), which ``tests/test_head_chain.py`` compares with this kernel, values and gradients, at bf16
tolerance. Products round to bf16 and accumulate in float32, as oneDNN's do under CPU bf16 autocast;
each gradient comes back in its input's dtype (float32 for the master weights and biases).

The kernel runs only on CPUs with AMX-BF16 tiles (``cpu_has_amx``); ``model.network.head_kernel``
(``auto | on | off``) chooses it (``auto``: wherever the fused heads run in bf16 on such a CPU).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor

from src.fields.linear_relu import linear_relu

AMX_FLAGS = ("amx_bf16", "amx_tile", "avx512_bf16")

log = logging.getLogger(__name__)


@functools.cache
def cpu_has_amx() -> bool:
    """True when /proc/cpuinfo reports AMX-BF16 tiles and AVX512-BF16 (what the kernel is built for)."""
    try:
        words = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return False
    return all(f in words for f in AMX_FLAGS)


@functools.cache
def head_chain_ready() -> bool:
    """True when this process can run the kernel: an AMX CPU, the extension built, tile use permitted."""
    return cpu_has_amx() and bool(_ops().head_chain_available())


def resolve_head_kernel(mode: bool | str, bf16: bool) -> bool:
    """Whether to run the heads' hidden layers through the kernel.

    Args:
        mode: ``"auto"`` (where ``bf16`` and the CPU has AMX; a failed build warns and falls back), ``"on"``/True
            (error if it cannot run), ``"off"``/False.
        bf16: the fused heads run their products in bf16 (``autocast_bf16`` resolved).
    """
    if mode in (False, "off", "false"):
        return False
    if mode in (True, "on", "true"):
        if not cpu_has_amx():
            raise RuntimeError("model.network.head_kernel=on needs a CPU with AMX-BF16 tiles and AVX512-BF16 "
                               f"(/proc/cpuinfo flags {', '.join(AMX_FLAGS)}); use head_kernel=auto or off")
        if not head_chain_ready():
            raise RuntimeError("model.network.head_kernel=on: Linux did not grant this process the AMX tile state "
                               "(arch_prctl ARCH_REQ_XCOMP_PERM); use head_kernel=auto or off")
        return True
    if mode != "auto":
        raise ValueError(f"model.network.head_kernel must be auto, on or off, got {mode!r}")
    if not (bf16 and cpu_has_amx()):
        return False
    try:
        return head_chain_ready()
    except RuntimeError as exc:  # the build failed (e.g. a compiler without AMX intrinsics): the oneDNN layers
        log.warning("head_kernel=auto: the AMX head kernel is unavailable, using the oneDNN layers (%s)", exc)
        return False


def pack_in(w: Tensor) -> Tensor:
    """[out, in] weight -> bf16 pack "VNNI over input" [in/2, out, 2] (p[k, o, j] = W[o, 2k + j])."""
    o, i = w.shape
    return w.detach().to(torch.bfloat16).reshape(o, i // 2, 2).permute(1, 0, 2).contiguous()


def pack_out(w: Tensor) -> Tensor:
    """[out, in] weight -> bf16 pack "VNNI over output" [out/2, in, 2] (p[k, i, j] = W[2k + j, i])."""
    o, i = w.shape
    return w.detach().to(torch.bfloat16).reshape(o // 2, 2, i).permute(0, 2, 1).contiguous()


def _ops():
    """The kernel's ops (``torch.ops.splatfields_cpu``), built and loaded once per process (the compiled-extension
    builder of the CPU rasterizer, ``src/rasterizer/_build.py``, builds it too)."""
    from src.rasterizer._build import load_head_chain_extension

    return load_head_chain_extension()


class _HeadChain(torch.autograd.Function):
    """h_L of the chain; inputs (x0, L, *weights, *adds). See the module docstring."""

    @staticmethod
    def forward(ctx, x0: Tensor, n_layers: int, *params: Tensor) -> Tensor:
        weights, adds = params[:n_layers], params[n_layers:]
        adds_c = [a.detach().float().contiguous() if a.dim() == 1 else a.detach() for a in adds]
        H = _ops().head_chain_forward(x0.detach(), [pack_in(w) for w in weights], adds_c)  # L+1 x [N, W] bf16
        ctx.save_for_backward(*H, *weights)
        ctx.meta = (n_layers, [a.dim() == 2 for a in adds], [a.dtype for a in adds], x0.dtype)
        return H[n_layers]

    @staticmethod
    def backward(ctx, g: Tensor):
        n_layers, is_skip, add_dtypes, x_dtype = ctx.meta
        saved = ctx.saved_tensors
        H, weights = list(saved[: n_layers + 1]), saved[n_layers + 1:]
        skip_dtypes = [dt for dt, s in zip(add_dtypes, is_skip, strict=True) if s]
        bf16_out = x_dtype == torch.bfloat16 and all(dt == torch.bfloat16 for dt in skip_dtypes)  # else float32
        g_x0, g_w, g_add = _ops().head_chain_backward(
            g.contiguous(), H, [pack_out(w) for w in weights], [int(s) for s in is_skip], bf16_out)
        g_ws = [g_w[i].to(w.dtype) for i, w in enumerate(weights)]
        g_adds = [ga.to(dt) for ga, dt in zip(g_add, add_dtypes, strict=True)]
        return (g_x0.to(x_dtype), None, *g_ws, *g_adds)


def head_chain(x0: Tensor, weights: Sequence[Tensor], adds: Sequence[Tensor], fast: bool = True) -> Tensor:
    """h_L = ReLU(... ReLU(ReLU(x0) W_1ᵀ + a_1) ... W_Lᵀ + a_L) -> [N, W].

    Args:
        x0: [N, W] pre-activation of h_0 (float32 or bf16; rows may be strided).
        weights: L weights [W, W] ([out, in], float32 masters).
        adds: L tensors: a bias [W] or a skip layer's input part [N, W].
        fast: the AMX kernel (bf16 output; needs ``head_chain_ready()``); False: the ``linear_relu`` reference
            in x0's dtype (under autocast, bf16 products as the kernel).
    """
    if not fast:
        h = torch.relu(x0)
        for w, a in zip(weights, adds, strict=True):
            h = linear_relu(h, w, a, None) if a.dim() == 1 else linear_relu(h, w, None, a)
        return h
    return _HeadChain.apply(x0, len(weights), *weights, *adds)
