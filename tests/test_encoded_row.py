"""The compiled input row [f, PE(x)] (src/fields/encoded_row.py) equals the torch row, values and gradients."""

from __future__ import annotations

import pytest
import torch

from src.fields.encoded_row import encoded_row, row_op_ready
from src.fields.encoding import PositionalEncoding

compiled = pytest.mark.skipif(not row_op_ready(), reason="the input-row op's extension could not be built here")


def _inputs(n: int, f_dim: int, d: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(n, f_dim, generator=g)
    x = torch.rand(n, d, generator=g) * 4 - 2  # beyond [-1, 1]: the high levels wrap several times
    x[:3] = torch.tensor([0.0, 1e-4, -1.0])[:, None]
    return f, x


def _run(f: torch.Tensor, x: torch.Tensor, pe: PositionalEncoding, grad: torch.Tensor, fast: bool):
    f, x = f.detach().clone().requires_grad_(), x.detach().clone().requires_grad_()
    row = encoded_row(f, x, pe, fast=fast)
    (row * grad.to(row.dtype)).sum().backward()
    return row.detach(), f.grad, x.grad


@compiled
@pytest.mark.parametrize("n,f_dim,d,levels", [(1000 + 7, 48, 3, 4), (33, 5, 2, 1), (17, 0, 3, 6)])
def test_op_equals_the_torch_row_in_float64(n, f_dim, d, levels):
    pe = PositionalEncoding(levels)
    f, x = _inputs(n, f_dim, d)
    grad = torch.randn(n, f_dim + pe.out_dim(d), generator=torch.Generator().manual_seed(1))
    row, g_f, g_x = _run(f, x, pe, grad, fast=True)
    ref, g_f_ref, g_x_ref = _run(f.double(), x.double(), pe.double(), grad.double(), fast=False)
    assert row.dtype == torch.float32 and row.shape == ref.shape
    torch.testing.assert_close(row.double(), ref, rtol=1e-6, atol=1e-6)
    if f_dim:  # (without features the torch row is PE alone: f has no gradient there)
        torch.testing.assert_close(g_f.double(), g_f_ref, rtol=0, atol=0)  # a copy of the row's gradient
    torch.testing.assert_close(g_x.double(), g_x_ref, rtol=1e-5, atol=1e-5)


@compiled
@pytest.mark.parametrize("d", [3, 2])  # 3: the op's unrolled path for positions; 2: its general path
def test_bf16_row_is_the_torch_row_bit_for_bit(d):
    """The op's sines and cosines are ATen's on the same x 2^l and it rounds to bf16 to nearest even, as torch does:
    the row equals ``input_row(f, pe(x))`` bit for bit (ties, infinities, subnormals; NaN where torch's is)."""
    pe = PositionalEncoding(4)
    f, x = _inputs(300, 48, d, seed=3)
    ties = torch.tensor([1 + 2 ** -8, 1 + 3 * 2 ** -8, -(1 + 2 ** -8), float("inf"), float("nan"), 2 ** -130])
    x[3: 3 + len(ties), 0] = ties  # halfway between two bf16 values: round to the even one
    row = encoded_row(f.bfloat16(), x, pe, fast=True)
    ref = encoded_row(f.bfloat16(), x, pe, fast=False)
    torch.testing.assert_close(row.float(), ref.float(), rtol=0, atol=0, equal_nan=True)
    assert row.isnan().any()


@compiled
def test_bf16_row_rounds_as_the_torch_row():
    """In bf16 (the fused heads under autocast) the op rounds each value as ``pe(x).to(bf16)`` does."""
    pe = PositionalEncoding(4)
    f, x = _inputs(500, 48, 3)
    grad = torch.randn(500, 48 + pe.out_dim(3), generator=torch.Generator().manual_seed(2))
    row, g_f, g_x = _run(f.bfloat16(), x, pe, grad, fast=True)
    ref, g_f_ref, g_x_ref = _run(f.bfloat16(), x, pe, grad, fast=False)
    assert row.dtype == g_f.dtype == torch.bfloat16 and g_x.dtype == torch.float32
    mismatch = (row.float() != ref.float()).float().mean().item()
    assert mismatch < 0.01  # float32 sin/cos vs double: a rounding boundary now and then
    torch.testing.assert_close(row.float(), ref.float(), rtol=2 ** -8, atol=2 ** -8)
    torch.testing.assert_close(g_f, g_f_ref, rtol=0, atol=0)
    torch.testing.assert_close(g_x, g_x_ref, rtol=1e-3, atol=1e-3)


@compiled
def test_gradient_only_where_asked():
    pe = PositionalEncoding(4)
    f, x = _inputs(40, 8, 3)
    f.requires_grad_(True)
    encoded_row(f, x, pe).square().sum().backward()  # x without gradient: the query points of the deform head
    assert f.grad is not None and x.grad is None
    torch.testing.assert_close(f.grad, 2 * f.detach())


def test_reference_where_the_op_does_not_apply():
    """float64 points, no input in the encoding, or ``fast=False``: the torch row."""
    f, x = _inputs(20, 4, 3)
    cases = [(PositionalEncoding(4), x.double(), True), (PositionalEncoding(2, include_input=False), x, True),
             (PositionalEncoding(4), x, False)]
    for pe, xx, fast in cases:
        row = encoded_row(f.to(xx.dtype), xx, pe, fast=fast)
        torch.testing.assert_close(row, torch.cat([f.to(xx.dtype), pe(xx)], dim=1))
