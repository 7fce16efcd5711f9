"""DropGaussian (``sparse=dropout``): unbiased opacity compensation, the progressive rate, no drop outside
training, gradients only through kept splats, and a resumed run that draws the same drops."""

from __future__ import annotations

import itertools

import pytest
import torch

from src.data.base import Scene, View
from src.eval.evaluator import views_psnr
from src.losses.objective import SplatLoss
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.sparse import DropGaussian, SparseRecipe
from src.strategy.base import NoDensification
from src.trainer.trainer import Trainer
from tests.conftest import random_camera, random_scene

pytestmark = pytest.mark.usefixtures("one_thread")
LR = {k: {"init": 1e-2} for k in ("means", "scales", "quats", "opacities", "sh0", "shN")}


def _bound(max_rate: float = 0.2, iterations: int = 100, total: int | None = None) -> DropGaussian:
    d = DropGaussian(max_rate=max_rate, total_iterations=total)
    d.bind(None, None, None, iterations)
    return d


@pytest.mark.parametrize("rate", [0.02, 0.1, 0.2, 0.5])
def test_compensation_preserves_the_expected_opacity_exactly(rate):
    # kept with probability 1 - r and scaled by 1 / (1 - r): E[factor] = 1
    assert (1 - rate) * DropGaussian.compensation(rate) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("rate", [0.1, 0.2])
def test_mean_over_draws_of_dropped_opacities_is_the_opacity(rate):
    splats = random_scene(500, seed=3)
    g = torch.Generator().manual_seed(0)
    draws = torch.stack([DropGaussian.drop(splats, rate, g).opacities for _ in range(400)])  # [400, N]
    kept = draws > 0
    assert kept.float().mean().item() == pytest.approx(1 - rate, abs=0.01)
    # a kept splat carries exactly opacity / (1 - r), a dropped one exactly 0
    assert torch.allclose(draws[kept], (splats.opacities / (1 - rate)).expand_as(draws)[kept], rtol=1e-6)
    # Monte Carlo mean within 5 standard errors (sd of the factor: sqrt(r / (1 - r)))
    se = splats.opacities * (rate / (1 - rate)) ** 0.5 / draws.shape[0] ** 0.5
    assert ((draws.mean(0) - splats.opacities).abs() <= 5 * se).float().mean() > 0.99
    assert (draws.mean() - splats.opacities.mean()).abs() < 0.01 * splats.opacities.mean()


def test_the_rate_follows_the_progressive_schedule():
    d = _bound(0.2, iterations=100)
    assert d.rate(0) == pytest.approx(0.2 * 1 / 100)  # iteration 0 is the authors' iteration 1
    assert d.rate(49) == pytest.approx(0.1)
    assert d.rate(99) == pytest.approx(0.2)
    assert d.rate(10_000) == pytest.approx(0.2)  # capped at gamma
    rates = [d.rate(i) for i in range(100)]
    assert all(b > a for a, b in itertools.pairwise(rates))  # strictly rising
    assert _bound(0.2, iterations=100, total=50).rate(24) == pytest.approx(0.1)  # an explicit t_total wins
    assert _bound(0.0).rate(99) == 0.0


def test_invalid_settings_are_refused():
    with pytest.raises(ValueError, match="max_rate"):
        DropGaussian(max_rate=1.0)
    with pytest.raises(ValueError, match="total_iterations"):
        DropGaussian(total_iterations=0)


def test_nothing_is_dropped_in_eval_mode_or_at_rate_zero():
    model = GaussianSplatModel(random_scene(50, seed=1).means, sh_degree=0)
    cam = random_camera(16, 16, seed=4)
    recipe = SparseRecipe(dropout=_bound(0.5, iterations=10))
    splats = model.splats_for([cam])
    g = torch.Generator().manual_seed(0)
    before = g.get_state()
    model.eval()
    assert recipe.train_splats(model, splats, 9, g)[0] is splats[0]
    assert torch.equal(g.get_state(), before)  # no random numbers drawn either
    model.train()
    dropped = recipe.train_splats(model, splats, 9, g)[0]
    assert (dropped.opacities == 0).any() and dropped.means is splats[0].means
    assert DropGaussian.drop(splats[0], 0.0, g) is splats[0]


