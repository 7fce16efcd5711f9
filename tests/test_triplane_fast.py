"""Exact rewrites of the tri-plane CNN against the per-plane reference path, in float64.

* ``subpixel_upsample_conv``: nearest ×2 + 3×3 conv as one 2×2 conv at the low resolution;
* ``stack_generators``: the three generators as one grouped-conv network with stacked parameters
  (optionally channels-last, GroupNorm with one channel per group as batch-statistics ``batch_norm``);
* ``CNNTriplaneBackbone(stack_planes=..., stack_channels_last=..., subpixel_upsample=...)``: same
  state dict, same planes, same gradient for every parameter.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from src.fields.backbones import CNNTriplaneBackbone
from src.fields.triplane import (
    TriplaneGenerator,
    split_plane_state,
    stack_generators,
    stack_plane_state,
    subpixel_kernels,
    subpixel_upsample_conv,
)
from tests.test_fields import assert_compiled_matches_eager

TOL = dict(rtol=1e-10, atol=1e-10)


def _randomise(module: torch.nn.Module, seed: int = 0, scale: float = 0.3) -> None:
    """Overwrite every parameter with noise (the zero-initialised residual branches included)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * scale)


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("groups,size", [(1, (5, 7)), (3, (4, 4)), (2, (1, 3))])
def test_subpixel_upsample_conv_matches_upsample_then_conv(groups, size, channels_last):
    g = torch.Generator().manual_seed(1)
    H, W = size
    n_in, n_out = 3, 4
    x = torch.randn(2, groups * n_in, H, W, generator=g, dtype=torch.float64)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_(True)
    w = torch.randn(groups, n_out, n_in, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(groups, n_out, generator=g, dtype=torch.float64, requires_grad=True)
    up = F.interpolate(x, scale_factor=2.0, mode="nearest")
    ref = F.conv2d(up, w.reshape(groups * n_out, n_in, 3, 3), b.reshape(-1), padding=1, groups=groups)
    got = subpixel_upsample_conv(x, w, b, groups=groups)
    assert got.shape == ref.shape == (2, groups * n_out, 2 * H, 2 * W)
    fmt = torch.channels_last if channels_last and not x.is_contiguous() else torch.contiguous_format
    assert got.is_contiguous(memory_format=fmt)  # the input's memory format
    torch.testing.assert_close(got, ref, **TOL)  # borders included: zero padding of the ×2 image
    grad = torch.randn(ref.shape, generator=g, dtype=torch.float64)
    for a, c, name in zip(torch.autograd.grad(ref, (x, w, b), grad), torch.autograd.grad(got, (x, w, b), grad),
                          ("x", "weight", "bias"), strict=True):
        torch.testing.assert_close(c, a, **TOL, msg=name)


def test_subpixel_kernels_are_sums_of_taps():
    w = torch.arange(9, dtype=torch.float64).reshape(1, 1, 3, 3)  # w[r, c] = 3r + c
    k = subpixel_kernels(w)  # [2 (a), 2 (b), 1, 1, 2, 2]
    assert k.shape == (2, 2, 1, 1, 2, 2)
    rows = {0: [[0], [1, 2]], 1: [[0, 1], [2]]}  # phase -> taps of the 3x3 kernel per 2x2 tap
    for a, b in itertools.product((0, 1), repeat=2):
        for r, c in itertools.product((0, 1), repeat=2):
            expect = sum(3 * i + j for i in rows[a][r] for j in rows[b][c])
            assert k[a, b, 0, 0, r, c].item() == expect


GEN = dict(noise_channels=3, noise_res=5, channels=8, out_channels=6, n_up_blocks=3, resnets_per_block=2)


@pytest.mark.parametrize("norm_groups", [8, 4])  # one channel per group (the configured 32/32), and two
@pytest.mark.parametrize("extra_mid", [False, True])
@pytest.mark.parametrize("subpixel,channels_last", [(False, False), (False, True), (True, False), (True, True)])
def test_stacked_generator_matches_per_plane_generators(norm_groups, extra_mid, subpixel, channels_last):
    gens = [TriplaneGenerator(**GEN, norm_groups=norm_groups, ref_extra_mid_resnet=extra_mid, seed=p,
                              subpixel_upsample=subpixel).double() for p in range(3)]
    for p, gen in enumerate(gens):
        _randomise(gen, seed=p)
    stacked = stack_generators(gens, channels_last=channels_last)
    assert stacked.planes == 3 and stacked.noise.dtype == torch.float64
    ref = torch.cat([gen() for gen in gens])
    got = stacked()
    assert got.shape == ref.shape == (3, 6, 20, 20) and got.is_contiguous()
    torch.testing.assert_close(got, ref, **TOL)
    weight = torch.randn(ref.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    g_ref = [torch.autograd.grad((ref * weight).sum(), list(gen.parameters()), retain_graph=True) for gen in gens]
    g_got = torch.autograd.grad((got * weight).sum(), list(stacked.parameters()))
    names = [n for n, _ in stacked.named_parameters()]
    assert names == [n for n, _ in gens[0].named_parameters()]
    for i, (b, name) in enumerate(zip(g_got, names, strict=True)):  # plane p's gradient is chunk p of the stacked one
        torch.testing.assert_close(b, torch.cat([g[i] for g in g_ref]), **TOL, msg=name)


def test_plane_state_round_trip_and_errors():
    gens = [TriplaneGenerator(**GEN, norm_groups=4, seed=p) for p in range(3)]
    states = [g.state_dict() for g in gens]
    stacked = stack_plane_state(states)
    assert stacked["noise"].shape == (3, 3, 5, 5) and stacked["conv_in.weight"].shape == (24, 3, 3, 3)
    for a, b in zip(split_plane_state(stacked, 3), states, strict=True):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="not a multiple of 2 planes"):
        split_plane_state(stacked, 2)
    with pytest.raises(ValueError, match="different keys"):
        stack_plane_state([states[0], TriplaneGenerator(**GEN, norm_groups=4, ref_extra_mid_resnet=True).state_dict()])
    with pytest.raises(ValueError, match="one configuration"):
        stack_generators([gens[0], TriplaneGenerator(**{**GEN, "channels": 4}, norm_groups=4)])
    torch.manual_seed(7)
    expect = torch.rand(3)
    torch.manual_seed(7)
    stack_generators(gens)
    assert torch.equal(torch.rand(3), expect)  # stacking leaves the global RNG (later inits) as it was


BACKBONE = dict(plane_channels=6, noise_channels=3, noise_res=5, channels=8, n_up_blocks=3, resnets_per_block=2,
                norm_groups=8)
VARIANTS = [dict(stack_planes=True), dict(stack_planes=True, stack_channels_last=True), dict(subpixel_upsample=True),
            dict(stack_planes=True, stack_channels_last=True, subpixel_upsample=True)]


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: "+".join(v))
def test_backbone_switches_keep_state_dict_planes_and_gradients(variant):
    ref = CNNTriplaneBackbone(**BACKBONE).double()
    fast = CNNTriplaneBackbone(**BACKBONE, **variant).double()
    _randomise(ref)
    assert fast.state_dict().keys() == ref.state_dict().keys()  # the per-plane layout either way
    fast.load_state_dict(ref.state_dict())
    back = CNNTriplaneBackbone(**BACKBONE).double()
    back.load_state_dict(fast.state_dict())  # and back: the stacked parameters split per plane
    assert all(torch.equal(back.state_dict()[k], v) for k, v in ref.state_dict().items())
    planes_ref, planes_fast = ref.prepare(), fast.prepare()
    torch.testing.assert_close(planes_fast, planes_ref, **TOL)
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 2 - 1
    ref(pts).square().sum().backward()
    fast(pts).square().sum().backward()
    grads = {n: p.grad for n, p in ref.named_parameters()}
    for name, pb in fast.named_parameters():
        assert pb.grad is not None, name
        if name.startswith("generators.") and fast.stack_planes:  # plane p's gradient is chunk p of the stacked one
            key = name.split(".", 2)[2]
            expect = torch.cat([grads[f"generators.{p}.{key}"] for p in range(3)])
        else:
            expect = grads[name]
        torch.testing.assert_close(pb.grad, expect, **TOL, msg=name)


