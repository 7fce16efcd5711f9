"""LightGaussian (Fan et al., NeurIPS 2024): global-significance pruning during training, SH distillation,
vector quantisation into ``splats_compressed.npz`` and evaluation of the decompressed splats."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from src.core.splats import Splats
from src.data.base import Scene, View
from src.eval.evaluator import views_psnr
from src.io.compressed import decode, encode, nearest_code, read_compressed, weighted_kmeans, write_compressed
from src.losses.objective import SplatLoss
from src.models.lightgaussian import LightGaussianModel
from src.models.sh import C0
from src.optim.adam import SplatOptimizer
from src.rasterizer.cpu import CpuRasterizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.run import run
from src.strategy.lightgaussian import LightGaussianStrategy, pseudo_camera
from src.strategy.significance import global_significance, splat_hits
from src.trainer.trainer import Trainer
from tests.conftest import random_camera, random_scene
from tests.scenes import write_blender_scene

REPO = Path(__file__).resolve().parents[1]
LR = {k: {"init": 1e-3} for k in ("means", "scales", "quats", "opacities", "sh0", "shN")}
LR["sh0"] = {"init": 2.5e-2}

pytestmark = pytest.mark.usefixtures("one_thread")


def _scene(n_views: int = 4, size: int = 24, n: int = 60, seed: int = 0) -> tuple[Scene, Splats]:
    """A tiny static scene whose images are torch_ref renders of random splats (also returned)."""
    gt = random_scene(n, seed=seed, spread=0.3, scale_range=(0.04, 0.12))
    gt.opacities = gt.opacities.clamp_min(0.5)
    rast = TorchRefRasterizer()
    views = []
    for i in range(n_views):
        cam = random_camera(size, size, seed=100 + i)
        with torch.no_grad():
            out = rast.render(gt, cam, torch.zeros(3))
        views.append(View(camera=cam, image=out.color, mask=out.alpha.clamp(0, 1), image_id=i))
    return Scene(name="tiny", train=views, val=[], test=views[:1], background=torch.zeros(3),
                 view_ids=list(range(n_views))), gt


def _model(gt: Splats, sh_degree: int = 0, seed: int = 1) -> LightGaussianModel:
    """A LightGaussianModel holding ``gt``'s splats (log-scales, logit opacities) and random higher SH bands."""
    m = LightGaussianModel(gt.means.clone(), sh_degree=sh_degree, sh_degree_interval=1)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.params["scales"].copy_(gt.scales.log())
        m.params["quats"].copy_(gt.quats)
        m.params["opacities"].copy_(torch.logit(gt.opacities))
        m.params["sh0"].copy_(((gt.colors - 0.5) / C0)[:, None])
        m.params["shN"].normal_(0.0, 0.6, generator=g)
    m.on_step(10 * sh_degree)  # every band active
    return m


# -- global significance ----------------------------------------------------------------------------------

@pytest.mark.parametrize("backend,antialiased", [("torch_ref", False), ("torch_ref", True), ("cpu", False),
                                                 ("cpu", True)])
def test_hits_are_the_pixels_with_a_nonzero_blending_weight(backend, antialiased):
    """splat_hits counts exactly the pixels where the rasterizer gives the splat a weight alpha T > 0."""
    dtype = torch.float64 if backend == "torch_ref" else torch.float32
    s = random_scene(50, seed=3, dtype=dtype, scale_range=(0.05, 0.3))
    cam = random_camera(40, 36, seed=1, dtype=dtype)
    rast = TorchRefRasterizer(antialiased=antialiased) if backend == "torch_ref" else CpuRasterizer(
        antialiased=antialiased)
    # one channel per splat: channel i of the image is splat i's blending weight at every pixel
    probe = Splats(s.means, s.scales, s.quats, s.opacities, torch.eye(s.n, dtype=dtype))
    with torch.no_grad():
        weights = rast.render(probe, cam, torch.zeros(s.n, dtype=dtype)).color  # [H, W, N]
    expected = (weights > 0).sum((0, 1)).to(dtype)
    hits = splat_hits(s, cam, antialiased=antialiased)
    assert hits.sum() > 100 and (hits == 0).any()  # the check is not vacuous: splats hit and missed
    assert torch.equal(hits, expected)


def test_hits_significance_is_hits_times_opacity_times_volume_power():
    scene, gt = _scene()
    m = _model(gt)
    rast = TorchRefRasterizer()
    got = global_significance(m, rast, scene.train, volume_power=0.1, score="hits")
    s = m.splats(scene.train[0].camera)
    hits = sum(splat_hits(s, v.camera) for v in scene.train)
    vol = s.scales.prod(-1).detach()
    assert torch.allclose(got, hits * s.opacities.detach() * (vol / vol.max()) ** 0.1)
    assert not torch.allclose(got, global_significance(m, rast, scene.train, 0.1, score="blend"))


