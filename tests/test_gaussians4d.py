"""4DGaussians: HexPlane lookups, Hadamard fusion, plane regularisers, deformation decoder and model."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from src.core.cameras import Camera, look_at
from src.data.base import View
from src.fields.hexplane import (
    PLANE_AXES,
    PLANE_NAMES,
    DeformationDecoder,
    HexPlaneEncoder,
    hadamard,
    plane_lookup,
    plane_tv,
    time_l1,
    time_smoothness,
)
from src.losses.objective import SplatLoss
from src.models.gaussians import GaussianSplatModel
from src.models.gaussians4d import HexPlaneGaussianModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.run import run
from src.strategy.base import NoDensification
from src.trainer.guard import DivergenceGuard
from src.trainer.trainer import Trainer
from src.utils.instantiate import ConfigError
from tests import format_writers as fw
from tests.conftest import random_camera
from tests.scenes import write_blender_scene
from tests.test_compose_matrix import compose_run

pytestmark = pytest.mark.usefixtures("one_thread")


def _bilinear_by_hand(plane: torch.Tensor, u: float, v: float) -> torch.Tensor:
    """[C] bilinear value at (u, v) in [-1, 1] with align_corners=True and border clamping, written out."""
    _, h, w = plane.shape
    x = min(max((u + 1) / 2 * (w - 1), 0.0), w - 1)
    y = min(max((v + 1) / 2 * (h - 1), 0.0), h - 1)
    x0, y0 = min(math.floor(x), w - 2), min(math.floor(y), h - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * plane[:, y0, x0] + fx * (1 - fy) * plane[:, y0, x0 + 1]
            + (1 - fx) * fy * plane[:, y0 + 1, x0] + fx * fy * plane[:, y0 + 1, x0 + 1])


def _model(n: int = 40, seed: int = 0, random_planes: bool = False, **kw) -> HexPlaneGaussianModel:
    """A small model; ``random_planes`` makes the space-time planes vary (at their start they are 1: static)."""
    g = torch.Generator().manual_seed(seed)
    args = dict(n_frames=6, resolution=4, multires=(1, 2), feature_dim=3, bounds=1.0, width=8, sh_degree=0,
                warm_up=0)
    args.update(kw)
    m = HexPlaneGaussianModel((torch.rand(n, 3, generator=g) * 1.6 - 0.8), **args)
    if random_planes:
        with torch.no_grad():
            for p in m.encoder.parameters():
                p.copy_(torch.rand(p.shape, generator=g) + 0.5)
    return m


# -- lookups ------------------------------------------------------------------------------------
def test_lookup_shapes_and_plane_layout():
    enc = HexPlaneEncoder(resolution=5, multires=(1, 2), time_resolution=3, feature_dim=4)
    assert enc.out_dim == 8
    for m, planes in zip((1, 2), enc.levels, strict=True):
        assert len(planes) == 6
        for (a, b), p in zip(PLANE_AXES, planes, strict=True):
            size = (5 * m, 5 * m, 5 * m, 3)
            assert tuple(p.shape) == (4, size[b], size[a])
    assert PLANE_NAMES == ("xy", "xz", "yz", "xt", "yt", "zt")
    xyz = torch.rand(7, 3) * 2 - 1
    assert enc(xyz, 0.25).shape == (7, 8)
    assert enc(xyz, torch.rand(7)).shape == (7, 8)
    assert plane_lookup(torch.rand(4, 3, 5), torch.rand(7, 2)).shape == (7, 4)


def test_lookup_matches_a_hand_computation():
    plane = torch.tensor([[[0.0, 1.0], [2.0, 3.0]]])  # [1, 2, 2]: columns along u, rows along v
    uv = torch.tensor([[0.0, 0.0], [-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [-0.5, 0.5], [3.0, -7.0]])
    got = plane_lookup(plane, uv)[:, 0]
    # centre = mean of the corners; corners exact; (-0.5, 0.5) -> x = 0.25, y = 0.75:
    # 0.75*0.25*0 + 0.25*0.25*1 + 0.75*0.75*2 + 0.25*0.75*3 = 1.75; outside -> border (u = 1, v = -1) -> 1
    torch.testing.assert_close(got, torch.tensor([1.5, 0.0, 1.0, 2.0, 1.75, 1.0]))
    g = torch.Generator().manual_seed(3)
    plane = torch.randn(3, 4, 6, generator=g, dtype=torch.float64)
    uv = torch.rand(20, 2, generator=g, dtype=torch.float64) * 2.4 - 1.2
    want = torch.stack([_bilinear_by_hand(plane, float(u), float(v)) for u, v in uv])
    torch.testing.assert_close(plane_lookup(plane, uv), want)


def test_encoder_is_the_hadamard_product_of_its_planes_concatenated_over_levels():
    g = torch.Generator().manual_seed(1)
    enc = HexPlaneEncoder(resolution=3, multires=(1, 2), time_resolution=4, feature_dim=2, bounds=1.0).double()
    with torch.no_grad():
        for p in enc.parameters():
            p.copy_(torch.rand(p.shape, generator=g, dtype=torch.float64) + 0.5)
    xyz = torch.rand(9, 3, generator=g, dtype=torch.float64) * 2 - 1
    t = 0.3
    q = torch.cat([xyz, torch.full((9, 1), 2 * t - 1, dtype=torch.float64)], dim=1)
    want = []
    for planes in enc.levels:
        f = torch.ones(9, 2, dtype=torch.float64)
        for (a, b), p in zip(PLANE_AXES, planes, strict=True):
            f = f * torch.stack([_bilinear_by_hand(p.detach(), float(r[a]), float(r[b])) for r in q])
        want.append(f)
    torch.testing.assert_close(enc(xyz, t), torch.cat(want, dim=1))
    a, b, c = (torch.rand(5, 2, generator=g) for _ in range(3))
    torch.testing.assert_close(hadamard([a, b, c]), a * b * c)


def test_each_plane_reads_its_own_axes():
    """All planes 1 except one ramp: the feature is that ramp's coordinate, so every axis pairing is right."""
    enc = HexPlaneEncoder(resolution=3, multires=(1,), time_resolution=5, feature_dim=1, bounds=2.0).double()
    xyz = torch.tensor([[0.4, -1.0, 1.2], [-1.6, 0.8, 0.2]], dtype=torch.float64)
    t = 0.75
    coord = torch.cat([xyz / 2.0, torch.full((2, 1), 2 * t - 1, dtype=torch.float64)], dim=1)  # in [-1, 1]
    for k, (a, b) in enumerate(PLANE_AXES):
        for along, axis in (("W", a), ("H", b)):
            with torch.no_grad():
                for p in enc.levels[0]:
                    p.fill_(1.0)
                p = enc.levels[0][k]
                h, w = p.shape[1:]
                ramp = torch.linspace(-1, 1, w if along == "W" else h, dtype=torch.float64)
                p.copy_(ramp.view(1, 1, w) if along == "W" else ramp.view(1, h, 1))
            torch.testing.assert_close(enc(xyz, t)[:, 0], coord[:, axis], msg=f"plane {PLANE_NAMES[k]} {along}")