def test_stacked_bf16_autocast_close_to_reference():
    """Under bfloat16 autocast (the CPU default where supported) the paths agree to bf16 rounding."""
    torch.manual_seed(0)
    ref = CNNTriplaneBackbone(**BACKBONE, autocast_bf16=True)
    fast = CNNTriplaneBackbone(**BACKBONE, autocast_bf16=True, stack_planes=True, stack_channels_last=True)
    _randomise(ref, scale=0.2)
    fast.load_state_dict(ref.state_dict())
    a, b = ref.prepare(), fast.prepare()
    assert a.dtype == b.dtype == torch.bfloat16 and b.shape == a.shape and b.is_contiguous()
    assert (b.float() - a.float()).abs().max() <= 0.05 * a.float().abs().max()


def test_config_enables_the_measured_rewrites():
    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf/field/cnn_triplane.yaml")
    assert cfg.stack_planes is True and cfg.stack_channels_last is True
    assert cfg.subpixel_upsample is False  # exact but measured slower on CPU (docs/benchmarks.md)
    assert cfg.norm_groups == cfg.channels  # one channel per group: the channels-last batch_norm form applies


def test_compiled_stacked_backbone_matches_eager():
    kw = dict(plane_channels=4, noise_channels=2, noise_res=4, channels=8, n_up_blocks=2, resnets_per_block=1,
              norm_groups=8, stack_planes=True, stack_channels_last=True)
    eager, compiled = CNNTriplaneBackbone(**kw), CNNTriplaneBackbone(**kw, compile=True)
    _randomise(eager, scale=0.2)
    compiled.load_state_dict(eager.state_dict())
    pts = torch.rand(32, 3, generator=torch.Generator().manual_seed(3)) * 2 - 1
    assert_compiled_matches_eager(eager, compiled, pts)
