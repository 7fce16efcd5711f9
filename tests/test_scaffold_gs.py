"""Scaffold-GS (``+experiment=scaffold_gs``): decoding k children per anchor, frustum culling, dropping
non-positive opacities, anchor growing on unoccupied voxels, pruning with the optimiser state, a smoke
training run, and checkpoints with changed anchor counts that resume to the same model."""

from __future__ import annotations

import math

import pytest
import torch

from src.core.cameras import Camera
from src.data.blender import BlenderDataset
from src.init import HullInit
from src.losses.objective import SplatLoss
from src.models.scaffold import ScaffoldGSModel, voxelize
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.strategy.anchor import AnchorStrategy, rows_in
from src.trainer.identity import shape_mismatch
from src.trainer.trainer import Trainer
from tests.scenes import write_blender_scene

pytestmark = pytest.mark.usefixtures("one_thread")

LR = {"offsets": {"init": 0.01, "final": 1e-4, "max_steps": 40, "scale_by_extent": True},
      "features": {"init": 0.0075}, "scaling": {"init": 0.007},
      "mlp_opacity": {"init": 0.002, "final": 2e-5, "max_steps": 40}, "mlp_cov": {"init": 0.004},
      "mlp_color": {"init": 0.008, "final": 5e-5, "max_steps": 40}}


def _camera(size: int = 32, f: float = 50.0) -> Camera:
    """A camera at the origin looking along +z: (x, y, z) projects to (f x / z + size / 2, f y / z + size / 2)."""
    return Camera(torch.eye(4), fx=f, fy=f, cx=size / 2, cy=size / 2, width=size, height=size)


def _model(anchors: torch.Tensor, k: int = 4, log_scale: float = math.log(1e-4), **kwargs) -> ScaffoldGSModel:
    """A model whose anchors are exactly ``anchors`` [A, 3], in that order, all scalings ``log_scale``."""
    m = ScaffoldGSModel(anchors, n_offsets=k, voxel_size=1e-3, **kwargs)
    assert m.n_splats == anchors.shape[0]
    m.anchors = anchors.clone()
    with torch.no_grad():
        m.params["scaling"].fill_(log_scale)
    return m


def _set_opacity_bias(m: ScaffoldGSModel, bias: list[float]) -> None:
    """Child j's opacity becomes tanh(bias[j]) whatever the input (last opacity layer: zero weights)."""
    last = m.mlp_opacity[2]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor(bias))


def test_voxelize_keeps_one_centre_per_occupied_voxel():
    pts = torch.tensor([[0.01, 0.02, 0.0], [0.04, -0.04, 0.01], [0.31, 0.0, 0.0], [0.29, 0.02, -0.03]])
    centres = voxelize(pts, 0.1)
    assert torch.allclose(centres, torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]]))


