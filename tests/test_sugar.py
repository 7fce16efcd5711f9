"""SuGaR (Guédon and Lepetit, CVPR 2024): the regularisers, the opacity prune and the Poisson mesh.

* the opacity entropy: 0 at opacities 0 and 1, its maximum log 2 at 0.5, gradients pushing away from 0.5;
* the SDF estimate from depth against a direct float64 reference: a tilted depth plane (bilinear sampling is
  exact on it) and the render of a single flat Gaussian (its depth map is the plane z = z0);
* the ideal SDF s* sqrt(-2 log d) against hand computations (one opaque flat Gaussian: the distance to its
  plane; a partly transparent one; d >= 1 gives 0), the density gradient against autograd, the samples'
  moments, the near-surface selection and the normal term of a flat Gaussian;
* the SDF term in units of a tenth of the scene's camera extent, each sample's error clamped at 10 x extent;
* the loss windows, the prune (exactly the splats below the threshold, once, at its iteration), and a run
  resumed within the surface terms' window that draws the same samples (from the run's generator) as the
  uninterrupted one;
* the mesh: points in the splats' planes with normals facing the cameras; without open3d, or with an open3d
  that cannot load, the writer records why no mesh was written; with it, a sphere of flat splats gives a
  mesh on the sphere;
* out-of-range values are one-line ConfigValueErrors naming the key; through the command line a bad value
  and a mistyped key of ``+experiment=sugar`` are one ``error:`` line with exit code 2.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats
from src.data.base import Scene, View
from src.fields.flows import quat_to_rotmat_wxyz
from src.io.mesh import MESH_PLY, PoissonMesh, oriented_splat_points
from src.losses.sugar import (
    SugarLoss,
    density_gradient,
    depth_map,
    flatness,
    gaussian_terms,
    ideal_sdf,
    near_surface,
    opacity_entropy,
    sample_in_splats,
    sdf_from_depth,
    surface_terms,
)
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.strategy.sugar import SugarStrategy, prune_below
from src.trainer.trainer import Trainer
from src.utils.instantiate import ConfigError, check_targets, takes
from src.utils.validate import ConfigValueError
from tests.cli_runs import one_error_line, run_cli
from tests.conftest import random_camera

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
HAS_OPEN3D = importlib.util.find_spec("open3d") is not None


def _camera(width: int = 24, height: int = 20, f: float = 30.0, dist: float = 3.0) -> Camera:
    """Camera at (0, 0, -dist) looking along +z (identity rotation), principal point at the image centre."""
    w2c = torch.eye(4, dtype=F64)
    w2c[2, 3] = dist
    return Camera(w2c, fx=f, fy=f * 1.1, cx=width / 2, cy=height / 2, width=width, height=height)


def _flat_splat(scales=(0.8, 0.6, 0.01), quat=(1.0, 0.0, 0.0, 0.0), mean=(0.0, 0.0, 0.0), opacity=0.99) -> Splats:
    return Splats(means=torch.tensor([mean], dtype=F64), scales=torch.tensor([scales], dtype=F64),
                  quats=torch.tensor([quat], dtype=F64), opacities=torch.tensor([opacity], dtype=F64),
                  colors=torch.full((1, 3), 0.5, dtype=F64))


# -- entropy -------------------------------------------------------------------------------------------------
def test_entropy_is_zero_at_0_and_1_and_largest_at_one_half():
    o = torch.linspace(0, 1, 101, dtype=F64)
    values = torch.stack([opacity_entropy(x[None]) for x in o])
    assert abs(float(values[0])) < 1e-9 and abs(float(values[-1])) < 1e-9  # 1e-10 inside the logarithms
    assert int(values.argmax()) == 50 and math.isclose(float(values[50]), math.log(2), rel_tol=1e-9)
    assert bool((values[1:-1] > values[0]).all()) and bool((values[1:-1] > values[-1]).all())
    x = torch.tensor([0.2, 0.45, 0.55, 0.9], dtype=F64, requires_grad=True)
    opacity_entropy(x).backward()
    assert bool((x.grad[:2] > 0).all()) and bool((x.grad[2:] < 0).all())  # descent moves away from 0.5
    ends = torch.tensor([0.0, 1.0])  # float32 opacities of exactly 0 and 1 (an underflowed sigmoid)
    ends.requires_grad_(True)
    opacity_entropy(ends).backward()
    assert bool(torch.isfinite(ends.grad).all())
    assert float(opacity_entropy(torch.zeros(0))) == 0.0


# -- SDF from depth ----------------------------------------------------------------------------------------------
def test_sdf_from_depth_on_a_tilted_plane_matches_a_direct_reference():
    cam = _camera()
    a, b, c = 0.03, -0.02, 3.5
    ii = torch.arange(cam.width, dtype=F64) + 0.5
    jj = torch.arange(cam.height, dtype=F64) + 0.5
    depth = a * ii[None, :] + b * jj[:, None] + c  # [H, W] linear in (u, v): bilinear sampling is exact
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(200, 3, generator=g, dtype=F64) * torch.tensor([1.2, 1.0, 2.0], dtype=F64) - torch.tensor(
        [0.6, 0.5, 1.0], dtype=F64)
    f_hat, inside = sdf_from_depth(pts, depth, cam)
    z = pts[:, 2] + 3.0  # camera frame: identity rotation, t = (0, 0, 3)
    u = cam.fx * pts[:, 0] / z + cam.cx
    v = cam.fy * pts[:, 1] / z + cam.cy
    expected_inside = (u >= 0.5) & (u <= cam.width - 0.5) & (v >= 0.5) & (v <= cam.height - 0.5)
    assert torch.equal(inside, expected_inside) and int(inside.sum()) > 100
    ref = a * u + b * v + c - z
    torch.testing.assert_close(f_hat[inside], ref[inside], rtol=0, atol=1e-12)


def test_sdf_from_the_render_of_one_flat_gaussian_is_the_distance_to_its_plane():
    """A fronto-parallel flat Gaussian at depth z0 renders depth z0 alpha; with far = z0 the map is z0."""
    cam = _camera()
    z0 = 3.0  # its centre at the world origin
    splats = _flat_splat()
    render = TorchRefRasterizer().render(splats, cam, torch.zeros(3, dtype=F64))
    assert float(render.alpha.max()) > 0.5
    torch.testing.assert_close(render.depth, z0 * render.alpha, rtol=0, atol=1e-12)
    depth = depth_map(render, torch.tensor(z0, dtype=F64))
    torch.testing.assert_close(depth, torch.full_like(depth, z0), rtol=0, atol=1e-12)
    g = torch.Generator().manual_seed(1)
    pts = (torch.rand(300, 3, generator=g, dtype=F64) - 0.5) * torch.tensor([1.0, 0.8, 1.0], dtype=F64)
    f_hat, inside = sdf_from_depth(pts, depth, cam)
    torch.testing.assert_close(f_hat[inside], -pts[inside, 2], rtol=0, atol=1e-12)  # z0 - (z0 + p_z)


# -- the ideal SDF of flat Gaussians -----------------------------------------------------------------------------
def _one(splats: Splats, points: torch.Tensor):
    """gaussian_terms of every point against the single splat."""
    rot = quat_to_rotmat_wxyz(splats.quats)
    s = points.shape[0]
    return gaussian_terms(points, splats.means.expand(s, 1, 3), rot.expand(s, 1, 3, 3), splats.scales.expand(s, 1, 3),
                          splats.opacities.expand(s, 1))


def test_ideal_sdf_of_one_opaque_flat_gaussian_is_the_distance_to_its_plane():
    q = torch.tensor([0.9, 0.2, -0.3, 0.25], dtype=F64)
    splats = _flat_splat(scales=(0.5, 0.3, 0.02), quat=q.tolist(), mean=(0.1, -0.2, 0.3), opacity=1.0)
    R = quat_to_rotmat_wxyz(q)
    normal = R[:, 2]  # the shortest axis
    deltas = torch.tensor([-0.05, -0.01, 0.0, 0.003, 0.04], dtype=F64)
    pts = splats.means + deltas[:, None] * normal
    contrib, m2, _ = _one(splats, pts)
    torch.testing.assert_close(m2[:, 0], (deltas / 0.02) ** 2)
    f = ideal_sdf(contrib.sum(-1), torch.full_like(deltas, 0.02))
    torch.testing.assert_close(f, deltas.abs(), rtol=0, atol=3e-7)  # 0.02 sqrt(1e-10) = 2e-7 at the plane


def test_ideal_sdf_by_hand_with_an_in_plane_offset_and_a_transparent_gaussian():
    splats = _flat_splat(scales=(0.5, 0.3, 0.02), opacity=0.8)  # identity rotation: axes x, y, z
    p = torch.tensor([[0.2, -0.1, 0.03]], dtype=F64)
    contrib, m2, _ = _one(splats, p)
    m2_hand = (0.2 / 0.5) ** 2 + (0.1 / 0.3) ** 2 + (0.03 / 0.02) ** 2
    d_hand = 0.8 * math.exp(-0.5 * m2_hand)
    assert math.isclose(float(m2[0, 0]), m2_hand, rel_tol=1e-12)
    assert math.isclose(float(contrib[0, 0]), d_hand, rel_tol=1e-12)
    f = ideal_sdf(contrib.sum(-1), torch.tensor([0.02], dtype=F64))
    assert math.isclose(float(f[0]), 0.02 * math.sqrt(-2 * math.log(d_hand)), rel_tol=1e-12)
    assert math.isclose(float(f[0]), 0.02 * math.sqrt(m2_hand - 2 * math.log(0.8)), rel_tol=1e-12)
    # a density of 1 or more (overlapping opaque Gaussians) is on the surface: f = s* sqrt(1e-10)
    assert float(ideal_sdf(torch.tensor([1.7], dtype=F64), torch.tensor([0.02], dtype=F64))[0]) < 1e-6


def test_density_gradient_matches_autograd():
    g = torch.Generator().manual_seed(3)
    s, k = 7, 4
    points = torch.randn(s, 3, generator=g, dtype=F64, requires_grad=True)
    means = torch.randn(s, k, 3, generator=g, dtype=F64) * 0.3 + points.detach()[:, None]
    rot = quat_to_rotmat_wxyz(torch.randn(s, k, 4, generator=g, dtype=F64))
    scales = torch.rand(s, k, 3, generator=g, dtype=F64) * 0.3 + 0.05
    opac = torch.rand(s, k, generator=g, dtype=F64)
    contrib, _, scaled = gaussian_terms(points, means, rot, scales, opac)
    (auto,) = torch.autograd.grad(contrib.sum(), points)
    torch.testing.assert_close(density_gradient(contrib, rot, scaled), auto, rtol=1e-10, atol=1e-12)


# -- sampling, selection and the normal term ---------------------------------------------------------------------
def test_samples_follow_the_scaled_gaussian():
    q = torch.tensor([0.7, -0.1, 0.4, 0.2], dtype=F64)
    splats = _flat_splat(scales=(0.4, 0.2, 0.05), quat=q.tolist(), mean=(0.3, 0.1, -0.2))
    R = quat_to_rotmat_wxyz(splats.quats)
    n = 200_000
    pts = sample_in_splats(splats, R, torch.zeros(n, dtype=torch.long), 1.5, torch.Generator().manual_seed(0))
    cov_ref = R[0] @ torch.diag((1.5 * splats.scales[0]) ** 2) @ R[0].T
    torch.testing.assert_close(pts.mean(0), splats.means[0], rtol=0, atol=5e-3)
    torch.testing.assert_close(torch.cov(pts.T), cov_ref, rtol=0, atol=4e-3)


def test_near_surface_keeps_the_splats_at_the_rendered_depth():
    cam = _camera()
    splats = Splats(means=torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.1, 0.5], [-0.1, 0.0, 0.03]], dtype=F64),
                    scales=torch.tensor([[0.3, 0.3, 0.02]] * 3, dtype=F64),
                    quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3, dtype=F64),
                    opacities=torch.full((3,), 0.9, dtype=F64), colors=torch.zeros(3, 3, dtype=F64))
    depth = torch.full((cam.height, cam.width), 3.0, dtype=F64)  # the plane z_world = 0
    rot = quat_to_rotmat_wxyz(splats.quats)
    near = near_surface(splats, rot, depth, cam, torch.ones(3, dtype=torch.bool), 2.0)
    assert near.tolist() == [True, False, True]  # 0.5 is ~25 std behind the plane, 0.03 ~1.4 std
    hidden = near_surface(splats, rot, depth, cam, torch.tensor([False, True, True]), 2.0)
    assert hidden.tolist() == [False, False, True]


def test_normal_term_of_a_flat_gaussian_is_small_and_gradients_are_finite():
    cam = _camera(32, 32, f=40.0)
    q = torch.tensor([0.95, 0.1, 0.2, 0.0], dtype=F64)  # tilted towards the camera
    splats = _flat_splat(scales=(0.6, 0.5, 0.004), quat=q.tolist(), opacity=0.99)
    for name in ("means", "scales", "quats", "opacities"):
        getattr(splats, name).requires_grad_(True)
    render = TorchRefRasterizer().render(splats, cam, torch.zeros(3, dtype=F64))
    sdf, normal = surface_terms(render, cam, splats, n_samples=256, k=4, extent=3.3,  # cameras 3 from the centre
                                generator=torch.Generator().manual_seed(0))
    assert float(normal.detach()) < 1e-2  # g is +-n up to O(s_min / s_max) (heavy-tailed near the plane)
    assert 0 < float(sdf.detach()) < 1.0
    (sdf + normal).backward()
    for name in ("means", "scales", "quats", "opacities"):
        grad = getattr(splats, name).grad
        assert grad is not None and bool(torch.isfinite(grad).all()), name


def test_flatness_acts_on_the_smallest_scale_only():
    scales = torch.tensor([[0.3, 0.1, 0.2], [0.05, 0.4, 0.2]], dtype=F64, requires_grad=True)
    value = flatness(scales)
    assert math.isclose(float(value.detach()), 0.5 * (0.1 / 0.2 + 0.05 / 0.2), rel_tol=1e-12)
    value.backward()
    assert torch.count_nonzero(scales.grad).item() == 2
    assert float(scales.grad[0, 1]) > 0 and float(scales.grad[1, 0]) > 0


# -- the loss windows --------------------------------------------------------------------------------------------
def test_loss_terms_act_in_their_windows():
    cam = _camera(32, 32, f=40.0)
    splats = _flat_splat(scales=(0.6, 0.5, 0.01), opacity=0.7)
    splats.opacities.requires_grad_(True)
    render = TorchRefRasterizer().render(splats, cam, torch.zeros(3, dtype=F64))
    view = View(camera=cam, image=torch.zeros(32, 32, 3, dtype=F64), mask=None, image_id=0)
    loss = SugarLoss(entropy_from=2, sdf_from=4, flat_from=3, flat_weight=0.01, n_samples=64, k_neighbours=1)
    names = {it: set(loss([render], [view], [splats], iteration=it)) - {"l1", "dssim", "total"} for it in range(6)}
    assert names[0] == names[1] == set()
    assert names[2] == {"entropy"} and names[3] == {"entropy", "flat"}
    assert names[4] == names[5] == {"flat", "sdf", "normal"}
    terms = loss([render], [view], [splats], iteration=2)
    torch.testing.assert_close(terms["entropy"], opacity_entropy(splats.opacities))


def _surface(extent: float, sigmas: float = 2.0):
    """surface_terms of one tilted flat splat (the same 256 samples for every ``extent``)."""
    cam = _camera(32, 32, f=40.0)
    splats = _flat_splat(scales=(0.6, 0.5, 0.05), quat=(0.95, 0.1, 0.2, 0.0), opacity=0.9)
    render = TorchRefRasterizer().render(splats, cam, torch.zeros(3, dtype=F64))
    return surface_terms(render, cam, splats, n_samples=256, k=1, sigmas=sigmas, extent=extent,
                         generator=torch.Generator().manual_seed(0))


def test_the_sdf_term_is_in_tenths_of_the_scene_extent_and_clamped_per_sample():
    sdf1, normal1 = _surface(extent=1.0)
    sdf2, normal2 = _surface(extent=2.0)
    assert 0 < float(sdf1) < 10.0  # no sample reaches the clamp at extent 1
    torch.testing.assert_close(sdf2, sdf1 / 2, rtol=1e-12, atol=0)  # not the view's distance: the scene's extent
    torch.testing.assert_close(normal2, normal1, rtol=0, atol=0)
    tiny = 1e-4  # errors of ~1e-2 in units of 1e-5 reach the clamp at 10 x 1e-4 = 1e-3
    sdf_tiny, _ = _surface(extent=tiny)
    assert math.isclose(float(sdf_tiny), 10 * tiny, rel_tol=0.05) and float(sdf_tiny) <= 10 * tiny + 1e-15


def test_bad_values_are_one_line_config_errors_naming_the_key():
    cases = [(lambda: SugarLoss(sdf_weight=-1), "loss.sdf_weight=-1: expected >= 0"),
             (lambda: SugarLoss(n_samples=0), "loss.n_samples=0: expected an integer >= 1"),
             (lambda: SugarLoss(near_surface_sigmas=0.0), "loss.near_surface_sigmas=0.0: expected a number > 0"),
             (lambda: SugarLoss(entropy_from=10, sdf_from=5), "loss.entropy_from=10: expected at most loss.sdf_from=5"),
             (lambda: SugarStrategy(prune_opacity_hard=1.5), "strategy.prune_opacity_hard=1.5: expected a value in"),
             (lambda: PoissonMesh(min_opacity=-0.1), "mesh.min_opacity=-0.1: expected a value in [0, 1]"),
             (lambda: PoissonMesh(decimation_target=0), "mesh.decimation_target=0: expected an integer >= 1 or null"),
             (lambda: PoissonMesh(poisson_depth=0), "mesh.poisson_depth=0: expected an integer >= 1")]
    for make, needle in cases:
        with pytest.raises(ConfigValueError) as err:
            make()
        assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_keys_of_the_base_loss_are_checked_and_run_time_objects_go_where_they_are_taken():
    """``**kwargs`` that go to SplatLoss take its parameters, not any name: a mistyped key is refused."""
    check_targets({"_target_": "src.losses.sugar.SugarLoss", "sdf_weight": 0.3, "lambda_mask": 0.0})
    check_targets({"_target_": "src.losses.surfel.SurfelLoss", "lambda_normal": 0.1, "lambda_dssim": 0.2})
    for target, key in (("src.losses.sugar.SugarLoss", "sdf_weigth"), ("src.losses.surfel.SurfelLoss", "lambda_mask_")):
        with pytest.raises(ConfigError, match=f"does not take '{key}'"):
            check_targets({"_target_": target, key: 0.3})
    with pytest.raises(ConfigError, match="does not take 'prune_att'"):
        check_targets({"_target_": "src.strategy.SugarStrategy", "prune_att": 3})
    g = torch.Generator()
    assert takes({"_target_": "src.losses.sugar.SugarLoss"}, extent=2.0, generator=g) == {"extent": 2.0, "generator": g}
    assert takes({"_target_": "src.losses.SplatLoss"}, extent=2.0, generator=g) == {}
    assert takes({"_target_": "src.losses.surfel.SurfelLoss"}, extent=2.0) == {}


# -- the prune ---------------------------------------------------------------------------------------------------
def _model(opacities: list[float]) -> tuple[GaussianSplatModel, SplatOptimizer]:
    n = len(opacities)
    model = GaussianSplatModel(torch.randn(n, 3, generator=torch.Generator().manual_seed(0)), sh_degree=0)
    o = torch.tensor(opacities)
    model.params["opacities"].data = torch.log(o) - torch.log1p(-o)
    opt = SplatOptimizer(model.param_groups(), {k: {"init": 1e-3} for k in model.params})
    return model, opt


def test_prune_removes_exactly_the_splats_below_the_threshold():
    opac = [0.1, 0.499, 0.5001, 0.9, 0.3, 0.75]
    model, opt = _model(opac)
    means = model.params["means"].detach().clone()
    assert prune_below(model, opt, 0.5) == 3
    keep = torch.tensor([o >= 0.5 for o in opac])
    assert torch.equal(model.params["means"].detach(), means[keep])
    assert bool((model.opacity_values() >= 0.5).all())
    assert prune_below(model, opt, 0.5) == 0
    every, opt2 = _model([0.1, 0.2])
    assert prune_below(every, opt2, 0.5) == 0 and every.n_splats == 2  # never the whole set


def test_prune_of_a_model_without_per_splat_opacities_is_a_one_line_config_error(monkeypatch):
    model, opt = _model([0.2, 0.8])
    monkeypatch.setattr(model, "opacity_values", lambda: None)  # as a field model before its first forward
    with pytest.raises(ConfigError, match=r"^strategy=sugar: .*GaussianSplatModel.*3DGS-family model") as err:
        prune_below(model, opt, 0.5)
    assert "\n" not in str(err.value) and model.n_splats == 2


def test_strategy_prunes_once_at_its_iteration():
    model, opt = _model([0.2, 0.6, 0.4, 0.8])
    strategy = SugarStrategy(prune_at=3, stop_iter=0, reset_every=0)
    g = torch.Generator().manual_seed(0)
    for it in range(5):
        stats = strategy.after_step(model, opt, it, g)
        assert ("sugar_prune" in stats) == (it == 2)
        assert model.n_splats == (4 if it < 2 else 2)


# -- a resumed run -----------------------------------------------------------------------------------------------
class _Recorded(SugarLoss):
    """SugarLoss that records which terms each call returned."""

    def __call__(self, *args, **kwargs):
        terms = super().__call__(*args, **kwargs)
        self.seen.append(set(terms))
        return terms


def _fit(run_dir, iterations: int) -> GaussianSplatModel:
    """SuGaR on three random views: entropy from iteration 1, the prune after 3, the surface terms from 3.

    One generator is the run's: the loss draws its samples from it and the trainer checkpoints it.
    """
    pts = (torch.rand(150, 3, generator=torch.Generator().manual_seed(3)) - 0.5) * 0.6
    model = GaussianSplatModel(pts, sh_degree=0)
    model.params["opacities"].data = torch.randn(150, generator=torch.Generator().manual_seed(4)) * 2  # logits
    views = [View(camera=random_camera(16, 16, seed=20 + i), image=torch.rand(16, 16, 3, generator=torch.Generator(
        ).manual_seed(i)), mask=None, image_id=i) for i in range(3)]
    scene = Scene(name="tiny", train=views, val=[], test=views[:1], background=torch.ones(3), view_ids=[0, 1, 2])
    generator = torch.Generator().manual_seed(0)
    loss = _Recorded(lambda_mask=0.0, entropy_from=1, sdf_from=3, flat_from=1, flat_weight=0.01, n_samples=64,
                     k_neighbours=4, extent=scene.extent, generator=generator)
    loss.seen = []
    strategy = SugarStrategy(prune_at=3, prune_opacity_hard=0.5, stop_iter=0, reset_every=0)
    trainer = Trainer(iterations=iterations, log_every=1000, progress=False, tensorboard=False, ckpt_every=0,
                      guard={"warmup": 10**6, "collapse_psnr": 0.0})
    lr = {k: {"init": 1e-2} for k in model.params}
    trainer.fit(model, scene, TorchRefRasterizer(), loss, lambda m: SplatOptimizer(m.param_groups(), lr), strategy,
                run_dir=run_dir, generator=generator)
    assert all({"sdf", "normal"} <= names for names in loss.seen[-2:])  # the surface terms drew samples
    return model


def test_a_resumed_run_draws_the_same_samples(tmp_path):
    """The surface terms draw from the run's generator, which checkpoints hold: resuming reproduces."""
    torch.manual_seed(123)
    full = _fit(tmp_path / "full", iterations=7)
    assert 0 < full.n_splats < 150  # the prune acted
    torch.manual_seed(123)  # as src.run seeds every run
    _fit(tmp_path / "cut", iterations=5)  # its checkpoint after 5 iterations, in the surface terms' window
    torch.manual_seed(789)  # another state: the checkpoint's must be restored
    resumed = _fit(tmp_path / "cut", iterations=7)
    for name, p in full.params.items():
        assert torch.equal(p, resumed.params[name]), name


