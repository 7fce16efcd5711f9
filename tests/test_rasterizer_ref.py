"""The torch reference rasterizer: finite differences (float64), known pixels, edge cases."""

from __future__ import annotations

import torch

from src.core.cameras import Camera, look_at
from src.core.splats import Splats
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene

ATTRS = ["means", "scales", "quats", "opacities", "colors"]


def _loss(splats: Splats, cam: Camera, weights: dict[str, torch.Tensor]) -> torch.Tensor:
    out = TorchRefRasterizer().render(splats, cam, torch.tensor([0.3, 0.5, 0.7], dtype=splats.means.dtype))
    return ((out.color * weights["c"]).sum() + (out.alpha * weights["a"]).sum()
            + (out.depth * weights["d"]).sum())


def test_gradients_match_central_differences_float64(tiny_scene):
    splats, cam = tiny_scene
    g = torch.Generator().manual_seed(3)
    H, W = cam.height, cam.width
    weights = {"c": torch.rand(H, W, 3, generator=g, dtype=torch.float64),
               "a": torch.rand(H, W, generator=g, dtype=torch.float64),
               "d": torch.rand(H, W, generator=g, dtype=torch.float64) * 0.1}
    params = {k: getattr(splats, k).clone().requires_grad_(True) for k in ATTRS}
    loss = _loss(Splats(**params), cam, weights)
    loss.backward()
    eps = 1e-7  # tiny step in float64: the alpha cut-offs make the image piecewise smooth only
    for name in ATTRS:
        base = getattr(splats, name)
        fd = torch.zeros_like(base)
        flat = fd.view(-1)
        for i in range(base.numel()):
            plus = base.clone().view(-1)
            minus = base.clone().view(-1)
            plus[i] += eps
            minus[i] -= eps
            lp = _loss(Splats(**{**params, name: plus.view_as(base)}), cam, weights)
            lm = _loss(Splats(**{**params, name: minus.view_as(base)}), cam, weights)
            flat[i] = (lp - lm) / (2 * eps)
        ad = params[name].grad
        rel = (ad - fd).norm() / fd.norm().clamp_min(1e-12)
        assert rel < 1e-5, f"{name}: autograd vs FD relative error {rel:.2e}"


def test_single_splat_centre_pixel_alpha():
    """A small splat centred on a pixel centre gives alpha = min(0.99, o) at that pixel."""
    cam = Camera(look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3)), 50.0, 50.0, 16.0, 16.0, 32, 32)
    # project the origin: lands on (16, 16) = the corner between pixels; shift to the centre of pixel (16, 16)
    uv, _ = cam.project(torch.zeros(1, 3))
    assert torch.allclose(uv, torch.tensor([[16.0, 16.0]]), atol=1e-5)
    mean = torch.tensor([[0.5 * 3.0 / 50.0, 0.0, -0.5 * 3.0 / 50.0]])  # +0.5 px in u and v
    for o in (0.5, 0.995):
        s = Splats(mean, torch.full((1, 3), 0.01), torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([o]),
                   torch.tensor([[1.0, 0.0, 0.0]]))
        out = TorchRefRasterizer().render(s, cam, torch.zeros(3))
        assert abs(out.alpha[16, 16].item() - min(0.99, o)) < 1e-5
        assert out.alpha[16, 16] == out.alpha.max()
        assert abs(out.depth[16, 16].item() - 3.0 * min(0.99, o)) < 1e-4


def test_empty_scene_and_behind_camera_give_background():
    cam = random_camera(24, 20, seed=0)
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = TorchRefRasterizer().render(Splats.empty(), cam, bg)
    assert out.color.shape == (20, 24, 3)
    assert torch.allclose(out.color, bg.expand(20, 24, 3))
    assert torch.all(out.alpha == 0)
    # splats behind the camera are culled
    s = random_scene(20, seed=4)
    eye = cam.center
    s.means = eye + (eye / eye.norm()) * (0.5 + torch.rand(20, 1))  # behind: further out along the eye ray
    out = TorchRefRasterizer().render(s, cam, bg)
    assert torch.all(out.radii == 0)
    assert torch.allclose(out.color, bg.expand(20, 24, 3))


def test_termination_and_saturation():
    """Many opaque splats: compositing stops before T would drop below 1e-4."""
    cam = Camera(look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3)), 40.0, 40.0, 8.0, 8.0, 16, 16)
    n = 10
    means = torch.zeros(n, 3)
    means[:, 1] = torch.linspace(-0.5, 0.5, n)  # front (closest to the camera at y=-3) first
    s = Splats(means, torch.full((n, 3), 1.0), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
               torch.full((n,), 0.98), torch.rand(n, 3))
    rast = TorchRefRasterizer()
    out = rast.render(s, cam, torch.zeros(3))
    a = [rast.render(s.index(torch.tensor([i])), cam, torch.zeros(3)).alpha[8, 8] for i in range(3)]
    # alpha ~ 0.978: after two splats T ~ 4.6e-4, a third would take it to ~1e-5 < 1e-4, so it stops
    expected = a[0] * s.colors[0] + (1 - a[0]) * a[1] * s.colors[1]
    assert torch.allclose(out.color[8, 8], expected, atol=1e-5)
    assert abs(out.alpha[8, 8].item() - (1 - (1 - a[0]) * (1 - a[1])).item()) < 1e-6
