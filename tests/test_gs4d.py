"""4D-GS: isoclinic rotations, slicing a 4D Gaussian at a time, covariance -> (scale, quat), the model."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from torch.distributions import MultivariateNormal

from src.data.multiview import BlenderMVDataset
from src.fields.flows import quat_to_rotmat_wxyz
from src.losses.objective import SplatLoss
from src.models.gs4d import (
    Gaussian4DModel,
    condition_on_time,
    covariance_to_scale_quat,
    isoclinic_rotation,
    left_matrix,
    quat_multiply,
    right_matrix,
    rotmat_to_quat,
)
from src.optim.adam import SplatOptimizer
from src.rasterizer.cpu import CpuRasterizer
from src.rasterizer.projection import quat_scale_to_cov3d
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.run import run
from src.strategy.base import NoDensification
from src.trainer.guard import DivergenceGuard
from src.trainer.trainer import Trainer
from src.utils.instantiate import ConfigError
from tests.conftest import random_camera
from tests.scenes import write_blender_scene

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[1]
F64 = torch.float64


def _random_4d(n: int, seed: int) -> tuple[torch.Tensor, ...]:
    """(means4 [n, 4], log-scales [n, 4], q_l [n, 4], q_r [n, 4]) in float64, well-conditioned."""
    g = torch.Generator().manual_seed(seed)
    means4 = torch.randn(n, 4, generator=g, dtype=F64)
    log_s = torch.rand(n, 4, generator=g, dtype=F64) * 1.5 - 2.5
    return means4, log_s, torch.randn(n, 4, generator=g, dtype=F64), torch.randn(n, 4, generator=g, dtype=F64)


def _conj(q: torch.Tensor) -> torch.Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def _sym(x: torch.Tensor) -> torch.Tensor:
    return 0.5 * (x + x.transpose(-1, -2))


def _cov_from_scale_quat(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] covariance as the rasterizer builds it from (scales, quats)."""
    c00, c01, c02, c11, c12, c22 = quat_scale_to_cov3d(quats, scales)
    return torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1).view(-1, 3, 3)


def _spd(n: int, seed: int, dtype=F64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 3, 3, generator=g, dtype=F64)
    return (a @ a.transpose(1, 2) + 0.1 * torch.eye(3, dtype=F64)).to(dtype)


# -- isoclinic rotation --------------------------------------------------------------------------
def test_multiplication_matrices_are_the_quaternion_products():
    """L(q) v and R(q) v equal q p and p q for p = t + x i + y j + z k, v = (x, y, z, t)."""
    g = torch.Generator().manual_seed(0)
    q, p = torch.randn(6, 4, generator=g, dtype=F64), torch.randn(6, 4, generator=g, dtype=F64)
    v = p[:, [1, 2, 3, 0]]  # (x, y, z, t)
    to_xyzt = [1, 2, 3, 0]
    torch.testing.assert_close((left_matrix(q) @ v[:, :, None])[..., 0], quat_multiply(q, p)[:, to_xyzt])
    torch.testing.assert_close((right_matrix(q) @ v[:, :, None])[..., 0], quat_multiply(p, q)[:, to_xyzt])


def test_isoclinic_rotation_is_proper_and_identity_at_identity():
    _, _, ql, qr = _random_4d(32, seed=1)
    rot = isoclinic_rotation(ql, qr)
    eye = torch.eye(4, dtype=F64).expand(32, 4, 4)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(32, dtype=F64))
    one = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    torch.testing.assert_close(isoclinic_rotation(one, one), torch.eye(4, dtype=F64)[None])
    # q_r = conj(q_l): the 3D rotation of q_l on (x, y, z), t fixed
    spatial = isoclinic_rotation(ql, _conj(ql))
    torch.testing.assert_close(spatial[:, :3, :3], quat_to_rotmat_wxyz(F.normalize(ql, dim=-1)))
    torch.testing.assert_close(spatial[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64).expand(32, 4))
    assert not torch.allclose(rot[:, 3, :3], torch.zeros(32, 3, dtype=F64))  # a general one mixes space and time