def test_gradients_reach_only_the_kept_splats():
    torch.manual_seed(0)
    pts = (torch.rand(60, 3, generator=torch.Generator().manual_seed(5)) - 0.5) * 0.8
    model = GaussianSplatModel(pts, sh_degree=0, init_opacity=0.5)
    cam = random_camera(24, 24, seed=6)
    splats = model.splats(cam)
    g = torch.Generator().manual_seed(1)
    probe = torch.Generator()
    probe.set_state(g.get_state())
    keep = torch.rand(splats.n, generator=probe) >= 0.4  # the draw DropGaussian.drop makes next
    dropped = DropGaussian.drop(splats, 0.4, g)
    out = TorchRefRasterizer().render(dropped, cam, torch.ones(3))
    (out.color.sum() + out.alpha.sum()).backward()
    for name, p in model.params.items():
        assert p.grad is not None, name
        rows = p.grad.reshape(p.shape[0], -1).abs().sum(1)  # [N]
        assert (rows[~keep] == 0).all(), f"{name}: a dropped splat received a gradient"
    assert (model.params["opacities"].grad[keep] != 0).any()
    assert (model.params["sh0"].grad.reshape(60, -1)[keep].abs().sum(1) > 0).sum() > 5


class _Recording(TorchRefRasterizer):
    """A reference rasterizer that records, per render, whether any opacity differed from the model's."""

    def __init__(self, model: GaussianSplatModel) -> None:
        super().__init__()
        self.model, self.log = model, []

    def render(self, splats, camera, background=None):
        own = torch.sigmoid(self.model.params["opacities"].detach())
        self.log.append(bool((splats.opacities.detach() != own).any()))
        return super().render(splats, camera, background)


def _scene() -> Scene:
    views = []
    for i in range(3):
        g = torch.Generator().manual_seed(20 + i)
        views.append(View(camera=random_camera(16, 16, seed=20 + i), image=torch.rand(16, 16, 3, generator=g),
                          mask=None, image_id=i))
    return Scene(name="tiny", train=views, val=[], test=views[:1], background=torch.ones(3), view_ids=[0, 1, 2])


def _fit(run_dir, iterations: int, total: int, recorder: bool = False):
    pts = (torch.rand(80, 3, generator=torch.Generator().manual_seed(3)) - 0.5) * 0.6
    model = GaussianSplatModel(pts, sh_degree=0)
    rast = _Recording(model) if recorder else TorchRefRasterizer()
    scene = _scene()
    marks: list[int] = []

    def curve(m) -> float:  # the held-out scorer's path: the model in eval mode, its own splats
        marks.append(len(rast.log)) if recorder else None
        m.eval()
        value = views_psnr(m.splats, rast, scene.test, scene.background)
        m.train()
        return value

    trainer = Trainer(iterations=iterations, log_every=1000, progress=False, tensorboard=False, ckpt_every=0,
                      guard={"warmup": 10**6, "collapse_psnr": 0.0})
    trainer.fit(model, scene, rast, SplatLoss(lambda_mask=0.0), lambda m: SplatOptimizer(m.param_groups(), LR),
                NoDensification(), run_dir=run_dir, generator=torch.Generator().manual_seed(0),
                curve=curve if recorder else None, curve_every=1 if recorder else 0,
                sparse=SparseRecipe(dropout=DropGaussian(max_rate=0.5, total_iterations=total)))
    return model, rast, marks


def test_training_steps_drop_and_the_curve_scorer_never_does(tmp_path):
    _, rast, marks = _fit(tmp_path, iterations=4, total=4, recorder=True)
    curve_renders = set(marks)  # the render right after each mark is the scorer's (one test view)
    train = [changed for i, changed in enumerate(rast.log) if i not in curve_renders]
    scored = [rast.log[i] for i in curve_renders]
    assert len(train) == 4 and all(train)  # every training render had dropped (and compensated) splats
    assert len(scored) == 4 and not any(scored)  # the held-out scorer rendered the model's own opacities


def test_a_resumed_run_draws_the_same_drops(tmp_path):
    full, _, _ = _fit(tmp_path / "full", iterations=6, total=6)
    _fit(tmp_path / "cut", iterations=3, total=6)  # writes its checkpoint at iteration 3
    resumed, _, _ = _fit(tmp_path / "cut", iterations=6, total=6)  # resumes from it
    for name, p in full.params.items():
        assert torch.equal(p, resumed.params[name]), name
    other, _, _ = _fit(tmp_path / "other", iterations=6, total=1000)  # other drops: another model
    assert not torch.equal(other.params["means"], full.params["means"])
