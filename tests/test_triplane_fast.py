"""Exact rewrites of the tri-plane CNN against the per-plane reference path, in float64.

* ``subpixel_upsample_conv``: nearest ×2 + 3×3 conv as one 2×2 conv at the low resolution;
* ``stacked_planes``: the three generators as one grouped-conv network (optionally channels-last,
  GroupNorm with one channel per group as batch-statistics ``batch_norm``);
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
from src.fields.triplane import TriplaneGenerator, stacked_planes, subpixel_kernels, subpixel_upsample_conv
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
def test_stacked_planes_match_per_plane_generators(norm_groups, extra_mid, subpixel, channels_last):
    gens = [TriplaneGenerator(**GEN, norm_groups=norm_groups, ref_extra_mid_resnet=extra_mid, seed=p).double()
            for p in range(3)]
    for p, gen in enumerate(gens):
        _randomise(gen, seed=p)
    ref = torch.cat([gen() for gen in gens])
    got = stacked_planes(gens, subpixel=subpixel, channels_last=channels_last)
    assert got.shape == ref.shape == (3, 6, 20, 20) and got.is_contiguous()
    torch.testing.assert_close(got, ref, **TOL)
    weight = torch.randn(ref.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    params = [p for gen in gens for p in gen.parameters()]
    g_ref = torch.autograd.grad((ref * weight).sum(), params)
    g_got = torch.autograd.grad((got * weight).sum(), params)
    names = [f"{i}.{n}" for i, gen in enumerate(gens) for n, _ in gen.named_parameters()]
    for a, b, name in zip(g_ref, g_got, names, strict=True):
        torch.testing.assert_close(b, a, **TOL, msg=name)


BACKBONE = dict(plane_channels=6, noise_channels=3, noise_res=5, channels=8, n_up_blocks=3, resnets_per_block=2,
                norm_groups=8)
VARIANTS = [dict(stack_planes=True), dict(stack_planes=True, stack_channels_last=True), dict(subpixel_upsample=True),
            dict(stack_planes=True, stack_channels_last=True, subpixel_upsample=True)]


@pytest.mark.parametrize("variant", VARIANTS, ids=lambda v: "+".join(v))
def test_backbone_switches_keep_state_dict_planes_and_gradients(variant):
    ref = CNNTriplaneBackbone(**BACKBONE).double()
    fast = CNNTriplaneBackbone(**BACKBONE, **variant).double()
    _randomise(ref)
    assert fast.state_dict().keys() == ref.state_dict().keys()
    fast.load_state_dict(ref.state_dict())
    planes_ref, planes_fast = ref.prepare(), fast.prepare()
    torch.testing.assert_close(planes_fast, planes_ref, **TOL)
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 2 - 1
    ref(pts).square().sum().backward()
    fast(pts).square().sum().backward()
    for (name, pa), pb in zip(ref.named_parameters(), fast.parameters(), strict=True):
        assert pa.grad is not None and pb.grad is not None, name
        torch.testing.assert_close(pb.grad, pa.grad, **TOL, msg=name)


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
