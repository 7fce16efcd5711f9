"""``trainer.random_background``: views re-composited exactly, and every step trained on its own colour."""

from __future__ import annotations

import pytest
import torch

from src.data.base import Scene, View
from src.losses.objective import SplatLoss
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.strategy.base import NoDensification
from src.trainer.trainer import Trainer
from tests.conftest import random_camera

WHITE = torch.ones(3)
LR = {k: {"init": 1e-3} for k in ("means", "scales", "quats", "opacities", "sh0", "shN")}


def _view(seed: int, size: int = 16, mask: bool = True) -> tuple[View, torch.Tensor, torch.Tensor]:
    """A view composited on white from a random RGB and alpha; also the RGB and alpha."""
    g = torch.Generator().manual_seed(seed)
    rgb, alpha = torch.rand(size, size, 3, generator=g), torch.rand(size, size, generator=g)
    image = rgb * alpha[..., None] + WHITE * (1 - alpha[..., None])
    cam = random_camera(size, size, seed=seed)
    return View(camera=cam, image=image, mask=alpha if mask else None, image_id=seed), rgb, alpha


def test_on_background_recomposites_exactly():
    view, rgb, alpha = _view(0)
    bg = torch.tensor([0.2, 0.5, 0.9])
    got = view.on_background(bg, WHITE)
    assert torch.allclose(got.image, rgb * alpha[..., None] + bg * (1 - alpha[..., None]), atol=1e-6)
    assert got.mask is view.mask and got.camera is view.camera
    assert torch.equal(view.on_background(WHITE, WHITE).image, view.image)
    with pytest.raises(ValueError, match="no mask"):
        _view(1, mask=False)[0].on_background(bg, WHITE)


def _fit(run_dir, random_background: bool, masks: bool = True, iterations: int = 4) -> list[torch.Tensor]:
    """Train a small 3DGS model; the background each step was given."""
    views = [_view(10 + i, mask=masks)[0] for i in range(3)]
    scene = Scene(name="tiny", train=views, val=[], test=views[:1], background=WHITE.clone(), view_ids=[0, 1, 2])
    seen: list[torch.Tensor] = []
    trainer = Trainer(iterations=iterations, log_every=1000, progress=False, tensorboard=False,
                      guard={"warmup": 10**6, "collapse_psnr": 0.0}, random_background=random_background)
    step = trainer.train_step

    def spy(model, views, *args):
        seen.append(args[-1])
        if random_background:  # every training image sits on the step's colour where its mask is empty
            for v in views:
                empty = v.mask == 0
                assert torch.allclose(v.image[empty], args[-1].expand(int(empty.sum()), 3)) or not empty.any()
        return step(model, views, *args)

    trainer.train_step = spy
    pts = (torch.rand(80, 3, generator=torch.Generator().manual_seed(3)) - 0.5) * 0.6
    model = GaussianSplatModel(pts, sh_degree=0)
    trainer.fit(model, scene, TorchRefRasterizer(), SplatLoss(), lambda m: SplatOptimizer(m.param_groups(), LR),
                NoDensification(), run_dir=run_dir, generator=torch.Generator().manual_seed(0))
    return seen


def test_each_step_trains_on_a_random_background(tmp_path):
    seen = _fit(tmp_path / "a", True)
    assert len(seen) == 4 and all(b.shape == (3,) and (b >= 0).all() and (b <= 1).all() for b in seen)
    assert len({tuple(b.tolist()) for b in seen}) == 4  # a new colour every step
    assert all(torch.equal(b, WHITE) for b in _fit(tmp_path / "b", False))  # off: the scene's background


def test_random_background_needs_masks(tmp_path):
    with pytest.raises(ValueError, match="random_background=true needs masked training views"):
        _fit(tmp_path, True, masks=False)


def test_a_non_boolean_setting_is_refused_before_the_run():
    from hydra import compose, initialize_config_module

    from src.utils.validate import ConfigValueError, validate_run_config

    with initialize_config_module("conf", version_base="1.3"):
        validate_run_config(compose("config", overrides=["trainer.random_background=true"]))
        with pytest.raises(ConfigValueError, match=r"trainer\.random_background='sometimes': expected true or false"):
            validate_run_config(compose("config", overrides=["trainer.random_background=sometimes"]))
