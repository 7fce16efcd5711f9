"""3DGS model: densification keeps Adam state consistent, the cap holds, PLY round trip."""

from __future__ import annotations

import torch

from src.io.ply import read_ply, write_ply
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.default import ADCStrategy

LR = {k: {"init": 1e-3} for k in ("means", "scales", "quats", "opacities", "sh0", "shN")}


def _model(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    return GaussianSplatModel(torch.rand(n, 3, generator=g) * 2 - 1, sh_degree=1)


def _step(model, opt):
    loss = sum((p**2).sum() for p in model.parameters())
    loss.backward()
    opt.step()
    opt.zero_grad()


def test_densify_and_prune_keep_optimizer_rows_consistent():
    m = _model()
    opt = SplatOptimizer(m.param_groups(), LR)
    _step(m, opt)
    n = m.n_splats
    clone = torch.zeros(n, dtype=torch.bool)
    clone[:5] = True
    split = torch.zeros(n, dtype=torch.bool)
    split[10:13] = True
    before_means = m.params["means"].detach().clone()
    m.densify(opt, clone, split, 2, torch.Generator().manual_seed(0))
    assert m.n_splats == n + 5 + 3  # +5 clones, +6 children, -3 parents
    # kept rows keep their values
    keep = ~split
    assert torch.equal(m.params["means"][: int(keep.sum())], before_means[keep])
    for g in opt.optimizer.param_groups:
        p = g["params"][0]
        st = opt.optimizer.state[p]
        assert st["exp_avg"].shape == p.shape, g["name"]
        assert any(p is q for q in m.parameters())
    prune = torch.zeros(m.n_splats, dtype=torch.bool)
    prune[::2] = True
    m.prune(opt, prune)
    _step(m, opt)  # Adam still runs with the edited state
    assert all(opt.optimizer.state[g["params"][0]]["exp_avg"].shape == g["params"][0].shape
               for g in opt.optimizer.param_groups)


def test_adc_respects_cap():
    m = _model(100)
    opt = SplatOptimizer(m.param_groups(), LR)
    strat = ADCStrategy(grad_threshold=0.0, start_iter=0, stop_iter=1000, every=1, max_splats=120,
                        reset_every=0, extent=1.0)
    strat.grad_accum = torch.rand(100)
    strat.count = torch.ones(100)
    strat.after_step(m, opt, 1, torch.Generator().manual_seed(0))
    assert m.n_splats <= 120


def test_ply_round_trip(tmp_path):
    m = _model(40)
    with torch.no_grad():
        m.params["opacities"].uniform_(-3, 3)
        m.params["sh0"].normal_()
        m.params["quats"].normal_()
    s = m.bake()
    write_ply(tmp_path / "a.ply", s)
    back = read_ply(tmp_path / "a.ply").splats
    for k in ("means", "scales", "quats", "opacities", "colors"):
        assert torch.allclose(getattr(back, k), getattr(s, k), atol=1e-5, rtol=1e-5), k


def test_checkpoint_state_dict_with_different_count():
    a, b = _model(30), _model(50, seed=1)
    b.load_state_dict(a.state_dict())
    assert b.n_splats == 30 and torch.equal(b.params["means"], a.params["means"])
