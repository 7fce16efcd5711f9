"""Mip-Splatting (Yu et al., CVPR 2024): the 3D smoothing filter and the 2D Mip filter.

* 3D filter (src/models/mip_splatting.py): the effective scales sqrt(s_i^2 + sigma^2) give the
  explicitly filtered covariance R S^2 R^T + sigma^2 I, the opacity factor is
  sqrt(det(Sigma) / det(Sigma + sigma^2 I)) (the filtered splat keeps its integral), the sampling
  rate nu = max f / z over the cameras whose frustum holds the centre, sigma^2 = s / nu^2, and the
  model keeps its filter in step with densification, pruning, the opacity reset and checkpoints;
* 2D Mip filter (the ``antialiased`` projection): the compensation equals
  sqrt(det(Sigma2D) / det(Sigma2D + 0.1 I)) computed from explicit matrices; the compiled projection
  is bit-identical to the torch one and its hand-written backward (compensation included) equals
  torch autograd; gradcheck (float64) of the torch reference and of the kernel; the CPU rasterizer
  renders like the torch reference with equal gradients; the default mode is unchanged.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from src.core.cameras import Camera
from src.core.splats import Splats
from src.fields.flows import quat_to_rotmat_wxyz
from src.models.gaussians import GaussianSplatModel
from src.models.mip_splatting import MipGaussianSplatModel, filter_variance, max_sampling_rate, smoothed_scales
from src.rasterizer.cpu import CpuRasterizer
from src.rasterizer.projection import AA_RATIO_MIN, EPS2D, project_splats
from src.rasterizer.projection_cpu import project_splats_fused
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene, rel_err, same_bits
from tests.test_projection_cpu import hard_scene

PARAMS = ("means", "quats", "scales")
ATTRS = ("means", "scales", "quats", "opacities", "colors")
OUTS = ("means2d", "conics", "depths", "radii", "visible", "compensation")

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.usefixtures("one_thread")


# ------------------------------------------------------------------------------------------------
# 3D smoothing filter: math


def test_smoothed_scales_equal_the_explicitly_filtered_covariance():
    g = torch.Generator().manual_seed(0)
    n = 50
    log_s = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 6 - 7)  # 1e-3 .. 0.4
    var = torch.rand(n, generator=g, dtype=torch.float64) * 1e-3
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    R = quat_to_rotmat_wxyz(q)  # [N, 3, 3]
    s = log_s.exp()
    cov = R @ torch.diag_embed(s * s) @ R.transpose(1, 2)
    cov_f = cov + var[:, None, None] * torch.eye(3, dtype=torch.float64)
    scales, factor = smoothed_scales(log_s, var)
    assert torch.allclose(R @ torch.diag_embed(scales * scales) @ R.transpose(1, 2), cov_f, rtol=1e-12, atol=1e-18)
    # 3D opacity compensation: sqrt(det(Sigma) / det(Sigma + var I)), the integral alpha sqrt(det) is kept
    want = torch.sqrt(torch.linalg.det(cov) / torch.linalg.det(cov_f))
    assert torch.allclose(factor, want, rtol=1e-9)
    assert torch.allclose(factor * scales.prod(-1), s.prod(-1), rtol=1e-12)
    assert bool((factor < 1).all())
    # no filter: the splat itself, factor exactly 1; finite gradients even where s^2 underflows
    scales0, factor0 = smoothed_scales(log_s, torch.zeros(n, dtype=torch.float64))
    assert torch.allclose(scales0, s, rtol=1e-15) and bool((factor0 == 1).all())
    tiny = torch.tensor([[-80.0, -3.0, 0.5]], requires_grad=True)  # exp(-160) underflows in float32
    sc, fa = smoothed_scales(tiny, torch.tensor([1e-4]))
    (sc.sum() + fa.sum()).backward()
    assert bool(torch.isfinite(tiny.grad).all()) and float(sc[0, 0].detach()) == pytest.approx(1e-2, rel=1e-5)


def _camera(eye: tuple[float, float, float], f: float = 50.0, size: int = 40) -> Camera:
    """Axis-aligned camera looking along +z from ``eye`` (identity rotation)."""
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = -torch.tensor(eye, dtype=torch.float64)
    return Camera(w2c, fx=f, fy=f, cx=size / 2, cy=size / 2, width=size, height=size)


def test_sampling_rate_is_the_max_focal_over_depth_of_the_cameras_that_see_the_point():
    near_cam = _camera((0.0, 0.0, -1.0), f=50.0)  # the origin at depth 1
    far_cam = _camera((0.0, 0.0, -4.0), f=100.0)  # ... at depth 4
    pts = torch.tensor([
        [0.0, 0.0, 0.0],     # both: max(50 / 1, 100 / 4) = 50
        [0.0, 0.0, 1.0],     # both: max(50 / 2, 100 / 5) = 25
        [0.5, 0.0, 0.0],     # near: u = 45 = 20 + 25 > 1.15 x 40 = 46? no: 45 <= 46 -> seen (margin); far too
        [0.6, 0.0, 0.0],     # near: u = 50 > 46 (outside even with the 15% margin); far: u = 35 -> 100 / 4
        [0.0, 0.0, -3.9],    # behind the near camera, at depth 0.1 <= near plane of the far one
        [0.0, 0.0, -5.0],    # behind both
    ], dtype=torch.float64)
    nu = max_sampling_rate(pts, [near_cam, far_cam])
    assert nu.tolist() == pytest.approx([50.0, 25.0, 50.0, 25.0, 0.0, 0.0])
    assert max_sampling_rate(pts, [near_cam], margin=0.0)[2] == 0.0  # no margin: u = 45 > 40
    var = filter_variance(nu, 0.2)
    assert var.tolist() == pytest.approx([0.2 / 50**2, 0.2 / 25**2, 0.2 / 50**2, 0.2 / 25**2,
                                          0.2 / 25**2, 0.2 / 25**2])  # unseen: the lowest seen rate
    assert filter_variance(torch.zeros(3), 0.2).tolist() == [0.0, 0.0, 0.0]


# ------------------------------------------------------------------------------------------------
# 3D smoothing filter: the model


def _scene(cams: list[Camera]) -> SimpleNamespace:
    return SimpleNamespace(train=[SimpleNamespace(camera=c) for c in cams])


def _model(n: int = 64, seed: int = 0, **kw) -> tuple[MipGaussianSplatModel, list[Camera]]:
    g = torch.Generator().manual_seed(seed)
    init = torch.rand(n, 3, generator=g) * 0.6 - 0.3
    model = MipGaussianSplatModel(init, sh_degree=0, **kw)
    cams = [random_camera(40, 30, seed=s) for s in range(3)]
    model.bind(_scene(cams))
    return model, cams


def test_model_renders_the_filtered_splats():
    model, cams = _model()
    var = filter_variance(max_sampling_rate(model.params["means"], cams), 0.2)
    assert torch.equal(model.filter_var, var) and bool((var > 0).all())
    s = model.splats(cams[0])
    raw = GaussianSplatModel.splats(model, cams[0])
    want_scales, factor = smoothed_scales(model.params["scales"], var)
    assert torch.allclose(s.scales, want_scales) and bool((s.scales > raw.scales).all())
    assert torch.allclose(s.opacities, raw.opacities * factor)
    b = model.bake()
    assert torch.allclose(b.scales, s.scales) and torch.allclose(b.opacities, s.opacities)
    # gradients reach the raw parameters through the filter
    (s.scales.sum() + s.opacities.sum()).backward()
    assert bool((model.params["scales"].grad.abs() > 0).all())


def test_model_filter_follows_densification_pruning_and_steps():
    model, cams = _model(filter_every=10)
    g = torch.Generator().manual_seed(1)
    n = model.n_splats
    clone = torch.zeros(n, dtype=torch.bool)
    clone[:5] = True
    split = torch.zeros(n, dtype=torch.bool)
    split[5:9] = True
    model.densify(None, clone, split, 2, g)
    assert model.filter_var.shape == (n + 5 + 4,)

    def fresh() -> torch.Tensor:
        return filter_variance(max_sampling_rate(model.params["means"], cams), 0.2)

    assert torch.equal(model.filter_var, fresh())
    model.prune(None, torch.arange(model.n_splats) % 3 == 0)
    assert torch.equal(model.filter_var, fresh())
    with torch.no_grad():
        model.params["means"] += 0.05  # the splats move: the rate is refreshed at the interval only
    stale = model.filter_var.clone()
    model.on_step(9)
    assert torch.equal(model.filter_var, stale)
    model.on_step(10)
    assert torch.equal(model.filter_var, fresh()) and not torch.equal(stale, fresh())


def test_opacity_reset_clamps_the_filtered_opacity():
    model, cams = _model()
    with torch.no_grad():
        model.params["opacities"].uniform_(-3.0, 6.0)
    before = model.splats(cams[0]).opacities.detach()
    raw_before = torch.sigmoid(model.params["opacities"].detach())
    model.reset_opacity(None, 0.01)
    after = model.splats(cams[0]).opacities.detach()
    assert torch.allclose(after, torch.minimum(before, torch.full_like(before, 0.01)), rtol=1e-4, atol=1e-9)
    assert bool((torch.sigmoid(model.params["opacities"].detach()) <= raw_before + 1e-7).all())


def test_model_checkpoint_round_trip_with_another_splat_count():
    model, cams = _model(n=64)
    other, _ = _model(n=30, seed=3)
    other.load_state_dict(model.state_dict())
    assert other.n_splats == 64 and torch.equal(other.filter_var, model.filter_var)
    assert torch.equal(other.splats(cams[0]).scales, model.splats(cams[0]).scales)


# ------------------------------------------------------------------------------------------------
# 2D Mip filter: projection


def _explicit_cov2d(s: Splats, cam: Camera) -> torch.Tensor:
    """[N, 2, 2] J W Sigma W^T J^T from 3x3 matrices (float64; no frustum clamp: on-screen splats)."""
    R = quat_to_rotmat_wxyz(torch.nn.functional.normalize(s.quats, dim=-1))
    cov = R @ torch.diag_embed(s.scales**2) @ R.transpose(1, 2)
    W = cam.world_to_cam[:3, :3]
    t = s.means @ W.T + cam.world_to_cam[:3, 3]
    z = t[:, 2]
    J = torch.zeros(len(s), 2, 3, dtype=torch.float64)
    J[:, 0, 0] = cam.fx / z
    J[:, 0, 2] = -cam.fx * t[:, 0] / z**2
    J[:, 1, 1] = cam.fy / z
    J[:, 1, 2] = -cam.fy * t[:, 1] / z**2
    T = J @ W
    return T @ cov @ T.transpose(1, 2)


def test_compensation_equals_the_determinant_ratio_of_explicit_matrices():
    s = random_scene(200, seed=3, dtype=torch.float64, spread=0.3, scale_range=(1e-4, 0.05))
    cam = random_camera(48, 40, seed=3, dtype=torch.float64)
    p = project_splats(s.means, s.quats, s.scales, cam, eps2d=0.1, antialiased=True)
    cov2d = _explicit_cov2d(s, cam)
    filt = cov2d + 0.1 * torch.eye(2, dtype=torch.float64)
    want = torch.sqrt(torch.clamp(torch.linalg.det(cov2d) / torch.linalg.det(filt), min=AA_RATIO_MIN))
    vis = p.visible
    assert int(vis.sum()) > 150
    assert torch.allclose(p.compensation[vis], want[vis], rtol=1e-7, atol=1e-9)
    conic = torch.linalg.inv(filt)
    assert torch.allclose(p.conics[vis], torch.stack([conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]], -1)[vis],
                          rtol=1e-7)
    assert float(p.compensation[vis].min()) < 0.5  # sub-pixel splats are dimmed
    # the 3DGS mode is the same projection with eps2d = 0.3 and no compensation
    d = project_splats(s.means, s.quats, s.scales, cam)
    a = project_splats(s.means, s.quats, s.scales, cam, eps2d=EPS2D, antialiased=True)
    assert d.compensation is None
    for k in OUTS[:-1]:
        assert same_bits(getattr(a, k), getattr(d, k)), k


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_fused_antialiased_forward_bit_identical(dtype: torch.dtype, seed: int):
    s, cam = hard_scene(3001, seed, dtype)  # odd N: SIMD packs and the scalar tail
    ref = project_splats(s.means, s.quats, s.scales, cam, eps2d=0.1, antialiased=True)
    got = project_splats_fused(s.means, s.quats, s.scales, cam, eps2d=0.1, antialiased=True)
    for k in OUTS:
        x, y = getattr(got, k), getattr(ref, k)
        assert same_bits(x, y), f"{k}: {int((x != y).sum())} of {x.numel()} differ"
    comp = ref.compensation[ref.visible]
    assert float(comp.min()) == pytest.approx(math.sqrt(AA_RATIO_MIN), rel=1e-5)  # the floor is reached
    assert 0.1 < float(comp.median()) < 1.0


def _cancellation(p) -> torch.Tensor:
    """[N] |a c| / |a c - b^2| of the unfiltered 2D covariance (recovered from the conics, filter 0.1)."""
    A, B, C = p.conics.detach().unbind(-1)
    det = A * C - B * B
    a, b, c = C / det - 0.1, -B / det, A / det - 0.1
    return (a * c).abs() / (a * c - b * b).abs()


def _grads(project, s: Splats, cam: Camera, seed: int = 0, outs=("means2d", "conics", "depths", "compensation")):
    """Project (antialiased), backprop a random linear function of ``outs``; return (out, grads).

    The compensation's weights are zero on culled splats, as in a render (their opacity is unused),
    and on splats whose det(Sigma2D) = a c - b^2 cancels by more than 100x (needles of thousands of
    px^2: both implementations then differ by that cancellation times the rounding error, which the
    per-element tolerance below does not allow; their forward is still bit-identical).
    """
    p = {k: getattr(s, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = project(p["means"], p["quats"], p["scales"], cam, eps2d=0.1, antialiased=True)
    g = torch.Generator().manual_seed(seed)
    dt = s.means.dtype
    loss = 0
    for k in outs:
        w = torch.randn(getattr(out, k).shape, generator=g).to(dt)
        if k == "compensation":
            w = w * (out.visible & (_cancellation(out) < 100))
        loss = loss + (getattr(out, k) * w).sum()
    loss.backward()
    return out, {k: p[k].grad for k in PARAMS}


@pytest.mark.parametrize("outs", [("means2d", "conics", "depths", "compensation"), ("compensation",)])
def test_fused_antialiased_grads_float64_match_torch_autograd(outs):
    """Also with the compensation's gradient alone (splats whose other incoming gradients are zero
    must not take the zero-gradient shortcut)."""
    s, cam = hard_scene(3000, 1, torch.float64)
    s.scales = s.scales.clamp(max=1e3)
    out, g_ref = _grads(project_splats, s, cam, 1, outs)
    _, g_got = _grads(project_splats_fused, s, cam, 1, outs)
    assert int((out.visible & (_cancellation(out) < 100)).sum()) > 500
    for k in PARAMS:
        ref, got = g_ref[k], g_got[k]
        assert same_bits(torch.isfinite(ref), torch.isfinite(got)), k
        fin = torch.isfinite(ref)
        err = (got[fin] - ref[fin]).abs()
        tol = 1e-10 * ref[fin].abs() + 1e-12 * ref[fin].abs().max()
        assert bool((err <= tol).all()), f"{k}: max err {err.max():.3e}"
        assert float(ref[fin].abs().max()) > 0


def test_fused_antialiased_grads_float32_match_torch_autograd():
    s, cam = hard_scene(3000, 0, torch.float32)
    s.scales = s.scales.clamp(max=10.0)
    _, g32 = _grads(project_splats, s, cam)
    _, g64 = _grads(project_splats, s.to(dtype=torch.float64), cam.to(dtype=torch.float64))
    _, gf = _grads(project_splats_fused, s, cam)
    for k in PARAMS:
        assert rel_err(gf[k], g32[k]) < 1e-3, k
        assert rel_err(gf[k], g64[k]) <= 1.5 * rel_err(g32[k], g64[k]) + 1e-7, k


def _gradcheck_scene(n: int = 12) -> tuple[Splats, Camera]:
    """A few on-screen splats, sub-pixel to a few pixels wide (the compensation varies), float64."""
    s = random_scene(n, seed=5, dtype=torch.float64, spread=0.3, scale_range=(0.002, 0.05))
    return s, random_camera(24, 20, seed=5, dtype=torch.float64)


def test_torch_reference_compensation_gradcheck():
    s, cam = _gradcheck_scene()
    p = project_splats(s.means, s.quats, s.scales, cam, eps2d=0.1, antialiased=True)
    assert bool(p.visible.all()) and float(p.compensation.min()) < 0.9
    inputs = tuple(t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales))

    def fn(m, q, sc):
        out = project_splats(m, q, sc, cam, eps2d=0.1, antialiased=True)
        return out.conics, out.compensation

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_fused_compensation_gradcheck():
    s, cam = _gradcheck_scene()
    inputs = tuple(t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales))

    def fn(m, q, sc):
        out = project_splats_fused(m, q, sc, cam, eps2d=0.1, antialiased=True)
        return out.means2d, out.conics, out.depths, out.compensation

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_torch_reference_antialiased_render_gradcheck():
    """The whole antialiased torch_ref render (float64), opacities and scales included."""
    s, cam = _gradcheck_scene(6)
    rast = TorchRefRasterizer(antialiased=True, filter_2d=0.1)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    inputs = tuple(getattr(s, k).clone().requires_grad_(True) for k in ("means", "scales", "opacities"))

    def fn(m, sc, o):
        out = rast.render(Splats(means=m, scales=sc, quats=s.quats, opacities=o, colors=s.colors), cam, bg)
        return out.color, out.alpha

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


# ------------------------------------------------------------------------------------------------
# 2D Mip filter: rasterizers


def _render_with_grads(rast, splats: Splats, cam: Camera, bg: torch.Tensor, seed: int = 0):
    params = {k: getattr(splats, k).detach().clone().requires_grad_(True) for k in ATTRS}
    out = rast.render(Splats(**params), cam, bg)
    g = torch.Generator().manual_seed(seed)
    H, W, C = out.color.shape
    loss = ((out.color * torch.rand(H, W, C, generator=g)).sum() + (out.alpha * torch.rand(H, W, generator=g)).sum()
            + (out.depth * torch.rand(H, W, generator=g) * 0.1).sum())
    loss.backward()
    return out, {k: params[k].grad for k in ATTRS}


@pytest.mark.parametrize("seed", [0, 1])
def test_cpu_antialiased_render_matches_torch_ref(seed: int):
    s = random_scene(300, seed=seed, spread=0.4, scale_range=(0.002, 0.06))  # many sub-pixel splats
    cam = random_camera(40, 32, seed=seed)
    bg = torch.tensor([0.3, 0.5, 0.7])
    ref_out, ref_g = _render_with_grads(TorchRefRasterizer(antialiased=True), s, cam, bg, seed)
    outs = {p: _render_with_grads(CpuRasterizer(antialiased=True, projection=p), s, cam, bg, seed)
            for p in ("fused", "torch")}
    for out, g in outs.values():
        for name in ("color", "alpha", "depth"):
            a, b = getattr(out, name), getattr(ref_out, name)
            assert torch.allclose(a, b, atol=1e-5, rtol=1e-5), f"{name}: max diff {(a - b).abs().max():.2e}"
        for k in ATTRS:
            assert rel_err(g[k], ref_g[k]) < 1e-4, k
    # the compiled projection renders bit-identically to the torch projection inside the cpu rasterizer
    for name in ("color", "alpha", "depth"):
        assert torch.equal(getattr(outs["fused"][0], name), getattr(outs["torch"][0], name)), name
    # the filter changes the image: no dilation, sub-pixel splats dimmed
    plain = CpuRasterizer().render(s, cam, bg)
    assert float((plain.color - outs["fused"][0].color.detach()).abs().max()) > 1e-2


@pytest.mark.parametrize("rasterizer", ["auto", "cpu", "torch_ref"])
def test_experiment_selects_both_filters(rasterizer: str):
    """+experiment=mip_splatting: the Mip model (s = 0.2) and the 2D Mip filter (0.1 px^2) with any CPU backend."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from src.utils.instantiate import build

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["+experiment=mip_splatting", f"rasterizer={rasterizer}"])
    rast = build(cfg.rasterizer)
    assert rast.antialiased is True and rast.filter_2d == 0.1
    model = build(cfg.model, init=torch.rand(20, 3), n_frames=1)
    assert isinstance(model, MipGaussianSplatModel) and model.filter_scale == 0.2
    assert cfg.method == "mip_splatting"


def test_default_rasterizers_are_not_antialiased():
    s = random_scene(100, seed=4)
    cam = random_camera(32, 32, seed=4)
    for cls in (CpuRasterizer, TorchRefRasterizer):
        assert cls().antialiased is False
        a = cls().render(s, cam)
        b = cls(antialiased=False, filter_2d=0.5).render(s, cam)  # the filter variance is unused then
        assert torch.equal(a.color, b.color)
