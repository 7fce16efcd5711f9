"""The compiled CPU rasterizer: parity with the torch reference, exact culling, determinism, errors.

The first test to render triggers the JIT build of the extension (cached on disk afterwards).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from src.core.cameras import Camera, look_at
from src.core.splats import Splats
from src.rasterizer.cpu import CpuRasterizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene

ATTRS = ["means", "scales", "quats", "opacities", "colors"]
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _one_thread():
    """Run single-threaded: much faster on a busy shared 2-core machine (OpenMP barriers spin).
    Multi-threaded results are covered by the determinism test (1 vs 2 threads bit-identical)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _render_with_grads(rast, splats: Splats, cam: Camera, bg: torch.Tensor, seed: int = 0):
    """Render, backprop a random linear loss of colour/alpha/depth; return (output, grads)."""
    params = {k: getattr(splats, k).detach().clone().requires_grad_(True) for k in ATTRS}
    out = rast.render(Splats(**params), cam, bg)
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(seed)
    H, W, C = out.color.shape
    loss = ((out.color * torch.rand(H, W, C, generator=g)).sum()
            + (out.alpha * torch.rand(H, W, generator=g)).sum()
            + (out.depth * torch.rand(H, W, generator=g) * 0.1).sum())
    loss.backward()
    grads = {k: params[k].grad for k in ATTRS}
    grads["means2d"] = out.means2d.grad
    return out, grads


def _assert_parity(splats: Splats, cam: Camera, bg: torch.Tensor, seed: int = 0, grad_tol: float = 1e-5):
    ref_out, ref_g = _render_with_grads(TorchRefRasterizer(), splats, cam, bg, seed)
    out, g = _render_with_grads(CpuRasterizer(), splats, cam, bg, seed)
    for name in ("color", "alpha", "depth"):
        a, b = getattr(out, name), getattr(ref_out, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-5), f"{name}: max diff {(a - b).abs().max():.2e}"
    assert torch.equal(out.radii, ref_out.radii)
    for name, ref in ref_g.items():
        got = g[name]
        assert got is not None and ref is not None, name
        denom = ref.norm()
        if denom == 0:
            assert got.abs().max() == 0, name
            continue
        rel = (got - ref).norm() / denom
        assert rel < grad_tol, f"{name}: gradient relative error {rel:.2e}"


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("bg_value", [0.0, 1.0, 0.5])
def test_parity_random_scenes(seed: int, bg_value: float):
    splats = random_scene(400, seed=seed)
    cam = random_camera(40, 40, seed=seed)
    _assert_parity(splats, cam, torch.full((3,), bg_value), seed)


def test_parity_five_channels_nonsquare_partial_tiles():
    splats = random_scene(500, seed=5, channels=5)
    cam = random_camera(45, 23, seed=5)  # 45 = 2*16 + 13, 23 = 16 + 7: partial border tiles
    _assert_parity(splats, cam, torch.tensor([0.1, 0.9, 0.3, 0.0, 1.0]), seed=5)


def _anisotropic_scene(n: int, seed: int, stretch: float, scale_range: tuple[float, float]) -> Splats:
    splats = random_scene(n, seed=seed, scale_range=scale_range)
    g = torch.Generator().manual_seed(seed)
    sel = torch.rand(n, generator=g) < 0.33  # a third of the splats: one axis `stretch` x longer
    splats.scales[sel, 0] *= stretch
    splats.opacities[:50] = 0.999  # alpha clamp at 0.99
    splats.opacities[50:80] = 0.003  # below 1/255 everywhere
    return splats


def test_parity_anisotropic_tiny_and_large_splats():
    splats = _anisotropic_scene(400, seed=7, stretch=8.0, scale_range=(0.0005, 0.2))
    cam = random_camera(50, 38, seed=7)
    _assert_parity(splats, cam, torch.tensor([0.5, 0.5, 0.5]), seed=7)


