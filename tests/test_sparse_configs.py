"""The ``sparse`` config group: every option composes with 3DGS, Mip-Splatting and the main job and builds
its recipe; ``sparse=none`` is empty; a two-stage run's first stage never gets the ingredient; each paper's
experiment differs from ``gs3d`` only where it says."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

import src.run  # noqa: F401 - registers the ${repo:} resolver
from src.init.stage1 import first_stage_config, has_ingredient, settings_digest
from src.sparse import SparseRecipe
from src.utils.instantiate import build

CONF = Path(__file__).resolve().parents[1] / "conf"
OPTIONS = sorted(p.stem for p in (CONF / "sparse").glob("*.yaml"))
METHODS = ["+experiment=gs3d", "+experiment=mip_splatting", "+experiment=splatfields3d_mip", None]


def _compose(overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=[o for o in overrides if o])


def test_the_default_is_no_ingredient():
    cfg = _compose(["+experiment=gs3d"])
    recipe = build(cfg.sparse)
    assert isinstance(recipe, SparseRecipe) and recipe.empty
    assert set(OPTIONS) == {"none", "dropout", "dropout_few_views", "opacity_decay", "dropout_decay", "binocular",
                            "corgs"}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("option", OPTIONS)
def test_every_option_composes_with_every_method_and_builds(option, method):
    cfg = _compose([method, f"sparse={option}"])
    recipe = build(cfg.sparse)
    assert isinstance(recipe, SparseRecipe)
    assert recipe.empty == (option == "none")
    slots = {k for k, v in recipe.slots.items() if v is not None}
    assert slots == {k for k, v in cfg.sparse.items() if k != "_target_" and v is not None}


def test_a_slot_is_removed_with_null():
    cfg = _compose(["+experiment=gs3d", "sparse=dropout", "sparse.dropout=null"])
    assert build(cfg.sparse).empty


def test_the_first_stage_of_a_two_stage_run_has_only_its_own_ingredient():
    cfg = _compose(["+experiment=splatfields3d_mip", "sparse=dropout"])
    assert cfg.sparse.dropout is not None
    c1 = first_stage_config(cfg)
    assert not has_ingredient(c1.sparse) and c1.method == "mip_splatting"
    own = _compose(["+experiment=splatfields3d_mip", "sparse@stage1.sparse=dropout"])
    c1_own = first_stage_config(own)
    assert has_ingredient(c1_own.sparse) and c1_own.sparse.dropout.max_rate == 0.2
    # a cached first stage trained without the ingredient is not taken for one trained with it, nor stored with it
    assert settings_digest(own) != settings_digest(cfg)
    plain_dir, own_dir = str(cfg.paths.stage1_dir), str(own.paths.stage1_dir)
    assert own_dir == plain_dir + "_dropout" and own.init.run_dir == own_dir


@pytest.mark.parametrize("experiment,option,changed", [
    ("dropgaussian", "dropout", {"strategy.grad_threshold", "strategy.stop_iter"}),
    ("binocular3dgs", "binocular", {"strategy.reset_every", "strategy.stop_iter", "model.sh_degree"}),
    ("corgs", "corgs", {"strategy.grad_threshold", "strategy.stop_iter", "model.sh_degree_interval"}),
])
def test_each_papers_experiment_is_gs3d_with_its_ingredient(experiment, option, changed):
    exp = OmegaConf.to_container(_compose([f"+experiment={experiment}"]), resolve=False)
    ref = OmegaConf.to_container(_compose(["+experiment=gs3d", f"sparse={option}"]), resolve=False)
    assert exp["method"] == exp["experiment_name"] == experiment

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            key = f"{prefix}{k}"
            out.update(flat(v, key + ".") if isinstance(v, dict) else {key: v})
        return out

    a, b = flat(exp), flat(ref)
    diff = {k for k in a.keys() | b.keys() if a.get(k) != b.get(k)}
    assert diff - {"method", "experiment_name", "loss.method", "model.method"} == changed


@pytest.mark.parametrize("experiment", [None, "+experiment=splatfields3d_mip"])
@pytest.mark.parametrize("n_views,rate", [(3, 0.2), (4, 0.2), (6, 0.0), (8, 0.0)])
def test_the_main_job_drops_splats_at_sparse_views_only(experiment, n_views, rate):
    """DropGaussian in the main job's second stage at 4 views or fewer (chosen on validation views), rate 0 above."""
    cfg = _compose([experiment, f"dataset.n_views={n_views}"])
    recipe = build(cfg.sparse)
    assert recipe.slots["dropout"].max_rate == rate
    assert _compose([experiment, f"dataset.n_views={n_views}", "sparse=none"]).sparse.get("dropout") is None


@pytest.mark.parametrize("n_views,scale", [(3, 3), (4, 3), (6, 1), (8, 1)])
def test_the_main_jobs_first_stage_trains_longer_at_sparse_views_only(n_views, scale):
    """The main job's first stage trains 3x the scale's budget at 4 views or fewer (chosen on validation views),
    its densification window and opacity-reset interval scaled with it; its second stage and other methods keep
    theirs."""
    cfg = _compose(["+experiment=splatfields3d_mip", f"dataset.n_views={n_views}"])
    stage1 = first_stage_config(cfg)
    assert stage1.trainer.iterations == 1500 * scale
    assert (stage1.strategy.start_iter, stage1.strategy.stop_iter, stage1.strategy.reset_every) == (
        300 * scale, 2500 * scale, 1000 * scale)
    assert stage1.strategy.every == 100  # the densification interval does not scale
    assert cfg.trainer.iterations == 600 and cfg.optim.lr.network.max_steps == 1500
    assert _compose(["+experiment=mip_splatting", f"dataset.n_views={n_views}"]).trainer.iterations == 1500
    forced = first_stage_config(_compose(["+experiment=splatfields3d_mip", f"dataset.n_views={n_views}",
                                          "schedule.budget_scale=1"]))
    assert (forced.trainer.iterations, forced.strategy.stop_iter) == (1500, 2500)  # the command line wins