def test_decode_gives_k_children_per_anchor_with_the_papers_attributes():
    anchors = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 2.5], [0.0, -0.1, 3.0]])
    m = _model(anchors, k=5, log_scale=math.log(0.05))
    _set_opacity_bias(m, [0.5] * 5)
    with torch.no_grad():
        m.params["offsets"].normal_(generator=torch.Generator().manual_seed(0))
        m.params["features"].normal_(generator=torch.Generator().manual_seed(1))
    cam = _camera()
    s = m.splats(cam)
    s.validate()
    assert s.n == 3 * 5 and s.colors.shape == (15, 3)
    expected = (anchors[:, None] + m.params["offsets"] * 0.05).reshape(-1, 3)  # x + O_j exp(l[:3])
    assert torch.allclose(s.means, expected, atol=1e-6)
    assert torch.allclose(s.opacities, torch.full((15,), math.tanh(0.5)))
    assert torch.allclose(s.quats.norm(dim=-1), torch.ones(15), atol=1e-6)
    assert bool((s.scales > 0).all() and (s.scales < 0.05).all())  # exp(l[3:]) x sigmoid(.)
    assert bool((s.colors > 0).all() and (s.colors < 1).all())
    assert m.anchor_decodes()[0].children.tolist() == list(range(15))
    # the decoders see the view: another camera position gives other colours
    moved = Camera(torch.tensor([[1.0, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
                   fx=50.0, fy=50.0, cx=16.0, cy=16.0, width=32, height=32)
    assert not torch.allclose(m.splats(moved).colors, s.colors)


def test_frustum_culling_keeps_exactly_the_anchors_projecting_into_the_image():
    anchors = torch.tensor([
        [0.0, 0.0, 2.0],     # centre of the image: in
        [0.3, 0.0, 2.0],     # u = 23.5: in
        [0.7, 0.0, 2.0],     # u = 33.5: right of the image
        [0.0, -0.7, 2.0],    # v = -1.5: above it
        [0.0, 0.0, -2.0],    # behind the camera
        [0.0, 0.0, 0.1],     # in front of the near plane (0.2)
        [0.6, 0.6, 3.0],     # u = v = 26: in
        [0.66, 0.0, 2.0],    # u = 32.5: half a pixel outside
    ])
    m = _model(anchors)
    cam = _camera()
    assert m.visible_anchors(cam).tolist() == [0, 1, 6]
    _set_opacity_bias(m, [0.5] * 4)
    m.on_step(0)
    s = m.splats(cam)
    assert s.n == 3 * 4 and m.anchor_decodes()[0].anchors.tolist() == [0, 1, 6]
    # an anchor whose footprint (3 x its offset scaling at its depth: 3.75 px here) reaches into the image
    with torch.no_grad():
        m.params["scaling"][7, :3] = math.log(0.05)
    assert m.visible_anchors(cam).tolist() == [0, 1, 6, 7]


def test_children_with_non_positive_opacity_are_dropped():
    anchors = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.1, 2.0]])
    m = _model(anchors, k=4)
    _set_opacity_bias(m, [0.5, -0.5, 0.0, 0.3])  # tanh: > 0, < 0, = 0 (dropped too), > 0
    s = m.splats(_camera())
    assert s.n == 4
    assert m.anchor_decodes()[0].children.tolist() == [0, 3, 4, 7]
    assert torch.allclose(s.opacities, torch.tensor([0.5, 0.3, 0.5, 0.3]).tanh())
    assert bool((s.opacities > 0).all())
    decoded = m.anchor_decodes()[0].opacity  # [V, k] before dropping
    assert decoded.shape == (2, 4) and float(decoded[0, 1]) < 0


def _seed_for(n: int, wanted: dict[int, list[int]], levels: int) -> int:
    """A generator seed whose per-level random pick (uniform > 0.5^(level+1)) keeps the children ``wanted``."""
    for seed in range(1000):
        g = torch.Generator().manual_seed(seed)
        picks = [torch.rand(n, generator=g) > 0.5 ** (level + 1) for level in range(levels)]
        if all(bool(picks[level][idx].all()) for level, idx in wanted.items()):
            return seed
    raise AssertionError("no seed")