def test_samples_come_from_the_given_generator_not_the_global_one():
    cam = _camera(32, 32, f=40.0)
    splats = _flat_splat(scales=(0.6, 0.5, 0.01), opacity=0.9)
    render = TorchRefRasterizer().render(splats, cam, torch.zeros(3, dtype=F64))
    view = View(camera=cam, image=torch.zeros(32, 32, 3, dtype=F64), mask=None, image_id=0)
    values = []
    for global_seed in (1, 2):
        torch.manual_seed(global_seed)
        loss = SugarLoss(entropy_from=0, sdf_from=0, n_samples=64, k_neighbours=1,
                         generator=torch.Generator().manual_seed(5))
        values.append(loss([render], [view], [splats], iteration=0)["sdf"])
    assert torch.equal(values[0], values[1])
    other = SugarLoss(entropy_from=0, sdf_from=0, n_samples=64, k_neighbours=1,
                      generator=torch.Generator().manual_seed(6))
    assert not torch.equal(other([render], [view], [splats], iteration=0)["sdf"], values[0])


# -- the mesh ----------------------------------------------------------------------------------------------------
def _sphere_of_flat_splats(n: int = 600) -> Splats:
    """Flat splats tangent to the unit sphere (their shortest axis along the radius)."""
    g = torch.Generator().manual_seed(0)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    axis = torch.linalg.cross(z.expand(n, 3), normals)  # rotate +z onto the normal
    angle = torch.acos(normals[:, 2].clamp(-1, 1))
    axis = torch.nn.functional.normalize(axis + 1e-12, dim=-1)
    quats = torch.cat([torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None] * axis], dim=1)
    return Splats(means=normals.clone(), scales=torch.tensor([[0.08, 0.08, 0.001]], dtype=F64).expand(n, 3),
                  quats=quats, opacities=torch.full((n,), 0.95, dtype=F64), colors=torch.zeros(n, 3, dtype=F64))


