"""Binocular3DGS's opacity decay (``sparse=opacity_decay``, ``sparse=dropout_decay``): one training step
multiplies every stored opacity by exactly 0.995, only after the start iteration, for 3DGS and
Mip-Splatting; models without stored opacities (SplatFields) are refused in one line."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from src.core.cameras import Camera
from src.core.splats import Splats
from src.data.base import View
from src.losses.objective import SplatLoss
from src.models.base import SplatModel
from src.models.gaussians import GaussianSplatModel
from src.models.mip_splatting import MipGaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.torch_ref import TorchRefRasterizer
from src.run import run
from src.sparse import DropGaussian, OpacityDecay, SparseRecipe
from src.sparse.opacity_decay import decayed_logits
from src.strategy.base import NoDensification
from src.trainer.guard import DivergenceGuard
from src.trainer.trainer import Trainer
from src.utils.instantiate import ConfigError
from tests.conftest import random_camera
from tests.scenes import write_blender_scene

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-13), (torch.float32, 2e-6)])
def test_the_decayed_logit_is_the_logit_of_the_scaled_opacity(dtype, rtol):
    o = torch.linspace(-12, 12, 2001, dtype=dtype)
    assert torch.allclose(torch.sigmoid(decayed_logits(o, 0.995)), 0.995 * torch.sigmoid(o), rtol=rtol, atol=0)
    assert torch.equal(decayed_logits(o, 1.0), torch.nn.functional.logsigmoid(o) - torch.log1p(-torch.sigmoid(o)))


def _step(model: SplatModel, recipe: SparseRecipe, it: int) -> None:
    """One training step in which the optimiser leaves the opacities alone (learning rate 0)."""
    lr = {k: {"init": 1e-3} for k, _ in model.params.items()}
    lr["opacities"] = {"init": 0.0}
    opt = SplatOptimizer(model.param_groups(), lr)
    g = torch.Generator().manual_seed(it)
    view = View(camera=random_camera(16, 16, seed=3), image=torch.rand(16, 16, 3, generator=g), mask=None,
                image_id=0)
    Trainer.train_step(model, [view], TorchRefRasterizer(), SplatLoss(lambda_mask=0.0), opt, NoDensification(),
                       DivergenceGuard(warmup=10**6, collapse_psnr=0.0), it, g, torch.ones(3), sparse=recipe)


@pytest.mark.parametrize("model_cls", [GaussianSplatModel, MipGaussianSplatModel])
def test_one_step_multiplies_every_opacity_by_exactly_the_factor(model_cls):
    pts = (torch.rand(40, 3, generator=torch.Generator().manual_seed(1)) - 0.5) * 0.6
    model = model_cls(pts, sh_degree=0, init_opacity=0.3)
    with torch.no_grad():
        model.params["opacities"].uniform_(-4, 4, generator=torch.Generator().manual_seed(2))
    recipe = SparseRecipe(opacity_decay=OpacityDecay(factor=0.995, start_iter=10))
    recipe.bind(model, None, None, 100)
    cam = random_camera(16, 16, seed=3)
    before = torch.sigmoid(model.params["opacities"].detach().clone())
    rendered_before = model.splats(cam).opacities.detach().clone()
    means_before = model.params["means"].detach().clone()
    _step(model, recipe, it=9)  # the authors' iteration 10: not after densify_from_iter = 10 yet
    assert torch.equal(torch.sigmoid(model.params["opacities"].detach()), before)
    assert not torch.equal(model.params["means"].detach(), means_before)  # the step itself did run
    _step(model, recipe, it=10)
    after = torch.sigmoid(model.params["opacities"].detach())
    assert torch.allclose(after, 0.995 * before, rtol=2e-6, atol=0)
    assert not torch.allclose(after, before, rtol=1e-4, atol=0)
    # what is rendered (Mip-Splatting: times its 3D filter's factor) shrinks by the same factor
    assert torch.allclose(model.splats(cam).opacities.detach(), 0.995 * rendered_before, rtol=1e-5, atol=0)


def test_dropout_and_decay_compose():
    pts = (torch.rand(40, 3, generator=torch.Generator().manual_seed(1)) - 0.5) * 0.6
    model = GaussianSplatModel(pts, sh_degree=0, init_opacity=0.3)
    recipe = SparseRecipe(dropout=DropGaussian(max_rate=0.3), opacity_decay=OpacityDecay(start_iter=0))
    recipe.bind(model, None, None, 10)
    before = torch.sigmoid(model.params["opacities"].detach().clone())
    _step(model, recipe, it=5)
    assert torch.allclose(torch.sigmoid(model.params["opacities"].detach()), 0.995 * before, rtol=2e-6)


class _FieldModel(SplatModel):
    """A model whose opacities come from elsewhere than a stored parameter (as SplatFields' network)."""

    method = "field"

    def splats(self, camera: Camera) -> Splats:
        return Splats.empty()

    def param_groups(self) -> list[dict]:
        return []

    @property
    def n_splats(self) -> int:
        return 0


def test_a_model_without_stored_opacities_is_refused_in_one_line():
    needle = r"sparse\.opacity_decay: .*stores none to decay.*sparse\.opacity_decay=null"
    with pytest.raises(ConfigError, match=needle) as info:
        SparseRecipe(opacity_decay=OpacityDecay()).bind(_FieldModel(), None, None, 10)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="factor"):
        OpacityDecay(factor=0.0)


def test_splatfields_with_opacity_decay_fails_before_training(tmp_path):
    scene = write_blender_scene(tmp_path / "scene", n_train=8, n_test=1, size=16)
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "+experiment=sf_mlp", f"dataset.root={scene}", f"paths.output_root={tmp_path / 'out'}",
            "sparse=dropout_decay", "+ci=smoke", "trainer.iterations=2", "trainer.tensorboard=false",
            "eval.save_renders=false", "dataset.downscale=1"])
    with pytest.raises(ConfigError, match=r"sparse\.opacity_decay: sf_mlp "):
        run(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoint.pt").exists()
