"""Budget strategy (relocation + growth to a cap) and significance scores."""

from __future__ import annotations

import torch

from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.strategy.budget import BudgetStrategy
from src.strategy.significance import splat_contributions
from tests.conftest import random_camera

LR = {k: {"init": 1e-3} for k in ("means", "scales", "quats", "opacities", "sh0", "shN")}


class _View:
    def __init__(self, cam):
        self.camera = cam


def _model(n=80, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = GaussianSplatModel((torch.rand(n, 3, generator=g) * 2 - 1) * 0.4, sh_degree=0)
    with torch.no_grad():
        m.params["opacities"].uniform_(-3, 3, generator=g)
        m.params["sh0"].normal_(generator=g)
    return m


def test_contributions_sum_to_the_alpha_image():
    m = _model()
    rast = TorchRefRasterizer()
    views = [_View(random_camera(24, 24, seed=s)) for s in range(3)]
    c = splat_contributions(m, rast, views)
    with torch.no_grad():
        alpha_sum = sum(rast.render(m.splats(v.camera), v.camera).alpha.sum() for v in views)
    assert c.shape == (m.n_splats,) and (c >= 0).all()
    assert torch.allclose(c.sum(), alpha_sum, rtol=1e-4)
    # a splat with zero contribution can be removed without changing any image
    zero = torch.nonzero(c == 0).squeeze(1)
    if zero.numel():
        keep = torch.ones(m.n_splats, dtype=torch.bool)
        keep[zero] = False
        with torch.no_grad():
            for v in views:
                a = rast.render(m.splats(v.camera), v.camera).color
                b = rast.render(m.splats(v.camera).index(keep), v.camera).color
                assert torch.allclose(a, b, atol=1e-6)


def test_budget_relocates_dead_and_grows_to_cap():
    m = _model(100)
    with torch.no_grad():
        m.params["opacities"][:20] = -10.0  # dead
    opt = SplatOptimizer(m.param_groups(), LR)
    strat = BudgetStrategy(max_splats=103, start_iter=0, stop_iter=100, every=1, grow_fraction=0.05)
    stats = strat.after_step(m, opt, 0, torch.Generator().manual_seed(0))
    assert stats["relocated"] == 20 and m.n_splats == 103
    assert (m.opacity_values() > 0.005).all()
    for g in opt.optimizer.param_groups:
        p = g["params"][0]
        assert opt.optimizer.state.get(p, {"exp_avg": p}) ["exp_avg"].shape == p.shape


def test_mcmc_copy_preserves_coincident_opacity():
    """A target and one exact copy composite to the target's original opacity: 1 - (1 - o')^2 = o."""
    m = _model(10)
    o = m.opacity_values()[3].clone()
    m.add_from(None, torch.tensor([3]), torch.Generator().manual_seed(0))
    o_new = m.opacity_values()[[3, 10]]
    assert torch.allclose(1 - (1 - o_new[0]) * (1 - o_new[1]), o, atol=1e-5)