def test_mesh_points_lie_in_the_splats_and_face_the_cameras():
    splats = _sphere_of_flat_splats()
    cams = torch.tensor([[3.0, 0, 0], [-3.0, 0, 0], [0, 3.0, 0], [0, -3.0, 0], [0, 0, 3.0], [0, 0, -3.0]], dtype=F64)
    pts, normals = oriented_splat_points(splats, cams, 5000, 0.5)
    assert pts.shape == normals.shape == (5000, 3)
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(5000, dtype=F64))
    # in-plane: a point's offset from the sphere's tangent plane at the nearest splat centre is ~0
    centre = splats.means[torch.cdist(pts, splats.means).argmin(-1)]
    assert float(((pts - centre) * centre).sum(-1).abs().max()) < 0.05
    assert float((normals * pts).sum(-1).min()) > 0.9  # outward: towards the cameras around the sphere
    low = Splats(**{**splats.__dict__, "opacities": torch.full((600,), 0.1, dtype=F64)})
    assert oriented_splat_points(low, cams, 100, 0.5)[0].shape == (0, 3)
    # splats without area (a zero or non-finite scale among the two largest) are never drawn; none left: no points
    flat, far = splats.scales.clone(), splats.means.clone()
    flat[:300, 1:] = 0.0
    flat[300:310, 2] = float("inf")
    far[:310] += 10.0  # the splats without area sit far from the sphere: a point drawn on one would show
    half = Splats(**{**splats.__dict__, "scales": flat, "means": far})
    pts, _ = oriented_splat_points(half, cams, 2000, 0.5)
    assert pts.shape == (2000, 3) and float(pts.norm(dim=-1).max()) < 1.5
    no_area = Splats(**{**splats.__dict__, "scales": torch.zeros_like(splats.scales)})
    assert oriented_splat_points(no_area, cams, 100, 0.5)[0].shape == (0, 3)


