"""2D Gaussian Splatting (Huang et al., SIGGRAPH 2024): the surfel rasterizer, its losses and the model.

* the torch reference against closed forms: a fronto-parallel surfel is exactly its perspective Gaussian,
  an edge-on one is the object-space low-pass filter alone, a tilted one matches an explicit 3D ray-plane
  intersection, the rectangle holds the projected 3-sigma disk, normals face the camera, two stacked
  surfels give w1 w2 (m1 - m2)^2 of distortion;
* gradcheck (float64) of the reference and of the compiled kernel; the kernel equals the reference in
  values and gradients (float64, several scenes including stacked opaque surfels, edge-on and near-plane
  ones) and in values in float32;
* the losses (depth normals of a plane, normal consistency of a flat surfel, the iteration offsets), the
  model (two scales, in-plane splits, baking) and the ``surfels`` option of every rasterizer.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from src.core.cameras import Camera
from src.core.splats import Splats, SurfelRenderOutput
from src.losses.surfel import SurfelLoss, depth_normals, normal_consistency
from src.models.surfels import SurfelSplatModel
from src.rasterizer.cpu import CpuRasterizer
from src.rasterizer.surfel_cpu import render_surfels_cpu
from src.rasterizer.surfel_ref import ALPHA_MIN, DIST_FAR, DIST_NEAR, project_surfels, quat_to_axes, render_surfels_ref
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64


def _camera(width: int = 24, height: int = 20, f: float = 30.0, dist: float = 3.0, dtype=F64) -> Camera:
    """Camera at (0, 0, -dist) looking along +z (identity rotation), principal point at the image centre."""
    w2c = torch.eye(4, dtype=dtype)
    w2c[2, 3] = dist
    return Camera(w2c, fx=f, fy=f * 1.1, cx=width / 2, cy=height / 2, width=width, height=height)


def _surfels(means, scales, quats, opac, colors=None) -> Splats:
    means = torch.as_tensor(means, dtype=F64).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.as_tensor(scales, dtype=F64).reshape(n, -1)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=F64) if colors is None else colors
    return Splats(means=means, scales=torch.cat([scales, torch.zeros(n, 1, dtype=F64)], 1),
                  quats=torch.as_tensor(quats, dtype=F64).reshape(n, 4),
                  opacities=torch.as_tensor(opac, dtype=F64).reshape(n), colors=colors)


def _pixels(cam: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    jj, ii = torch.meshgrid(torch.arange(cam.height, dtype=F64), torch.arange(cam.width, dtype=F64), indexing="ij")
    return ii + 0.5, jj + 0.5  # [H, W] pixel centres x, y


def _explicit_uv(s: Splats, cam: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(u, v, depth) [H, W] of one surfel by intersecting each pixel's 3D ray with its plane."""
    x, y = _pixels(cam)
    d_cam = torch.stack([(x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy, torch.ones_like(x)], -1)  # [H, W, 3]
    R = cam.world_to_cam[:3, :3]
    o = cam.center
    d = d_cam @ R  # world directions R^T d
    tu, tv, tw = (a[0] for a in quat_to_axes(s.quats))
    p = s.means[0]
    t = ((p - o) @ tw) / (d @ tw)  # [H, W] ray parameter (z-depth, as d_cam has z = 1)
    P = o + t[..., None] * d
    return ((P - p) @ tu) / s.scales[0, 0], ((P - p) @ tv) / s.scales[0, 1], t


# ------------------------------------------------------------------------------------------------
# the reference against closed forms


def test_fronto_parallel_surfel_is_its_perspective_gaussian():
    cam = _camera()
    s = _surfels([0.1, -0.05, 0.0], [0.3, 0.2], [1.0, 0.0, 0.0, 0.0], [0.8])
    out = render_surfels_ref(s, cam)
    x, y = _pixels(cam)
    z = 3.0
    u = (x - (cam.fx * 0.1 / z + cam.cx)) * z / (cam.fx * 0.3)
    v = (y - (cam.fy * -0.05 / z + cam.cy)) * z / (cam.fy * 0.2)
    c = out.means2d[0].detach()
    filt = torch.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2))  # G(|x - c| / sigma), sigma = sqrt(2) / 2
    want = 0.8 * torch.maximum(torch.exp(-0.5 * (u * u + v * v)), filt)
    rect = project_surfels(s.means, s.quats, s.scales, cam).rects[0]
    inside = torch.zeros_like(want, dtype=torch.bool)
    inside[rect[1]:rect[3] + 1, rect[0]:rect[2] + 1] = True
    want = torch.where(inside & (want >= ALPHA_MIN), want, torch.zeros_like(want))
    assert torch.allclose(out.alpha, want, atol=1e-12)
    assert bool((want > 0.5).any()) and bool((out.alpha[~inside] == 0).all())
    # the plane is at depth 3 everywhere, the normal (world) faces the camera: -z
    hit = out.alpha > 0
    assert torch.allclose(out.depth[hit] / out.alpha[hit], torch.full_like(out.depth[hit], z), atol=1e-12)
    n = out.normals[hit] / out.alpha[hit][:, None]
    assert torch.allclose(n, torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand_as(n), atol=1e-12)
    assert torch.allclose(out.distortion, torch.zeros_like(out.distortion))  # one surfel: no pair