def test_lookup_gradcheck_float64():
    g = torch.Generator().manual_seed(2)
    plane = torch.randn(2, 3, 4, generator=g, dtype=torch.float64, requires_grad=True)
    uv = (torch.rand(6, 2, generator=g, dtype=torch.float64) * 1.8 - 0.9).requires_grad_(True)
    assert torch.autograd.gradcheck(plane_lookup, (plane, uv))
    enc = HexPlaneEncoder(resolution=2, multires=(1, 2), time_resolution=3, feature_dim=2).double()
    xyz = (torch.rand(4, 3, generator=g, dtype=torch.float64) * 1.6 - 0.8).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: enc(x, 0.4), (xyz,))


# -- regularisers ---------------------------------------------------------------------------------
def test_plane_regularisers_on_hand_examples():
    p = torch.tensor([[[0.0, 1.0, 3.0], [2.0, 2.0, 2.0]]])  # [1, 2, 3]
    # dH = [2, 1, -1] -> mean 2; dW = [1, 2, 0, 0] -> mean 5/4; TV = 2 (2 + 5/4) = 6.5
    torch.testing.assert_close(plane_tv(p), torch.tensor(6.5))
    q = (torch.arange(4.0) ** 2).view(1, 4, 1)  # time along H: t^2 -> second difference 2 everywhere
    torch.testing.assert_close(time_smoothness(q), torch.tensor(4.0))
    torch.testing.assert_close(time_smoothness(torch.rand(2, 2, 5)), torch.tensor(0.0))  # T < 3: no second difference
    torch.testing.assert_close(time_l1(torch.tensor([[[1.0, 0.5, 3.0]]])), torch.tensor(2.5 / 3))
    enc = HexPlaneEncoder(resolution=3, multires=(1, 2), time_resolution=4, feature_dim=2)
    reg = enc.regularisers()
    want_tv = sum(plane_tv(lv[i]) for lv in enc.levels for i in (0, 1, 2))
    want_smooth = sum(time_smoothness(lv[i]) for lv in enc.levels for i in (3, 4, 5))
    torch.testing.assert_close(reg["plane_tv"], want_tv)
    torch.testing.assert_close(reg["time_smooth"], want_smooth)
    torch.testing.assert_close(reg["time_l1"], torch.tensor(0.0))  # space-time planes start at 1
    quirk = enc.regularisers(plane_tv_quirk=True)["plane_tv"]
    torch.testing.assert_close(quirk, sum(time_smoothness(lv[i]) for lv in enc.levels for i in (0, 1, 2)))


