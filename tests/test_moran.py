"""Moran's I (supplementary B.1): loop reference, known values, kNN, loss, covariance features."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml

from src.core.splats import Splats
from src.losses.moran import MoranLoss, covariance_features, knn_indices, morans_i


def _slow_morans_i(points, attr, k=5, center=True, self_weight_quirk=False, eps=1e-4):
    """Direct transcription of Eqs. B.3–B.5 with Python loops (float64)."""
    pts = points.double().tolist()
    a = attr.double()
    if a.ndim == 1:
        a = a[:, None]
    if center:
        a = a - a.mean(0, keepdim=True)
    vals = a.tolist()
    n, n_feat = len(pts), len(vals[0])

    def dist(i, j):
        return math.sqrt(sum((pts[i][c] - pts[j][c]) ** 2 for c in range(3)))

    total = 0.0
    for s in range(n):
        others = sorted((dist(s, j), j) for j in range(n) if j != s)
        nb = [s] + [j for _, j in others[: k - 1]]
        W = [[0.0] * k for _ in range(k)]
        for i in range(k):
            for j in range(k):
                d = dist(nb[i], nb[j])
                if self_weight_quirk:
                    W[i][j] = 1.0 / d if d > 1e-5 else 1e-5
                else:
                    W[i][j] = 0.0 if i == j else 1.0 / d
        w_sum = sum(map(sum, W))
        if self_weight_quirk:
            W = [[w / w_sum for w in row] for row in W]
            w_sum = 1.0
        for f in range(n_feat):
            x = [vals[nb[i]][f] for i in range(k)]
            num = sum(W[i][j] * x[i] * x[j] for i in range(k) for j in range(k))
            total += k / w_sum * num / (sum(v * v for v in x) + eps)
    return total / (n * n_feat)


@pytest.mark.parametrize("center", [True, False])
@pytest.mark.parametrize("quirk", [False, True])
def test_vectorised_matches_loop_implementation(center, quirk):
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(40, 3, generator=g)
    attr = torch.rand(40, 3, generator=g) + pts[:, :1]  # some spatial correlation
    fast = morans_i(pts, attr, k=5, center=center, self_weight_quirk=quirk)
    slow = _slow_morans_i(pts, attr, k=5, center=center, self_weight_quirk=quirk)
    assert abs(fast.item() - slow) < 1e-5
    one_dim = morans_i(pts, attr[:, 1], k=5, center=center, self_weight_quirk=quirk)
    assert abs(one_dim.item() - _slow_morans_i(pts, attr[:, 1], 5, center, quirk)) < 1e-5


def test_knn_includes_self_first_and_chunking_is_exact():
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(300, 3, generator=g)
    full = knn_indices(pts, 5)
    chunked = knn_indices(pts, 5, max_chunk_elems=1000)  # 3 rows per chunk
    assert torch.equal(full, chunked)
    assert torch.equal(full[:, 0], torch.arange(300))
    d = torch.cdist(pts, pts)
    ref = d.topk(5, largest=False).indices
    assert torch.equal(full.sort(1).values, ref.sort(1).values)
    dup = torch.cat([pts[:10], pts[:10]])  # coincident points: the query still comes first
    assert torch.equal(knn_indices(dup, 2)[:, 0], torch.arange(20))


def test_constant_attribute_uncentred_is_one():
    pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(2))
    val = morans_i(pts, torch.full((500,), 0.7), center=False)
    assert abs(val.item() - 1.0) < 1e-3


def test_linear_ramp_on_grid_is_strongly_positive():
    ax = torch.linspace(-1, 1, 14)
    pts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    pts = pts + 1e-3 * torch.randn(pts.shape, generator=torch.Generator().manual_seed(3))  # break ties
    val = morans_i(pts, pts[:, 0].clone(), center=True)
    assert val.item() > 0.5


def test_iid_noise_centred_is_near_zero():
    g = torch.Generator().manual_seed(4)
    pts = torch.rand(2000, 3, generator=g)
    val = morans_i(pts, torch.randn(2000, 3, generator=g), center=True)
    assert abs(val.item()) < 0.1


def test_differentiable_in_attributes_only():
    g = torch.Generator().manual_seed(5)
    pts = torch.rand(100, 3, generator=g).requires_grad_(True)
    attr = torch.rand(100, 2, generator=g).requires_grad_(True)
    morans_i(pts, attr).backward()
    assert attr.grad is not None and torch.isfinite(attr.grad).all() and attr.grad.abs().sum() > 0
    assert pts.grad is None  # neighbourhoods and weights are constants


def test_moran_loss_on_splats():
    g = torch.Generator().manual_seed(6)
    n = 300
    pts = torch.rand(n, 3, generator=g)
    # constant, non-zero attributes (an all-zero channel scores I = 0 / (0 + eps) = 0, as the reference)
    smooth = Splats(means=pts, scales=torch.full((n, 3), 0.05), quats=torch.full((n, 4), 0.5),
                    opacities=torch.full((n,), 0.8), colors=torch.full((n, 3), 0.5))
    noisy = Splats(means=pts, scales=torch.rand(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                   opacities=torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g))
    loss_fn = MoranLoss(center=False)  # the reference's training loss: uncentred
    ls = loss_fn(pts, smooth)
    ln = loss_fn(pts, {k: getattr(noisy, k) for k in ("colors", "opacities", "scales", "quats")})
    assert ls.item() < 5e-3  # constant attributes, uncentred: I ≈ 1 for all four
    identity_quats = {"quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)}
    zero_xyz = MoranLoss(attributes=("quats",), center=False)(pts, identity_quats)
    assert abs(zero_xyz.item() - 0.75) < 1e-3  # channels x, y, z are all zero -> I = 0 there
    assert 0.0 < ln.item() <= 1.0
    centred = MoranLoss(attributes=("colors",))(pts, noisy)  # centred (the default)
    assert centred.item() > 0.8  # centred i.i.d. colours: I ≈ 0 -> loss ≈ 1


def test_covariance_features():
    g = torch.Generator().manual_seed(7)
    s = torch.rand(50, 3, generator=g) + 0.1
    ident = torch.tensor([[1.0, 0, 0, 0]]).repeat(50, 1)
    cov = covariance_features(s, ident)
    expected = torch.zeros(50, 6)
    expected[:, 0], expected[:, 3], expected[:, 5] = s[:, 0] ** 2, s[:, 1] ** 2, s[:, 2] ** 2
    assert torch.allclose(cov, expected, atol=1e-6)
    # 90° about z swaps the x and y variances
    qz = torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]]).repeat(50, 1)
    cz = covariance_features(s, qz)
    assert torch.allclose(cz[:, 0], s[:, 1] ** 2, atol=1e-5)
    assert torch.allclose(cz[:, 3], s[:, 0] ** 2, atol=1e-5)


def test_training_loss_centring_is_a_config_choice():
    from src.losses.objective import SplatLoss

    g = torch.Generator().manual_seed(8)
    n = 300
    noisy = Splats(means=torch.rand(n, 3, generator=g), scales=torch.rand(n, 3, generator=g) + 0.1,
                   quats=torch.rand(n, 4, generator=g) + 0.1, opacities=torch.rand(n, generator=g) + 0.1,
                   colors=torch.rand(n, 3, generator=g) + 0.1)
    # i.i.d. positive attributes: the reference's uncentred I is high (loss small), the centred I ≈ 0
    quirk = SplatLoss(lambda_moran=1.0, moran_center=False).moran(noisy.means, noisy, 0)
    textbook = SplatLoss(lambda_moran=1.0).moran(noisy.means, noisy, 0)  # the default: textbook B.4, the paper's intent
    assert quirk.item() < 0.35 < 0.8 < textbook.item()
    conf = yaml.safe_load((Path(__file__).resolve().parents[1] / "conf" / "loss" / "default.yaml").read_text())
    assert conf["moran_center"] is True


def test_the_training_objective_trains_with_the_tested_moran_loss():
    """SplatLoss's Moran term is MoranLoss (one implementation), its neighbourhoods cached between iterations."""
    from src.losses.objective import SplatLoss

    g = torch.Generator().manual_seed(8)
    n = 200
    pts = torch.rand(n, 3, generator=g)
    s = Splats(means=pts, scales=torch.rand(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
               opacities=torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g))
    objective = SplatLoss(lambda_dssim=0.0, lambda_mask=0.0, lambda_moran=0.5, moran_every=10)
    assert isinstance(objective.moran, MoranLoss)
    direct = MoranLoss(every=10)(pts, s)
    assert torch.equal(objective.moran(pts, s, iteration=0), direct)
    first = objective.moran.neighbours(pts, 0)
    moved = pts + 0.3 * torch.rand(n, 3, generator=g)
    assert objective.moran.neighbours(moved, 5) is first  # cached within `every` iterations
    assert not torch.equal(objective.moran.neighbours(moved, 10), first)  # recomputed after
