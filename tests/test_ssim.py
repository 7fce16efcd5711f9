"""The batched SSIM (one blur call for every map and image) against the direct form, in float64."""

from __future__ import annotations

import torch

from src.losses.ssim import ssim, ssim_per_image, ssim_reference


def _pair(seed: int, h: int = 23, w: int = 31, c: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    return a, (a + 0.2 * torch.rand(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)


def test_batched_ssim_matches_the_reference_in_values_and_gradients():
    pairs = [_pair(s) for s in range(3)]
    a = torch.stack([p[0] for p in pairs]).requires_grad_(True)
    b = torch.stack([p[1] for p in pairs])
    per = ssim_per_image(a, b)
    ref = [ssim_reference(a[i], b[i]) for i in range(3)]
    assert torch.allclose(per, torch.stack(ref), rtol=0, atol=1e-12)
    (g_fast,) = torch.autograd.grad(ssim(a, b), a)
    (g_ref,) = torch.autograd.grad(sum(ref) / 3, a)
    assert torch.allclose(g_fast, g_ref, rtol=0, atol=1e-12)
    single = ssim(a[0], b[0])
    assert torch.allclose(single, ref[0], rtol=0, atol=1e-12)


def test_ssim_is_one_for_equal_images_and_below_for_different_ones():
    a, b = _pair(7)
    assert abs(float(ssim(a, a)) - 1.0) < 1e-12 and float(ssim(a, b)) < 0.99


def test_the_objective_batches_dssim_exactly():
    from src.core.splats import RenderOutput
    from src.data.base import View
    from src.losses.objective import SplatLoss

    pairs = [_pair(s, 16, 16) for s in range(4)]
    renders = [RenderOutput(color=p[0], alpha=torch.ones(16, 16, dtype=torch.float64),
                            depth=torch.zeros(16, 16, dtype=torch.float64), means2d=torch.zeros(0),
                            radii=torch.zeros(0)) for p in pairs]
    views = [View(camera=None, image=p[1], mask=None, image_id=i) for i, p in enumerate(pairs)]
    d = SplatLoss(lambda_dssim=0.2, lambda_mask=0.0)(renders, views, [])["dssim"]
    expected = sum(1 - ssim_reference(p[0], p[1]) for p in pairs) / 4
    assert torch.allclose(d, expected, rtol=0, atol=1e-12)
