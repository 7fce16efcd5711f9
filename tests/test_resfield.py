"""ResFieldLinear: static equivalence, per-frame weights, parameter count, interpolation."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from src.fields.resfield import ResFieldLinear


@pytest.mark.parametrize("rank,n_frames", [(0, 0), (0, 10), (4, 0)])
def test_static_equals_nn_linear(rank, n_frames):
    torch.manual_seed(0)
    layer = ResFieldLinear(7, 5, rank=rank, n_frames=n_frames)
    ref = nn.Linear(7, 5)
    ref.load_state_dict(layer.state_dict())  # same keys: weight, bias only
    x = torch.randn(11, 7)
    assert torch.equal(layer(x), ref(x))
    assert torch.equal(layer(x, frame_id=3, time=0.5), ref(x))
    assert layer.extra_params() == 0
    assert sum(p.numel() for p in layer.parameters()) == 7 * 5 + 5


def test_parameter_count_formula():
    layer = ResFieldLinear(13, 9, rank=6, n_frames=20)
    base = 13 * 9 + 9
    total = sum(p.numel() for p in layer.parameters())
    assert layer.extra_params() == 6 * (9 * 13) + 20 * 6
    assert total - base == layer.extra_params()
    assert layer.coefficients.shape == (20, 6) and layer.matrices.shape == (6, 9 * 13)
    # both factors 0.01·randn
    assert 0.003 < layer.matrices.std().item() < 0.03


def test_frames_have_different_weights_and_matching_formula():
    torch.manual_seed(1)
    layer = ResFieldLinear(6, 4, rank=3, n_frames=5)
    x = torch.randn(8, 6)
    w0, w3 = layer.weight_at(frame_id=0), layer.weight_at(frame_id=3)
    assert not torch.allclose(w0, w3)
    assert not torch.allclose(layer(x, frame_id=0), layer(x, frame_id=3))
    # W_t = W + Σ_r c[t, r] M_r; bias not time-dependent
    manual = layer.weight + sum(layer.coefficients[3, r] * layer.matrices[r].view(4, 6) for r in range(3))
    assert torch.allclose(w3, manual, atol=1e-7)
    assert torch.allclose(layer(x, frame_id=3), x @ manual.T + layer.bias, atol=1e-6)


def test_interpolation_at_frame_time_equals_lookup():
    torch.manual_seed(2)
    T = 7
    look = ResFieldLinear(5, 3, rank=2, n_frames=T, mode="lookup")
    interp = ResFieldLinear(5, 3, rank=2, n_frames=T, mode="interpolation")
    interp.load_state_dict(look.state_dict())
    x = torch.randn(4, 5)
    for k in range(T):
        assert torch.allclose(interp(x, time=k / (T - 1)), look(x, frame_id=k), atol=1e-6)
    # halfway between frames 2 and 3: the average of the two weights
    w_mid = interp.weight_at(time=2.5 / (T - 1))
    assert torch.allclose(w_mid, 0.5 * (look.weight_at(frame_id=2) + look.weight_at(frame_id=3)), atol=1e-6)
    # clamped outside [0, 1]
    assert torch.allclose(interp.weight_at(time=1.7), look.weight_at(frame_id=T - 1))


def test_gradient_only_reaches_the_used_frame():
    torch.manual_seed(3)
    layer = ResFieldLinear(5, 3, rank=2, n_frames=4)
    layer(torch.randn(6, 5), frame_id=2).square().sum().backward()
    g = layer.coefficients.grad
    assert g[2].abs().sum() > 0
    assert torch.all(g[[0, 1, 3]] == 0)
    assert layer.matrices.grad.abs().sum() > 0


def test_missing_or_bad_frame_raises():
    layer = ResFieldLinear(5, 3, rank=2, n_frames=4)
    x = torch.randn(2, 5)
    with pytest.raises(ValueError):
        layer(x)
    with pytest.raises(IndexError):
        layer(x, frame_id=4)
    with pytest.raises(ValueError):
        ResFieldLinear(5, 3, rank=2, n_frames=4, mode="interpolation")(x, frame_id=1)


def test_weight_at_keeps_the_masters_dtype_under_autocast():
    """Under CPU bf16 autocast (the fused heads' region) the residual is still formed in float32: the same weight
    as without autocast, bit for bit (autocast would round the basis and the residual to bf16)."""
    layer = ResFieldLinear(16, 8, rank=4, n_frames=3)
    plain = layer.weight_at(frame_id=2)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under = layer.weight_at(frame_id=2)
    assert under.dtype == torch.float32 and torch.equal(under, plain)
    under.sum().backward()
    assert layer.matrices.grad.dtype == torch.float32 and layer.coefficients.grad.abs().sum() > 0