def test_edge_on_surfel_is_the_low_pass_filter_at_its_centre_depth():
    cam = _camera()
    q = [math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]  # normal along world x: edge-on to the camera
    s = _surfels([0.0, 0.0, 0.5], [0.3, 0.3], q, [0.9])
    out = render_surfels_ref(s, cam)
    x, y = _pixels(cam)
    c = out.means2d[0].detach()
    want = 0.9 * torch.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2))
    want = torch.where(want >= ALPHA_MIN, want, torch.zeros_like(want))
    assert torch.allclose(out.alpha, want, atol=1e-12) and float(out.alpha.max()) > 0.3
    hit = out.alpha > 0
    assert torch.allclose(out.depth[hit] / out.alpha[hit], torch.full_like(out.depth[hit], 3.5), atol=1e-12)


def test_tilted_surfel_matches_an_explicit_ray_plane_intersection():
    cam = random_camera(26, 22, seed=3, dtype=F64)
    q = torch.tensor([0.8, 0.3, -0.4, 0.2], dtype=F64)
    s = _surfels([0.05, 0.1, -0.1], [0.45, 0.25], q, [0.95])
    out = render_surfels_ref(s, cam)
    u, v, t = _explicit_uv(s, cam)
    x, y = _pixels(cam)
    c = out.means2d[0].detach()
    rho3d = u * u + v * v
    rho2d = 2 * ((x - c[0]) ** 2 + (y - c[1]) ** 2)
    want = 0.95 * torch.exp(-0.5 * torch.minimum(rho3d, rho2d))
    rect = project_surfels(s.means, s.quats, s.scales, cam).rects[0]
    inside = torch.zeros_like(want, dtype=torch.bool)
    inside[rect[1]:rect[3] + 1, rect[0]:rect[2] + 1] = True
    # the rectangle holds the projected 3-sigma disk (and the filter's 3-sigma square)
    assert bool(inside[(rho3d <= 9) & (t > 0)].all()) and bool(inside[rho2d <= 9].all())
    want = torch.where(inside & (want >= ALPHA_MIN), want, torch.zeros_like(want))
    assert torch.allclose(out.alpha, want, atol=1e-12)
    surface = (rho3d <= rho2d) & (out.alpha > 0)
    assert int(surface.sum()) > 20
    assert torch.allclose(out.depth[surface] / out.alpha[surface], t[surface], atol=1e-10)