# -- pruning during training --------------------------------------------------------------------------------

def _strategy(iterations: int, **kw) -> LightGaussianStrategy:
    args = {"prune_at": [0.5], "prune_ratio": 0.66, "distill_at": None, "start_iter": 10**6, "reset_every": 0}
    return LightGaussianStrategy(iterations=iterations, **{**args, **kw})


def test_prune_keeps_the_most_significant_fraction_at_the_scheduled_iteration():
    scene, gt = _scene(n=90)
    m = _model(gt)
    rast = TorchRefRasterizer()
    st = _strategy(8)  # 0.5 x 8: after iteration 4 (1-based), i.e. after_step(iteration=3)
    st.bind(scene, rast)
    assert st.prune_iters == [4] and st.stop_iter == 4  # densification ends at the first prune
    g = torch.Generator().manual_seed(0)
    n = m.n_splats
    for it in range(3):
        st.after_step(m, None, it, g)
        assert m.n_splats == n
    score = global_significance(m, rast, scene.train, 0.1, "hits")
    keep = torch.argsort(score, descending=True, stable=True)[: n - round(0.66 * n)]
    expected = m.params["means"].detach()[torch.sort(keep).values].clone()
    stats = st.after_step(m, None, 3, g)
    assert stats["pruned"] == round(0.66 * n) and m.n_splats == n - round(0.66 * n)
    assert torch.equal(m.params["means"].detach(), expected)  # exactly the top (1 - ratio), order kept
    for it in range(4, 8):
        st.after_step(m, None, it, g)
    assert m.n_splats == n - round(0.66 * n)


def test_repeated_prunes_decay():
    scene, gt = _scene(n=80)
    m = _model(gt)
    st = _strategy(40, prune_at=[0.25, 0.5], prune_ratio=0.5, prune_decay=0.5)
    st.bind(scene, TorchRefRasterizer())
    assert st.prune_iters == [10, 20]
    g = torch.Generator().manual_seed(0)
    for it in range(40):
        st.after_step(m, None, it, g)
    n1 = 80 - round(0.5 * 80)
    assert m.n_splats == n1 - round(0.25 * n1)


def test_distillation_needs_a_model_that_can_distil():
    from src.models.gaussians import GaussianSplatModel

    scene, gt = _scene(n=20)
    st = _strategy(8, distill_at=0.5)
    st.bind(scene, TorchRefRasterizer())
    with pytest.raises(TypeError, match="model=lightgaussian"):
        st.after_step(GaussianSplatModel(gt.means.clone(), sh_degree=0), None, 0, torch.Generator())


def test_experiment_config_maps_the_reference_schedule_to_the_run():
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["+experiment=lightgaussian", "trainer.iterations=1500"])
    from src.utils.instantiate import build

    st = build(cfg.strategy, extent=1.0)
    assert isinstance(st, LightGaussianStrategy)
    assert st.prune_iters == [1125] and st.distill_iter == 1312 and st.stop_iter == 1125  # 30k / 35k of 40k
    assert st.prune_ratio == 0.66 and st.volume_power == 0.1 and st.score == "hits" and st.distill_degree == 0
    assert cfg.compress.vq_ratio == 0.6 and cfg.compress.codebook_size == 256
    assert cfg.model._target_.endswith("LightGaussianModel")


# -- SH distillation --------------------------------------------------------------------------------------

def test_pseudo_camera_moves_the_centre_only():
    cam = random_camera(24, 24, seed=5)
    p = pseudo_camera(cam, 0.05, torch.Generator().manual_seed(0))
    assert torch.equal(p.world_to_cam[:3, :3], cam.world_to_cam[:3, :3])
    d = (p.center - cam.center).norm()
    assert 1e-4 < float(d) < 0.5 and p.fx == cam.fx and p.width == cam.width


