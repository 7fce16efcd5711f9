"""Binocular3DGS's self-consistency (``sparse=binocular``): the shifted camera, the disparity warp (a
fronto-parallel textured plane rendered from the shifted camera and warped back with its known depth
matches the original render where they overlap), gradients into the rendered depth, and the loss in a
training step."""

from __future__ import annotations

import math

import pytest
import torch

from src.core.cameras import Camera
from src.core.splats import Splats
from src.data.base import View
from src.models.gaussians import GaussianSplatModel
from src.models.sh import rgb_to_sh0
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.sparse import BinocularConsistency, SparseRecipe
from src.sparse.binocular import edge_aware_smoothness, shifted_camera, warp_from_shifted
from tests.conftest import random_camera

pytestmark = pytest.mark.usefixtures("one_thread")
W = H = 32
FX = 40.0
Z0 = 2.0


def _camera(z: float = 0.0) -> Camera:
    """A camera at (0, 0, ``z``) looking along +z (OpenCV), principal point at the image centre."""
    w2c = torch.eye(4)
    w2c[2, 3] = -z
    return Camera(w2c, fx=FX, fy=FX, cx=W / 2, cy=H / 2, width=W, height=H, name="front")


def _plane(z: float = Z0, step: float = 0.04) -> Splats:
    """Opaque, flat splats on the plane z = ``z`` with a smooth colour texture, wider than the view."""
    g = torch.arange(-1.4, 1.4 + 1e-9, step)
    y, x = torch.meshgrid(g, g, indexing="ij")
    means = torch.stack([x.reshape(-1), y.reshape(-1), torch.full((x.numel(),), z)], dim=1)  # [N, 3]
    n = means.shape[0]
    colors = torch.stack([0.5 + 0.4 * torch.sin(3.0 * means[:, 0]) * torch.cos(2.0 * means[:, 1]),
                          0.5 + 0.3 * torch.cos(2.5 * means[:, 0] + means[:, 1]),
                          0.5 + 0.2 * torch.sin(4.0 * means[:, 1])], dim=1)
    scales = torch.tensor([0.6 * step, 0.6 * step, 1e-5]).expand(n, 3).clone()
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone()
    return Splats(means=means, scales=scales, quats=quats, opacities=torch.full((n,), 0.99), colors=colors)


def test_the_shifted_camera_moves_along_its_own_x_axis():
    cam = random_camera(16, 16, seed=7)
    moved = shifted_camera(cam, 0.3)
    x_axis = cam.world_to_cam[0, :3]  # the first row of R: the camera's x axis in world coordinates
    assert torch.allclose(moved.center - cam.center, 0.3 * x_axis, atol=1e-5)
    assert torch.equal(moved.world_to_cam[:3, :3], cam.world_to_cam[:3, :3]) and moved.fx == cam.fx
    p = torch.tensor([[0.1, -0.2, 0.05]])
    (uv, z), (uv2, z2) = cam.project(p), moved.project(p)
    assert torch.allclose(z, z2, atol=1e-5)
    assert torch.allclose(uv2 - uv, torch.tensor([[-cam.fx * 0.3 / float(z[0]), 0.0]]), atol=1e-3)


@pytest.mark.parametrize("shift_px", [4, -3])
def test_warping_the_shifted_render_of_a_plane_reproduces_the_original(shift_px):
    cam, rast, bg = _camera(), TorchRefRasterizer(), torch.ones(3)
    plane = _plane()
    baseline = shift_px * Z0 / FX  # disparity fx * d / z = shift_px pixels
    original = rast.render(plane, cam, bg)
    shifted = rast.render(plane, shifted_camera(cam, baseline), bg)
    assert (original.alpha > 0.98).all() and not torch.allclose(original.color, shifted.color, atol=1e-2)
    depth = torch.full((H, W), Z0)
    warped, inside, disparity = warp_from_shifted(shifted.color, depth, FX, baseline)
    assert torch.allclose(disparity, torch.full((H, W), float(shift_px)))
    assert int(inside.sum()) == H * (W - abs(shift_px)) and not inside.all()
    margin = torch.zeros(H, W, dtype=torch.bool)
    margin[2:-2, 2:-2] = True  # splats cut by the image border differ between the views
    overlap = inside & margin
    err = (warped - original.color).abs()[overlap]  # [M, 3]
    assert err.max() < 3e-3 and err.mean() < 1e-4  # float rounding, and a few footprints clipped differently
    # with the depth the original render itself gives (depth / alpha) the warp is the same
    z = original.depth / original.alpha
    assert torch.allclose(z[overlap], torch.full_like(z[overlap], Z0), rtol=1e-4)
    warped_z, _, _ = warp_from_shifted(shifted.color, z, FX, baseline)
    err_z = (warped_z - original.color).abs()[overlap]
    assert err_z.max() < 3e-3 and err_z.mean() < 1e-4
    # a wrong depth does not reproduce it
    wrong, _, _ = warp_from_shifted(shifted.color, depth * 2, FX, baseline)
    assert (wrong - original.color).abs()[overlap].mean() > 20 * err.mean() + 0.005


