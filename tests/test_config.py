"""Config composition: every group option instantiates; `+ci=smoke` wins when last; clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import MissingConfigException
from omegaconf import OmegaConf

import src.run  # noqa: F401 - registers the ${repo:} resolver
from src.utils.instantiate import build

CONF = Path(__file__).resolve().parents[1] / "conf"
# groups instantiated by build(); runtime-only constructor arguments are supplied per group
RUNTIME_KWARGS = {"strategy": {"extent": 1.0}}


def _compose(overrides: list[str]):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=overrides, return_hydra_config=False)


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("group", ["dataset", "init", "model", "rasterizer", "loss", "optim", "strategy",
                                   "trainer", "eval", "field", "flow"])
def test_every_option_of_every_group_instantiates(group, tmp_path):
    from tests.scenes import write_blender_scene

    root = write_blender_scene(tmp_path / "scene", n_train=6, n_test=2, size=24)
    for opt in options(group):
        # the default two-stage protocol reads init=from_run; other inits belong to the single-stage one
        cfg = _compose([f"{group}={opt}", f"dataset.root={root}", "init.run_dir=/nonexistent"]
                       if opt == "from_run" else [f"{group}={opt}", f"dataset.root={root}", "protocol=single_stage"])
        if opt == "none":  # placeholder options of methods without fields
            continue
        node = {"field": lambda c: c.model.network.backbone, "flow": lambda c: c.model.flow}.get(
            group, lambda c: c[group])(cfg)
        assert "_target_" in node, f"{group}/{opt}.yaml has no _target_"
        if group == "rasterizer" and opt == "gsplat" and not __import__("torch").cuda.is_available():
            with pytest.raises(Exception, match="CUDA"):  # Hydra wraps it in InstantiationException
                build(node)
            continue
        if group == "model":
            import torch

            obj = build(node, init=torch.rand(50, 3) * 2 - 1, n_frames=1)
        elif group == "flow" and node.get("_partial_"):
            obj = build(node)()  # partial: completed by SplatFieldsModel with n_frames
        else:
            obj = build(node, **RUNTIME_KWARGS.get(group, {}))
        assert obj is not None, f"{group}={opt} built None"


def test_experiment_files_compose():
    for exp in options("experiment"):
        cfg = _compose([f"+experiment={exp}"])
        assert cfg.experiment_name == exp, f"experiment/{exp}.yaml must set experiment_name: {exp}"


def test_smoke_wins_when_last_and_loses_when_first():
    last = _compose(["+experiment=gs3d", "+ci=smoke"])
    assert last.trainer.iterations == 20
    assert last.rasterizer._target_.endswith("TorchRefRasterizer")
    # documents the ordering rule: groups appended later win
    first = _compose(["+ci=smoke", "+experiment=gs3d", "trainer.iterations=77"])
    assert first.trainer.iterations == 77


def test_unknown_component_lists_choices():
    with pytest.raises(MissingConfigException) as e:
        _compose(["rasterizer=nope"])
    msg = str(e.value)
    assert "nope" in msg and "torch_ref" in msg


def test_contract_keys_exist():
    cfg = _compose([])
    for key in ("dataset.root", "dataset.n_views", "trainer.iterations", "seed"):
        assert OmegaConf.select(cfg, key, default="__missing__") != "__missing__", key


@pytest.mark.parametrize("extra", [[], ["+ablation=no_norm"], ["+ablation=mlp_backbone"], ["dataset.n_views=4"]])
def test_the_main_job_is_splatfields3d_mip_and_splatfields3d_2stage_the_papers_protocol(extra):
    """`python -m src.run` composes the same model, strategy, init, first stage and rasterizer as
    `+experiment=splatfields3d_mip`; `+experiment=splatfields3d_2stage` differs only by its protocol.

    The experiments extend `splatfields3d`, which selects densification for the single-stage protocol;
    the two-stage protocols keep their query points fixed, so they must not inherit it.
    """
    main = _compose(extra)
    mip = _compose(["+experiment=splatfields3d_mip", *extra])
    paper = _compose(["+experiment=splatfields3d_2stage", *extra])
    paper_protocol = _compose(["+experiment=splatfields3d_2stage", "protocol=two_stage_mip", *extra])
    for key in ("strategy", "init", "model", "stage1", "loss", "optim", "trainer", "rasterizer"):
        assert OmegaConf.to_container(mip[key]) == OmegaConf.to_container(main[key]), key
        assert OmegaConf.to_container(paper_protocol[key]) == OmegaConf.to_container(main[key]), key
    for cfg in (main, paper):
        assert cfg.strategy._target_.endswith("NoDensification")
    assert paper.stage1.model._target_.endswith(".GaussianSplatModel") and paper.model.filter_3d == 0.0
    assert main.stage1.model._target_.endswith("MipGaussianSplatModel") and main.rasterizer.antialiased


def test_two_stage_mip_protocol_differs_from_two_stage_only_where_it_says():
    """protocol=two_stage_mip: a Mip-Splatting first stage in its own cache (three times the budget at 4 views or
    fewer), the 2D Mip filter in both stages, the 3D filter on the predicted splats, and a second stage on
    several views per step, stopped before its LR schedule ends (schedule.two_stage_mip_*); everything else
    as protocol=two_stage."""
    plain = _compose(["protocol=two_stage", "dataset.n_views=4"])
    mip = _compose(["protocol=two_stage_mip", "dataset.n_views=4"])
    assert mip.stage1.model._target_.endswith("MipGaussianSplatModel")
    assert plain.stage1.model._target_.endswith(".GaussianSplatModel")
    assert mip.rasterizer.antialiased and not plain.rasterizer.antialiased
    assert mip.model.filter_3d == 0.2 and plain.model.filter_3d == 0.0
    assert mip.model.network.backbone.n_up_blocks == 2 and plain.model.network.backbone.n_up_blocks == 3  # 40 / 80 px
    paper_mip = _compose(["protocol=two_stage_mip", "scale=paper"])
    assert paper_mip.model.network.backbone.n_up_blocks == 4  # scale=paper keeps B.2's 160 px planes
    cli = _compose(["field_budget.triplane_up_blocks=3"])  # a command-line override wins
    assert cli.model.network.backbone.n_up_blocks == 3
    assert mip.init.run_dir.endswith("/mip_views4_it4500_seed0")
    assert plain.init.run_dir.endswith("/views4_it1500_seed0") and "mip_" not in plain.init.run_dir
    # the main job's second stage (scale=cpu): stopped at 600 iterations on the network LR schedule of a
    # full 1 500-iteration second stage; one view per step at 4 training views or fewer, 4 above
    assert (mip.trainer.iterations, plain.trainer.iterations) == (600, 1500)
    assert (mip.trainer.views_per_step, plain.trainer.views_per_step) == (1, 1)
    for views, per_step in ((3, 1), (4, 1), (6, 4), (8, 4), (None, 4)):
        n = "null" if views is None else views
        assert _compose(["protocol=two_stage_mip", f"dataset.n_views={n}"]).trainer.views_per_step == per_step
    assert _compose(["protocol=two_stage_mip", "dataset.n_views=6",
                     "schedule.two_stage_mip_sparse_views=6"]).trainer.views_per_step == 1
    assert _compose(["protocol=two_stage_mip", "dataset.n_views=4",
                     "schedule.two_stage_mip_views_per_step=2"]).trainer.views_per_step == 2
    assert mip.optim.lr.network.max_steps == plain.optim.lr.network.max_steps == 1500
    early = _compose(["protocol=two_stage_mip", "schedule.two_stage_mip_stop_at=900"])
    assert (early.trainer.iterations, early.optim.lr.network.max_steps) == (900, 1500)
    for key in ("strategy", "init", "optim", "trainer", "loss"):
        a, b = (OmegaConf.to_container(c[key], resolve=True) for c in (plain, mip))
        if key == "init":
            a.pop("run_dir"), b.pop("run_dir")
        if key == "trainer":
            for d in (a, b):
                d.pop("iterations"), d.pop("views_per_step")
        assert a == b, key
    # the CLI first stage keeps its own path (no stage1 node there, no prefix)
    assert _compose(["+experiment=gs3d_stage1"]).paths.stage1_dir.endswith("/views8_it1500_seed0")


@pytest.mark.parametrize("scale", ["cpu", "paper"])
def test_budget_scale_scales_every_iteration_count_of_a_schedule(scale):
    """schedule.budget_scale=N: N x the iterations, densification window, opacity-reset interval and the warm-ups
    (2DGS's losses, Deformable-3DGS and 4DGaussians); the densification interval stays."""
    one, two = (_compose([f"scale={scale}", "+experiment=gs2d", f"schedule.budget_scale={n}"]) for n in (1, 2))
    assert two.trainer.iterations == 2 * one.trainer.iterations
    for key in ("start_iter", "stop_iter", "reset_every"):
        assert two.strategy[key] == 2 * one.strategy[key], key
    assert two.strategy.every == one.strategy.every
    assert (two.loss.dist_from, two.loss.normal_from) == (2 * one.loss.dist_from, 2 * one.loss.normal_from)
    for exp, key in (("deformable3dgs", "model.warm_up"), ("gaussians4d", "model.warm_up")):
        a, b = (_compose([f"scale={scale}", f"+experiment={exp}", f"schedule.budget_scale={n}"]) for n in (1, 2))
        assert OmegaConf.select(b, key) == 2 * OmegaConf.select(a, key), exp