def test_extreme_anisotropy_against_float64_oracle():
    """Needle-like splats (up to 12 units long): float32 itself is off by ~2e-5 here, so compare
    both float32 rasterizers with the float64 reference instead of with each other."""
    splats = _anisotropic_scene(400, seed=7, stretch=30.0, scale_range=(0.0005, 0.4))
    cam = random_camera(50, 38, seed=7)
    bg = torch.tensor([0.5, 0.5, 0.5])
    _, g64 = _render_with_grads(TorchRefRasterizer(), splats.to(dtype=torch.float64),
                                cam.to(dtype=torch.float64), bg.double(), seed=7)
    _, g32 = _render_with_grads(TorchRefRasterizer(), splats, cam, bg, seed=7)
    _, gc = _render_with_grads(CpuRasterizer(), splats, cam, bg, seed=7)
    for k in ATTRS:
        ref = g64[k]
        err_ref = ((g32[k].double() - ref).norm() / ref.norm()).item()
        err_cpu = ((gc[k].double() - ref).norm() / ref.norm()).item()
        assert err_cpu <= 1.5 * err_ref + 1e-6, f"{k}: cpu {err_cpu:.2e} vs torch_ref f32 {err_ref:.2e}"


def test_parity_saturated_dense_scene():
    """Many opaque overlapping splats: termination (T < 1e-4) inside tiles."""
    splats = random_scene(1500, seed=3, spread=0.2, scale_range=(0.05, 0.2))
    splats.opacities.fill_(0.95)
    cam = random_camera(33, 33, seed=3)
    _assert_parity(splats, cam, torch.tensor([1.0, 1.0, 1.0]), seed=3)


def test_parity_behind_camera_and_off_screen():
    cam = random_camera(32, 24, seed=4)
    splats = random_scene(300, seed=4, spread=2.0)  # many outside the frustum
    eye = cam.center
    splats.means[:60] = eye + (eye / eye.norm()) * (0.5 + torch.rand(60, 1))  # behind the camera
    splats.means[60:70] = eye * 0.95  # just in front of the near plane region
    _assert_parity(splats, cam, torch.tensor([0.2, 0.4, 0.6]), seed=4)


def test_parity_mostly_culled_scene():
    """~90 % of the splats culled (behind the camera, outside the frustum, zero-size tile rects):
    only the visible ones are packed and binned; the gradient rows of the culled splats are exact
    zeros, as in the reference, and the rest match it."""
    cam = random_camera(40, 30, seed=11)
    splats = random_scene(2000, seed=11)
    eye = cam.center
    g = torch.Generator().manual_seed(11)
    splats.means[:1200] = eye + (eye / eye.norm()) * (0.5 + torch.rand(1200, 1, generator=g))  # behind
    splats.means[1200:1800] = splats.means[1200:1800] * 40.0  # far outside the frustum
    _assert_parity(splats, cam, torch.tensor([0.3, 0.6, 0.9]), seed=11)
    proj_visible = CpuRasterizer().render(splats, cam).radii > 0
    assert 50 < int(proj_visible.sum()) < 400
    _, grads = _render_with_grads(CpuRasterizer(), splats, cam, torch.tensor([0.3, 0.6, 0.9]), seed=11)
    for k in ("opacities", "colors", "means2d"):
        assert torch.all(grads[k][~proj_visible] == 0), k


def test_depth_order_wide_key_range_and_negative_depths():
    """Keys differing in every byte (all four radix digits), negative and tied depths."""
    from src.kernels.build import load_extension

    g = torch.Generator().manual_seed(1)
    d = torch.cat([torch.rand(3000, generator=g) * 1e6, -torch.rand(500, generator=g) * 10,
                   torch.rand(1500, generator=g) * 1e-3, torch.full((200,), 2.5)])
    d = d[torch.randperm(d.numel(), generator=g)]
    for vis in (torch.ones(d.numel(), dtype=torch.bool), torch.rand(d.numel(), generator=g) > 0.5):
        got = load_extension().depth_order(d, vis)
        idx = torch.nonzero(vis).squeeze(1)
        want = idx[torch.argsort(d[idx], stable=True)]
        assert torch.equal(got, want)
    assert load_extension().depth_order(d, torch.zeros(d.numel(), dtype=torch.bool)).numel() == 0