def test_normals_face_the_camera_whatever_the_quaternion_sign_of_the_normal():
    cam = random_camera(20, 20, seed=1, dtype=F64)
    q = torch.tensor([[0.9, 0.2, 0.3, -0.1]], dtype=F64)
    w, x, y, z = q[0]
    flipped = torch.tensor([[-x, w, z, -y]], dtype=F64)  # q * (0, 1, 0, 0): 180 deg about t_u, normal reversed
    assert torch.allclose(quat_to_axes(flipped)[2], -quat_to_axes(q)[2], atol=1e-12)
    a = render_surfels_ref(_surfels([0.0, 0.0, 0.0], [0.4, 0.3], q, [0.7]), cam)
    b = render_surfels_ref(_surfels([0.0, 0.0, 0.0], [0.4, 0.3], flipped, [0.7]), cam)
    assert torch.allclose(a.alpha, b.alpha, atol=1e-12) and torch.allclose(a.normals, b.normals, atol=1e-12)
    hit = a.alpha > 0.05
    n = a.normals[hit] / a.alpha[hit][:, None]
    to_camera = cam.center.to(F64) - torch.zeros(3, dtype=F64)
    assert bool(((n @ to_camera) > 0).all())


def test_two_stacked_surfels_give_the_pairwise_distortion():
    cam = _camera()
    s = _surfels([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], [[0.5, 0.5], [0.5, 0.5]], [[1.0, 0, 0, 0]] * 2, [0.6, 0.7])
    out = render_surfels_ref(s, cam)
    i, j = cam.width // 2, cam.height // 2  # pixel next to the common centre
    x, y = i + 0.5, j + 0.5

    def g(z: float) -> float:  # surface Gaussian of a fronto-parallel surfel at depth z through (x, y)
        u = (x - cam.cx) * z / (cam.fx * 0.5)
        v = (y - cam.cy) * z / (cam.fy * 0.5)
        return math.exp(-0.5 * (u * u + v * v))

    def m(z: float) -> float:
        return DIST_FAR / (DIST_FAR - DIST_NEAR) * (1 - DIST_NEAR / z)

    a1, a2 = 0.6 * g(3.0), 0.7 * g(4.0)
    w1, w2 = a1, a2 * (1 - a1)
    assert float(out.distortion[j, i]) == pytest.approx(w1 * w2 * (m(3.0) - m(4.0)) ** 2, rel=1e-10)
    assert float(out.depth[j, i]) == pytest.approx(3.0 * w1 + 4.0 * w2, rel=1e-12)


# ------------------------------------------------------------------------------------------------
# gradients: gradcheck and the compiled kernel against the reference


def _weights(cam: Camera, seed: int = 0, dtype=F64) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(cam.height, cam.width, k, generator=g, dtype=dtype) for k in (3, 1, 1, 3, 1)]


def _objective(out: SurfelRenderOutput, w: list[torch.Tensor]) -> torch.Tensor:
    """A scalar reading every output (distortion scaled up to weigh like the others)."""
    return ((out.color * w[0]).sum() + (out.alpha * w[1][..., 0]).sum() + (out.depth * w[2][..., 0]).sum()
            + (out.normals * w[3]).sum() + 1e3 * (out.distortion * w[4][..., 0]).sum())


