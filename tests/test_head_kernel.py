"""The AMX field-head kernel (src/fields/head_kernel.py) against its references, values and gradients.

The kernel rounds its products' operands to bf16 (as oneDNN does under CPU bf16 autocast), so it is
held to the error of the oneDNN bf16 reference: both are measured against float64 autograd on the same
inputs, and the kernel's relative error may not exceed the reference's by more than half (a wrong
layout, mask, skip or transpose gives errors of order one). The reference (``fast=False``) is checked
against float64 autograd of the explicit formula. Kernel tests skip on CPUs without AMX-BF16.
"""

from __future__ import annotations

import copy

import pytest
import torch
import torch.nn.functional as F

from src.fields import CNNTriplaneBackbone, OffsetFlow, SplatFieldNetwork
from src.fields.head_kernel import (
    BLOCK_ROWS,
    cpu_has_amx,
    head_mlp,
    head_packs,
    heads_mlp,
    pack_in,
    pack_out,
    resolve_head_kernel,
)

amx = pytest.mark.skipif(not cpu_has_amx(), reason="needs a CPU with AMX-BF16 tiles")


def _problem(n: int, k: int, width: int, n_hidden: int, skip_at: int | None, n_out: int, x_dtype: torch.dtype,
             seed: int = 0):
    """A head: x a strided view [N, K], input weights (first, skip), hidden weights, biases, output layer."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, k + 5, generator=g)[:, 2: 2 + k].to(x_dtype)  # rows strided
    a = [torch.randn(width, k, generator=g) * (2.0 / k) ** 0.5 for _ in range(1 + (skip_at is not None))]
    hidden = [torch.randn(width, width, generator=g) * (2.0 / width) ** 0.5 for _ in range(n_hidden)]
    bias = [torch.randn(width, generator=g) * 0.1 for _ in range(n_hidden + 1)]
    reads = [0] + [1 if layer == skip_at else -1 for layer in range(1, n_hidden + 1)]
    w_out, b_out = torch.randn(n_out, width, generator=g) * 0.1, torch.randn(n_out, generator=g) * 0.1
    grad = torch.randn(n, n_out, generator=g)
    return x, a, hidden, bias, reads, w_out, b_out, grad


def _run(problem, mode: str, rows: tuple[int, int] = BLOCK_ROWS) -> list[torch.Tensor]:
    """(y, grads of x, a, hidden, bias, w_out, b_out) by 'kernel', 'onednn' (bf16 reference) or 'float64'."""
    x, a, hidden, bias, reads, w_out, b_out, grad = problem
    dt = torch.float64 if mode == "float64" else None
    params = [t.detach().to(dt or t.dtype).requires_grad_() for t in (x, *a, *hidden, *bias, w_out, b_out)]
    na, nh = len(a), len(hidden)
    x_, a_, h_, b_ = params[0], params[1: 1 + na], params[1 + na: 1 + na + nh], params[1 + na + nh: -2]
    if mode == "float64":
        y = head_mlp(x_, a_, h_, b_, reads, params[-2], params[-1], fast=False)
    else:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            y = head_mlp(x_, a_, h_, b_, reads, params[-2], params[-1], fast=mode == "kernel", block_rows=rows)
    assert y.dtype == (torch.float64 if mode == "float64" else torch.float32)
    (y.double() * grad.double()).sum().backward()
    assert all(p.grad.dtype == p.dtype for p in params)
    return [y.detach().double(), *[p.grad.double() for p in params]]


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@amx
@pytest.mark.parametrize("k,width,n_hidden,skip_at,n_out,x_dtype,rows", [
    (75, 128, 6, 4, 3, torch.bfloat16, BLOCK_ROWS),  # the deform head (8 linears, skip into 4), bf16 input row
    (75, 128, 6, 4, 3, torch.bfloat16, (256, 32)),   # other block sizes
    (75, 64, 3, None, 4, torch.float32, BLOCK_ROWS),  # a 64-wide head, float32 input row
    (40, 32, 0, None, 1, torch.float32, (64, 64)),    # input and output layers only
    (96, 64, 2, 2, 33, torch.float32, BLOCK_ROWS),    # whole input tiles, a skip into the last hidden layer, 33 outputs
    (75, 128, 6, 4, 128, torch.bfloat16, BLOCK_ROWS),  # a flow trunk: 128 features out (a tiled output layer)
])
def test_kernel_as_accurate_as_the_onednn_bf16_reference(k, width, n_hidden, skip_at, n_out, x_dtype, rows):
    problem = _problem(1000 + 13, k, width, n_hidden, skip_at, n_out, x_dtype)  # N not a multiple of any block
    truth = _run(problem, "float64")
    kern = _run(problem, "kernel", rows)
    ref = _run(problem, "onednn")
    names = ["y", "d x", *[f"d A{i}" for i in range(1 + (skip_at is not None))],
             *[f"d W{i + 1}" for i in range(n_hidden)], *[f"d b{i}" for i in range(n_hidden + 1)], "d W_out", "d b_out"]
    for name, got, r, t in zip(names, kern, ref, truth, strict=True):
        e_k, e_r = _rel(got, t), _rel(r, t)
        assert e_k <= 1.5 * e_r + 2e-3, f"{name}: kernel error {e_k:.4f} vs oneDNN bf16 reference {e_r:.4f}"


@amx
def test_kernel_error_is_detected_by_the_comparison():
    """The accuracy rule fails on a wrong kernel: a swapped weight gives an error of order one."""
    problem = _problem(200, 64, 64, 2, None, 3, torch.float32)
    truth = _run(problem, "float64")
    x, a, hidden, *rest = problem
    swapped = _run((x, a, [hidden[0].t().contiguous(), hidden[1]], *rest), "kernel")
    assert _rel(swapped[0], truth[0]) > 0.1


@amx
@pytest.mark.parametrize("x_dtype", [torch.bfloat16, torch.float32])
def test_heads_sharing_an_input_row_sum_their_x_gradients_in_the_kernel(x_dtype):
    """``heads_mlp`` on one input row: each head's output and weight gradients as the head alone, and the row's
    gradient the sum over the heads (added in the kernel, rounded once) held to the oneDNN bf16 reference's
    error against float64; a head whose output is unused contributes nothing."""
    shapes = [(128, 6, 4, 3), (64, 3, None, 1), (64, 3, None, 4), (64, 3, None, 3)]  # deform-, opacity-, rotation-like
    heads = [_problem(700 + 5, 75, *shape, x_dtype, seed=i) for i, shape in enumerate(shapes)]
    x = heads[0][0]

    def run(mode: str, used: int) -> list[torch.Tensor]:
        dt = torch.float64 if mode == "float64" else x.dtype
        xx = x.detach().to(dt).requires_grad_()
        layers, params = [], []
        for _, a, hidden, bias, reads, w_out, b_out, _ in heads:
            ps = [t.detach().to(torch.float64 if mode == "float64" else t.dtype).requires_grad_()
                  for t in (*a, *hidden, *bias, w_out, b_out)]
            na, nh = len(a), len(hidden)
            layers.append((ps[:na], ps[na: na + nh], ps[na + nh: -2], reads, ps[-2], ps[-1]))
            params += ps
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=mode != "float64"):
            ys = heads_mlp(xx, layers, fast=mode == "kernel")
        sum((y.double() * h[-1].double()).sum() for y, h in zip(ys[:used], heads[:used], strict=True)).backward()
        grads = [torch.zeros_like(p) if p.grad is None else p.grad for p in params]
        return [*(y.detach().double() for y in ys), xx.grad.double(), *(g.double() for g in grads)]

    for used in (4, 3):  # every head's output in the loss; the last one's unused
        truth, kern, ref = run("float64", used), run("kernel", used), run("onednn", used)
        for i, (got, r, t) in enumerate(zip(kern, ref, truth, strict=True)):
            if t.norm() == 0:  # the unused head's parameters: no gradient either way
                assert got.norm() == 0 and r.norm() == 0, i
                continue
            e_k, e_r = _rel(got, t), _rel(r, t)
            assert e_k <= 1.5 * e_r + 2e-3, f"output {i}: kernel error {e_k:.4f} vs oneDNN bf16 reference {e_r:.4f}"
        single = _run(heads[0], "kernel")  # the first head alone: its output as in the group
        torch.testing.assert_close(kern[0], single[0], rtol=0, atol=0)


def test_reference_matches_the_formula_in_float64():
    x, a, hidden, bias, reads, w_out, b_out, grad = _problem(77, 27, 32, 3, 2, 4, torch.float64)
    got = _run((x, a, hidden, bias, reads, w_out, b_out, grad), "float64")
    params = [t.detach().double().requires_grad_() for t in (x, *a, *hidden, *bias, w_out, b_out)]
    xd, a0, a1, w1, w2, w3, b0, b1, b2, b3, wo, bo = params
    h = torch.relu(xd @ a0.t() + b0)
    h = torch.relu(h @ w1.t() + b1)
    h = torch.relu(h @ w2.t() + xd @ a1.t() + b2)  # the skip layer (reads = [0, -1, 1, -1])
    h = torch.relu(h @ w3.t() + b3)
    y = h @ wo.t() + bo
    (y * grad).sum().backward()
    for a_, b_ in zip(got, [y.detach(), *[p.grad for p in params]], strict=True):
        torch.testing.assert_close(a_, b_, rtol=1e-10, atol=1e-12)


def test_weight_packs_follow_their_layouts():
    w = torch.randn(64, 32)  # [out, in]
    wb = w.to(torch.bfloat16)
    p_in, p_out = pack_in(w), pack_out(w)
    assert p_in.shape == (16, 64, 2) and p_out.shape == (32, 32, 2)
    assert torch.equal(p_in[5, 7, 1], wb[7, 2 * 5 + 1]) and torch.equal(p_out[5, 7, 1], wb[2 * 5 + 1, 7])


@amx
@pytest.mark.parametrize("over_input", [True, False])
def test_compiled_packs_equal_the_torch_packs(over_input):
    """``head_packs`` (one compiled call per head) equals ``pack_in`` / ``pack_out`` of the stacked weights with the
    input weights zero-padded to 32 columns, bit for bit, from strided views (a column slice, a transpose)."""
    g = torch.Generator().manual_seed(5)
    big = torch.randn(64, 200, generator=g)
    a = [big[:, 10:85], torch.randn(75, 64, generator=g).t(), torch.randn(64, 75, generator=g)]  # [W, K] views
    hidden = [big[:, 100:164], torch.randn(64, 64, generator=g)]
    a[2][0, :3] = torch.tensor([1 + 2 ** -8, 1 + 3 * 2 ** -8, -(1 + 3 * 2 ** -8)])  # ties: round to the even bf16
    pa, ph = head_packs(a, hidden, over_input)
    pack = pack_in if over_input else pack_out
    a_ref = pack(F.pad(torch.stack(a), (0, 96 - 75)))  # [S, ...] with K 75 -> Kp 96
    assert [p.shape for p in pa] == [a_ref.shape[1:]] * 3 and all(p.dtype == torch.bfloat16 for p in pa + ph)
    assert all(torch.equal(p, r) for p, r in zip(pa, a_ref.unbind(0), strict=True))
    assert all(torch.equal(p, r) for p, r in zip(ph, pack(torch.stack(hidden)).unbind(0), strict=True))
    with pytest.raises(RuntimeError, match=r"hidden weight 0 must be a float32 CPU \[64, 64\]"):
        head_packs(a, [hidden[0][:, :32]], over_input)


def test_head_mlp_names_a_wrong_layer_list():
    x, a, hidden, bias, reads, w_out, b_out, _ = _problem(10, 8, 32, 2, None, 3, torch.float32)
    with pytest.raises(ValueError, match="2 hidden layers need 3 biases"):
        head_mlp(x, a, hidden, bias[:2], reads, w_out, b_out, fast=False)


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
    import src.fields.head_kernel as hk

    def failed_build() -> bool:
        raise RuntimeError("Building the CPU extension head_amx failed (no AMX intrinsics)")

    monkeypatch.setattr(hk, "cpu_has_amx", lambda: True)
    monkeypatch.setattr(hk, "head_kernel_ready", failed_build)
    assert hk.resolve_head_kernel("auto", True) is False
    assert "using the oneDNN layers" in caplog.text
    with pytest.raises(RuntimeError, match="head_amx failed"):
        hk.resolve_head_kernel("on", True)


@amx
def test_kernel_rejects_a_width_or_block_it_cannot_tile():
    """A width or a block size that is not a multiple of 32 is one clear error, not a wrong result."""
    x, a, hidden, bias, reads, w_out, b_out, _ = _problem(40, 16, 48, 1, None, 3, torch.float32)
    with pytest.raises(RuntimeError, match="width 48 must be a multiple of 32"):
        head_mlp(x, a, hidden, bias, reads, w_out, b_out)
    x, a, hidden, bias, reads, w_out, b_out, _ = _problem(40, 16, 32, 1, None, 3, torch.float32)
    with pytest.raises(RuntimeError, match="block_rows 48 must be 32, 64"):
        head_mlp(x, a, hidden, bias, reads, w_out, b_out, block_rows=(48, 32))


def _network_errors(head_kernel: bool) -> dict[str, float]:
    """Relative errors of a dynamic network's outputs and of each module's gradient (all its parameters' as one
    vector) in bf16 against its float64 copy on the reference path."""
    torch.manual_seed(0)
    backbone = CNNTriplaneBackbone(plane_channels=8, noise_channels=4, noise_res=6, channels=32, n_up_blocks=2,
                                   resnets_per_block=1, norm_groups=32)
    net = SplatFieldNetwork(backbone=backbone, deform_layers=6, deform_width=64, deform_skips=(3,), color_width=64,
                            color_skips=(2,), scale_width=32, opacity_width=32, rotation_width=32, rotation_skips=(1,),
                            flow_layers=4, flow_width=32, flow_skips=(2,), deform_zero_init=False,
                            rotation_zero_init=False, view_dependent=False, dynamic=True, n_frames=4, rank=2,
                            flow=OffsetFlow(hidden_dim=32), fused=True, autocast_bf16=True, head_kernel=head_kernel)
    with torch.no_grad():  # non-zero residual branches and output layers: every path carries gradient
        for p in net.parameters():
            if p.abs().max() == 0:
                p.normal_(0.0, 0.1)
    ref = copy.deepcopy(net).double()
    ref.fused = False
    g = torch.Generator().manual_seed(0)
    x = torch.rand(517, 3, generator=g) * 1.6 - 0.8
    base = torch.rand(517, 3, generator=g) * 0.05 + 0.01
    res = {}
    for m, dt in ((ref, torch.float64), (net, torch.float32)):
        out = m(x.to(dt), base.to(dt), frame_id=2, time=0.5)
        w = torch.Generator().manual_seed(1)
        loss = sum((out[k].double() * torch.randn(out[k].shape, generator=w, dtype=torch.float64)).sum() for k in out)
        loss.backward()
        grads: dict[str, list[torch.Tensor]] = {}
        for name, p in m.named_parameters():
            grads.setdefault(name.split(".")[0], []).append(p.grad.double().flatten())
        res[dt] = {**{k: v.detach().double() for k, v in out.items()}, **{k: torch.cat(v) for k, v in grads.items()}}
    return {k: _rel(res[torch.float32][k], res[torch.float64][k]) for k in res[torch.float64]}


@amx
def test_network_through_the_kernel_as_accurate_as_the_bf16_layers():
    """Every head of a dynamic network (skips, PE(t) in the biases, ResField weights, a flow trunk) through the
    kernel: outputs and each head's gradient as close to the float64 reference path as the oneDNN bf16 layers.
    (Over 517 splats the ratio of the two bf16 errors spreads 0.7-1.4 between inputs; a wrong wiring gives
    errors of order one.)"""
    kern, dense = _network_errors(True), _network_errors(False)
    heads = {"deform_mlp", "color_mlp", "scale_mlp", "opacity_mlp", "rotation_mlp", "flow_mlp"}
    assert heads <= set(kern) and set(kern) == set(dense)
    for k in dense:
        assert kern[k] <= 2.0 * dense[k] + 2e-3, f"{k}: kernel error {kern[k]:.4f} vs oneDNN bf16 {dense[k]:.4f}"