def test_background_gradient():
    splats = random_scene(300, seed=9)
    cam = random_camera(36, 28, seed=9)
    grads = []
    for rast in (TorchRefRasterizer(), CpuRasterizer()):
        bg = torch.tensor([0.2, 0.5, 0.8], requires_grad=True)
        out = rast.render(splats, cam, bg)
        w = torch.rand(out.color.shape, generator=torch.Generator().manual_seed(0))
        (out.color * w).sum().backward()
        grads.append(bg.grad)
    assert torch.allclose(grads[0], grads[1], rtol=1e-5, atol=1e-6)


def test_empty_scene_and_all_culled():
    cam = random_camera(24, 20, seed=0)
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = CpuRasterizer().render(Splats.empty(), cam, bg)
    assert out.color.shape == (20, 24, 3)
    assert torch.allclose(out.color, bg.expand(20, 24, 3))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0)
    s = random_scene(20, seed=4)
    eye = cam.center
    s.means = eye + (eye / eye.norm()) * (0.5 + torch.rand(20, 1))
    _, g = _render_with_grads(CpuRasterizer(), s, cam, bg)
    for k in ATTRS:
        assert torch.all(g[k] == 0), k


def test_single_splat_matches_reference_and_known_alpha():
    cam = Camera(look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3)), 50.0, 50.0, 16.0, 16.0, 32, 32)
    mean = torch.tensor([[0.5 * 3.0 / 50.0, 0.0, -0.5 * 3.0 / 50.0]])  # centre of pixel (16, 16)
    s = Splats(mean, torch.full((1, 3), 0.01), torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([0.5]),
               torch.tensor([[1.0, 0.0, 0.0]]))
    out = CpuRasterizer().render(s, cam, torch.zeros(3))
    assert abs(out.alpha[16, 16].item() - 0.5) < 1e-6
    assert abs(out.depth[16, 16].item() - 1.5) < 1e-5
    _assert_parity(s, cam, torch.tensor([0.3, 0.3, 0.3]))


def test_culling_is_exact_and_results_are_deterministic():
    """Exact culling on/off, repeated runs and 1 vs 2 threads give bit-identical outputs and grads."""
    # enough (splat, tile) pairs (> MIN_PAIRS_PARALLEL) for the multi-threaded tile loops
    splats = random_scene(6000, seed=11, scale_range=(0.005, 0.2))
    cam = random_camera(100, 76, seed=11)
    bg = torch.tensor([0.3, 0.6, 0.9])
    runs = [_render_with_grads(CpuRasterizer(cull=True), splats, cam, bg),
            _render_with_grads(CpuRasterizer(cull=True), splats, cam, bg),
            _render_with_grads(CpuRasterizer(cull=False), splats, cam, bg)]
    torch.set_num_threads(2)  # the fixture restores the thread count
    runs.append(_render_with_grads(CpuRasterizer(cull=True), splats, cam, bg))
    (out0, g0), *rest = runs
    for out, g in rest:
        for name in ("color", "alpha", "depth"):
            assert torch.equal(getattr(out, name), getattr(out0, name)), name
        for k in ATTRS:
            assert torch.equal(g[k], g0[k]), k