def _gradcheck(render, n: int = 5, seed: int = 3) -> None:
    s = random_scene(n, seed=seed, dtype=F64, spread=0.3, scale_range=(0.2, 0.5))
    cam = random_camera(20, 18, seed=1, dtype=F64)
    w = _weights(cam)
    bg = torch.tensor([0.9, 0.5, 0.2], dtype=F64)
    leaves = [t.clone().requires_grad_() for t in (s.means, s.scales, s.quats, s.opacities, s.colors, bg)]

    def f(means, scales, quats, opac, colors, background):
        return _objective(render(Splats(means, scales, quats, opac, colors), cam, background), w)

    assert torch.autograd.gradcheck(f, tuple(leaves), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_reference_gradcheck():
    _gradcheck(render_surfels_ref)


def test_kernel_gradcheck():
    _gradcheck(render_surfels_cpu, seed=4)


def _hard_scene(kind: str) -> tuple[Splats, Camera]:
    if kind == "random":
        return (random_scene(60, seed=5, dtype=F64, spread=0.4, scale_range=(0.05, 0.4)),
                random_camera(37, 29, seed=6, dtype=F64))
    if kind == "opaque_stack":  # alpha clamped at 0.99, transmittance terminates after two layers
        n = 6
        means = torch.zeros(n, 3, dtype=F64)
        means[:, 2] = torch.linspace(-0.5, 0.5, n, dtype=F64)
        means[:, 0] = torch.linspace(-0.1, 0.1, n, dtype=F64)
        return (_surfels(means, torch.full((n, 2), 0.6, dtype=F64), torch.tensor([[1.0, 0.05, -0.05, 0.02]] * n),
                         torch.full((n,), 0.999, dtype=F64)), _camera(33, 21))
    if kind == "edge_on_and_near":  # the low-pass filter wins; intersections behind the near plane
        q = torch.tensor([[math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0],
                          [0.7, 0.7, 0.1, 0.0], [1.0, 0.0, 0.0, 0.0], [0.6, -0.2, 0.7, 0.3]], dtype=F64)
        means = torch.tensor([[0.0, 0.0, 0.3], [0.1, -0.1, -2.6], [0.05, 0.02, -2.75], [-0.1, 0.1, 0.0]], dtype=F64)
        return _surfels(means, [[0.3, 0.2], [0.6, 0.5], [0.05, 0.08], [0.4, 0.1]], q, [0.9, 0.8, 0.7, 0.6]), _camera()
    raise ValueError(kind)


def _pair_cases(s: Splats, cam: Camera) -> dict[str, int]:
    """How many (pixel, surfel) pairs with alpha >= 1/255 fall in each branch (all pixels, before compositing)."""
    proj = project_surfels(s.means, s.quats, s.scales, cam)
    x, y = (t.reshape(-1, 1) for t in _pixels(cam))
    tr = proj.transforms.detach()
    k = x[..., None] * tr[None, :, 6:9] - tr[None, :, 0:3]
    l = y[..., None] * tr[None, :, 6:9] - tr[None, :, 3:6]
    p = torch.linalg.cross(k, l, dim=-1)
    u, v = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    rho3d = u * u + v * v
    c = proj.means2d.detach()
    rho2d = 2 * ((c[None, :, 0] - x) ** 2 + (c[None, :, 1] - y) ** 2)
    depth = u * tr[None, :, 6] + v * tr[None, :, 7] + tr[None, :, 8]
    i, j = x - 0.5, y - 0.5
    r = proj.rects
    inside = (r[None, :, 0] <= i) & (i <= r[None, :, 2]) & (r[None, :, 1] <= j) & (j <= r[None, :, 3])
    live = inside & (s.opacities[None] * torch.exp(-0.5 * torch.minimum(rho3d, rho2d)) >= ALPHA_MIN)
    surface = rho3d <= rho2d
    return {"surface": int((live & surface & (depth >= DIST_NEAR)).sum()), "filter": int((live & ~surface).sum()),
            "behind_near": int((live & surface & (depth < DIST_NEAR)).sum())}


@pytest.mark.parametrize("kind", ["random", "opaque_stack", "edge_on_and_near"])
def test_kernel_matches_reference_in_values_and_gradients(kind):
    s, cam = _hard_scene(kind)
    w = _weights(cam, seed=1)
    bg = torch.tensor([1.0, 0.5, 0.25], dtype=F64)
    results = []
    for render in (render_surfels_ref, render_surfels_cpu):
        leaves = [t.clone().requires_grad_() for t in (s.means, s.scales, s.quats, s.opacities, s.colors, bg)]
        out = render(Splats(*leaves[:5]), cam, leaves[5])
        out.means2d.retain_grad()
        _objective(out, w).backward()
        outs = [out.color, out.alpha, out.depth, out.normals, out.distortion]
        results.append(([o.detach() for o in outs], [t.grad for t in leaves] + [out.means2d.grad], out))
    (v_ref, g_ref, o_ref), (v_cpu, g_cpu, o_cpu) = results
    for a, b in zip(v_ref, v_cpu, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    for a, b in zip(g_ref, g_cpu, strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-11 * float(a.abs().max().clamp_min(1)))
    assert torch.equal(o_ref.radii, o_cpu.radii)
    if kind == "opaque_stack":  # the clamp and the termination were exercised
        assert float(o_ref.alpha.detach().max()) > 1 - 1e-3 and float((o_ref.distortion > 0).sum()) > 10
    if kind == "edge_on_and_near":  # every branch of the pair rules was exercised
        assert min(_pair_cases(s, cam).values()) > 10


def test_kernel_float32_matches_reference():
    s, cam = _hard_scene("random")
    s32, cam32 = s.to(dtype=torch.float32), cam.to(dtype=torch.float32)
    ref = render_surfels_ref(s, cam)
    out = render_surfels_cpu(s32, cam32)
    for a, b in ((ref.color, out.color), (ref.alpha, out.alpha), (ref.depth, out.depth), (ref.normals, out.normals)):
        assert torch.allclose(a.float(), b, atol=2e-4)


# ------------------------------------------------------------------------------------------------
# losses


def test_depth_normals_of_a_plane():
    cam = random_camera(16, 14, seed=2, dtype=F64)
    # a plane through the origin, tilted by about 20 degrees from facing the camera (every ray meets it in front)
    n_world = torch.nn.functional.normalize(cam.center / cam.center.norm() + torch.tensor([0.3, -0.2, 0.1], dtype=F64),
                                            dim=0)
    # depth of the plane n . X = 0 along each pixel's ray (z-depth)
    x, y = _pixels(cam)
    d_cam = torch.stack([(x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy, torch.ones_like(x)], -1)
    d = d_cam @ cam.world_to_cam[:3, :3]
    t = -(cam.center @ n_world) / (d @ n_world)
    alpha = torch.full_like(t, 0.5)
    got = depth_normals(t * alpha, alpha, cam)
    assert torch.allclose(got[1:-1, 1:-1], n_world.expand(14 - 2, 16 - 2, 3), atol=1e-10)
    assert bool((got[0] == 0).all()) and bool((got[:, -1] == 0).all())


def test_normal_consistency_vanishes_on_a_flat_opaque_surfel():
    cam = _camera(20, 20)
    s = _surfels([0.0, 0.0, 0.0], [20.0, 20.0], [0.98, 0.1, -0.15, 0.0], [0.99])
    out = render_surfels_ref(s, cam)
    assert float(out.alpha[1:-1, 1:-1].min()) > 0.98
    per_pixel = 1 - (out.normals * depth_normals(out.depth, out.alpha, cam) * out.alpha[..., None]).sum(-1)
    assert float(per_pixel[1:-1, 1:-1].abs().max()) < 0.03  # 1 - alpha^2 inside, the border is 1
    assert float(normal_consistency(out, cam)) == pytest.approx(float(per_pixel.mean()), rel=1e-9)


class _View:
    def __init__(self, camera: Camera, image: torch.Tensor) -> None:
        self.camera, self.image, self.mask = camera, image, None


def test_surfel_loss_adds_its_terms_from_their_iterations():
    s = random_scene(30, seed=1, dtype=F64, spread=0.3, scale_range=(0.1, 0.3))
    cam = random_camera(20, 16, seed=0, dtype=F64)
    out = render_surfels_ref(s, cam)
    view = _View(cam, torch.rand(16, 20, 3, dtype=F64))
    loss = SurfelLoss(lambda_dist=1000.0, lambda_normal=0.05, dist_from=10, normal_from=20)
    early = loss([out], [view], [s], iteration=9)
    assert "dist" not in early and "normal" not in early
    mid = loss([out], [view], [s], iteration=10)
    assert "dist" in mid and "normal" not in mid
    late = loss([out], [view], [s], iteration=20)
    assert float(late["total"]) == pytest.approx(
        float(early["total"] + 1000.0 * late["dist"] + 0.05 * late["normal"]), rel=1e-12)
    assert float(late["dist"]) > 0 and float(late["normal"]) > 0
    plain = TorchRefRasterizer().render(s, cam)
    with pytest.raises(TypeError, match="surfels=true"):
        loss([plain], [view], [s], iteration=0)


def test_surfel_loss_weighs_each_distortion_form_with_its_own_weight():
    """gsplat's L1 raw-depth distortion (``distortion_form="depth_l1"``) takes ``lambda_dist_l1``, the
    reference's squared NDC form ``lambda_dist``; a mixed batch averages the weighted terms."""
    s = random_scene(30, seed=1, dtype=F64, spread=0.3, scale_range=(0.1, 0.3))
    cam = random_camera(20, 16, seed=0, dtype=F64)
    ndc = render_surfels_ref(s, cam)
    l1 = dataclasses.replace(ndc, distortion=ndc.distortion * 7.0, distortion_form="depth_l1")
    view = _View(cam, torch.rand(16, 20, 3, dtype=F64))
    loss = SurfelLoss(lambda_dist=1000.0, lambda_dist_l1=0.5, lambda_normal=0.0, dist_from=0)
    base = SurfelLoss(lambda_dist=0.0, lambda_dist_l1=0.0, lambda_normal=0.0)([ndc], [view], [s])["total"]
    d = float(ndc.distortion.mean())
    assert d > 0
    assert float(loss([ndc], [view], [s])["total"] - base) == pytest.approx(1000.0 * d, rel=1e-10)
    assert float(loss([l1], [view], [s])["total"] - base) == pytest.approx(0.5 * 7.0 * d, rel=1e-10)
    mixed = loss([ndc, l1], [view, view], [s, s])
    assert float(mixed["total"] - base) == pytest.approx((1000.0 * d + 0.5 * 7.0 * d) / 2, rel=1e-10)
    assert float(mixed["dist"]) == pytest.approx((d + 7.0 * d) / 2, rel=1e-10)
    with pytest.raises(ValueError, match="unknown distortion_form"):
        loss([dataclasses.replace(ndc, distortion_form="l2")], [view], [s])


# ------------------------------------------------------------------------------------------------
# model and rasterizer options


def test_model_has_two_scales_and_splits_in_the_surfel_plane():
    torch.manual_seed(0)
    init = torch.rand(40, 3) * 0.6 - 0.3
    model = SurfelSplatModel(init, sh_degree=0)
    assert model.params["scales"].shape == (40, 2)
    s = model.splats(random_camera(16, 16))
    assert s.scales.shape == (40, 3) and bool((s.scales[:, 2] == 0).all()) and bool((s.scales[:, :2] > 0).all())
    b = model.bake()
    assert torch.equal(b.scales, s.scales.detach()) and torch.allclose(b.quats.norm(dim=-1), torch.ones(40))
    split = torch.zeros(40, dtype=torch.bool)
    split[:5] = True
    parents_means = model.params["means"].data[:5].clone()
    normals = quat_to_axes(model.params["quats"].data[:5])[2]
    parent_scales = model.params["scales"].data[:5].clone()
    model.densify(None, torch.zeros(40, dtype=torch.bool), split, 2, torch.Generator().manual_seed(0))
    assert model.n_splats == 40 - 5 + 10
    kids = model.params["means"].data[-10:] - parents_means.repeat(2, 1)
    assert torch.allclose((kids * normals.repeat(2, 1)).sum(-1), torch.zeros(10), atol=1e-6)  # in-plane
    assert bool((kids.norm(dim=-1) > 0).all())
    assert torch.allclose(model.params["scales"].data[-10:], parent_scales.repeat(2, 1) - math.log(1.6))


def test_rasterizer_options_route_to_the_surfel_renderers():
    s = random_scene(20, seed=2, dtype=F64, spread=0.3, scale_range=(0.1, 0.3))
    cam = random_camera(20, 16, seed=3, dtype=F64)
    ref = TorchRefRasterizer(surfels=True).render(s, cam)
    cpu = CpuRasterizer(surfels=True).render(s, cam)
    assert isinstance(ref, SurfelRenderOutput) and isinstance(cpu, SurfelRenderOutput)
    assert torch.allclose(ref.color, cpu.color, atol=1e-12)
    assert not isinstance(TorchRefRasterizer().render(s, cam), SurfelRenderOutput)
    for cls in (TorchRefRasterizer, CpuRasterizer):
        with pytest.raises(ValueError, match="cannot be combined"):
            cls(surfels=True, antialiased=True)