def test_without_open3d_the_run_records_that_no_mesh_was_written(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d raises ImportError
    out = PoissonMesh(n_points=1000).write(_sphere_of_flat_splats(), torch.eye(3, dtype=F64) * 3, tmp_path)
    assert out["written"] is False and "open3d is not installed" in out["reason"] and "\n" not in out["reason"]
    assert not (tmp_path / MESH_PLY).exists()


def test_a_failed_mesh_write_leaves_no_file_behind(tmp_path):
    """open3d writing part of the file and then reporting failure: neither mesh.ply nor the temporary file stays."""
    from types import SimpleNamespace

    from src.io.mesh import _write_atomic

    def half_write(name, mesh):
        Path(name).write_text("ply\nformat ascii 1.0\n")  # a truncated header
        return False

    fake = SimpleNamespace(io=SimpleNamespace(write_triangle_mesh=half_write))
    with pytest.raises(RuntimeError, match=f"could not write {tmp_path / MESH_PLY}"):
        _write_atomic(fake, None, tmp_path / MESH_PLY)
    assert list(tmp_path.iterdir()) == []


class _Unloadable(importlib.abc.MetaPathFinder):
    """Finds ``open3d`` as a present package whose shared library cannot load (an OSError from ctypes)."""

    def find_spec(self, name, path, target=None):
        if name == "open3d":
            raise OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")
        return None


def test_an_open3d_that_cannot_load_is_recorded_and_the_run_goes_on(tmp_path, monkeypatch):
    monkeypatch.delitem(sys.modules, "open3d", raising=False)
    monkeypatch.setattr(sys, "meta_path", [_Unloadable(), *sys.meta_path])
    out = PoissonMesh(n_points=1000).write(_sphere_of_flat_splats(), torch.eye(3, dtype=F64) * 3, tmp_path)
    assert out["written"] is False and "\n" not in out["reason"]
    assert out["reason"].startswith("open3d cannot be loaded (libusb-1.0.so.0: cannot open shared object file")
    assert not (tmp_path / MESH_PLY).exists()


def test_mesh_samples_favour_the_splats_with_the_largest_area():
    """Splats are drawn in proportion to the product of their two largest scales, whatever the axis order and
    for a perfectly flat splat too (smallest scale 0)."""
    splats = Splats(means=torch.tensor([[0.0, 0, 0], [5.0, 0, 0]], dtype=F64),
                    scales=torch.tensor([[0.0, 0.3, 0.3], [0.1, 0.01, 0.1]], dtype=F64),  # areas 0.09 and 0.01
                    quats=torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64), opacities=torch.full((2,), 0.9, dtype=F64),
                    colors=torch.zeros(2, 3, dtype=F64))
    pts, normals = oriented_splat_points(splats, torch.tensor([[2.5, 0.0, 3.0]], dtype=F64), 20_000, 0.5)
    first = pts[:, 0] < 2.5
    assert abs(float(first.double().mean()) - 0.9) < 0.01
    assert float(pts[first, 0].abs().max()) < 1e-12 and float(pts[~first, 1].abs().max()) < 1e-12  # in-plane
    assert torch.equal(normals[first], torch.tensor([1.0, 0, 0], dtype=F64).expand(int(first.sum()), 3))
    assert torch.equal(normals[~first], torch.tensor([0, 1.0, 0], dtype=F64).expand(int((~first).sum()), 3))