# -- slicing ---------------------------------------------------------------------------------------
def test_slice_matches_the_closed_form_on_the_full_covariance():
    means4, log_s, ql, qr = _random_4d(16, seed=2)
    rot = isoclinic_rotation(ql, qr)
    t = 0.37
    means, cov, marginal = condition_on_time(means4, rot, log_s.exp(), t)
    sigma4 = rot @ torch.diag_embed(log_s.exp() ** 2) @ rot.transpose(1, 2)  # [16, 4, 4] built explicitly
    s11, s12, s22 = sigma4[:, :3, :3], sigma4[:, :3, 3:], sigma4[:, 3:, 3:]
    gain = torch.linalg.solve(s22, s12.transpose(1, 2)).transpose(1, 2)  # Sigma_12 Sigma_22^-1, [16, 3, 1]
    torch.testing.assert_close(means, means4[:, :3] + (gain * (t - means4[:, 3:, None])).squeeze(-1))
    torch.testing.assert_close(cov, s11 - gain @ s12.transpose(1, 2))
    torch.testing.assert_close(marginal, torch.exp(-0.5 * (t - means4[:, 3]) ** 2 / s22[:, 0, 0]))
    # Schur-complement identities: the xyz block of Sigma4^-1 is the inverse conditional covariance,
    # det Sigma4 = Sigma_tt det Sigma_{xyz|t}
    torch.testing.assert_close(torch.linalg.inv(sigma4)[:, :3, :3], torch.linalg.inv(cov))
    torch.testing.assert_close(torch.linalg.det(sigma4), s22[:, 0, 0] * torch.linalg.det(cov))


def test_the_4d_density_factorises_into_the_marginal_and_the_slice():
    """log N4((x, t)) = log N1(t; mu_t, Sigma_tt) + log N3(x; mu_{xyz|t}, Sigma_{xyz|t}) at any x."""
    means4, log_s, ql, qr = _random_4d(8, seed=3)
    rot = isoclinic_rotation(ql, qr)
    sigma4 = rot @ torch.diag_embed(log_s.exp() ** 2) @ rot.transpose(1, 2)
    t = -0.2
    means, cov, marginal = condition_on_time(means4, rot, log_s.exp(), t)
    x = means + torch.randn(8, 3, generator=torch.Generator().manual_seed(4), dtype=F64) * 0.1
    xt = torch.cat([x, torch.full((8, 1), t, dtype=F64)], 1)
    joint = MultivariateNormal(means4, covariance_matrix=sigma4).log_prob(xt)
    var_t = sigma4[:, 3, 3]
    log_marginal = torch.log(marginal) - 0.5 * torch.log(2 * math.pi * var_t)  # marginal = the unnormalised N1
    torch.testing.assert_close(joint, log_marginal + MultivariateNormal(means, covariance_matrix=cov).log_prob(x))


@pytest.mark.parametrize("t_offset", [0.0, 0.3])
def test_time_aligned_splat_slices_to_its_spatial_gaussian(t_offset):
    """q_r = conj(q_l) keeps the time axis: the slice is the 3D Gaussian (R3(q_l), s_xyz) at mu_xyz."""
    means4, log_s, ql, _ = _random_4d(10, seed=5)
    means, cov, marginal = condition_on_time(means4, isoclinic_rotation(ql, _conj(ql)), log_s.exp(),
                                             means4[:, 3] + t_offset)
    r3 = quat_to_rotmat_wxyz(F.normalize(ql, dim=-1))
    torch.testing.assert_close(means, means4[:, :3])
    torch.testing.assert_close(cov, r3 @ torch.diag_embed(log_s[:, :3].exp() ** 2) @ r3.transpose(1, 2))
    torch.testing.assert_close(marginal, torch.exp(-0.5 * t_offset**2 / log_s[:, 3].exp() ** 2))


def test_slicing_gradcheck_float64():
    means4, log_s, ql, qr = (x.requires_grad_(True) for x in _random_4d(3, seed=6))
    t = torch.tensor([0.1, 0.5, -0.4], dtype=F64, requires_grad=True)

    def sliced(m, s, a, b, tt):
        return condition_on_time(m, isoclinic_rotation(a, b), s.exp(), tt)

    assert torch.autograd.gradcheck(sliced, (means4, log_s, ql, qr, t))


# -- covariance -> (scale, quat) --------------------------------------------------------------------
def test_rotmat_to_quat_round_trips():
    q = F.normalize(torch.randn(64, 4, generator=torch.Generator().manual_seed(7), dtype=F64), dim=-1)
    q = torch.cat([q, torch.eye(4, dtype=F64)])  # the four branches' extremes
    back = rotmat_to_quat(quat_to_rotmat_wxyz(q))
    torch.testing.assert_close(back, torch.where(q[:, :1] < 0, -q, q))


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_covariance_to_scale_quat_reproduces_the_covariance(dtype):
    cov = _spd(64, seed=8, dtype=dtype)
    r = quat_to_rotmat_wxyz(torch.randn(3, 4, generator=torch.Generator().manual_seed(9))).to(dtype)
    degenerate = r @ torch.diag_embed(torch.tensor([[0.04, 0.04, 0.04], [0.01, 0.09, 0.09], [0.02, 0.02, 0.3]],
                                                   dtype=dtype)) @ r.transpose(1, 2)
    cov = torch.cat([cov, degenerate])
    scales, quats = covariance_to_scale_quat(cov)
    assert (scales > 0).all() and torch.allclose(quats.norm(dim=-1), torch.ones(len(cov), dtype=dtype))
    assert (scales[:, :-1] <= scales[:, 1:]).all()  # ascending eigenvalues
    torch.testing.assert_close(_cov_from_scale_quat(scales, quats), cov, rtol=1e-5, atol=1e-6)


