"""The compiled tri-plane sampler (src/fields/triplane_sample.py) equals grid_sample, values and gradients."""

from __future__ import annotations

import pytest
import torch

from src.fields.triplane_sample import sample_planes, sampler_ready

compiled = pytest.mark.skipif(not sampler_ready(), reason="the sampler's extension could not be built here")


def _inputs(n: int, c: int, r: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    planes = torch.randn(3, c, r, r, generator=g)
    uv = torch.rand(3, n, 2, generator=g) * 2.4 - 1.2  # some reads outside the planes (zero padding)
    uv[0, :4] = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0], [1.0 - 1.0 / r, -1.0 + 1.0 / r]])  # edges, centres
    grad = torch.randn(n, 3 * c, generator=g)
    return planes, uv, grad


def _run(planes: torch.Tensor, uv: torch.Tensor, grad: torch.Tensor, fast: bool) -> tuple[torch.Tensor, torch.Tensor]:
    p = planes.detach().clone().requires_grad_()
    out = sample_planes(p, uv, fast=fast)
    (out * grad.to(out.dtype)).sum().backward()
    return out.detach(), p.grad


@compiled
@pytest.mark.parametrize("n,c,r", [(1000 + 7, 16, 40), (33, 5, 7)])
def test_kernel_equals_grid_sample_in_float64(n, c, r):
    planes, uv, grad = _inputs(n, c, r)
    out, g_planes = _run(planes, uv, grad, fast=True)
    ref, g_ref = _run(planes.double(), uv.double(), grad.double(), fast=False)
    torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(g_planes.double(), g_ref, rtol=1e-5, atol=1e-4)


def test_points_with_gradient_take_grid_sample():
    """The kernel gives no gradient to the points; points that need one are read by grid_sample."""
    planes, uv, grad = _inputs(50, 4, 8)
    uv = uv.requires_grad_()
    out = sample_planes(planes, uv)
    (out * grad).sum().backward()
    assert uv.grad is not None and uv.grad.abs().sum() > 0


@compiled
def test_kernel_names_mismatched_shapes():
    planes, uv, _ = _inputs(10, 4, 8)
    with pytest.raises(RuntimeError, match=r"expected planes \[P, C, R, R\] and uv \[P, N, 2\]"):
        torch.ops.splatfields_cpu.triplane_sample_forward(planes, uv[:2].contiguous())
