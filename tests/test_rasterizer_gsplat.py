"""gsplat backend: GPU-only parity with the torch reference (skipped without CUDA)."""

from __future__ import annotations

import pytest
import torch

from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def test_importing_the_backend_does_not_need_gsplat():
    import src.rasterizer.gsplat_backend as gb

    assert gb.GsplatRasterizer.name == "gsplat"
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            gb.GsplatRasterizer()


@cuda
@pytest.mark.cuda
def test_gsplat_matches_reference_away_from_borders():
    pytest.importorskip("gsplat")
    from src.rasterizer.gsplat_backend import GsplatRasterizer

    s = random_scene(2000, seed=0, spread=0.4, scale_range=(0.01, 0.04))
    cam = random_camera(64, 64, seed=1)
    ref = TorchRefRasterizer().render(s, cam, torch.ones(3))
    out = GsplatRasterizer().render(s.to("cuda"), cam.to("cuda"), torch.ones(3, device="cuda"))
    diff = (out.color.cpu() - ref.color).abs()
    assert diff.mean() < 5e-3 and torch.quantile(diff.flatten(), 0.99) < 5e-2


def _parity(rasterizer_kwargs: dict, tol_mean: float = 5e-3, tol_q99: float = 5e-2) -> None:
    """gsplat and the torch reference with the same settings agree on colour and alpha (away from the
    tile-rule differences at splat borders: mean and 99th percentile of the absolute difference)."""
    pytest.importorskip("gsplat")
    from src.rasterizer.gsplat_backend import GsplatRasterizer

    s = random_scene(2000, seed=0, spread=0.4, scale_range=(0.01, 0.04))
    cam = random_camera(64, 64, seed=1)
    ref = TorchRefRasterizer(**rasterizer_kwargs).render(s, cam, torch.ones(3))
    out = GsplatRasterizer(**rasterizer_kwargs).render(s.to("cuda"), cam.to("cuda"), torch.ones(3, device="cuda"))
    for name in ("color", "alpha"):
        diff = (getattr(out, name).cpu() - getattr(ref, name)).abs()
        assert diff.mean() < tol_mean and torch.quantile(diff.flatten(), 0.99) < tol_q99, name


@cuda
@pytest.mark.cuda
def test_gsplat_antialiased_matches_reference():
    _parity({"antialiased": True, "filter_2d": 0.1})


@cuda
@pytest.mark.cuda
def test_gsplat_surfels_match_reference():
    _parity({"surfels": True}, tol_mean=1e-2, tol_q99=1e-1)


@cuda
@pytest.mark.cuda
def test_gsplat_gradients_point_the_same_way_as_the_reference():
    """The colour loss's gradients with respect to the splat means, the colours and the projected centres
    (``means2d.grad``, what adaptive density control reads): cosine > 0.9."""
    pytest.importorskip("gsplat")
    from src.rasterizer.gsplat_backend import GsplatRasterizer

    cam = random_camera(64, 64, seed=1)
    grads = []
    for rast, dev in ((TorchRefRasterizer(), "cpu"), (GsplatRasterizer(), "cuda")):
        s = random_scene(500, seed=0, spread=0.4, scale_range=(0.02, 0.05)).to(dev)
        means = s.means.clone().requires_grad_(True)
        colors = s.colors.clone().requires_grad_(True)
        out = rast.render(type(s)(means=means, scales=s.scales, quats=s.quats, opacities=s.opacities,
                                  colors=colors), cam.to(dev), torch.ones(3, device=dev))
        out.means2d.retain_grad()
        (out.color - 0.5).square().mean().backward()
        assert out.means2d.grad is not None, f"{rast.name}: no view-space gradient, nothing would densify"
        grads.append((means.grad.cpu().flatten(), colors.grad.cpu().flatten(), out.means2d.grad.cpu().flatten()))
    for a, b in zip(*grads, strict=True):
        assert torch.nn.functional.cosine_similarity(a, b, dim=0) > 0.9