def test_a_fractional_disparity_interpolates_between_pixels():
    img = torch.arange(W, dtype=torch.float32).expand(H, W)[..., None]  # [H, W, 1] value = column index
    warped, inside, _ = warp_from_shifted(img, torch.full((H, W), 2.0), fx=5.0, baseline=1.0)  # 2.5 px
    assert torch.allclose(warped[inside][:, 0], (torch.arange(W) - 2.5).expand(H, W)[inside], atol=1e-5)


def test_gradient_flows_into_the_depth():
    cam, rast, bg = _camera(), TorchRefRasterizer(), torch.ones(3)
    plane = _plane()
    shifted = rast.render(plane, shifted_camera(cam, 0.1), bg)
    depth = torch.full((H, W), Z0, requires_grad=True)
    warped, inside, disparity = warp_from_shifted(shifted.color, depth, FX, 0.1)
    target = rast.render(plane, cam, bg).color
    loss = (inside[..., None] * (warped - target).abs()).mean() + edge_aware_smoothness(disparity, target)
    loss.backward()
    assert depth.grad is not None and depth.grad.abs().sum() > 0 and torch.isfinite(depth.grad).all()


def _model_and_view(seed: int = 0):
    """A textured plane 3 units in front of a camera 3 units from the origin, its splats' depths perturbed."""
    plane = _plane(z=0.0, step=0.08)
    model = GaussianSplatModel(plane.means.clone(), sh_degree=0, init_opacity=0.9)
    with torch.no_grad():
        model.params["sh0"].copy_(rgb_to_sh0(plane.colors[:, None, :]))  # the plane's texture
        model.params["means"][:, 2] += 0.05 * torch.randn(model.n_splats, generator=torch.Generator().manual_seed(seed))
    cam = _camera(z=-3.0)
    target = TorchRefRasterizer().render(plane, cam, torch.ones(3)).color.detach()
    return model, View(camera=cam, image=target, mask=None, image_id=0)


def test_the_loss_starts_when_configured_and_reaches_the_rendered_depth():
    model, view = _model_and_view()
    rast, bg = TorchRefRasterizer(), torch.ones(3)
    ing = BinocularConsistency(start=0.5)
    recipe = SparseRecipe(binocular=ing)
    recipe.bind(model, None, rast, iterations=10)
    assert ing.start_iter == 5
    render = rast.render(model.splats(view.camera), view.camera, bg)
    g = torch.Generator().manual_seed(0)
    assert recipe.loss_terms(model, [view], [render], rast, bg, 4, g) == {}
    render.depth.retain_grad()
    terms = recipe.loss_terms(model, [view], [render], rast, bg, 5, g)
    assert set(terms) == {"binocular", "binocular_smooth"}
    assert all(math.isfinite(float(t.detach())) for t in terms.values())
    assert float(terms["binocular"].detach()) > 0
    sum(terms.values()).backward()
    assert render.depth.grad is not None and render.depth.grad.abs().sum() > 0
    assert model.params["means"].grad[:, 2].abs().sum() > 0  # the splats' depths are pulled


def test_baselines_are_random_signed_and_bounded():
    ing = BinocularConsistency(max_baseline=0.1)
    cam = random_camera(16, 16, seed=1)  # 3 units from the origin
    g = torch.Generator().manual_seed(0)
    d = [ing.baseline(cam, g) for _ in range(200)]
    assert max(abs(x) for x in d) <= 0.1 * float(cam.center.norm()) + 1e-9
    assert min(d) < -0.1 and max(d) > 0.1
    with pytest.raises(ValueError, match=r"sparse\.binocular"):
        BinocularConsistency(max_baseline=0.0)