def test_growing_adds_anchors_only_at_unoccupied_voxels_above_the_threshold():
    anchors = torch.tensor([[0.0, 0.0, 2.0], [0.4, 0.0, 2.0], [-0.4, 0.0, 2.0]])
    m = _model(anchors, k=4, log_scale=0.0)  # offset scaling 1: child = anchor + offset
    m.voxel.fill_(0.1)
    with torch.no_grad():
        m.params["features"].copy_(torch.tensor([[1.0, -1.0], [0.0, 3.0], [2.0, 0.0]]).repeat(1, 16))
        m.params["offsets"].copy_(torch.tensor([
            [[0.41, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.52, 0.0], [0.0, 0.0, 0.3]],   # 0: occupied, new, new, low grad
            [[-0.39, 0.21, 0.0], [0.0, 0.6, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]],  # 1: child 1's voxel, unjudged
            [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        ]))
    opt = SplatOptimizer(m.param_groups(), LR)
    strat = AnchorStrategy(grad_threshold=1e-3, stat_from=0, start_iter=0, stop_iter=100, every=10, levels=1,
                           init_factor=1.0, level_factor=4.0)
    strat._ensure(m, torch.device("cpu"))
    grads = torch.zeros(12)
    grads[[0, 1, 2, 4, 5, 6]] = 2e-3   # above the threshold
    grads[3] = 5e-4                    # below it
    strat.grad_accum = grads * 10
    strat.grad_count = torch.full((12,), 10.0)
    strat.grad_count[5] = 3            # drawn in too few renders to be judged (needs > 10 x 0.8 x 0.5)
    strat.grad_accum[5] = 2e-3 * 3
    seed = _seed_for(12, {0: [1, 2, 3, 4, 5, 6, 7]}, levels=1)  # children that would grow but for the rules
    stats = strat.after_step(m, opt, 9, torch.Generator().manual_seed(seed))  # the reference's iteration 10
    # child 0 at (0.41, 0, 2): anchor 1's voxel; children 1 and 4 at (0, 0.2, 2) and (0.01, 0.21, 2): one new
    # voxel centre (0, 0.2, 2); child 2 at (0, 0.52, 2): (0, 0.5, 2); child 3: below the threshold; child 5:
    # not judged; child 6 at (0.5, 0, 2): (0.5, 0, 2); child 7: no gradient
    want = {(0.0, 0.2, 2.0), (0.0, 0.5, 2.0), (0.5, 0.0, 2.0)}
    new = {tuple(round(v, 4) for v in p.tolist()) for p in m.anchor_means()[3:]}
    assert new == want and stats["grow"] == len(want)
    assert torch.equal(m.anchor_means()[:3], anchors)
    # the new anchors: zero offsets, scaling log(voxel), the channel-wise max of their parents' features
    assert torch.equal(m.params["offsets"][3:], torch.zeros(len(want), 4, 3))
    assert torch.allclose(m.params["scaling"][3:], torch.full((len(want), 6), math.log(0.1)))
    row = next(i for i, p in enumerate(m.anchor_means().tolist()) if abs(p[0]) < 1e-6 and abs(p[1] - 0.2) < 1e-6)
    assert m.params["features"][row, :2].tolist() == [1.0, 3.0]  # max of anchor 0's (1, -1) and anchor 1's (0, 3)
    for gr in opt.optimizer.param_groups:  # the optimiser holds the grown tensors
        assert any(gr["params"][0] is p for p in m.parameters())
    # statistics: the judged children restart, the new anchors' children are appended
    assert strat.grad_count.shape == (m.n_splats * 4,) and float(strat.grad_count[5]) == 3
    assert float(strat.grad_count[:12].sum()) == 3


def test_finer_levels_need_higher_gradients():
    anchors = torch.tensor([[0.0, 0.0, 2.0]])
    m = _model(anchors, k=2, log_scale=0.0)
    m.voxel.fill_(0.1)
    with torch.no_grad():
        m.params["offsets"].copy_(torch.tensor([[[0.06, 0.0, 0.0], [0.0, 0.06, 0.0]]]))
    strat = AnchorStrategy(grad_threshold=1e-3, levels=2, init_factor=2.0, level_factor=4.0, every=10)
    # level 0: voxel 0.2, both children in the anchor's voxel; level 1: voxel 0.05, threshold 2e-3
    grads = torch.tensor([3e-3, 1.5e-3])
    seed = _seed_for(2, {0: [0, 1], 1: [0, 1]}, levels=2)
    strat.grow(m, None, grads, torch.ones(2, dtype=torch.bool), torch.Generator().manual_seed(seed))
    assert torch.allclose(m.anchor_means()[1:], torch.tensor([[0.05, 0.0, 2.0]]))


def test_rows_in_matches_a_set_lookup():
    g = torch.Generator().manual_seed(0)
    rows, table = torch.randint(0, 4, (50, 3), generator=g), torch.randint(0, 4, (30, 3), generator=g)
    known = {tuple(r) for r in table.tolist()}
    assert rows_in(rows, table).tolist() == [tuple(r) in known for r in rows.tolist()]


def test_pruning_removes_exactly_the_low_opacity_anchors_and_shrinks_the_optimiser_state():
    g = torch.Generator().manual_seed(0)
    anchors = torch.rand(6, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0])
    m = _model(anchors, k=3)
    opt = SplatOptimizer(m.param_groups(), LR)
    m.on_step(0)
    loss = sum((s**2).sum() for s in (m.splats(_camera()).colors, m.params["offsets"], m.params["features"]))
    loss.backward()
    opt.step()
    before = {name: opt.optimizer.state[m.params[name]]["exp_avg"].clone() for name in ("offsets", "features")}
    strat = AnchorStrategy(stat_from=0, start_iter=0, stop_iter=100, every=10, min_opacity=0.005)
    strat._ensure(m, torch.device("cpu"))
    strat.visits = torch.tensor([10.0, 10, 10, 10, 5, 10])            # anchor 4: judged in too few renders
    strat.opacity_accum = torch.tensor([1.0, 0.01, 0.3, 0.0, 0.0, 0.06])  # < 0.005 x 10 = 0.05: anchors 1, 3, 4
    stats = strat.after_step(m, opt, 9, torch.Generator().manual_seed(0))
    keep = torch.tensor([True, False, True, False, True, True])
    assert stats == {"grow": 0, "prune": 2, "n_splats": 4}
    assert torch.equal(m.anchor_means(), anchors[keep])
    for name in ("offsets", "features"):
        p = m.params[name]
        st = opt.optimizer.state[p]
        assert st["exp_avg"].shape == p.shape and torch.equal(st["exp_avg"], before[name][keep])
    assert all(gr["params"][0] is m.params[gr["name"]] for gr in opt.optimizer.param_groups[:3])
    assert strat.visits.tolist() == [0.0, 0.0, 5.0, 0.0] and strat.grad_count.shape == (12,)
    m.on_step(1)
    m.splats(_camera()).colors.sum().backward()
    opt.step()  # Adam runs on the pruned tensors