def test_lane_culling_at_a_silhouette_is_exact():
    """The per-vector early-out (skip a half-row whose pixels inside the splat's inflated ellipse
    have all terminated / all have an earlier last contributor, before the exp) is exact: on the
    benchmark's object scene (silhouette half-rows that never terminate as a whole) with opacities
    spread down to just above 1/255, culling on and off give bit-identical images and gradients."""
    from src.bench.rasterizer import SCENES

    splats, cam = SCENES["object"](20000, 64, 0)
    g = torch.Generator().manual_seed(0)
    low = torch.rand(splats.opacities.shape[0], generator=g) < 0.3
    splats.opacities[low] = (1.0 / 255.0) * (1.0 + 0.05 * torch.rand(int(low.sum()), generator=g))
    bg = torch.tensor([0.2, 0.5, 0.7])
    (out0, g0), (out1, g1) = (_render_with_grads(CpuRasterizer(cull=c, count_pairs=True), splats, cam, bg)
                              for c in (True, False))
    for name in ("color", "alpha", "depth"):
        assert torch.equal(getattr(out0, name), getattr(out1, name)), name
    for k in ATTRS:
        assert torch.equal(g0[k], g1[k]), k


def test_multi_chunk_binning_is_deterministic():
    """With > 2 x 16384 splats the binning splits the depth-sorted splats into per-thread chunks:
    1 vs 2 threads and culling on/off must still give bit-identical images and gradients."""
    splats = random_scene(40000, seed=5, scale_range=(0.003, 0.03))
    cam = random_camera(64, 48, seed=5)
    bg = torch.tensor([0.2, 0.4, 0.6])
    one = _render_with_grads(CpuRasterizer(cull=True), splats, cam, bg)
    plain = _render_with_grads(CpuRasterizer(cull=False), splats, cam, bg)
    torch.set_num_threads(2)  # the fixture restores the thread count
    two = _render_with_grads(CpuRasterizer(cull=True), splats, cam, bg)
    for out, g in (plain, two):
        for name in ("color", "alpha", "depth"):
            assert torch.equal(getattr(out, name), getattr(one[0], name)), name
        for k in ATTRS:
            assert torch.equal(g[k], one[1][k]), k
    assert float(one[0].alpha.detach().max()) > 0.5  # the scene is in view


@pytest.mark.parametrize("channels", [3, 5])
def test_depth_windows_are_exact(channels: int):
    """The forward bins and composites the depth-sorted splats in windows and stops binning onto
    tiles whose pixels have all terminated: images and gradients are bit-identical to one window
    (the plain binning), for small windows, the default rule and 2 threads, while far fewer
    (splat, tile) pairs are stored on a scene that saturates."""
    torch.manual_seed(0)
    splats = random_scene(30000, seed=21, scale_range=(0.02, 0.15))  # dense: tiles saturate
    splats.opacities = torch.full_like(splats.opacities, 2.0)  # logit: alpha ~ 0.88 at the centre
    if channels != 3:
        splats.colors = torch.rand(30000, channels)
    cam = random_camera(64, 48, seed=21)
    bg = torch.linspace(0.1, 0.9, channels)

    def run(first_window: int, threads: int = 1):
        torch.set_num_threads(threads)  # the fixture restores the thread count
        r = CpuRasterizer(count_pairs=True, first_window=first_window)
        out, g = _render_with_grads(r, splats, cam, bg)
        return out, g, r.last_stats

    plain = run(10**9)
    assert plain[2]["depth_windows"] == 1
    for fw, threads in ((64, 1), (0, 1), (1000, 2)):
        out, g, st = run(fw, threads)
        # (the default first window leaves no splat behind it whose rect meets a live tile here)
        assert st["depth_windows"] > 1 or fw == 0
        limit = (0.5 if fw == 64 else 0.9) * plain[2]["tile_pairs"]
        assert st["tile_pairs"] < limit, (fw, st["tile_pairs"], plain[2]["tile_pairs"])
        for name in ("color", "alpha", "depth"):
            assert torch.equal(getattr(out, name), getattr(plain[0], name)), (fw, name)
        for k in ATTRS:
            assert torch.equal(g[k], plain[1][k]), (fw, k)


