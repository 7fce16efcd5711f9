"""The fused C++ projection (src/rasterizer/projection_cpu.py) against the torch projection.

* forward: bit-identical means2d, conics, depths, radii and visible (float32 and float64) on random
  splats in every regime: behind the camera / at the near plane, beyond and exactly at the frustum
  clamp, tiny and huge scales, unnormalised quaternions, off-screen and degenerate splats;
* backward: equal to torch autograd of the torch projection (float64: to ~1e-12; float32: to float
  rounding, and at least as close to the float64 truth as torch's own float32 gradients), and to
  finite differences (``torch.autograd.gradcheck`` on the kernel in float64);
* the rasterizer: ``CpuRasterizer(projection="fused")`` renders bit-identically to
  ``projection="torch"`` with equal gradients (parity with torch_ref: tests/test_rasterizer_cpu.py).

The first test builds the extension if needed (cached on disk).
"""

from __future__ import annotations

import math

import pytest
import torch

from src.core.cameras import Camera
from src.core.splats import Splats
from src.rasterizer.cpu import CpuRasterizer
from src.rasterizer.projection import FRUSTUM_CLAMP, NEAR_PLANE, Projected, project_splats
from src.rasterizer.projection_cpu import project_splats_fused
from tests.conftest import random_camera, random_scene, rel_err, same_bits
from tests.test_rasterizer_cpu import _render_with_grads

BG = torch.tensor([0.3, 0.5, 0.7])  # background of the render-level parity checks

OUTS = ("means2d", "conics", "depths", "radii", "visible")
PARAMS = ("means", "quats", "scales")