def _scene(tmp_path):
    root = write_blender_scene(tmp_path / "scene", n_train=6, n_test=2, size=24)
    return BlenderDataset(root=str(root), n_views=6).load()


def _fit(scene, run_dir, iterations: int, total: int = 40) -> tuple[ScaffoldGSModel, list[float]]:
    """Scaffold-GS trained ``iterations`` of a ``total``-iteration schedule (growing and pruning every 5)."""
    torch.manual_seed(0)
    pts = HullInit(n_points=300)(scene, torch.Generator().manual_seed(0))
    model = ScaffoldGSModel(pts, n_offsets=4)
    strategy = AnchorStrategy(grad_threshold=1e-5, stat_from=1, start_iter=5, stop_iter=total - 5, every=5,
                              success_threshold=0.5, extent=scene.extent)
    trainer = Trainer(iterations=iterations, log_every=1, progress=False, tensorboard=False,
                      guard={"warmup": 10**6, "collapse_psnr": 0.0})
    losses: list[float] = []
    loss = SplatLoss(lambda_mask=0.0)

    def recording(renders, views, splats, iteration=0):
        terms = loss(renders, views, splats, iteration=iteration)
        losses.append(float(terms["total"].detach()))
        return terms

    lr = {k: {**v, "max_steps": total} if "max_steps" in v else v for k, v in LR.items()}
    trainer.fit(model, scene, TorchRefRasterizer(), recording, lambda mdl: SplatOptimizer(mdl.param_groups(), lr),
                strategy, run_dir=run_dir, generator=torch.Generator().manual_seed(0))
    return model, losses


def test_a_smoke_run_reduces_the_loss_and_a_resumed_run_is_the_same(tmp_path):
    scene = _scene(tmp_path)
    full, losses = _fit(scene, tmp_path / "full", 40)
    assert sum(losses[-8:]) / 8 < 0.8 * sum(losses[:8]) / 8, losses
    n0 = ScaffoldGSModel(HullInit(n_points=300)(scene, torch.Generator().manual_seed(0)), n_offsets=4).n_splats
    assert full.n_splats != n0  # anchors were grown or pruned
    _fit(scene, tmp_path / "cut", 20)
    resumed, _ = _fit(scene, tmp_path / "cut", 40)
    assert resumed.n_splats == full.n_splats
    state, again = full.state_dict(), resumed.state_dict()
    for key in state:
        assert torch.equal(state[key], again[key]), key


def test_a_checkpoint_with_another_anchor_count_loads_and_renders_the_same():
    g = torch.Generator().manual_seed(0)
    a = ScaffoldGSModel(torch.rand(200, 3, generator=g) - 0.5 + torch.tensor([0.0, 0.0, 3.0]), n_offsets=3)
    b = ScaffoldGSModel(torch.rand(50, 3, generator=g) - 0.5, n_offsets=3)
    opt = SplatOptimizer(a.param_groups(), LR)
    a.grow_anchors(opt, torch.tensor([[0.0, 0.0, 3.0], [0.1, 0.0, 3.0]]), 0.05, torch.tensor([0, 1]),
                   torch.tensor([0, 1]))
    a.prune_anchors(opt, torch.arange(a.n_splats) % 7 == 0)
    state = a.state_dict()
    # what the trainer's identity check compares: the per-anchor first dimension only
    assert shape_mismatch(state, b.state_dict(), a.n_splats, b.n_splats) is None
    b.load_state_dict(state)
    assert b.n_splats == a.n_splats and b.anchor_voxel_size() == a.anchor_voxel_size()
    cam = _camera(f=40.0)
    sa, sb = a.splats(cam), b.splats(cam)
    assert sa.n > 0 and torch.equal(sa.means, sb.means) and torch.equal(sa.colors, sb.colors)
    assert len(SplatOptimizer(b.param_groups(), LR).optimizer.param_groups) == 6
