"""A field head's layers as one AMX-BF16 kernel (``csrc/head_amx.cpp``).

A head of the fused path reads its input row ``x = [f, PE(x)]`` [N, K] at its first linear and at each
skip linear, runs equal-width ReLU layers and ends in a linear output:

    h_0 = ReLU(x A_0ᵀ + b_0),   h_l = ReLU(h_{l-1} W_lᵀ [+ x A_sᵀ at a skip layer] + b_l)   (l = 1..L),
    y   = h_L W_outᵀ + b_out                                                               [N, O] float32.

``head_mlp(x, a, hidden, bias, reads_x, w_out, b_out)`` returns y. With ``fast=False`` it is the same
function through oneDNN, one layer at a time (the slow reference; under autocast its products run in
bf16 as the kernel's do), which ``tests/test_head_kernel.py`` compares with the kernel, values and
gradients, both against float64 autograd. The kernel's products round their operands to bf16 and
accumulate in float32, as oneDNN's do under CPU bf16 autocast; a narrow output layer (fewer than
``TILE_OUTPUT`` values: a head's colour, opacity, scale or rotation) runs in float32 on the bf16 h_L, as the
fused path's float32 output layers do, a wide one (a flow trunk's features) as one more bf16 product. Every
gradient comes back in its input's dtype.
``heads_mlp(x, heads)`` runs several heads that read the same row as one autograd function: the kernel's
backward adds each head's row gradient into one tensor, a block at a time in cache.

The kernel runs only on CPUs with AMX-BF16 tiles (``cpu_has_amx``); ``model.network.head_kernel``
(``auto | on | off``) chooses it (``auto``: wherever the fused heads run in bf16 on such a CPU).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

AMX_FLAGS = ("amx_bf16", "amx_tile", "avx512_bf16")
# splats per block of the kernel's forward and backward (32, 64, ..., 256): larger blocks reload the backward's
# float32 weight-gradient tiles less often (measured 0.80x the backward's time at 128 against 32, one process)
# and the forward's products gain nothing from them (32: 0.95x the forward's time at 128)
BLOCK_ROWS = (32, 128)
# outputs from which the kernel's output layer is a bf16 tile product (csrc kTileOutput)
TILE_OUTPUT = 32

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
def head_kernel_ready() -> bool:
    """True when this process can run the kernel: an AMX CPU, the extension built, tile use permitted."""
    return cpu_has_amx() and bool(_ops().head_available())


def resolve_head_kernel(mode: bool | str, bf16: bool) -> bool:
    """Whether to run each head's layers through the kernel.

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
        if not head_kernel_ready():
            raise RuntimeError("model.network.head_kernel=on: Linux did not grant this process the AMX tile state "
                               "(arch_prctl ARCH_REQ_XCOMP_PERM); use head_kernel=auto or off")
        return True
    if mode != "auto":
        raise ValueError(f"model.network.head_kernel must be auto, on or off, got {mode!r}")
    if not (bf16 and cpu_has_amx()):
        return False
    try:
        return head_kernel_ready()
    except RuntimeError as exc:  # the build failed (e.g. a compiler without AMX intrinsics): the oneDNN layers
        log.warning("head_kernel=auto: the AMX head kernel is unavailable, using the oneDNN layers (%s)", exc)
        return False


