"""``trainer.compile``: the backend it names, what it compiles, and that a compiled step equals the eager one."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

import src.run  # noqa: F401 - registers ${repo:}
from src.data.base import View
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.strategy.base import NoDensification
from src.trainer.guard import DivergenceGuard
from src.trainer.trainer import Trainer
from src.utils.instantiate import build
from src.utils.validate import ConfigValueError, compile_backend, validate_run_config
from tests.conftest import random_camera

CONF = Path(__file__).resolve().parents[1] / "conf"


def _cfg(overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def test_backend_names():
    assert compile_backend(False) is None and compile_backend(None) is None
    assert compile_backend(True) == "inductor"
    assert compile_backend("eager") == "eager"
    with pytest.raises(ValueError, match=r"trainer\.compile"):
        compile_backend("no_such_backend")


def test_an_unknown_backend_is_refused_before_the_run():
    with pytest.raises(ConfigValueError, match=r"trainer\.compile='nope'"):
        validate_run_config(_cfg(["trainer.compile=nope"]))
    validate_run_config(_cfg(["trainer.compile=eager"]))


def test_config_default_is_eager_and_builds():
    cfg = _cfg([])
    assert cfg.trainer.compile is False
    assert build(cfg.trainer).compile is None


def _steps(model, compile_to: str | None, n: int = 3) -> list[float]:
    """Train ``model`` for ``n`` steps on one random 24 px view; the losses."""
    cfg = _cfg(["+experiment=splatfields3d"])
    g = torch.Generator().manual_seed(0)
    cam = random_camera(24, 24, seed=2)
    target = torch.rand(24, 24, 3, generator=g)
    view = View(camera=cam, image=target, mask=(target[..., 0] > 0.5).float(), image_id=0)
    model.bind(SimpleNamespace(train=[view]))
    trainer = Trainer(iterations=n, compile=compile_to or False)
    assert trainer.compile_networks(model) == ([type(model.network).__name__] if compile_to else [])
    opt = build(cfg.optim)(groups=model.param_groups(), extent=2.0)
    guard = DivergenceGuard(check_grads=False, collapse_psnr=-math.inf)
    losses = []
    for it in range(n):
        out = Trainer.train_step(model, [view], TorchRefRasterizer(), build(cfg.loss), opt, NoDensification(), guard,
                                 it, g, torch.ones(3))
        losses.append(float(out["terms"]["total"].detach()))
    return losses


@pytest.mark.parametrize("backend", ["eager", "inductor"])
def test_compiled_field_network_trains_as_the_eager_one(backend):
    """The field network (fused heads, linear + ReLU layers) compiles, and its steps match eager ones."""
    cfg = _cfg(["+experiment=splatfields3d", "field_budget.triplane_up_blocks=1", "field_budget.head_width=32"])
    pts = (torch.rand(150, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1) * 0.4
    eager = build(cfg.model, init=pts, n_frames=1)
    with torch.no_grad():  # non-zero output layers, so every head shapes the loss from the first step
        for p in eager.network.parameters():
            if p.abs().sum() == 0:
                p.normal_(0, 1e-2)
    compiled = copy.deepcopy(eager)
    ref = _steps(eager, None)
    got = _steps(compiled, backend)
    assert compiled.network._compiled_call_impl is not None
    assert set(compiled.state_dict()) == set(eager.state_dict())  # checkpoints load either way
    assert got == pytest.approx(ref, rel=1e-4, abs=1e-6)  # inductor reorders float32 sums
    assert ref[-1] != ref[0]  # the steps trained
