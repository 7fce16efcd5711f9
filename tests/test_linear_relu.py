"""The fused hidden layer ReLU(h Wᵀ + b + r): hand-written backward against autograd in float64, and the
oneDNN forward (float32, bfloat16) against the addmm reference, values and gradients."""

from __future__ import annotations

import pytest
import torch

from src.fields import linear_relu as lr
from src.kernels.cpu import cpu_has_native_bf16
from tests.conftest import rel_err


def _inputs(dtype: torch.dtype, n: int = 37, d_in: int = 12, d_out: int = 9, seed: int = 0) -> tuple:
    g = torch.Generator().manual_seed(seed)
    h = torch.randn(n, d_in, generator=g, dtype=torch.float64)
    w = torch.randn(d_out, d_in, generator=g, dtype=torch.float64) / d_in**0.5
    b = torch.randn(d_out, generator=g, dtype=torch.float64) * 0.3
    r = torch.randn(n, d_out, generator=g, dtype=torch.float64) * 0.5
    return tuple(t.to(dtype).requires_grad_(True) for t in (h, w, b, r))


def _reference(h, w, b, r):
    y = h @ w.t()
    if b is not None:
        y = y + b
    if r is not None:
        y = y + r
    return torch.relu(y)


@pytest.mark.parametrize("with_b,with_r", [(True, False), (False, True), (True, True), (False, False)])
def test_backward_matches_autograd_float64(with_b, with_r):
    h, w, b, r = _inputs(torch.float64)
    b, r = (b if with_b else None), (r if with_r else None)
    args = [t for t in (h, w, b, r) if t is not None]
    assert torch.autograd.gradcheck(lambda *a: lr.linear_relu(h, w, b, r, fast=False), tuple(args))
    y = lr.linear_relu(h, w, b, r, fast=False)
    assert torch.allclose(y, _reference(h, w, b, r), atol=1e-12)
    gy = torch.randn_like(y)
    mine = torch.autograd.grad(y, args, gy)
    ref = torch.autograd.grad(_reference(h, w, b, r), args, gy)
    for a, c in zip(mine, ref, strict=True):
        assert torch.allclose(a, c, atol=1e-12)


@pytest.mark.skipif(not torch.backends.mkldnn.is_available(), reason="oneDNN not built into this torch")
@pytest.mark.parametrize("dtype,tol", [
    (torch.float32, 1e-5),
    pytest.param(torch.bfloat16, 2e-2, marks=pytest.mark.skipif(not cpu_has_native_bf16(), reason="no native bf16")),
])
@pytest.mark.parametrize("with_r", [False, True])
def test_onednn_forward_matches_reference(dtype, tol, with_r):
    """oneDNN's fused product + bias (+ r) + ReLU equals addmm + ReLU; the shared backward then agrees too."""
    h, w, b, r = _inputs(dtype, n=300, d_in=64, d_out=48)
    r = r if with_r else None
    b = None if with_r else b  # the skip layers' bias travels inside r
    assert lr._onednn_ok(h)
    args = [t for t in (h, w, b, r) if t is not None]
    outs = {}
    for fast in (True, False):
        y = lr.linear_relu(h, w, b, r, fast=fast)
        assert y.dtype == dtype
        gy = torch.ones_like(y)
        outs[fast] = (y.detach(), *torch.autograd.grad(y, args, gy))
    for a, c in zip(outs[True], outs[False], strict=True):
        assert rel_err(a, c) < tol
    grads = outs[True][1:]
    for t, gr in zip(args, grads, strict=True):
        assert gr.dtype == t.dtype and gr.shape == t.shape


def test_weights_in_float32_under_bfloat16_activations():
    """bf16 activations with float32 master weights: the weight/bias gradients come back in float32."""
    h, _, _, _ = _inputs(torch.bfloat16, n=64, d_in=16, d_out=8)
    _, w, b, _ = _inputs(torch.float32, n=64, d_in=16, d_out=8)
    y = lr.linear_relu(h, w, b)
    assert y.dtype == torch.bfloat16
    gw, gb = torch.autograd.grad(y.float().sum(), (w, b))
    assert gw.dtype == torch.float32 and gb.dtype == torch.float32
    ref_w, ref_b = torch.autograd.grad(_reference(h.float(), w, b, None).sum(), (w, b))
    assert rel_err(gw, ref_w) < 3e-2 and rel_err(gb, ref_b) < 3e-2