def test_distillation_lowers_the_sh_degree_and_its_loss_decreases(tmp_path):
    # one training camera: around it a DC colour can reproduce the teacher's degree-1 colours closely
    scene, gt = _scene(n=40, n_views=1)
    m = _model(gt, sh_degree=1)
    assert m.active_sh_degree == 1 and m.params["shN"].shape[1] == 3
    rast = TorchRefRasterizer()
    iters = 60
    st = _strategy(iters, prune_at=[], distill_at=5 / iters, distill_degree=0, pseudo_std=0.05)
    losses: list[float] = []
    base = SplatLoss(lambda_dssim=0.2, lambda_mask=0.1)

    def loss_fn(renders, views, splats, iteration=0):
        terms = base(renders, views, splats, iteration)
        losses.append(float(terms["total"].detach()))
        return terms

    trainer = Trainer(iterations=iters, log_every=1000, image_every=0, progress=False, tensorboard=False,
                      guard={"warmup": 10**6, "collapse_psnr": 0.0})
    teacher_sh = None

    def make_opt(model):
        return SplatOptimizer(model.param_groups(), LR)

    orig = st.after_step

    def after_step(model, optimizer, iteration, generator):  # capture the teacher when it is taken
        nonlocal teacher_sh
        out = orig(model, optimizer, iteration, generator)
        if model.distilling and teacher_sh is None:
            teacher_sh = model.teacher_sh.clone()
        return out

    st.after_step = after_step
    trainer.fit(m, scene, rast, loss_fn, make_opt, st, tmp_path, torch.Generator().manual_seed(0))
    assert m.distilling and m.teacher_sh_degree == 1
    assert m.params["shN"].shape[1] == 0 and m.active_sh_degree == 0 and m.max_sh_degree == 0
    assert torch.equal(m.teacher_sh, teacher_sh)  # the teacher stays frozen
    distill = losses[5:]  # after iteration 5 (the SH degree is 1 from iteration 1)
    first, last = np.mean(distill[:6]), np.mean(distill[-6:])
    assert last < 0.3 * first, (first, last)


def test_distilling_model_checkpoint_round_trip():
    scene, gt = _scene(n=30)
    m = _model(gt, sh_degree=2)
    opt = SplatOptimizer(m.param_groups(), LR)
    m.start_distillation(opt, degree=1, freeze_opacity=True)
    assert m.params["shN"].shape[1] == 3 and m.teacher_sh.shape[1] == 9
    assert any(p is m.params["shN"] for g in opt.optimizer.param_groups for p in g["params"])
    fresh = LightGaussianModel(gt.means.clone(), sh_degree=2, sh_degree_interval=1)
    fresh.load_state_dict(m.state_dict())
    fresh.on_step(100)
    assert fresh.distilling and fresh.active_sh_degree == 1 and fresh.teacher_sh_degree == 2
    cam = scene.train[0].camera
    a, b = m.splats(cam), fresh.splats(cam)
    assert torch.equal(a.colors, b.colors) and not b.opacities.requires_grad  # opacities frozen
    assert torch.equal(m.teacher_splats(cam).colors, fresh.teacher_splats(cam).colors)


# -- vector quantisation -------------------------------------------------------------------------------------

