"""Every experiment composes and runs with every reader it is meant for (2 iterations, tiny fixtures).

The experiments are the files of ``conf/experiment/``: a new file joins the matrix by itself. An
experiment's readers follow from its composed config: the reader it composes with by default names its
family (static: blender, dtu, colmap; multi-view dynamic: blender_mv, owlii; monocular dynamic: dnerf, nerfies),
and a family is static exactly when the experiment's model does not model motion (``src.run.DYNAMIC_MODELS``
or ``model.network.dynamic``). A combination that makes no sense fails with one line that says why (a static
scene for a motion model, a reader that does not take the experiment's keys).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from src.run import DYNAMIC_MODELS, run
from src.utils.instantiate import ConfigError
from tests import format_writers as fw
from tests.colmap_models import write_model as write_colmap_model
from tests.scenes import write_blender_scene

REPO = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (REPO / "conf" / "experiment").glob("*.yaml"))
MEANT_FOR = {"static": ("blender", "dtu", "colmap"), "multiview": ("blender_mv", "owlii"),
             "monocular": ("dnerf", "nerfies")}
#: Experiments whose readers are not those of the family their default reader names (none today): name -> family.
FAMILY_EXCEPTIONS: dict[str, str] = {}


def describe(experiment: str) -> tuple[str, bool]:
    """The reader ``+experiment=NAME`` composes with by default, and whether its model models motion."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"+experiment={experiment}"], return_hydra_config=True)
    dynamic = (bool(OmegaConf.select(cfg, "model.network.dynamic", default=False))
               or str(OmegaConf.select(cfg, "model._target_", default="")) in DYNAMIC_MODELS)
    return str(cfg.hydra.runtime.choices["dataset"]), dynamic


def family_of(experiment: str, reader: str) -> str:
    """The family of readers ``experiment`` is meant for (its exception, else the family of ``reader``)."""
    if experiment in FAMILY_EXCEPTIONS:
        return FAMILY_EXCEPTIONS[experiment]
    families = [name for name, readers in MEANT_FOR.items() if reader in readers]
    if not families:
        raise ValueError(f"experiment {experiment!r} composes with dataset={reader}, which is in no family of "
                         f"MEANT_FOR: add the reader to a family or the experiment to FAMILY_EXCEPTIONS")
    return families[0]


DESCRIBED = {e: describe(e) for e in EXPERIMENTS}
FAMILY = {e: family_of(e, reader) for e, (reader, _) in DESCRIBED.items()}
CASES = [(e, d) for e in EXPERIMENTS for d in MEANT_FOR[FAMILY[e]]]

pytestmark = pytest.mark.usefixtures("one_thread")


def test_every_experiment_is_in_the_matrix():
    assert EXPERIMENTS, "no experiment found in conf/experiment/"
    assert sorted({e for e, _ in CASES}) == EXPERIMENTS
    # the derivation on experiments whose family is known by name
    assert FAMILY["gs3d"] == FAMILY["splatfields3d_mip"] == FAMILY["dropgaussian"] == "static"
    assert FAMILY["owl_4view"] == FAMILY["deformable3dgs"] == FAMILY["gaussians4d"] == "multiview"
    assert FAMILY["monocular"] == FAMILY["deformable3dgs_monocular"] == "monocular"


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_family_agrees_with_the_model(experiment):
    """A static family exactly for a model without motion: a dynamic model on a static reader is refused."""
    _, dynamic = DESCRIBED[experiment]
    assert (FAMILY[experiment] != "static") == dynamic, (experiment, FAMILY[experiment], dynamic)


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory) -> dict[str, Path]:
    """One tiny scene per reader (10 cameras for the multi-view ones, so owl_10view has its views)."""
    base = tmp_path_factory.mktemp("matrix")
    fw.write_blender_mv(base / "blender_mv", n_cams=10, n_test_cams=1, n_frames=2, size=16)
    fw.write_owlii(base / "owlii", n_cams=10, n_frames=2, size=(16, 12))
    fw.write_dtu(base / "dtu", n_images=30, size=(16, 12))
    fw.write_dnerf(base / "dnerf", n_train=6, n_val=1, n_test=2, size=16)
    fw.write_nerfies(base / "nerfies", n_train=6, n_val=2, size=(16, 12))
    write_blender_scene(base / "blender", n_train=8, n_test=2, size=16)
    (base / "colmap").mkdir()
    write_colmap_model(base / "colmap", "bin")  # a pycolmap-written model of photos without masks
    return {name: base / name for name in ("blender", "dtu", "colmap", "blender_mv", "owlii", "dnerf", "nerfies")}


def compose_run(experiment: str, dataset: str, root: Path, out: Path, *extra: str):
    """The config of ``python -m src.run +experiment=E dataset=D dataset.root=R +ci=smoke`` at 2 iterations."""
    overrides = [f"+experiment={experiment}", f"dataset={dataset}", f"dataset.root={root}",
                 f"paths.output_root={out}", "+ci=smoke", "trainer.iterations=2", "trainer.ckpt_every=0",
                 "dataset.downscale=1", "trainer.tensorboard=false", "eval.save_renders=false", *extra]
    if dataset in ("dtu", "colmap"):
        overrides.append("dataset.n_views=3")
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize("experiment,dataset", CASES)
def test_experiment_runs_with_its_readers(fixtures, tmp_path, experiment, dataset):
    cfg = compose_run(experiment, dataset, fixtures[dataset], tmp_path / "outputs")
    record = run(cfg, tmp_path / "run")
    assert record["status"] == "ok", record.get("error") or record.get("reason")
    assert record["experiment"] == experiment and record["metrics"]["n_splats"] > 0
    assert (tmp_path / "run" / "splats.ply").is_file()


@pytest.mark.parametrize("experiment,dataset,needle", [
    ("owl_4view", "blender", "does not take 'camera_ids'"),
    ("owl_4view", "dtu", "does not take 'camera_ids'"),
    ("splatfields4d", "blender", "models motion"),
    ("deformable3dgs", "dtu", "models motion"),
])
def test_nonsense_combination_fails_in_one_line(fixtures, tmp_path, experiment, dataset, needle):
    cfg = compose_run(experiment, dataset, fixtures[dataset], tmp_path / "outputs")
    with pytest.raises(ConfigError, match=needle) as info:
        run(cfg, tmp_path / "run")
    assert "\n" not in str(info.value)
    assert not (tmp_path / "run" / "splats.ply").exists()