def test_model_regularisers_are_weighted_and_off_during_the_warm_up():
    m = _model(warm_up=10, lambda_plane_tv=2.0, lambda_time_smooth=3.0, lambda_time_l1=0.0)
    assert m.regularisers(9) == {}
    reg = m.regularisers(10)
    raw = m.encoder.regularisers()
    assert set(reg) == {"plane_tv", "time_smooth"}
    torch.testing.assert_close(reg["plane_tv"], 2.0 * raw["plane_tv"])
    torch.testing.assert_close(reg["time_smooth"], 3.0 * raw["time_smooth"])


# -- decoder and model ------------------------------------------------------------------------------
def test_gradients_reach_every_plane_and_the_decoder():
    m = _model(zero_init=False).train()
    m.on_step(0)
    cam = replace(random_camera(16, 16, seed=1), time=0.6)
    s = m.splats(cam)
    loss = s.means.square().sum() + s.scales.sum() + s.quats[:, 1:].sum() + sum(m.regularisers(0).values())
    loss.backward()
    for k, planes in enumerate(m.encoder.levels):
        for name, p in zip(PLANE_NAMES, planes, strict=True):
            assert p.grad is not None and p.grad.abs().sum() > 0, f"level {k} plane {name}"
    for name, p in m.decoder.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert m.params["means"].grad.abs().sum() > 0


def test_decoder_layout_and_zero_init():
    d = DeformationDecoder(in_dim=6, width=8, depth=1, zero_init=True)
    assert [type(x).__name__ for x in d.trunk] == ["Linear", "ReLU", "Linear"]
    dx, ds, dq = d(torch.randn(5, 6))
    assert dx.shape == (5, 3) and ds.shape == (5, 3) and dq.shape == (5, 4)
    assert not dx.any() and not ds.any() and not dq.any()
    dx, _, _ = DeformationDecoder(in_dim=6, width=8)(torch.randn(5, 6))  # default: Xavier heads
    assert dx.abs().sum() > 0


def test_zero_init_deformation_leaves_the_canonical_splats_unchanged():
    g = torch.Generator().manual_seed(4)
    init = torch.rand(30, 3, generator=g) * 1.6 - 0.8
    m = HexPlaneGaussianModel(init, n_frames=6, resolution=4, feature_dim=3, width=8, sh_degree=1, warm_up=0,
                               zero_init=True)
    ref = GaussianSplatModel(init, sh_degree=1)
    with torch.no_grad():  # canonical parameters away from their uniform start
        for k in m.params:
            v = torch.randn(m.params[k].shape, generator=g) * 0.3
            m.params[k].copy_(m.params[k] + v)
            ref.params[k].copy_(m.params[k])
    m.on_step(2000)
    ref.on_step(2000)
    for t in (0.0, 0.5, 1.0):
        cam = replace(random_camera(16, 16, seed=2), time=t)
        got, want = m.splats(cam), ref.splats(cam)
        torch.testing.assert_close(got.means, want.means)
        torch.testing.assert_close(got.scales, want.scales)
        torch.testing.assert_close(got.quats, torch.nn.functional.normalize(want.quats, dim=-1))
        torch.testing.assert_close(got.opacities, want.opacities)
        torch.testing.assert_close(got.colors, want.colors)