def _attrs(n: int, degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return {"means": torch.randn(n, 3, generator=g), "scales": torch.randn(n, 3, generator=g) - 3,
            "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
            "opacities": torch.randn(n, generator=g) * 2, "sh": torch.randn(n, k, 3, generator=g)}


def test_vq_round_trip_error_is_bounded_and_the_codebook_is_as_configured():
    n, degree, codes = 500, 1, 32
    a = _attrs(n, degree)
    sig = torch.rand(n, generator=torch.Generator().manual_seed(1))
    arrays = encode(a, sig, vq_ratio=0.6, codebook_size=codes, kmeans_iters=20)
    d = decode(arrays)
    assert arrays["codebook"].shape == (codes, 4 * 3) and arrays["codebook"].dtype == np.float16
    for k in ("scales", "quats", "opacities"):
        assert arrays[k].dtype == np.float16 and torch.allclose(d[k], a[k].reshape(d[k].shape), atol=2e-3, rtol=1e-3)
    assert arrays["means"].dtype == np.float32 and torch.equal(d["means"], a["means"])
    order = torch.argsort(sig, descending=True, stable=True)
    raw, vq = order[: n - round(0.6 * n)], order[n - round(0.6 * n):]
    assert torch.equal(d["sh"][raw], a["sh"][raw].half().float())  # the most significant keep their SH
    flat, dec = a["sh"][vq].reshape(len(vq), -1), d["sh"][vq].reshape(len(vq), -1)
    book = torch.from_numpy(arrays["codebook"].astype(np.float32))
    assert torch.equal(dec, book[nearest_code(flat, book)])  # each gets its nearest code
    err = ((dec - flat) ** 2).sum(1).mean()
    assert err < 0.75 * ((flat - flat.mean(0)) ** 2).sum(1).mean()  # far below one code for all


def test_vq_is_exact_when_the_vectors_fit_the_codebook():
    a = _attrs(300, 0)
    protos = torch.randn(20, 1, 3, generator=torch.Generator().manual_seed(4))
    a["sh"] = protos[torch.arange(300) % 20]
    d = decode(encode(a, torch.ones(300), vq_ratio=1.0, codebook_size=32, kmeans_iters=30))
    assert torch.allclose(d["sh"], a["sh"].half().float(), atol=1e-6)


def test_weighted_kmeans_follows_the_weights():
    x = torch.tensor([[0.0], [1.0], [10.0]])
    book, _ = weighted_kmeans(x, torch.tensor([1.0, 1.0, 0.0]), 1, 10, torch.Generator().manual_seed(0))
    assert torch.allclose(book, torch.tensor([[0.5]]), atol=1e-4)  # the weightless row hardly pulls


def test_compressed_file_loads_without_pickle(tmp_path):
    arrays = encode(_attrs(200, 1), torch.rand(200), codebook_size=16)
    size = write_compressed(tmp_path / "s.npz", arrays)
    assert size == (tmp_path / "s.npz").stat().st_size
    with np.load(tmp_path / "s.npz", allow_pickle=False) as f:
        assert all(f[k].dtype.kind in "fiu" for k in f.files)
    got, want = read_compressed(tmp_path / "s.npz"), decode(arrays)
    assert all(torch.equal(got[k], want[k]) for k in want)
    np.savez(tmp_path / "evil.npz", **{**arrays, "n": np.array([object()], dtype=object)})
    with pytest.raises(ValueError, match=r"evil\.npz"):  # an object array is refused, never unpickled
        read_compressed(tmp_path / "evil.npz")


# -- the experiment end to end ---------------------------------------------------------------------------

def _compose(root: Path, *extra: str):
    overrides = ["+experiment=lightgaussian", f"dataset.root={root}", "+ci=smoke", "trainer.iterations=40",
                 "dataset.downscale=1", "trainer.tensorboard=false", "eval.save_renders=false", "eval.fps_repeats=0",
                 "model.sh_degree_interval=10", *extra]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory) -> Path:
    return write_blender_scene(tmp_path_factory.mktemp("lg") / "scene", n_train=8, n_test=2, size=24)


def test_run_records_sizes_and_scores_the_decompressed_splats(tiny_root, tmp_path):
    rec = run(_compose(tiny_root), tmp_path / "run")
    assert rec["status"] == "ok", rec.get("error")
    m = rec["metrics"]
    npz, ply = tmp_path / "run" / "splats_compressed.npz", tmp_path / "run" / "splats.ply"
    assert m["size_mb"] == npz.stat().st_size / 2**20 and m["size_mb_ply"] == ply.stat().st_size / 2**20
    assert m["size_mb"] < m["size_mb_ply"] and m["sh_degree"] == 0
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["metrics"]["size_mb"] == m["size_mb"]
    # test PSNR = the PSNR of the splats decoded from the file (DC colours after distillation to degree 0)
    d = read_compressed(npz)
    s = Splats(means=d["means"], scales=d["scales"].exp(), quats=d["quats"], opacities=torch.sigmoid(d["opacities"]),
               colors=(C0 * d["sh"][:, 0] + 0.5).clamp_min(0))
    cfg = _compose(tiny_root)
    from src.utils.instantiate import build

    scene = build(cfg.dataset).load()
    assert m["psnr"] == pytest.approx(views_psnr(lambda _c: s, TorchRefRasterizer(), scene.test, scene.background))
    assert m["n_splats"] == s.n < 300  # pruned (hull init: 300 points at the smoke scale)


@pytest.mark.slow
def test_run_interrupted_while_distilling_resumes_to_the_same_result(tiny_root, tmp_path, monkeypatch):
    extra = ("trainer.ckpt_every=5",)
    full = run(_compose(tiny_root, *extra), tmp_path / "full")
    orig = LightGaussianStrategy.step_views

    def interrupted(self, model, views, iteration, generator):
        if iteration == 37:  # distillation started after iteration 35; checkpoint after 35
            raise KeyboardInterrupt
        return orig(self, model, views, iteration, generator)

    monkeypatch.setattr(LightGaussianStrategy, "step_views", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(_compose(tiny_root, *extra), tmp_path / "resumed")
    ck = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)
    assert ck["iteration"] == 34 and "teacher_sh" in ck["model"]
    monkeypatch.setattr(LightGaussianStrategy, "step_views", orig)
    resumed = run(_compose(tiny_root, *extra), tmp_path / "resumed")
    assert resumed["status"] == "ok"
    for k in ("psnr", "n_splats", "size_mb", "psnr_before_vq"):
        assert resumed["metrics"][k] == full["metrics"][k], k
