"""SplatFields model: config build, baking equivalence, densification without duplicates, 4D wiring."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

import src.run  # noqa: F401 - registers ${repo:}
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.utils.instantiate import build
from tests.conftest import random_camera

CONF = Path(__file__).resolve().parents[1] / "conf"
REPO = CONF.parent


def _model(overrides: list[str], n: int = 200, n_frames: int = 1, seed: int = 0):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g) * 2 - 1) * 0.5
    return build(cfg.model, init=pts, n_frames=n_frames), cfg


def test_static_model_bakes_to_the_same_image():
    model, _ = _model(["+experiment=splatfields3d", "scale=paper"])  # B.2 sizes (160x160 planes)
    cam = random_camera(32, 32, seed=1)
    rast = TorchRefRasterizer()
    with torch.no_grad():
        live = rast.render(model.splats(cam), cam, torch.ones(3)).color
        baked = rast.render(model.bake(), cam, torch.ones(3)).color
    assert torch.allclose(live, baked, atol=1e-6)
    assert 0.85e6 < model.n_params() < 1.1e6  # ~1 M parameters for the static model (B.2)


def test_gradients_reach_every_network_parameter_through_the_rasterizer():
    model, _ = _model(["+experiment=sf_mlp"], n=150)
    # make zero-initialised output layers non-zero so every upstream weight gets a gradient
    with torch.no_grad():
        for p in model.network.parameters():
            if p.abs().sum() == 0:
                p.normal_(0, 1e-2)
    cam = random_camera(24, 24, seed=3)
    out = TorchRefRasterizer().render(model.splats(cam), cam, torch.ones(3))
    (out.color.mean() + out.alpha.mean()).backward()
    missing = [n for n, p in model.network.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert not missing, missing


@pytest.mark.parametrize("mode,expect_dupes", [("jitter", False), ("exact_quirk", True)])
def test_clones_are_new_query_points_unless_quirk(mode, expect_dupes):
    model, _ = _model(["+experiment=sf_mlp", f"model.clone_mode={mode}"], n=100)
    clone = torch.zeros(100, dtype=torch.bool)
    clone[:10] = True
    model.densify(None, clone, torch.zeros(100, dtype=torch.bool), 2, torch.Generator().manual_seed(0))
    assert model.n_splats == 110
    n_unique = torch.unique(model.canonical, dim=0).shape[0]
    assert (n_unique < 110) == expect_dupes


def test_dynamic_model_is_time_dependent_and_identity_flow_at_init():
    model, _ = _model(["+experiment=splatfields4d", "model.network.rank=4"], n=100, n_frames=6)
    assert model.network.dynamic and model.n_frames == 6
    cam0 = random_camera(16, 16, seed=0)
    cam5 = random_camera(16, 16, seed=0)
    cam5.time, cam5.frame_id = 1.0, 5
    with torch.no_grad():
        a, b = model.bake(time=0.0, frame_id=0), model.bake(time=1.0, frame_id=5)
    # zero-initialised deform/flow outputs: centres start at the canonical points at every time
    assert torch.allclose(a.means, model.canonical) and torch.allclose(b.means, model.canonical)
    assert not torch.allclose(a.colors, b.colors)  # time enters every head (PE(t) + ResFields)
    assert len(model.splats_for([cam0, cam0])) == 2


@pytest.mark.slow
@pytest.mark.parametrize("exp", ["splatfields3d", "sf_mlp", "sf_mlp_norm", "sf_cnn", "gs3d_moran"])
def test_ablation_rows_run(tmp_path, exp):
    from tests.scenes import write_blender_scene

    root = write_blender_scene(tmp_path / "scene", n_train=10, n_test=2, size=48)
    out = tmp_path / exp
    p = subprocess.run([sys.executable, "-m", "src.run", f"+experiment={exp}", f"dataset.root={root}",
                        f"hydra.run.dir={out}", "+ci=smoke", "trainer.iterations=6", "init.n_points=200"],
                       cwd=REPO, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    import json

    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "ok" and rec["method"] == exp


@pytest.mark.slow
@pytest.mark.parametrize("exp", ["owl_4view", "deformable3dgs", "monocular"])
def test_dynamic_experiments_run_on_shipped_data(tmp_path, exp):
    """`+experiment=<4D preset> +ci=smoke` end to end on the shipped multi-view / monocular sequences."""
    import json

    out = tmp_path / exp
    p = subprocess.run([sys.executable, "-m", "src.run", f"+experiment={exp}", f"hydra.run.dir={out}", "+ci=smoke",
                        "trainer.iterations=4", "init.n_points=200", "threads=1"],
                       cwd=REPO, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "ok"
    assert rec["per_frame"] and len({f["time"] for f in rec["per_frame"]}) > 1
    assert rec["metrics"]["fps_baked"] > 0 and rec["metrics"]["fps_fields"] > 0


def test_3d_smoothing_filter_on_predicted_splats():
    """model.filter_3d applies Mip-Splatting's 3D filter to the field's splats (training and baked),
    and leaves them untouched when 0 or before cameras are bound."""
    from types import SimpleNamespace

    from src.models.mip_splatting import filter_variance, max_sampling_rate, smoothed_scales

    cams = [random_camera(32, 32, seed=s) for s in (1, 2)]
    scene = SimpleNamespace(train=[SimpleNamespace(camera=c) for c in cams])
    plain, _ = _model(["+experiment=splatfields3d"])
    filt, _ = _model(["+experiment=splatfields3d", "model.filter_3d=0.2"])
    filt.network.load_state_dict(plain.network.state_dict())
    with torch.no_grad():
        unbound = filt.splats(cams[0])
        ref = plain.splats(cams[0])
        assert torch.equal(unbound.scales, ref.scales) and torch.equal(unbound.opacities, ref.opacities)
        plain.bind(scene)
        assert torch.equal(plain.splats(cams[0]).scales, ref.scales)  # filter_3d = 0: no filter
        filt.bind(scene)
        got, baked = filt.splats(cams[0]), filt.bake()
        var = filter_variance(max_sampling_rate(ref.means, cams), 0.2)
        scales, factor = smoothed_scales(torch.log(ref.scales), var)
    assert bool((var > 0).all())
    assert torch.allclose(got.scales, scales, rtol=1e-5) and torch.allclose(baked.scales, scales, rtol=1e-5)
    assert torch.allclose(got.opacities, ref.opacities * factor, rtol=1e-5)
    assert bool((got.opacities < ref.opacities).all())  # a filtered splat spreads its mass
    out = filt.splats(cams[1])
    (out.opacities.sum() + out.scales.sum() + out.colors.sum() + out.means.sum() + out.quats.sum()).backward()
    assert all(p.grad is not None for p in filt.network.parameters() if p.requires_grad)