def test_warm_up_keeps_the_deformation_off_in_training_only():
    m = _model(zero_init=False, warm_up=5)
    cam = replace(random_camera(16, 16, seed=1), time=0.8)
    m.train()
    m.on_step(4)
    torch.testing.assert_close(m.splats(cam).means, m.params["means"])
    m.on_step(5)
    assert not torch.allclose(m.splats(cam).means, m.params["means"])
    m.eval()
    m.on_step(0)  # evaluation always deforms
    assert not torch.allclose(m.splats(cam).means, m.params["means"])
    baked = m.bake(time=0.8)
    torch.testing.assert_close(baked.means, m.splats(cam).means)


def test_splats_for_shares_the_deformation_of_one_time():
    m = _model(zero_init=False, random_planes=True).eval()
    cams = [replace(random_camera(16, 16, seed=s), time=t) for s, t in ((1, 0.2), (2, 0.2), (3, 0.9))]
    calls = []
    m.encoder.register_forward_hook(lambda *_: calls.append(1))
    got = m.splats_for(cams)
    assert len(calls) == 2
    for s, c in zip(got, cams, strict=True):
        want = m.splats(c)
        torch.testing.assert_close(s.means, want.means)
        torch.testing.assert_close(s.colors, want.colors)
    assert not torch.allclose(got[0].means, got[2].means)


def test_time_resolution_follows_the_frame_count_and_param_groups_cover_everything():
    assert _model(n_frames=24).encoder.time_resolution == 12
    assert _model(n_frames=1).encoder.time_resolution == 2
    assert _model(time_resolution=7).encoder.time_resolution == 7
    m = _model()
    names = [g["name"] for g in m.param_groups()]
    assert names[-2:] == ["grid", "deform"]
    grouped = {id(p) for g in m.param_groups() for p in g["params"]}
    assert grouped == {id(p) for p in m.parameters()}


def test_trainer_adds_the_model_regularisers_to_the_loss():
    m = _model(n=60, lambda_plane_tv=1.0, lambda_time_smooth=1.0, lambda_time_l1=1.0)
    m.train()
    f = 20.0
    cam = Camera(look_at(torch.tensor([0.0, -3.0, 0.5]), torch.zeros(3)), f, f, 8.0, 8.0, 16, 16, time=0.4)
    view = View(camera=cam, image=torch.rand(16, 16, 3), mask=None, image_id=0)
    lr = {k: {"init": 1e-3} for k in ("means", "scales", "quats", "opacities", "sh0", "shN", "grid", "deform")}
    opt = SplatOptimizer(m.param_groups(), lr=lr)
    loss = SplatLoss(lambda_mask=0.0)
    raw = {k: float(v.detach()) for k, v in m.regularisers(0).items()}
    step = Trainer.train_step(m, [view], TorchRefRasterizer(), loss, opt, NoDensification(),
                              DivergenceGuard(check_grads=True, collapse_psnr=-math.inf), 0,
                              torch.Generator().manual_seed(0), torch.ones(3))
    terms = step["terms"]
    assert {k: float(terms[k].detach()) for k in raw} == pytest.approx(raw)
    objective = (1 - loss.lambda_dssim) * terms["l1"] + loss.lambda_dssim * terms["dssim"]
    torch.testing.assert_close(terms["total"], objective + sum(terms[k] for k in raw))


@pytest.mark.parametrize("experiment,writer", [("gaussians4d", "blender_mv"), ("gaussians4d_monocular", "dnerf")])
def test_experiment_trains_with_the_deformation_on(tmp_path, experiment, writer):
    """Both presets end to end with no warm-up, so training deforms and regularises from the first step."""
    if writer == "blender_mv":
        fw.write_blender_mv(tmp_path / writer, n_cams=6, n_test_cams=1, n_frames=3, size=16)
    else:
        fw.write_dnerf(tmp_path / writer, n_train=6, n_val=1, n_test=2, size=16)
    cfg = compose_run(experiment, writer, tmp_path / writer, tmp_path / "out", "schedule.hexplane_warm_up=0",
                      "trainer.iterations=3")
    record = run(cfg, tmp_path / "run")
    assert record["status"] == "ok", record.get("error") or record.get("reason")
    assert record["method"] == "gaussians4d" and len({f["time"] for f in record["per_frame"]}) > 1


def test_experiment_refuses_a_static_scene(tmp_path):
    write_blender_scene(tmp_path / "blender", n_train=8, n_test=2, size=16)
    cfg = compose_run("gaussians4d", "blender", tmp_path / "blender", tmp_path / "out")
    with pytest.raises(ConfigError, match="models motion"):
        run(cfg, tmp_path / "run")
