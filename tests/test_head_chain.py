"""The AMX head-chain kernel (src/fields/head_chain.py) against its references, values and gradients.

The kernel rounds its products' operands to bf16 (as oneDNN does under CPU bf16 autocast), so it is
held to the error of the oneDNN bf16 chain: both are measured against float64 autograd on the same
inputs, and the kernel's relative error may not exceed the oneDNN chain's by more than half (a wrong
layout, mask or transpose gives errors of order one). The chain reference (``fast=False``) is checked
against float64 autograd exactly. Kernel tests skip on CPUs without AMX-BF16.
"""

from __future__ import annotations

import pytest
import torch

from src.fields.head_chain import cpu_has_amx, head_chain, pack_in, pack_out, resolve_head_kernel

amx = pytest.mark.skipif(not cpu_has_amx(), reason="needs a CPU with AMX-BF16 tiles")


def _problem(n: int, width: int, n_layers: int, skip_at: int | None, x_dtype: torch.dtype, seed: int = 0):
    """Inputs of a chain: x0 a strided view, biases, one skip layer's part a strided view."""
    g = torch.Generator().manual_seed(seed)
    wide = torch.randn(n, 3 * width, generator=g)  # [N, 3W]: x0 and the skip part are column blocks of it
    ws = [torch.randn(width, width, generator=g) * (2.0 / width) ** 0.5 for _ in range(n_layers)]
    bs = [torch.randn(width, generator=g) * 0.1 for _ in range(n_layers)]
    grad = torch.randn(n, width, generator=g)
    return wide.to(x_dtype), ws, bs, grad, skip_at


def _run(wide, ws, bs, grad, skip_at, mode: str):
    """(h_L, grads of wide, weights, biases) by 'kernel', 'onednn' (bf16 reference) or 'float64' autograd."""
    dt = torch.float64 if mode == "float64" else None
    wide = wide.detach().to(dt or wide.dtype).requires_grad_()
    ws = [w.detach().to(dt or w.dtype).requires_grad_() for w in ws]
    bs = [b.detach().to(dt or b.dtype).requires_grad_() for b in bs]
    width = ws[0].shape[0]
    x0 = wide[:, :width]
    adds = [wide[:, 2 * width:] if i == skip_at else b for i, b in enumerate(bs)]
    if mode == "float64":
        h = torch.relu(x0)
        for w, a in zip(ws, adds, strict=True):
            h = torch.relu(h @ w.t() + a)
    else:
        x_in = x0 if mode == "kernel" else x0.to(torch.bfloat16)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            h = head_chain(x_in, ws, adds, fast=mode == "kernel")
    (h.double() * grad.double()).sum().backward()
    return [h.detach().double(), wide.grad.double(), *[w.grad.double() for w in ws],
            *[b.grad.double() for i, b in enumerate(bs) if i != skip_at]]


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@amx
@pytest.mark.parametrize("width,n_layers,skip_at,x_dtype", [
    (128, 6, 3, torch.float32),   # the deform head's hidden layers (skip before linear 4)
    (64, 3, 2, torch.bfloat16),   # a 64-wide head, bf16 input as under autocast
    (32, 1, None, torch.float32),
])
def test_kernel_as_accurate_as_the_onednn_bf16_chain(width, n_layers, skip_at, x_dtype):
    problem = _problem(1000 + 13, width, n_layers, skip_at, x_dtype)  # N not a multiple of the 32-row block
    truth = _run(*problem, mode="float64")
    kern = _run(*problem, mode="kernel")
    ref = _run(*problem, mode="onednn")
    names = ["h_L", "d wide", *[f"d W{i}" for i in range(n_layers)], *["d b"] * (n_layers - (skip_at is not None))]
    for name, k, r, t in zip(names, kern, ref, truth, strict=True):
        e_k, e_r = _rel(k, t), _rel(r, t)
        assert e_k <= 1.5 * e_r + 2e-3, f"{name}: kernel error {e_k:.4f} vs oneDNN bf16 chain {e_r:.4f}"


@amx
def test_kernel_error_is_detected_by_the_comparison():
    """The accuracy rule fails on a wrong kernel: a swapped weight pack gives an error of order one."""
    problem = _problem(200, 64, 2, None, torch.float32)
    truth = _run(*problem, mode="float64")
    wide, ws, bs, grad, skip_at = problem
    swapped = _run(wide, [ws[0].t().contiguous(), ws[1]], bs, grad, skip_at, mode="kernel")
    assert _rel(swapped[0], truth[0]) > 0.1


def test_chain_reference_matches_autograd_in_float64():
    wide, ws, bs, grad, skip_at = _problem(77, 32, 3, 1, torch.float64)
    truth = _run(wide, ws, bs, grad, skip_at, mode="float64")
    wide = wide.detach().requires_grad_()
    ws_ = [w.detach().double().requires_grad_() for w in ws]
    bs_ = [b.detach().double().requires_grad_() for b in bs]
    adds = [wide[:, 64:] if i == skip_at else b for i, b in enumerate(bs_)]
    h = head_chain(wide[:, :32], ws_, adds, fast=False)
    (h * grad.double()).sum().backward()
    got = [h.detach(), wide.grad, *[w.grad for w in ws_], *[b.grad for i, b in enumerate(bs_) if i != skip_at]]
    for a, b in zip(got, truth, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_weight_packs_follow_their_layouts():
    w = torch.randn(64, 32)  # [out, in]
    wb = w.to(torch.bfloat16)
    p_in, p_out = pack_in(w), pack_out(w)
    assert p_in.shape == (16, 64, 2) and p_out.shape == (32, 32, 2)
    assert torch.equal(p_in[5, 7, 1], wb[7, 2 * 5 + 1]) and torch.equal(p_out[5, 7, 1], wb[2 * 5 + 1, 7])


def test_resolve_head_kernel_modes():
    assert resolve_head_kernel("off", True) is False
    assert resolve_head_kernel(False, True) is False
    if not cpu_has_amx():
        assert resolve_head_kernel("auto", True) is False
        with pytest.raises(RuntimeError, match="AMX-BF16"):
            resolve_head_kernel("on", True)
    else:
        assert resolve_head_kernel("auto", False) is False  # float32 heads: the kernel is bf16 only
    with pytest.raises(ValueError, match="auto, on or off"):
        resolve_head_kernel("sometimes", True)


def test_auto_falls_back_when_the_kernel_cannot_be_built(monkeypatch, caplog):
    import src.fields.head_chain as hc

    def failed_build() -> bool:
        raise RuntimeError("Building the CPU extension head_chain failed (no AMX intrinsics)")

    monkeypatch.setattr(hc, "cpu_has_amx", lambda: True)
    monkeypatch.setattr(hc, "head_chain_ready", failed_build)
    assert hc.resolve_head_kernel("auto", True) is False
    assert "using the oneDNN layers" in caplog.text
    with pytest.raises(RuntimeError, match="head_chain failed"):
        hc.resolve_head_kernel("on", True)


@amx
def test_kernel_rejects_a_width_it_cannot_tile():
    """A width that is not a multiple of 32 is one clear error, not a wrong result."""
    x0, w, b = torch.randn(40, 48), torch.randn(48, 48), torch.randn(48)
    with pytest.raises(RuntimeError, match="width 48 must be a multiple of 32"):
        head_chain(x0, [w], [b])