def pack_in(w: Tensor) -> Tensor:
    """[..., out, in] weight(s) -> bf16 pack "VNNI over input" [..., in/2, out, 2] (p[k, o, j] = W[o, 2k + j])."""
    *lead, o, i = w.shape
    return w.detach().to(torch.bfloat16).reshape(*lead, o, i // 2, 2).transpose(-3, -2).contiguous()


def pack_out(w: Tensor) -> Tensor:
    """[..., out, in] weight(s) -> bf16 pack "VNNI over output" [..., out/2, in, 2] (p[k, i, j] = W[2k + j, i])."""
    *lead, o, i = w.shape
    return w.detach().to(torch.bfloat16).reshape(*lead, o // 2, 2, i).transpose(-2, -1).contiguous()


def head_packs(a: Sequence[Tensor], hidden: Sequence[Tensor], over_input: bool) -> tuple[list[Tensor], list[Tensor]]:
    """A head's bf16 weight packs for the kernel, one compiled call: ``a`` [W, K] float32 input weights (zero-padded
    to Kp), ``hidden`` [W, W] float32 (any strides). ``over_input``: the forward's packs, ``pack_in`` of each (inputs
    [Kp/2, W, 2], hidden [W/2, W, 2]); else the backward's, ``pack_out`` ([W/2, Kp, 2], [W/2, W, 2])."""
    pa, ph = _ops().head_pack(list(a), list(hidden), over_input)
    return list(pa.unbind(0)), list(ph.unbind(0))


def _ops():
    """The kernel's ops (``torch.ops.splatfields_cpu``), built and loaded once per process (the compiled-extension
    builder of the CPU rasterizer, ``src/kernels/build.py``, builds it too)."""
    from src.kernels.build import load_head_extension

    return load_head_extension()


class _Heads(torch.autograd.Function):
    """y of each head of a group that reads one input row x; inputs (x, metas, *params of head 0, *params of
    head 1, ...), each head's params (*a, *hidden, *bias, w_out, b_out) and meta (n_a, L, reads_x, block_rows).
    The backward adds every head's x gradient into one tensor inside the kernel (no sum of [N, K] tensors)."""

    @staticmethod
    def forward(ctx, x: Tensor, metas: tuple[tuple[int, int, tuple[int, ...], tuple[int, int]], ...],
                *params: Tensor) -> tuple[Tensor, ...]:
        ys, saved, spans, k = [], [x], [], 0
        for n_a, n_h, reads_x, rows in metas:
            p = params[k: k + n_a + 2 * n_h + 3]
            k += len(p)
            a, hidden, bias = p[:n_a], p[n_a: n_a + n_h], p[n_a + n_h: n_a + 2 * n_h + 1]
            w_out, b_out = p[-2], p[-1]
            bias_all = torch.stack([b.detach().float() for b in bias])  # [L + 1, W]
            w_out32 = w_out.detach().float().contiguous()  # [O, W]
            a32, h32 = [w.detach().float() for w in a], [w.detach().float() for w in hidden]  # [W, K] / [W, W] each
            a_packs, h_packs = head_packs(a32, h32, over_input=True)
            y, H = _ops().head_forward(x.detach(), a_packs, h_packs, bias_all, list(reads_x), w_out32,
                                       b_out.detach().float().contiguous(), rows[0])
            ys.append(y)
            spans.append((len(saved), len(p)))
            saved += [w_out32, *H, *a32, *h32]  # the weights as they came (views: packed again for the backward)
        ctx.save_for_backward(*saved)
        ctx.meta = (metas, spans, [p.dtype for p in params])
        return tuple(ys)

    @staticmethod
    def backward(ctx, *g_ys: Tensor | None):
        metas, spans, dtypes = ctx.meta
        x, *_ = saved = ctx.saved_tensors
        g_x, grads = None, []
        for (n_a, n_h, reads_x, rows), (start, n_params), g_y in zip(metas, spans, g_ys, strict=True):
            if g_y is None:  # this head's output is unused: no gradient from it
                grads += [None] * n_params
                continue
            w_out32 = saved[start]
            H = saved[start + 1: start + n_h + 2]
            weights = saved[start + n_h + 2: start + 2 * n_h + 2 + n_a]  # a [W, K] x S, then hidden [W, W] x L
            a_packs, h_packs = head_packs(weights[:n_a], weights[n_a:], over_input=False)
            g_x, g_a, g_w, g_b, g_wo, g_bo = _ops().head_backward(
                g_y.float().contiguous(), x, list(H), a_packs, h_packs, list(reads_x), w_out32, rows[1], g_x)
            k = x.shape[1]
            grads += [*g_a[:, :, :k].unbind(0), *g_w.unbind(0), *g_b.unbind(0), g_wo, g_bo]
        grads = [g if g is None else g.to(dt) for g, dt in zip(grads, dtypes, strict=True)]
        return (g_x, None, *grads)


HeadLayers = tuple[Sequence[Tensor], Sequence[Tensor], Sequence[Tensor], Sequence[int], Tensor, Tensor]
"""One head's layers as ``head_mlp`` takes them: (a, hidden, bias, reads_x, w_out, b_out)."""


def heads_mlp(x: Tensor, heads: Sequence[HeadLayers], fast: bool = True,
              block_rows: tuple[int, int] = BLOCK_ROWS) -> list[Tensor]:
    """``[head_mlp(x, *h, fast) for h in heads]``: the heads of a group that read the same input row, their x
    gradients summed inside the kernel's backward (fast). Each output [N, O_h] float32."""
    for _, hidden, bias, reads_x, _, _ in heads:
        if reads_x[0] != 0 or len(reads_x) != len(hidden) + 1 or len(bias) != len(hidden) + 1:
            raise ValueError(f"head_mlp: {len(hidden)} hidden layers need {len(hidden) + 1} biases and reads_x "
                             f"starting at 0, got {len(bias)} and {list(reads_x)}")
    if not fast:
        return [_reference(x, *h) for h in heads]
    rows = (int(block_rows[0]), int(block_rows[1]))
    metas = tuple((len(a), len(hidden), tuple(int(r) for r in reads_x), rows) for a, hidden, _, reads_x, _, _ in heads)
    params = [t for a, hidden, bias, _, w_out, b_out in heads for t in (*a, *hidden, *bias, w_out, b_out)]
    return list(_Heads.apply(x, metas, *params))


def _reference(x: Tensor, a: Sequence[Tensor], hidden: Sequence[Tensor], bias: Sequence[Tensor],
               reads_x: Sequence[int], w_out: Tensor, b_out: Tensor) -> Tensor:
    """``head_mlp`` through oneDNN, one layer at a time (bf16 products under autocast, the output layer in the
    masters' dtype)."""
    h = torch.relu(F.linear(x, a[0], bias[0]))  # [N, W]
    for l, w in enumerate(hidden, start=1):
        z = F.linear(h, w, bias[l])
        if reads_x[l] >= 0:
            z = z + F.linear(x, a[reads_x[l]])
        h = torch.relu(z)
    if w_out.shape[0] >= TILE_OUTPUT:  # a wide output: one more product (bf16 under autocast), in float32
        return F.linear(h, w_out, b_out).to(torch.promote_types(w_out.dtype, torch.float32))
    with torch.autocast(x.device.type, enabled=False):  # in the masters' dtype (float32; float64 in checks)
        return F.linear(h.to(w_out.dtype), w_out, b_out)


def head_mlp(x: Tensor, a: Sequence[Tensor], hidden: Sequence[Tensor], bias: Sequence[Tensor],
             reads_x: Sequence[int], w_out: Tensor, b_out: Tensor, fast: bool = True,
             block_rows: tuple[int, int] = BLOCK_ROWS) -> Tensor:
    """y = h_L W_outᵀ + b_out of one head (module docstring) -> [N, O] float32.

    Args:
        x: [N, K] input row (float32 or bf16; rows may be strided).
        a: input weights [W, K]: the first layer's, then each skip layer's ([out, in], float32 masters).
        hidden: L weights [W, W] of layers 1..L (at a skip layer: the part that reads h).
        bias: L + 1 biases [W] of layers 0..L.
        reads_x: L + 1 indices into ``a``: the input weight layer l adds (-1: none; layer 0 reads ``a[0]``).
        w_out, b_out: the output layer, [O, W] and [O].
        fast: the AMX kernel (needs ``head_kernel_ready()``); False: the oneDNN reference, one layer at a
            time (bf16 products under autocast, the output layer in the masters' dtype).
        block_rows: splats per block of the kernel's forward and backward (each 32, 64, ..., 256).
    """
    return heads_mlp(x, [(a, hidden, bias, reads_x, w_out, b_out)], fast, block_rows)[0]
