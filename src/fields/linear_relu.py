"""One hidden layer of a field head, ``y = ReLU(h Wᵀ + b [+ r])``, with a hand-written backward.

Autograd's own graph of ``relu(linear(h, W, b))`` under CPU bf16 autocast costs, per layer, a
bias copy into the product's output, an out-of-place ReLU, casts, and in the backward a separate
ReLU mask pass: on a [10 k, 128] activation these elementwise passes cost as much as the products
(docs/benchmarks.md). This layer does the forward as ONE oneDNN call with the bias and the ReLU in
the product's epilogue (``torch.ops.mkldnn._linear_pointwise``; the skip layers' precomputed input
part ``r`` is a binary "add" post-op, then an in-place ReLU) and keeps only the output ``y`` for
the backward, whose mask is ``y > 0``:

    g' = g · [y > 0]     ∂h = g' W     ∂W = g'ᵀ h     ∂b = Σ_rows g'     ∂r = g'

The products run in the dtype of ``h`` (bf16 under autocast: the weights are cast, their
gradients returned in the weights' dtype). ``fast=False`` (and any device or dtype without oneDNN)
computes the forward as ``addmm`` + in-place ReLU instead, with the same backward; the tests check
the backward against autograd in float64 and the oneDNN forward against the reference.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from src.kernels.cpu import cpu_has_native_bf16


def _onednn_ok(h: Tensor) -> bool:
    """True when oneDNN's fused linear serves ``h``: CPU, mkldnn built, float32 or (native) bfloat16."""
    if h.device.type != "cpu" or not torch.backends.mkldnn.is_available():
        return False
    return h.dtype == torch.float32 or (h.dtype == torch.bfloat16 and cpu_has_native_bf16())


class _LinearReLU(torch.autograd.Function):
    """``ReLU(h Wᵀ + b + r)``; b and r may be None. See the module docstring."""

    @staticmethod
    def forward(ctx, h: Tensor, w: Tensor, b: Tensor | None, r: Tensor | None, fast: bool) -> Tensor:
        dt = h.dtype
        wc = w.to(dt).contiguous()  # [out, in]
        bc = b.to(dt) if b is not None else None  # [out]
        if fast and _onednn_ok(h) and h.is_contiguous():
            if r is None:
                y = torch.ops.mkldnn._linear_pointwise(h, wc, bc, "relu", [], "")  # [N, out]
            else:
                y = torch.ops.mkldnn._linear_pointwise.binary(h, r.to(dt).contiguous(), wc, bc, "add")
                y.relu_()
        else:
            if r is None:
                y = torch.mm(h, wc.t()) if bc is None else torch.addmm(bc, h, wc.t())
            else:
                y = torch.addmm(r.to(dt), h, wc.t())
                if bc is not None:
                    y += bc
            y.relu_()
        ctx.save_for_backward(h, wc, y)
        ctx.meta = (w.dtype, None if b is None else b.dtype, None if r is None else r.dtype)
        return y

    @staticmethod
    def backward(ctx, g: Tensor):
        h, wc, y = ctx.saved_tensors
        w_dt, b_dt, r_dt = ctx.meta
        g = torch.ops.aten.threshold_backward(g.to(y.dtype), y, 0)  # g · [y > 0], [N, out]
        gh = torch.mm(g, wc) if ctx.needs_input_grad[0] else None  # [N, in]
        gw = torch.mm(g.t(), h).to(w_dt) if ctx.needs_input_grad[1] else None  # [out, in]
        gb = g.sum(0).to(b_dt) if b_dt is not None and ctx.needs_input_grad[2] else None  # [out]
        gr = g.to(r_dt) if r_dt is not None and ctx.needs_input_grad[3] else None  # [N, out]
        return gh, gw, gb, gr, None


def linear_relu(h: Tensor, w: Tensor, b: Tensor | None = None, r: Tensor | None = None,
                fast: bool = True) -> Tensor:
    """ReLU(h Wᵀ + b + r) for h [N, in], W [out, in], b [out] or None, r [N, out] or None -> [N, out].

    Runs in h's dtype (W, b, r cast to it; their gradients come back in their own dtypes).
    ``fast``: the oneDNN fused forward where it applies (CPU float32/bf16); False: addmm + ReLU.
    Under ``torch.compile`` (``trainer.compile``) it is autograd's ``relu(linear(h, W, b) + r)``, which the
    compiler fuses itself (inductor cannot lower oneDNN's fused linear on weights that train).
    """
    if torch.compiler.is_compiling():
        y = F.linear(h, w.to(h.dtype), None if b is None else b.to(h.dtype))  # [N, out]
        return F.relu(y if r is None else y + r.to(h.dtype))
    return _LinearReLU.apply(h, w, b, r, fast)
