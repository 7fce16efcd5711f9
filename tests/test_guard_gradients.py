"""The divergence guard's gradient check: one fused test, the same verdict as a per-parameter test."""

from __future__ import annotations

import math

import pytest
import torch

from src.trainer.guard import DivergenceError, DivergenceGuard


def _params(*grads: torch.Tensor | None) -> list[torch.nn.Parameter]:
    ps = []
    for g in grads:
        p = torch.nn.Parameter(torch.zeros(g.shape, dtype=g.dtype) if g is not None else torch.zeros(2))
        p.grad = g
        ps.append(p)
    return ps


def _reference_ok(params) -> bool:
    return all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in params)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_entry_fails_and_names_its_tensor(bad):
    g = torch.randn(4, 3)
    g[2, 1] = bad
    params = _params(torch.randn(5), None, g, torch.randn(2, 2))
    assert not _reference_ok(params)
    with pytest.raises(DivergenceError, match=r"non-finite gradient \(shape \(4, 3\)\) at iteration 7"):
        DivergenceGuard().check_gradients(params, 7)


def test_finite_gradients_pass_even_near_the_float32_limit():
    params = _params(torch.full((3,), 3.0e38), torch.tensor([-3.0e38, 1.0]), torch.zeros(0), None,
                     torch.randn(6, dtype=torch.float64))
    assert _reference_ok(params)
    DivergenceGuard().check_gradients(params, 0)  # no overflow of a sum of squares: max |g| is used
    DivergenceGuard().check_gradients(_params(None, None), 0)  # no gradient at all


def test_switched_off_it_checks_nothing():
    DivergenceGuard(check_grads=False).check_gradients(_params(torch.tensor([math.nan])), 0)
