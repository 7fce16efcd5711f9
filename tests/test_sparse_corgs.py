"""CoR-GS (``sparse=corgs``): co-pruning removes exactly the splats without a partner in the other model,
pseudo cameras lie between training cameras, the co-regularisation term, the pair's packed checkpoint,
and a co-trained run that resumes to the same models (in process, and killed with SIGKILL)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from src.core.cameras import Camera, look_at
from src.data.base import Scene, View
from src.losses.objective import SplatLoss
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.sparse import CoRGS, CoTrainedPair, CoTrainingStrategy, MemberOptimizers, SparseRecipe, optimizer_for
from src.sparse.corgs import co_prune_masks, interpolate_rotation, nearest_distances, pseudo_camera
from src.strategy.default import ADCStrategy
from src.trainer.identity import shape_mismatch
from src.trainer.trainer import Trainer
from tests.test_resume import kill_after_checkpoints

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[1]
LR = {k: {"init": 1e-2} for k in ("means", "scales", "quats", "opacities", "sh0", "shN")}


def test_co_pruning_masks_mark_exactly_the_unmatched_points():
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0], [0.0, 2.0, 0.0]])
    b = torch.tensor([[0.05, 0.0, 0.0], [1.0, 0.08, 0.0], [-3.0, 0.0, 0.0], [0.0, 2.1, 0.0]])
    ma, mb = co_prune_masks(a, b, threshold=0.1)
    # a[3] and b[3] are exactly 0.1 apart: a partner "within" tau, kept (pruned only beyond it)
    assert ma.tolist() == [False, False, True, False]
    assert mb.tolist() == [False, False, True, False]
    ma, mb = co_prune_masks(a, b, threshold=0.06)
    assert ma.tolist() == [False, True, True, True] and mb.tolist() == [False, True, True, True]
    empty_a, empty_b = co_prune_masks(a, b[:0], threshold=1.0)
    assert empty_a.all() and empty_b.shape == (0,)


def test_nearest_distances_in_chunks_match_brute_force():
    g = torch.Generator().manual_seed(0)
    p, q = torch.rand(101, 3, generator=g), torch.rand(37, 3, generator=g)
    brute = torch.cdist(p, q).min(dim=1).values
    assert torch.allclose(nearest_distances(p, q, chunk=7), brute)


def _pair(points_a: torch.Tensor, points_b: torch.Tensor) -> CoTrainedPair:
    return CoTrainedPair(GaussianSplatModel(points_a, sh_degree=0), GaussianSplatModel(points_b, sh_degree=0))


def _cams(n: int = 6, radius: float = 3.0, size: int = 16) -> list[Camera]:
    """Cameras on a circle of ``radius`` around the origin at a little height, looking at it."""
    out = []
    for i in range(n):
        t = 2 * math.pi * i / n
        eye = torch.tensor([radius * math.cos(t), radius * math.sin(t), 0.8], dtype=torch.float64)
        w2c = look_at(eye, torch.zeros(3, dtype=torch.float64)).float()
        out.append(Camera(w2c, fx=20.0, fy=20.0, cx=size / 2, cy=size / 2, width=size, height=size, name=f"c{i}"))
    return out


def _scene(n: int = 4) -> Scene:
    views = []
    for i, cam in enumerate(_cams(n)):
        g = torch.Generator().manual_seed(30 + i)
        views.append(View(camera=cam, image=torch.rand(16, 16, 3, generator=g), mask=None, image_id=i))
    return Scene(name="ring", train=views, val=[], test=views[:1], background=torch.ones(3),
                 view_ids=list(range(n)), extent=2.0)


def test_co_pruning_in_a_step_removes_exactly_the_unmatched_splats():
    shared = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0]])
    a = torch.cat([shared, torch.tensor([[0.9, 0.9, 0.9], [0.31, 0.0, 0.0]])])  # a[3] unmatched, a[4] near a b
    b = torch.cat([shared + 0.01, torch.tensor([[-0.9, 0.0, 0.0]])])  # b[3] unmatched
    pair = _pair(a, b)
    opt = optimizer_for(pair, lambda groups: SplatOptimizer(groups, LR))
    assert isinstance(opt, MemberOptimizers) and len(opt.members) == 2
    ing = CoRGS(prune_every=10, prune_start=5, prune_threshold=0.05)  # tau = 0.05 x extent 2 = 0.1
    ing.bind(pair, _scene(), None, 100)
    assert ing.after_step(pair, opt, 8, None) == {}  # the authors' iteration 9: not a multiple of 10
    stats = ing.after_step(pair, opt, 9, None)
    assert stats == {"coprune": 1, "second.coprune": 1}
    keep_a = torch.cat([shared, torch.tensor([[0.31, 0.0, 0.0]])])
    assert torch.equal(pair.members[0].params["means"].detach(), keep_a)
    assert torch.equal(pair.members[1].params["means"].detach(), shared + 0.01)
    assert pair.n_splats == 7 and pair.first.n_splats == 4
    # the optimisers follow the pruned parameters
    assert all(p is g["params"][0] for o, m in zip(opt.members, pair.members, strict=True)
               for g, p in zip(o.optimizer.param_groups, m.params.values(), strict=True))
    assert not CoRGS(prune_every=10, prune_start=10).prune_due(9)  # after prune_start only (1-based)


def test_pseudo_cameras_lie_between_training_cameras():
    cams = _cams(6)
    anchor = cams[0]
    near = min(cams[1:], key=lambda c: float((c.center - anchor.center).norm()))
    full_angle = _angle(anchor.world_to_cam[:3, :3], near.world_to_cam[:3, :3])
    for s in (0.0, 0.25, 0.5, 0.9, 1.0):
        p = pseudo_camera(anchor, cams, s)
        c = p.center.double()
        a, b = anchor.center.double(), near.center.double()
        assert torch.allclose(c, (1 - s) * a + s * b, atol=1e-5)  # on the segment, a fraction s along it
        assert float((c - a).norm() + (b - c).norm()) == pytest.approx(float((b - a).norm()), abs=1e-5)
        r = p.world_to_cam[:3, :3]
        assert torch.allclose(r @ r.T, torch.eye(3), atol=1e-5) and float(torch.linalg.det(r)) > 0
        assert _angle(anchor.world_to_cam[:3, :3], r) == pytest.approx(s * full_angle, abs=1e-4)
        assert (p.fx, p.width, p.time, p.frame_id) == (anchor.fx, anchor.width, anchor.time, anchor.frame_id)
        _, z = p.project(torch.zeros(1, 3))
        assert float(z) > 0  # still facing the scene
    assert pseudo_camera(anchor, [anchor], 0.5) is anchor


def _angle(ra: torch.Tensor, rb: torch.Tensor) -> float:
    """The rotation angle between ``ra`` and ``rb`` (atan2 of the skew and the trace: exact near 0)."""
    rel = (ra.T @ rb).double()
    skew = torch.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    return math.atan2(float(skew.norm()) / 2, (float(rel.trace()) - 1) / 2)


def test_interpolated_rotations_are_geodesic():
    ra = torch.eye(3)
    rb = interpolate_rotation(ra, torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), 1.0)
    half = interpolate_rotation(ra, rb, 0.5)
    c = math.cos(math.pi / 4)
    assert torch.allclose(half, torch.tensor([[c, -c, 0.0], [c, c, 0.0], [0.0, 0.0, 1.0]]), atol=1e-6)


def test_co_regularisation_pulls_each_model_towards_the_other():
    g = torch.Generator().manual_seed(4)
    pts = (torch.rand(60, 3, generator=g) - 0.5) * 0.8
    pair = _pair(pts, pts.clone())
    scene, rast, bg = _scene(), TorchRefRasterizer(), torch.ones(3)
    ing = CoRGS(coreg_start=0.0)
    ing.bind(pair, scene, rast, 10)
    views = scene.train[:1] * 2  # the step's view, once per member
    same = ing.loss_terms(pair, views, [], rast, bg, 0, torch.Generator().manual_seed(0))["coreg"]
    assert float(same.detach()) == pytest.approx(0.0, abs=1e-6)  # identical models agree everywhere
    with torch.no_grad():
        pair.members[1].params["sh0"].add_(0.3)
    term = ing.loss_terms(pair, views, [], rast, bg, 0, torch.Generator().manual_seed(0))["coreg"]
    assert float(term.detach()) > 0.01
    term.backward()
    assert all(m.params["sh0"].grad is not None and m.params["sh0"].grad.abs().sum() > 0 for m in pair.members)
    late = CoRGS(coreg_start=0.5)
    late.bind(pair, scene, rast, 10)
    assert late.loss_terms(pair, views, [], rast, bg, 4, torch.Generator()) == {}


def test_the_pair_checkpoint_is_packed_and_loads_into_a_fresh_pair():
    g = torch.Generator().manual_seed(5)
    pair = _pair(torch.rand(30, 3, generator=g), torch.rand(17, 3, generator=g))
    state = pair.state_dict()
    assert state["params.means"].shape == (47, 3) and state["pair.counts"].tolist() == [30, 17]
    fresh = _pair(torch.rand(10, 3, generator=g), torch.rand(10, 3, generator=g))
    # what the trainer's identity check compares: a per-splat size change only
    assert shape_mismatch(state, fresh.state_dict(), pair.n_splats, fresh.n_splats) is None
    fresh.load_state_dict(state)
    for a, b in zip(pair.members, fresh.members, strict=True):
        assert a.n_splats == b.n_splats
        assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    with pytest.raises(RuntimeError, match="co-trained pair"):
        fresh.load_state_dict(pair.members[0].state_dict())


def _fit(run_dir, iterations: int) -> CoTrainedPair:
    """A co-trained 3DGS pair with densification, co-pruning and co-regularisation (6 its in all)."""
    scene = _scene()
    pts = (torch.rand(80, 3, generator=torch.Generator().manual_seed(3)) - 0.5) * 0.6

    def strategy():
        return ADCStrategy(grad_threshold=1e-9, start_iter=1, stop_iter=6, every=2, reset_every=0, extent=2.0)

    recipe = SparseRecipe(corgs=CoRGS(prune_every=3, prune_start=1, prune_threshold=0.005, coreg_start=0.0))
    model, strat = recipe.prepare(GaussianSplatModel(pts, sh_degree=0), strategy(),
                                  lambda: GaussianSplatModel(pts, sh_degree=0), strategy)
    assert isinstance(model, CoTrainedPair) and isinstance(strat, CoTrainingStrategy)
    trainer = Trainer(iterations=iterations, log_every=1000, progress=False, tensorboard=False,
                      guard={"warmup": 10**6, "collapse_psnr": 0.0})
    trainer.fit(model, scene, TorchRefRasterizer(), SplatLoss(lambda_mask=0.0),
                lambda m: optimizer_for(m, lambda groups: SplatOptimizer(groups, LR)), strat, run_dir=run_dir,
                generator=torch.Generator().manual_seed(0), sparse=recipe)
    return model


def test_co_training_diverges_the_models_and_a_resumed_run_is_the_same(tmp_path):
    full = _fit(tmp_path / "full", 6)
    a, b = full.members
    assert a.n_splats != 80 and b.n_splats != 80  # densified (and co-pruned)
    assert a.n_splats != b.n_splats or not torch.equal(a.params["means"], b.params["means"])
    _fit(tmp_path / "cut", 3)
    resumed = _fit(tmp_path / "cut", 6)
    for m, r in zip(full.members, resumed.members, strict=True):
        assert m.n_splats == r.n_splats
        for k in m.params:
            assert torch.equal(m.params[k], r.params[k]), k


@pytest.mark.slow
def test_a_sigkilled_co_trained_run_resumes_to_identical_metrics(tmp_path):
    from tests.scenes import write_blender_scene

    scene = write_blender_scene(tmp_path / "scene", n_train=10, n_test=2, size=32)

    def command(run_dir: Path) -> list[str]:
        return [sys.executable, "-m", "src.run", "+experiment=corgs", f"dataset.root={scene}",
                f"hydra.run.dir={run_dir}", "threads=1", "eval.save_renders=false", "eval.fps_repeats=0",
                "+ci=smoke", "trainer.iterations=30", "trainer.ckpt_every=10"]

    full, killed = tmp_path / "full", tmp_path / "killed"
    p = subprocess.run(command(full), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    kill_after_checkpoints(command(killed), killed / "checkpoint.pt", n=1)
    ck = torch.load(killed / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert ck["iteration"] < 29 and ck["model"]["pair.counts"].shape == (2,)  # killed mid-training
    p = subprocess.run(command(killed), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "resumed from" in p.stdout + p.stderr
    ra, rb = (json.loads((d / "metrics.json").read_text()) for d in (full, killed))
    assert ra["status"] == rb["status"] == "ok"
    for key in ("psnr", "ssim", "n_splats", "psnr_train"):
        assert ra["metrics"][key] == pytest.approx(rb["metrics"][key], abs=1e-9), key