@pytest.mark.skipif(not HAS_OPEN3D, reason="open3d not installed (pip install -e '.[mesh]')")
def test_poisson_mesh_of_a_sphere_of_flat_splats_lies_on_the_sphere(tmp_path):
    import open3d as o3d

    cams = torch.tensor([[3.0, 0, 0], [-3.0, 0, 0], [0, 3.0, 0], [0, -3.0, 0], [0, 0, 3.0], [0, 0, -3.0]], dtype=F64)
    out = PoissonMesh(n_points=20_000, poisson_depth=6).write(_sphere_of_flat_splats(), cams, tmp_path)
    assert out["written"] is True and out["n_triangles"] > 100
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / MESH_PLY))
    radii = torch.as_tensor(__import__("numpy").asarray(mesh.vertices)).norm(dim=-1)
    assert abs(float(radii.median()) - 1.0) < 0.03 and float((radii - 1).abs().quantile(0.9)) < 0.08
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary file was renamed


def test_render_output_depth_semantics_used_by_the_loss():
    """RenderOutput.depth is sum z alpha T: depth_map adds the uncovered part of each pixel at ``far``."""
    r = RenderOutput(color=torch.zeros(1, 2, 3), alpha=torch.tensor([[1.0, 0.25]]), depth=torch.tensor([[2.0, 0.5]]),
                     means2d=torch.zeros(0, 2), radii=torch.zeros(0))
    torch.testing.assert_close(depth_map(r, 4.0), torch.tensor([[2.0, 0.5 + 0.75 * 4.0]]))


# -- through the command line ------------------------------------------------------------------------------------
@pytest.mark.parametrize("override, needle", [
    ("loss.sdf_weight=-1", "loss.sdf_weight=-1: expected >= 0"),
    ("+loss.sdf_weigth=0.3", "loss: src.losses.sugar.SugarLoss does not take 'sdf_weigth'"),
    ("mesh.min_opacity=2", "mesh.min_opacity=2: expected a value in [0, 1]"),
])
def test_cli_bad_sugar_settings_are_one_error_line(tmp_path, override, needle):
    proc = run_cli("+experiment=sugar", override, f"hydra.run.dir={tmp_path / 'run'}", "threads=1", "+ci=smoke")
    assert needle in one_error_line(proc)