def test_depth_windows_are_exact_with_depth_ties():
    """Splats on three depth planes (exactly equal depths; an axis-aligned camera), the nearest
    one opaque over part of the image: the first window (splats nearer than a sampled
    depth quantile) and the splats behind it that still meet a live tile are each sorted stably,
    so ties keep the original order exactly as the one-window depth sort does."""
    g = torch.Generator().manual_seed(5)
    n = 6000
    plane = torch.cat([torch.zeros(n // 2, 1), torch.randint(1, 3, (n - n // 2, 1), generator=g).float()])
    xy = torch.rand(n, 2, generator=g) * 6 - 3
    xy[:, 0] = torch.where(plane[:, 0] == 0, xy[:, 0] * 0.25 - 0.75, xy[:, 0])  # nearest plane: x < 0
    means = torch.cat([xy, plane * 0.5 - 0.5], dim=1)
    splats = Splats(means=means, scales=torch.rand(n, 3, generator=g) * 0.1 + 0.05,
                    quats=torch.randn(n, 4, generator=g), opacities=torch.full((n,), 0.95),
                    colors=torch.rand(n, 3, generator=g))
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0  # camera at z = -3 looking along +z: depth = z + 3 exactly
    cam = Camera(w2c, fx=40.0, fy=40.0, cx=32.0, cy=24.0, width=64, height=48)
    bg = torch.tensor([0.2, 0.4, 0.6])
    plain = _render_with_grads(CpuRasterizer(first_window=10**9), splats, cam, bg)
    for fw, threads in ((64, 1), (700, 1), (2500, 2)):
        torch.set_num_threads(threads)  # the fixture restores the thread count
        r = CpuRasterizer(first_window=fw)
        out, grads = _render_with_grads(r, splats, cam, bg)
        assert r.last_stats["depth_windows"] > 1
        for name in ("color", "alpha", "depth"):
            assert torch.equal(getattr(out, name), getattr(plain[0], name)), (fw, name)
        for k in ATTRS:
            assert torch.equal(grads[k], plain[1][k]), (fw, k)
    assert float(plain[0].alpha.detach().mean()) > 0.9  # the planes cover the image


def test_depth_windows_exact_on_images_wider_than_64_tiles():
    """A wide image (1040 x 24 px: 65 tile columns, more than one 64-bit word per tile row) through
    the live-tile test of the splats behind the first window: still bit-identical to one window, and
    equal to torch_ref."""
    g = torch.Generator().manual_seed(9)
    n = 8000
    means = torch.cat([torch.rand(n, 1, generator=g) * 90 - 45, torch.rand(n, 1, generator=g) * 0.6 - 0.3,
                       torch.rand(n, 1, generator=g) * 0.5], dim=1)
    splats = Splats(means=means, scales=torch.rand(n, 3, generator=g) * 0.1 + 0.05,
                    quats=torch.randn(n, 4, generator=g), opacities=torch.full((n,), 0.95),
                    colors=torch.rand(n, 3, generator=g))
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    cam = Camera(w2c, fx=40.0, fy=40.0, cx=520.0, cy=12.0, width=1040, height=24)
    bg = torch.tensor([0.3, 0.3, 0.3])
    plain = _render_with_grads(CpuRasterizer(first_window=10**9), splats, cam, bg)
    r = CpuRasterizer(first_window=200)
    out, grads = _render_with_grads(r, splats, cam, bg)
    assert r.last_stats["depth_windows"] > 1
    for name in ("color", "alpha", "depth"):
        assert torch.equal(getattr(out, name), getattr(plain[0], name)), name
    for k in ATTRS:
        assert torch.equal(grads[k], plain[1][k]), k
    assert float(plain[0].alpha.detach().mean()) > 0.5  # saturating: the windows cull
    _assert_parity(splats, cam, bg)  # and the wide-image binning itself matches torch_ref


def test_depth_windows_non_saturating_scene_bins_the_rest_at_once():
    """Where almost no pixel terminates (small, faint splats), the default rule bins everything
    after the first window at once (2 windows) and the result is still that of one window."""
    splats = random_scene(40000, seed=8, scale_range=(0.002, 0.01))
    splats.opacities = torch.full_like(splats.opacities, -3.0)  # logit: alpha <= 0.05
    cam = random_camera(64, 48, seed=8)
    bg = torch.tensor([0.5, 0.5, 0.5])
    r = CpuRasterizer(count_pairs=True)
    out, g = _render_with_grads(r, splats, cam, bg)
    assert r.last_stats["depth_windows"] == 2
    plain_out, plain_g = _render_with_grads(CpuRasterizer(first_window=10**9), splats, cam, bg)
    for name in ("color", "alpha", "depth"):
        assert torch.equal(getattr(out, name), getattr(plain_out, name)), name
    for k in ATTRS:
        assert torch.equal(g[k], plain_g[k]), k


def test_pair_statistics():
    splats = random_scene(800, seed=2)
    cam = random_camera(40, 40, seed=2)
    r = CpuRasterizer(count_pairs=True)
    _render_with_grads(r, splats, cam, torch.zeros(3))
    st = r.last_stats
    assert 0 < st["contrib_pairs"] <= st["eval_fwd"]
    assert st["eval_bwd"] <= st["eval_fwd"] and st["tile_pairs"] > 0
    assert st["contrib_pairs"] <= 40 * 40 * 800


def test_fast_exp_relative_error():
    from src.kernels.build import load_extension

    x = torch.linspace(-87.0, 0.0, 200_001)
    y = load_extension().fast_exp(x)
    ref = torch.exp(x.double())
    rel = ((y.double() - ref).abs() / ref).max().item()
    assert rel < 3e-7, rel


@pytest.mark.parametrize("n, threads", [(5000, 1), (70001, 1), (70001, 2)])
def test_depth_order_is_stable_argsort(n: int, threads: int):
    """The radix sort equals a stable argsort (any thread count), with ties, invisible splats and a
    narrow key range (constant high digits)."""
    from src.kernels.build import load_extension

    torch.set_num_threads(threads)  # the fixture restores the thread count
    g = torch.Generator().manual_seed(n)
    d = torch.rand(n, generator=g) * 3 + 0.3
    d[::7] = d[3]  # ties
    d[1::5] = 2.0 + torch.rand(len(d[1::5]), generator=g) * 1e-3  # differ in low digits only
    vis = torch.rand(n, generator=g) > 0.2
    got = load_extension().depth_order(d, vis)
    idx = torch.nonzero(vis).squeeze(1)
    want = idx[torch.argsort(d[idx], stable=True)]
    assert torch.equal(got, want)


def test_inference_without_grad():
    splats = random_scene(200, seed=1)
    cam = random_camera(30, 30, seed=1)
    with torch.no_grad():
        out = CpuRasterizer().render(splats, cam)
        ref = TorchRefRasterizer().render(splats, cam)
    assert torch.allclose(out.color, ref.color, atol=1e-5)


def test_clear_errors():
    cam = random_camera(16, 16)
    s = random_scene(10)
    with pytest.raises(TypeError, match="float32"):
        CpuRasterizer().render(s.to(dtype=torch.float64), cam)
    with pytest.raises(ValueError, match="CPU"):
        CpuRasterizer().render(s.to(device="meta"), cam)
    bad = random_scene(10)
    bad.quats = bad.quats[:, :3]
    with pytest.raises(ValueError, match="quats"):
        CpuRasterizer().render(bad, cam)
    with pytest.raises(ValueError, match="background"):
        CpuRasterizer().render(s, cam, torch.zeros(4))
    # non-contiguous inputs are fine
    nc = Splats(s.means.t().contiguous().t(), s.scales, s.quats, s.opacities, s.colors[:, [2, 1, 0]])
    assert not nc.means.is_contiguous()
    CpuRasterizer().render(nc, cam)
    # the compiled op itself checks dtypes, shapes and contiguity
    from src.kernels.build import load_extension

    ext = load_extension()
    n = 4
    args = [torch.zeros(n, 2), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, 4), torch.ones(n),
            torch.ones(n, dtype=torch.int32), torch.ones(n, dtype=torch.bool), torch.zeros(3), 16, 16,
            True, False, 0]
    with pytest.raises(RuntimeError, match="float32"):
        ext.forward(args[0].double(), *args[1:])
    with pytest.raises(RuntimeError, match="contiguous"):
        ext.forward(torch.zeros(2, n).t(), *args[1:])
    with pytest.raises(RuntimeError, match="conics"):
        ext.forward(args[0], torch.zeros(n, 2), *args[2:])


def test_import_does_not_build():
    code = ("import src.rasterizer.cpu, src.kernels.build as b; "
            "assert b._module is None; print('ok')")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr


def test_bench_smoke():
    from src.bench.rasterizer import run

    res = run([(32, 300)], reps=1, log=lambda _: None)
    row = res["rows"][0]
    assert res["peak_gflops"] > 0
    assert set(row["ms"]) >= {"cpu", "torch_ref"}
    assert row["contrib_pairs"] > 0 and row["floor_ms"] > 0
    assert row["grad_rel_err"] < 1e-5
    assert math.isfinite(row["speedup_vs_ref"])


def test_bench_floors_use_the_best_peak_of_the_run(monkeypatch):
    """The peak and bandwidth are re-measured before every row; every row's floor uses the best of
    the run (a low reading, e.g. while the host is busy, would inflate the floors), all readings are
    kept."""
    import src.bench.rasterizer as bench

    peaks = iter([100.0, 400.0, 200.0])
    bws = iter([10.0, 5.0, 20.0])
    monkeypatch.setattr(bench, "measure_peak_gflops", lambda reps=5: next(peaks))
    monkeypatch.setattr(bench, "measure_copy_gbps", lambda reps=5: next(bws))
    res = bench.run([(32, 300), (32, 400), (40, 300)], reps=1, log=lambda _: None, scenes=("cube",))
    assert res["peak_gflops"] == 400.0 and res["copy_gbps"] == 20.0
    assert res["peak_gflops_samples"] == [100.0, 400.0, 200.0]
    for row in res["rows"]:
        assert row["floor_ms"] == pytest.approx(row["contrib_pairs"] * bench.FLOPS_PER_PAIR / 400e9 * 1e3)
        traffic = (row["n_splats"] * bench.BYTES_PER_SPLAT + row["pixels"] * bench.BYTES_PER_PIXEL) / 20e9 * 1e3
        assert row["traffic_floor_ms"] == pytest.approx(traffic)
        assert row["x_floor"]["cpu"] == pytest.approx(row["ms"]["cpu"] / row["floor_ms"])


def test_bench_cube_scene_matches_the_study():
    """The ``cube`` scene has the study's 3-20 px splat radii at every width; rows name their scene
    and an unknown scene is refused with the list of known ones."""
    from src.bench.rasterizer import SCENES, run
    from src.rasterizer.projection import project_splats

    for width in (100, 400):
        splats, cam = SCENES["cube"](2000, width, 0)
        proj = project_splats(splats.means, splats.quats, splats.scales, cam)
        r = proj.radii[proj.visible].float()
        assert proj.visible.float().mean() > 0.95
        assert 2.0 <= float(r.min()) and float(r.max()) <= 30.0  # 3 sigma of +-35 % anisotropic 3-20 px
        assert 5.0 < float(r.median()) < 12.0
    res = run([(32, 200)], reps=1, log=lambda _: None, scenes=("object", "cube"))
    assert [row["scene"] for row in res["rows"]] == ["object", "cube"]
    with pytest.raises(ValueError, match="unknown scene"):
        run([(32, 200)], reps=1, log=lambda _: None, scenes=("sphere",))