def test_conversion_gradient_is_the_eigendecomposition_derivative():
    """Undamped, the gradients of the scales and the quaternion are those of the eigendecomposition."""
    cov = _spd(4, seed=10).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c: covariance_to_scale_quat(_sym(c), 0.0), (cov,))
    # the round trip is the identity on symmetric matrices, with the identity as its derivative
    assert torch.autograd.gradcheck(lambda c: _cov_from_scale_quat(*covariance_to_scale_quat(_sym(c), 0.0)), (cov,))


def test_conversion_gradient_is_finite_for_an_isotropic_covariance():
    cov = (0.01 * torch.eye(3)).repeat(2, 1, 1).requires_grad_(True)
    scales, quats = covariance_to_scale_quat(cov)
    (scales.sum() + (quats * torch.tensor([0.3, 1.0, -2.0, 0.5])).sum()).backward()
    assert torch.isfinite(cov.grad).all()


# -- the model ----------------------------------------------------------------------------------------
def _model(n: int = 60, seed: int = 0, **kw) -> Gaussian4DModel:
    """A small model with random 4D parameters (not at their identity / isotropic start)."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    m = Gaussian4DModel(torch.rand(n, 3, generator=g) * 1.2 - 0.6, n_frames=10, **kw)
    with torch.no_grad():
        for name in ("quats", "quats_r", "sh_rest"):
            m.params[name].add_(torch.randn(m.params[name].shape, generator=g) * 0.2)
        m.params["scales"].add_(torch.randn(n, 4, generator=g) * 0.2)
        m.params["times"].copy_(torch.rand(n, generator=g))
    return m


def test_gradients_reach_every_parameter_through_the_rasterizer():
    m = _model(sh_degree=1, n_fourier=2).train()
    m.on_step(1000)  # SH degree 1
    cam = replace(random_camera(24, 24, seed=1), time=0.45)
    out = TorchRefRasterizer().render(m.splats(cam), cam, torch.ones(3))
    (out.color * torch.rand(out.color.shape, generator=torch.Generator().manual_seed(2))).sum().backward()
    for name, p in m.params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_culled_splats_are_parked_in_training_and_dropped_in_evaluation():
    m = _model(n=80, seed=3)
    cam = replace(random_camera(24, 24, seed=4), time=0.9)
    kept = m.time_slice(cam.time).index
    assert 0 < len(kept) < m.n_splats
    m.train()
    s = m.splats(cam)
    assert s.n == m.n_splats
    culled = torch.ones(m.n_splats, dtype=torch.bool)
    culled[kept] = False
    assert (s.opacities[culled] == 0).all() and (s.opacities[kept] > 0).all()
    radii = TorchRefRasterizer().render(s, cam, torch.ones(3)).radii
    assert (radii[culled] == 0).all()  # not "visible": no densification statistics, as the reference
    m.eval()
    e = m.splats(cam)
    assert e.n == len(kept)
    torch.testing.assert_close(e.means, s.means[kept])
    torch.testing.assert_close(e.opacities, s.opacities[kept])
    baked = m.bake(time=cam.time)
    torch.testing.assert_close(baked.means, e.means)
    torch.testing.assert_close(baked.colors, m.colors(m.time_slice(cam.time), None))


def test_splats_for_slices_once_per_time():
    m = _model().eval()
    cams = [replace(random_camera(16, 16, seed=s), time=t) for s, t in ((1, 0.2), (2, 0.2), (3, 0.7))]
    calls = []
    original = m.time_slice
    m.time_slice = lambda t: calls.append(t) or original(t)
    got = m.splats_for(cams)
    assert calls == [0.2, 0.7]
    for s, c in zip(got, cams, strict=True):
        torch.testing.assert_close(s.colors, Gaussian4DModel.splats(m, c).colors)


def test_split_samples_children_from_the_4d_gaussian():
    """Children's (x, y, z, t) offsets follow the parent's Sigma4; all scales / (0.8 n_split); clone copies."""
    m = _model(n=3, seed=5)
    opt = SplatOptimizer(m.param_groups(), lr={k: {"init": 1e-3} for k in m.params})
    parent = {k: v.detach().clone() for k, v in m.params.items()}
    n_split = 4000
    m.densify(opt, clone=torch.tensor([True, False, False]), split=torch.tensor([False, True, False]),
              n_split=n_split, generator=torch.Generator().manual_seed(6))
    assert m.n_splats == 3 + n_split  # parents 0 and 2, the clone of 0, the children of 1
    torch.testing.assert_close(m.params["means"][2], parent["means"][0])
    offsets = torch.cat([m.params["means"][3:], m.params["times"][3:, None]], 1).detach().double()
    offsets = offsets - torch.cat([parent["means"][1], parent["times"][1:2]]).double()
    rot = isoclinic_rotation(parent["quats"][1:2], parent["quats_r"][1:2]).double()[0]
    sigma4 = rot @ torch.diag(parent["scales"][1].double().exp() ** 2) @ rot.T
    torch.testing.assert_close(offsets.T @ offsets / n_split, sigma4, rtol=0.1, atol=0.1 * float(sigma4.diag().max()))
    shrunk = parent["scales"][1] - math.log(0.8 * n_split)
    torch.testing.assert_close(m.params["scales"][3:], shrunk.expand(n_split, 4))
    for p in m.params.values():  # Adam state resized with the parameters
        assert opt.optimizer.state.get(p) is None or opt.optimizer.state[p]["exp_avg"].shape == p.shape


def test_prune_opacity_reset_and_resume():
    m = _model(n=10)
    m.prune(None, torch.arange(10) < 3)
    assert m.n_splats == 7 and all(p.shape[0] == 7 for p in m.params.values())
    m.reset_opacity(None, 0.01)
    assert (m.opacity_values() <= 0.01 + 1e-6).all()
    assert m.max_scale().shape == (7,) and m.canonical_means().shape == (7, 3)
    resumed = Gaussian4DModel(torch.rand(10, 3), n_frames=10)  # a checkpoint of another splat count loads
    resumed.load_state_dict(m.state_dict())
    for name, p in m.params.items():
        torch.testing.assert_close(resumed.params[name], p)


def test_initial_time_scale_follows_the_frame_spacing():
    m = Gaussian4DModel(torch.rand(20, 3), n_frames=21, time_scale_frames=3.0)
    torch.testing.assert_close(m.params["scales"][:, 3].exp(), torch.full((20,), 3.0 / 20))
    assert m.params["times"].min() >= -0.1 and m.params["times"].max() <= 1.1
    torch.testing.assert_close(m.params["quats"], torch.tensor([1.0, 0, 0, 0]).expand(20, 4))


def test_training_on_the_shipped_flag_sequence_reduces_the_loss():
    scene = BlenderMVDataset(root=str(REPO / "data" / "dynamic_mv" / "flag"), n_views=4, downscale=4.0, frames=8,
                             n_test=1).load()
    frames = Trainer.views_by_frame(scene)
    torch.manual_seed(0)
    m = Gaussian4DModel(torch.rand(1500, 3) * 1.6 - 0.8, n_frames=scene.n_frames, sh_degree=0).train()
    lr = {"means": {"init": 1.6e-4 * scene.extent}, "times": {"init": 1.6e-4}, "scales": {"init": 5e-3},
          "quats": {"init": 1e-3}, "quats_r": {"init": 1e-3}, "opacities": {"init": 5e-2}, "sh0": {"init": 2.5e-3},
          "sh_rest": {"init": 1.25e-4}}
    opt = SplatOptimizer(m.param_groups(), lr={k: {"init": v["init"] * 4} for k, v in lr.items()})
    loss, rast = SplatLoss(lambda_mask=0.0), CpuRasterizer()
    guard = DivergenceGuard(check_grads=True, collapse_psnr=-math.inf)
    gen = torch.Generator().manual_seed(0)
    losses = []
    for it in range(40):
        views = frames[(it * 7) % len(frames)][:2]
        step = Trainer.train_step(m, views, rast, loss, opt, NoDensification(), guard, it, gen, scene.background)
        losses.append(float(step["terms"]["total"].detach()))
    assert sum(losses[-8:]) / 8 < 0.7 * sum(losses[:8]) / 8, losses


def test_experiment_refuses_a_static_scene(tmp_path):
    write_blender_scene(tmp_path / "blender", n_train=8, n_test=2, size=16)
    overrides = ["+experiment=gs4d", "dataset=blender", f"dataset.root={tmp_path / 'blender'}",
                 f"paths.output_root={tmp_path / 'out'}", "+ci=smoke", "trainer.iterations=2", "dataset.downscale=1"]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    with pytest.raises(ConfigError, match="models motion"):
        run(cfg, tmp_path / "run")


def test_parameters_are_built_on_the_initial_points_device(monkeypatch):
    """A CUDA run hands the model its initial points on the GPU: every parameter is made on that device (the
    "meta" device stands in for the GPU; the kNN scale, which goes through NumPy, is replaced)."""
    import src.models.gs4d as gs4d_module

    monkeypatch.setattr(gs4d_module, "knn_base_scale", lambda p: torch.ones(len(p), device=p.device))
    model = Gaussian4DModel(torch.zeros(6, 3, device="meta"), n_frames=5)
    assert {name: p.device.type for name, p in model.params.items()} == dict.fromkeys(model.params, "meta")