@pytest.fixture(autouse=True)
def _one_thread():
    """Single-threaded (shared 2-core machine); the thread-count test sets 2 threads itself."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _assert_same_projection(a: Projected, b: Projected) -> None:
    for k in OUTS:
        x, y = getattr(a, k), getattr(b, k)
        assert same_bits(x, y), f"{k}: {int((x != y).sum())} of {x.numel()} entries differ"


def hard_scene(n: int, seed: int, dtype: torch.dtype = torch.float32) -> tuple[Splats, Camera]:
    """Random splats in every regime of the projection (see the module docstring)."""
    g = torch.Generator().manual_seed(seed)
    cam = random_camera(64, 48, seed=seed, dtype=dtype)
    s = random_scene(n, seed=seed, spread=1.5, scale_range=(0.01, 0.3), dtype=dtype)
    u = torch.rand(n, generator=g)
    # scales: log-uniform over 1e-7 .. 1e2, plus a few absurd ones (inf/NaN covariances)
    s.scales = torch.exp(torch.rand(n, 3, generator=g) * math.log(1e9) + math.log(1e-7)).to(dtype)
    s.scales[u < 0.02] *= 1e20
    # quaternions of norm 1e-3 .. 1e3
    s.quats = s.quats * torch.exp(torch.randn(n, 1, generator=g) * 3).to(dtype)
    # behind the camera, at the near plane, far off-screen (clamped Jacobian)
    eye = cam.center.to(dtype)
    fwd = -eye / eye.norm()  # the camera looks at the origin
    k = n // 10
    jitter = torch.randn(2 * k, 3, generator=g).to(dtype) * 0.3
    s.means[:k] = eye - fwd * (torch.rand(k, 1, generator=g).to(dtype) * 2) + jitter[:k]  # behind
    s.means[k:2 * k] = eye + fwd * (torch.rand(k, 1, generator=g).to(dtype) * 0.4) + 0.1 * jitter[k:]  # near
    side = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
    s.means[2 * k:3 * k] = (eye + fwd * 0.5 + side * (torch.randn(k, 1, generator=g).to(dtype) * 3))
    return s, cam


def clamp_camera(dtype: torch.dtype) -> Camera:
    """Identity pose (camera coordinates = world coordinates), off-centre principal point."""
    return Camera(torch.eye(4, dtype=dtype), fx=80.0, fy=90.0, cx=30.25, cy=20.5, width=64, height=48)


def clamp_scene(dtype: torch.dtype) -> tuple[Splats, Camera]:
    """Splats whose x/z or y/z equals a frustum-clamp bound exactly, or one ulp either side of it.

    With the identity pose, tx = px and tz = pz exactly, and z in {1, 2, 4} keeps x/z exact.
    """
    cam = clamp_camera(dtype)
    lims = {"x+": FRUSTUM_CLAMP * (cam.width - cam.cx) / cam.fx, "x-": -FRUSTUM_CLAMP * cam.cx / cam.fx,
            "y+": FRUSTUM_CLAMP * (cam.height - cam.cy) / cam.fy, "y-": -FRUSTUM_CLAMP * cam.cy / cam.fy}
    pts = []
    for name, lim in lims.items():
        b = torch.tensor(lim, dtype=dtype)  # the bound as torch's clamp sees it
        for v in (b, torch.nextafter(b, torch.tensor(math.inf, dtype=dtype)),
                  torch.nextafter(b, torch.tensor(-math.inf, dtype=dtype))):
            for z in (1.0, 2.0, 4.0):
                p = [0.1 * z, -0.05 * z, z]
                p[0 if name[0] == "x" else 1] = float(v) * z
                pts.append(p)
    n = len(pts)
    g = torch.Generator().manual_seed(0)
    s = Splats(means=torch.tensor(pts, dtype=dtype),
               scales=(torch.rand(n, 3, generator=g) * 0.2 + 0.05).to(dtype),
               quats=torch.randn(n, 4, generator=g).to(dtype),
               opacities=torch.full((n,), 0.5, dtype=dtype), colors=torch.rand(n, 3, generator=g).to(dtype))
    # sanity: the constructed points really sit on the bounds
    xr = s.means[:, 0] / s.means[:, 2]
    assert bool((xr == torch.tensor(lims["x+"], dtype=dtype)).any())
    return s, cam


def near_plane_scene(dtype: torch.dtype) -> tuple[Splats, Camera]:
    """Depths exactly at the near plane, one ulp around it, at 0 and negative (identity pose)."""
    cam = clamp_camera(dtype)
    near = torch.tensor(NEAR_PLANE, dtype=dtype)
    zs = [near, torch.nextafter(near, torch.tensor(1.0, dtype=dtype)),
          torch.nextafter(near, torch.tensor(0.0, dtype=dtype)), torch.tensor(0.0, dtype=dtype),
          torch.tensor(-0.5, dtype=dtype), torch.tensor(0.3, dtype=dtype)]
    z = torch.stack(zs)
    n = len(zs)
    means = torch.stack([0.01 * torch.ones(n, dtype=dtype), -0.02 * torch.ones(n, dtype=dtype), z], -1)
    g = torch.Generator().manual_seed(1)
    s = Splats(means=means, scales=torch.tensor([0.01, 0.03, 0.002], dtype=dtype).repeat(n, 1),
               quats=torch.randn(n, 4, generator=g).to(dtype), opacities=torch.full((n,), 0.5, dtype=dtype),
               colors=torch.rand(n, 3, generator=g).to(dtype))
    return s, cam


def _grads(project, s: Splats, cam: Camera, seed: int = 0) -> tuple[Projected, dict[str, torch.Tensor]]:
    """Project, backprop a random linear function of (means2d, conics, depths); return grads."""
    p = {k: getattr(s, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = project(p["means"], p["quats"], p["scales"], cam)
    g = torch.Generator().manual_seed(seed)
    dt = s.means.dtype
    loss = sum((getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g).to(dt)).sum()
               for k in ("means2d", "conics", "depths"))
    loss.backward()
    return out, {k: p[k].grad for k in PARAMS}


# ------------------------------------------------------------------------------------------------
# forward


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_bit_identical_hard_scenes(dtype: torch.dtype, seed: int):
    s, cam = hard_scene(3000, seed, dtype)
    ref = project_splats(s.means, s.quats, s.scales, cam)
    got = project_splats_fused(s.means, s.quats, s.scales, cam)
    _assert_same_projection(got, ref)
    # the scene exercises every regime
    vis = ref.visible
    assert 0.2 < vis.float().mean() < 0.95
    assert int((ref.depths <= NEAR_PLANE).sum()) > 100
    assert int((~torch.isfinite(ref.conics).all(-1)).sum()) > 0 or dtype == torch.float64
    assert int(ref.radii.max()) > 64 and int(ref.radii[vis].min()) <= 3  # low-pass minimum: 3


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_bit_identical_at_clamp_and_near_plane(dtype: torch.dtype):
    for s, cam in (clamp_scene(dtype), near_plane_scene(dtype)):
        _assert_same_projection(project_splats_fused(s.means, s.quats, s.scales, cam),
                                project_splats(s.means, s.quats, s.scales, cam))
    s, cam = near_plane_scene(dtype)
    vis = project_splats_fused(s.means, s.quats, s.scales, cam).visible
    assert vis.tolist() == [False, True, False, False, False, True]  # strictly z > near


def test_forward_standard_scenes_and_empty():
    for seed in range(3):
        s = random_scene(500, seed=seed)
        cam = random_camera(40, 30, seed=seed)
        _assert_same_projection(project_splats_fused(s.means, s.quats, s.scales, cam),
                                project_splats(s.means, s.quats, s.scales, cam))
    e = Splats.empty()
    out = project_splats_fused(e.means, e.quats, e.scales, random_camera())
    assert out.means2d.shape == (0, 2) and out.conics.shape == (0, 3) and out.radii.shape == (0,)


def test_non_contiguous_inputs_and_float64_camera():
    s = random_scene(200, seed=4)
    cam = random_camera(32, 32, seed=4, dtype=torch.float64)  # cast to float32 like the torch path
    means = s.means.t().contiguous().t()
    quats = torch.cat([s.quats, s.quats], dim=1)[:, :4]
    assert not means.is_contiguous() and not quats.is_contiguous()
    _assert_same_projection(project_splats_fused(means, quats, s.scales, cam),
                            project_splats(means.contiguous(), quats.contiguous(), s.scales, cam))


# ------------------------------------------------------------------------------------------------
# backward


@pytest.mark.parametrize("seed", [0, 1])
def test_grads_float64_match_torch_autograd(seed: int):
    """Same graph, both in float64: gradients agree to ~1e-12 per element (finite entries)."""
    s, cam = hard_scene(3000, seed, torch.float64)
    s.scales = s.scales.clamp(max=1e3)  # keep the covariances finite
    out_r, g_ref = _grads(project_splats, s, cam, seed)
    out_f, g_got = _grads(project_splats_fused, s, cam, seed)
    _assert_same_projection(out_f, out_r)
    for k in PARAMS:
        ref, got = g_ref[k], g_got[k]
        assert same_bits(torch.isfinite(ref), torch.isfinite(got)), k
        fin = torch.isfinite(ref)
        err = (got[fin] - ref[fin]).abs()
        tol = 1e-10 * ref[fin].abs() + 1e-12 * ref[fin].abs().max()
        assert bool((err <= tol).all()), f"{k}: max err {err.max():.3e}"


@pytest.mark.parametrize("seed", [0, 1])
def test_grads_float32_match_torch_autograd(seed: int):
    """float32: fused grads are within float rounding of torch's float32 autograd and at least as
    close to the float64 autograd of the same inputs (the fused backward accumulates in double)."""
    s, cam = hard_scene(3000, seed, torch.float32)
    s.scales = s.scales.clamp(max=10.0)
    _, g32 = _grads(project_splats, s, cam, seed)
    _, g64 = _grads(project_splats, s.to(dtype=torch.float64), cam.to(dtype=torch.float64), seed)
    _, gf = _grads(project_splats_fused, s, cam, seed)
    for k in PARAMS:
        err_torch32 = rel_err(g32[k], g64[k])
        err_fused = rel_err(gf[k], g64[k])
        assert rel_err(gf[k], g32[k]) < 1e-5, k
        assert err_fused <= 1.5 * err_torch32 + 1e-7, f"{k}: fused {err_fused:.2e} vs torch f32 {err_torch32:.2e}"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grads_at_clamp_bounds_and_near_plane(dtype: torch.dtype):
    """Clamp backward passes at the bound itself (torch's rule), culled splats get torch's grads."""
    for s, cam in (clamp_scene(dtype), near_plane_scene(dtype)):
        _, g_ref = _grads(project_splats, s, cam)
        _, g_got = _grads(project_splats_fused, s, cam)
        tol = 1e-10 if dtype == torch.float64 else 1e-5
        for k in PARAMS:
            assert rel_err(g_got[k], g_ref[k]) < tol, k


def test_grads_finite_differences_float64():
    """gradcheck of the kernel: visible, clamped (off-screen) and behind-camera splats, unnormalised
    quaternions, anisotropic scales; all away from the clamp/near-plane kinks."""
    s, cam = hard_scene(60, 3, torch.float64)
    g = torch.Generator().manual_seed(3)
    s.scales = torch.exp(torch.rand(60, 3, generator=g, dtype=torch.float64) * 4 - 5)  # 0.007 .. 0.37
    # unnormalised, but not so small that eps = 1e-6 is a large step on the unit sphere
    s.quats = s.quats / s.quats.norm(dim=-1, keepdim=True) * torch.exp(
        torch.rand(60, 1, generator=g, dtype=torch.float64) * 3 - 1.5)
    ref = project_splats(s.means, s.quats, s.scales, cam)
    tz, uv = ref.depths, ref.means2d
    assert int((tz <= NEAR_PLANE).sum()) >= 5 and int(ref.visible.sum()) >= 5
    off = (uv[:, 0] < -0.3 * cam.width) | (uv[:, 0] > 1.3 * cam.width)
    assert int((off & (tz > NEAR_PLANE)).sum()) >= 2, "no clamped splats in the scene"
    kink = (tz - NEAR_PLANE).abs() < 1e-3
    keep = ~kink
    means, quats, scales = (t[keep].clone().requires_grad_(True) for t in (s.means, s.quats, s.scales))

    def fn(m, q, sc):
        p = project_splats_fused(m, q, sc, cam)
        return p.means2d, p.conics, p.depths

    assert torch.autograd.gradcheck(fn, (means, quats, scales), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_grad_of_unused_outputs_and_no_grad():
    s = random_scene(100, seed=2)
    cam = random_camera(32, 32, seed=2)
    grads = []
    for project in (project_splats, project_splats_fused):
        m = s.means.clone().requires_grad_(True)
        p = project(m, s.quats, s.scales, cam)  # quats/scales do not require grad
        p.means2d.sum().backward()  # conics, depths unused
        grads.append(m.grad)
    assert rel_err(grads[1], grads[0]) < 1e-6
    assert not p.radii.requires_grad and not p.visible.requires_grad
    with torch.no_grad():
        q = project_splats_fused(s.means, s.quats, s.scales, cam)
    assert not q.means2d.requires_grad


def test_deterministic_across_threads():
    s, cam = hard_scene(20_000, 5)  # > MIN_SPLATS_PARALLEL: the OpenMP loop splits
    s.scales = s.scales.clamp(max=10.0)
    a = _grads(project_splats_fused, s, cam)
    torch.set_num_threads(2)  # the fixture restores the thread count
    b = _grads(project_splats_fused, s, cam)
    _assert_same_projection(a[0], b[0])
    for k in PARAMS:
        assert same_bits(a[1][k], b[1][k]), k


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_backward_reads_strided_gradient_rows_in_place(dtype: torch.dtype):
    """Output gradients that are column views of one wide buffer (as the CPU rasterizer's backward
    hands them over: rows of [N, R]) give bit-identical gradients to contiguous copies; so do
    broadcast (stride-0) and transposed (non-contiguous rows, copied) gradients."""
    from src.kernels.build import load_extension
    from src.rasterizer.projection_cpu import _camera_args

    s, cam = hard_scene(1003, 7, dtype)  # odd N: SIMD packs plus the scalar tail
    s.scales = s.scales.clamp(max=10.0)
    ext = load_extension()
    viewmat = cam.world_to_cam.to(dtype).contiguous()
    args = (s.means.contiguous(), s.quats.contiguous(), s.scales.contiguous(), viewmat, *_camera_args(cam))
    g = torch.Generator().manual_seed(7)
    wide = torch.randn(1003, 11, generator=g, dtype=dtype)  # [N, R]
    views = (wide[:, 1:3], wide[:, 4:7], wide[:, 9])  # means2d [N, 2], conics [N, 3], depths [N]
    assert not any(v.is_contiguous() for v in views)
    finite = ext.project_forward(*args)[5]  # [N] bool
    got = ext.project_backward(*args, *views, finite)
    want = ext.project_backward(*args, *(v.contiguous() for v in views), finite)
    for x, y in zip(got, want, strict=True):
        assert same_bits(x, y)
    # through autograd: stride-0 (expanded) and transposed gradients
    m = s.means.clone().requires_grad_(True)
    p = project_splats_fused(m, s.quats, s.scales, cam)
    gm2 = torch.randn(2, 1003, generator=g, dtype=dtype).t()  # [N, 2], non-contiguous rows
    gdep = torch.ones((), dtype=dtype).expand(1003)  # [N], stride 0
    torch.autograd.backward([p.means2d, p.depths], [gm2, gdep])
    m2 = s.means.clone().requires_grad_(True)
    p2 = project_splats_fused(m2, s.quats, s.scales, cam)
    torch.autograd.backward([p2.means2d, p2.depths], [gm2.contiguous(), gdep.contiguous()])
    assert same_bits(m.grad, m2.grad)


def _grads_given(project, s: Splats, cam: Camera, out_grads: list[torch.Tensor]) -> dict[str, torch.Tensor]:
    """Project and backpropagate the given gradients of (means2d, conics, depths)."""
    p = {k: getattr(s, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = project(p["means"], p["quats"], p["scales"], cam)
    torch.autograd.backward([out.means2d, out.conics, out.depths], out_grads)
    return {k: p[k].grad for k in PARAMS}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_output_gradients_skip_is_exact(dtype: torch.dtype):
    """Splats whose output gradients are all zero (occluded ones, in a render) take the shortcut of
    zero gradients where the forward intermediates are finite: the same as torch autograd (0, or
    non-finite where an intermediate overflows, for which the full chain rule runs); the other
    ("live") splats, staged into SIMD packs and a scalar tail, are bit-identical to a run without
    any zero-gradient splat (lanes are independent)."""
    n = 2003
    s, cam = hard_scene(n, 3, dtype)
    s.scales = s.scales.clamp(max=10.0)
    s.scales[-7:] = 1e30 if dtype == torch.float32 else 1e300  # covariance overflows to inf
    g = torch.Generator().manual_seed(3)
    keep = torch.rand(n, generator=g) < 0.3
    keep[:400] = False  # whole packs of zero-gradient splats
    keep[-3] = True
    out_grads = [torch.randn(n, 2, generator=g).to(dtype), torch.randn(n, 3, generator=g).to(dtype),
                 torch.randn(n, generator=g).to(dtype)]
    masked = [out_grads[0] * keep[:, None], out_grads[1] * keep[:, None], out_grads[2] * keep]
    g_ref = _grads_given(project_splats, s, cam, masked)
    g_got = _grads_given(project_splats_fused, s, cam, masked)
    sub = Splats(s.means[keep], s.scales[keep], s.quats[keep], s.opacities[keep], s.colors[keep])
    g_sub = _grads_given(project_splats_fused, sub, cam, [t[keep] for t in out_grads])
    zero_rows = ~keep
    for k in PARAMS:
        ref, got = g_ref[k][zero_rows], g_got[k][zero_rows]
        assert same_bits(torch.isfinite(got), torch.isfinite(ref)), k
        assert bool((got[torch.isfinite(got)] == 0).all()), k
        assert not bool(torch.isfinite(g_got[k][-7:][zero_rows[-7:]]).all()), k  # as torch: not finite
        assert same_bits(g_got[k][keep], g_sub[k]), k


def test_camera_with_grad_falls_back_to_torch():
    s = random_scene(50, seed=1)
    cam = random_camera(32, 32, seed=1)
    w2c = cam.world_to_cam.clone().requires_grad_(True)
    cam_g = Camera(w2c, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    p = project_splats_fused(s.means, s.quats, s.scales, cam_g)
    p.means2d.sum().backward()
    assert w2c.grad is not None and w2c.grad.abs().sum() > 0


def test_clear_errors():
    s = random_scene(10)
    cam = random_camera()
    with pytest.raises(TypeError, match="float64"):
        project_splats_fused(s.means, s.quats.double(), s.scales, cam)
    with pytest.raises(ValueError, match="quats"):
        project_splats_fused(s.means, s.quats[:, :3], s.scales, cam)
    with pytest.raises(ValueError, match="CPU"):
        project_splats_fused(s.means.to("meta"), s.quats, s.scales, cam)
    with pytest.raises(TypeError, match="float32/float64"):
        project_splats_fused(s.means.half(), s.quats.half(), s.scales.half(), cam)
    with pytest.raises(ValueError, match="projection"):
        CpuRasterizer(projection="nope")


# ------------------------------------------------------------------------------------------------
# rasterizer


@pytest.mark.parametrize("seed", [0, 1])
def test_rasterizer_fused_vs_torch_projection(seed: int):
    """Bit-identical images (the projection forward is bit-identical), gradients to float rounding;
    the screen-space gradient (densification statistic) reaches the returned means2d."""
    s = random_scene(600, seed=seed, scale_range=(0.01, 0.15))
    cam = random_camera(48, 40, seed=seed)
    out_t, g_t = _render_with_grads(CpuRasterizer(projection="torch"), s, cam, BG, seed)
    out_f, g_f = _render_with_grads(CpuRasterizer(), s, cam, BG, seed)
    for k in ("color", "alpha", "depth", "radii"):
        assert torch.equal(getattr(out_f, k), getattr(out_t, k)), k
    assert torch.equal(g_f["means2d"], g_t["means2d"])
    assert torch.equal(g_f["opacities"], g_t["opacities"]) and torch.equal(g_f["colors"], g_t["colors"])
    for k in PARAMS:
        assert rel_err(g_f[k], g_t[k]) < 1e-5, k


def test_cpu_config_uses_fused_projection():
    from pathlib import Path

    from omegaconf import OmegaConf

    from src.utils.instantiate import build

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "rasterizer" / "cpu.yaml")
    assert cfg.projection == "fused"
    rast = build(cfg)
    assert isinstance(rast, CpuRasterizer) and rast.projection == "fused"
    assert cfg.first_window == 0 and rast.first_window == 0  # the knob reaches the rasterizer
    assert CpuRasterizer().projection == "fused"


def test_bench_reports_projection_times():
    from src.bench.rasterizer import format_table, run

    res = run([(32, 300)], reps=1, log=lambda _: None)
    row = res["rows"][0]
    assert set(row["proj_ms"]) == {"torch", "fused"} and set(row["proj_ms_min"]) == {"torch", "fused"}
    assert all(v > 0 for v in row["proj_ms"].values())
    assert {"cpu", "cpu_torch_proj", "torch_ref"} <= set(row["ms"])
    assert row["grad_rel_err"] < 1e-5  # existing keys unchanged
    table = format_table(res)
    assert "proj fused ms" in table and "cpu_torch_proj ms" in table
    # the memory-traffic floor: 112 B per splat + 40 B per pixel at the measured copy bandwidth
    assert res["copy_gbps"] > 0
    expect = (300 * 112 + 32 * 32 * 40) / (res["copy_gbps"] * 1e9) * 1e3
    assert abs(row["traffic_floor_ms"] - expect) < 1e-9 * expect + 1e-12
    bound = max(row["floor_ms"], row["traffic_floor_ms"])
    for k, v in row["ms"].items():
        assert abs(row["x_bound"][k] - v / bound) < 1e-9 * row["x_bound"][k]
        assert row["x_bound"][k] <= row["x_floor"][k] + 1e-12
    assert "traffic floor ms" in table and "cpu x max(floors)" in table


def test_build_cache_key_is_stable():
    """The projection's cache directory is the one its build key names (torch's loader appends to
    the flag lists it is given; the keys must not depend on what was loaded before)."""
    import src.kernels.build as b

    b.load_extension()
    key = b.build_key(b.projection_compile_flags(), b.PROJ_SOURCES)
    assert (b.cache_root() / f"project_cpu_{key}").is_dir()
    assert b.LDFLAGS == ["-fopenmp"]
