"""Every experiment composes and runs with every reader it is meant for (2 iterations, tiny fixtures).

Static experiments x {blender, dtu}; multi-view dynamic experiments x {blender_mv, owlii}; monocular
dynamic experiments x {dnerf, nerfies}. A combination that makes no sense fails with one line that says
why (a static scene for a motion model, a reader that does not take the experiment's keys).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from src.run import run
from src.utils.instantiate import ConfigError
from tests import format_writers as fw
from tests.scenes import write_blender_scene

REPO = Path(__file__).resolve().parents[1]
STATIC = ["gs3d", "gs3d_auto", "gs3d_moran", "gs3d_stage1", "sf_cnn", "sf_mlp", "sf_mlp_norm", "splatfields3d",
          "splatfields3d_2stage", "splatfields3d_mip", "mip_splatting", "gs2d", "lightgaussian", "dropgaussian",
          "binocular3dgs", "corgs"]
MULTIVIEW = ["splatfields4d", "owl_4view", "owl_6view", "owl_8view", "owl_10view", "deformable3dgs", "gaussians4d"]
MONOCULAR = ["monocular", "deformable3dgs_monocular", "gaussians4d_monocular"]
MEANT_FOR = {"static": ("blender", "dtu"), "multiview": ("blender_mv", "owlii"), "monocular": ("dnerf", "nerfies")}
CASES = ([(e, d) for e in STATIC for d in MEANT_FOR["static"]]
         + [(e, d) for e in MULTIVIEW for d in MEANT_FOR["multiview"]]
         + [(e, d) for e in MONOCULAR for d in MEANT_FOR["monocular"]])

pytestmark = pytest.mark.usefixtures("one_thread")


def test_every_experiment_is_in_the_matrix():
    shipped = sorted(p.stem for p in (REPO / "conf" / "experiment").glob("*.yaml"))
    assert sorted(STATIC + MULTIVIEW + MONOCULAR) == shipped, "a new experiment needs its readers in the matrix"


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
    return {name: base / name for name in ("blender", "dtu", "blender_mv", "owlii", "dnerf", "nerfies")}


def compose_run(experiment: str, dataset: str, root: Path, out: Path, *extra: str):
    """The config of ``python -m src.run +experiment=E dataset=D dataset.root=R +ci=smoke`` at 2 iterations."""
    overrides = [f"+experiment={experiment}", f"dataset={dataset}", f"dataset.root={root}",
                 f"paths.output_root={out}", "+ci=smoke", "trainer.iterations=2", "trainer.ckpt_every=0",
                 "dataset.downscale=1", "trainer.tensorboard=false", "eval.save_renders=false", *extra]
    if dataset == "dtu":
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