def test_auto_on_cuda_without_gsplat_uses_the_reference(monkeypatch):
    """On CUDA the compiled kernel (CPU-only) is never picked: a missing gsplat takes torch_ref."""
    import builtins

    from src.rasterizer.auto import auto_rasterizer

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    real_import = builtins.__import__

    def no_gsplat(name, *args, **kwargs):
        if name == "gsplat" or name.startswith("gsplat."):
            raise ImportError("No module named 'gsplat'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_gsplat)
    rast = auto_rasterizer(antialiased=True)
    assert isinstance(rast, TorchRefRasterizer) and rast.antialiased
    surf = auto_rasterizer(surfels=True)
    assert isinstance(surf, TorchRefRasterizer) and surf.surfels


def test_auto_on_cuda_renders_surfels_with_gsplat(monkeypatch):
    """2D surfels on CUDA take gsplat's 2DGS path (a stand-in gsplat module here)."""
    from src.rasterizer.auto import auto_rasterizer
    from src.rasterizer.gsplat_backend import GsplatRasterizer

    _fake_gsplat(monkeypatch)  # also reports a CUDA device
    surf = auto_rasterizer(surfels=True, device="cuda:0")
    assert isinstance(surf, GsplatRasterizer) and surf.surfels


def test_auto_follows_the_runs_device(monkeypatch):
    """A run on the CPU of a CUDA machine (``device=cpu``) gets a CPU rasterizer, not gsplat."""
    from src.rasterizer.auto import auto_rasterizer
    from src.rasterizer.cpu import CpuRasterizer

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert isinstance(auto_rasterizer(device="cpu"), CpuRasterizer)
    assert isinstance(auto_rasterizer(surfels=True, device="cpu"), CpuRasterizer)


def _fake_gsplat(monkeypatch) -> dict:
    """A stand-in ``gsplat`` module whose rasterizers follow gsplat's batched API on the CPU: the image
    depends on the projected centres ``meta["means2d"]`` [1, N, 2] (Gaussian blobs), as gsplat's does."""
    import sys
    import types

    seen: dict = {}

    def project(means, viewmats, Ks):
        cam = means @ viewmats[0, :3, :3].T + viewmats[0, :3, 3]  # [N, 3]
        uv = cam[:, :2] / cam[:, 2:3] @ Ks[0, :2, :2].T + Ks[0, :2, 2]  # [N, 2] pixels
        return uv[None], cam[:, 2]

    def blobs(means2d, colors, width, height):
        ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
        pix = torch.stack([xs, ys], -1).reshape(-1, 1, 2)  # [P, 1, 2]
        w = torch.exp(-((pix - means2d[0][None]) ** 2).sum(-1) / 4.0)  # [P, N]
        img = (w @ colors.reshape(-1, colors.shape[-1])).reshape(1, height, width, -1)
        return img, w.sum(-1).clamp(max=1).reshape(1, height, width, 1)

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **_):
        means2d, z = project(means, viewmats, Ks)
        img, alpha = blobs(means2d, colors, width, height)
        seen["means2d"] = means2d
        means2d.retain_grad()
        depth = alpha * z.mean()
        radii = torch.full((1, means.shape[0], 2), 3, dtype=torch.int32)
        return torch.cat([img, depth], -1), alpha, {"means2d": means2d, "radii": radii}

    def rasterization_2dgs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **_):
        means2d, z = project(means, viewmats, Ks)
        densify = torch.zeros_like(means2d, requires_grad=True)  # gsplat: holds the densification gradient
        img, alpha = blobs(means2d + densify, colors[0], width, height)
        seen["gradient_2dgs"] = densify
        densify.retain_grad()
        normals = torch.zeros(1, height, width, 3)
        meta = {"means2d": means2d.detach(), "radii": torch.full((1, means.shape[0]), 3, dtype=torch.int32),
                "gradient_2dgs": densify}
        return (torch.cat([img, alpha * z.mean()], -1), alpha, normals, normals, torch.zeros(1, height, width, 1),
                alpha, meta)

    fake = types.ModuleType("gsplat")
    fake.rasterization, fake.rasterization_2dgs = rasterization, rasterization_2dgs
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    return seen


@pytest.mark.parametrize("surfels", [False, True])
def test_the_gsplat_wrappers_hand_the_view_space_gradient_to_means2d(monkeypatch, surfels):
    """RenderOutput.means2d.grad after the backward holds gsplat's screen-space gradient (camera 0),
    which adaptive density control reads; a slice of gsplat's batched tensor would stay empty."""
    from src.rasterizer.gsplat_backend import GsplatRasterizer

    seen = _fake_gsplat(monkeypatch)
    s = random_scene(20, seed=0, spread=0.3)
    means = s.means.clone().requires_grad_(True)
    out = GsplatRasterizer(surfels=surfels).render(type(s)(means=means, scales=s.scales, quats=s.quats,
                                                        opacities=s.opacities, colors=s.colors),
                                                   random_camera(16, 16, seed=1), torch.ones(3))
    out.color.square().sum().backward()
    source = seen["gradient_2dgs" if surfels else "means2d"]
    assert out.means2d.is_leaf and out.means2d.grad is not None and out.means2d.grad.shape == (20, 2)
    assert out.means2d.grad.abs().sum() > 0 and torch.equal(out.means2d.grad, source.grad[0])
    if surfels:  # gsplat's distortion map is its L1 raw-depth form, weighted by loss.lambda_dist_l1
        assert out.distortion_form == "depth_l1"
