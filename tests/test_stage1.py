"""The two-stage Blender protocol in one command: the in-process 3DGS first stage (src/init/stage1.py)."""

from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

import src.run  # noqa: F401 - registers the ${repo:} and ${half:} resolvers
from src.init.stage1 import check_first_stage
from src.io.ply import read_ply
from tests.test_run import run_cli


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory):
    from tests.scenes import write_blender_scene

    return write_blender_scene(tmp_path_factory.mktemp("s1") / "scene", n_train=10, n_test=2, size=48)


def test_auto_first_stage_equals_the_cli_first_stage_and_is_reused(tmp_path, scene_root):
    common = [f"dataset.root={scene_root}", "dataset.n_views=4", "+ci=smoke"]
    # stage 1 from the command line (+experiment=gs3d_stage1) into its own output root
    cli_root = tmp_path / "cli"
    p = run_cli("+experiment=gs3d_stage1", f"paths.output_root={cli_root}", *common)
    assert p.returncode == 0, p.stderr[-3000:]
    (cli_dir,) = (cli_root / "stage1" / "scene").iterdir()
    assert cli_dir.name == "views4_it20_seed0"
    # the same stage trained in-process by the SplatFields run, then re-used by a second run
    auto_root = tmp_path / "auto"
    recs = []
    for name in ("sf_a", "sf_b"):
        p = run_cli("+experiment=splatfields3d_2stage", f"paths.output_root={auto_root}",
                    f"hydra.run.dir={tmp_path / name}", *common)
        assert p.returncode == 0, p.stderr[-3000:]
        recs.append(json.loads((tmp_path / name / "metrics.json").read_text()))
    auto_dir = auto_root / "stage1" / "scene" / "views4_it20_seed0"
    assert [r["stage1"]["trained_now"] for r in recs] == [True, False]
    assert recs[0]["stage1"]["dir"] == str(auto_dir)
    assert not (auto_root / "stage1" / "scene" / "views4_it20_seed0.partial").exists()
    a, b = read_ply(cli_dir / "splats.ply").splats, read_ply(auto_dir / "splats.ply").splats
    assert a.means.shape == b.means.shape and (a.means == b.means).all() and (a.colors == b.colors).all()
    # the second-stage result does not depend on whether stage 1 was trained in this process
    assert recs[0]["metrics"]["psnr"] == recs[1]["metrics"]["psnr"]
    assert recs[0]["metrics"]["stage1_train_s"] > 0
    # a first stage trained for other settings is refused, naming the directory and the key
    with pytest.raises(ValueError, match=r"views4_it20_seed0.*n_views: 4 != 6"):
        check_first_stage(auto_dir, {"scene": "scene", "n_views": 6, "seed": 0, "iterations": 20, "n_points": 300})
    # ... and so is one of another first-stage model
    stored = json.loads((auto_dir / "metrics.json").read_text())["stage1_keys"]
    assert stored["model"].endswith("GaussianSplatModel")
    with pytest.raises(ValueError, match=r"model: .*GaussianSplatModel != .*MipGaussianSplatModel"):
        check_first_stage(auto_dir, {**stored, "model": "src.models.mip_splatting.MipGaussianSplatModel"})
    # ... and so is one trained on renders of the scene at another resolution
    with pytest.raises(ValueError, match=r"image_size: \[\d+, \d+\] != \[200, 200\]"):
        check_first_stage(auto_dir, {**stored, "image_size": [200, 200]})
    # ... also when the command line wrote it (+experiment=gs3d_stage1): every run records its image size
    assert json.loads((cli_dir / "metrics.json").read_text())["image_size"] == stored["image_size"]
    assert check_first_stage(cli_dir, stored) is not None
    with pytest.raises(ValueError, match=r"image_size: \[\d+, \d+\] != \[200, 200\]"):
        check_first_stage(cli_dir, {**stored, "image_size": [200, 200]})


def test_first_stage_nodes_may_refer_to_the_run():
    """Interpolations inside ``stage1.trainer`` resolve against the run's config (the node is removed)."""
    from hydra import compose, initialize_config_module

    from src.init.stage1 import first_stage_config

    with initialize_config_module("conf", version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=splatfields3d_mip",
                                           "+stage1.trainer.ckpt_every=${stage1.iterations}"])
    c1 = first_stage_config(cfg)
    assert c1.trainer.ckpt_every == cfg.stage1.iterations and c1.trainer.views_per_step == 1


def test_first_stage_settings_enter_the_cache_key(tmp_path):
    """Another first-stage trainer, loss, optimiser or density control is another cache; second-stage
    settings (its iterations, views per step) are not."""
    from hydra import compose, initialize_config_module

    from src.init.stage1 import settings_digest

    with initialize_config_module("conf", version_base="1.3"):
        def digest(*extra):
            return settings_digest(compose("config", overrides=["+experiment=splatfields3d_mip", *extra]))

        base = digest()
        assert digest("schedule.two_stage_mip_stop_at=1500", "schedule.two_stage_mip_views_per_step=1",
                      "schedule.stage2_iterations=500", "seed=1") == base
        changed = [digest("+stage1.trainer.random_background=true"), digest("+stage1.loss.lambda_dssim=0.5"),
                   digest("strategy@stage1.strategy=none"), digest("stage1.optim.lr.opacities.init=0.1")]
        assert base not in changed and len(set(changed)) == len(changed)
    stored = {"scene": "s", "n_views": 4, "seed": 0, "iterations": 20, "n_points": 300, "settings": base}
    (tmp_path / "splats.ply").write_text("")
    (tmp_path / "metrics.json").write_text(json.dumps({"stage1_keys": stored}))
    assert check_first_stage(tmp_path, stored) is not None
    with pytest.raises(ValueError, match=f"settings: {base} != {changed[0]}"):
        check_first_stage(tmp_path, {**stored, "settings": changed[0]})


def test_first_stage_off_names_the_command(tmp_path, scene_root):
    p = run_cli("+experiment=splatfields3d_2stage", "stage1.auto=false", f"paths.output_root={tmp_path}",
                f"dataset.root={scene_root}", f"hydra.run.dir={tmp_path / 'sf'}", "+ci=smoke")
    assert p.returncode != 0
    rec = json.loads((tmp_path / "sf" / "metrics.json").read_text())
    assert rec["status"] == "failed" and "gs3d_stage1" in rec["error"]


def test_first_stage_config_mirrors_the_gs3d_experiment():
    from hydra import compose, initialize_config_module

    from src.init.stage1 import first_stage_config

    with initialize_config_module("conf", version_base="1.3"):
        gs = compose("config", overrides=["+experiment=gs3d_stage1"])
        # a second-stage-only setting leaves the first stage (and so its cache) as it is
        for extra in ([], ["trainer.random_background=true"], ["trainer.views_per_step=4"],
                      ["loss.lambda_moran=0.5", "loss.lambda_norm=0.2"],
                      ["trainer.views_per_step=4", "~stage1.trainer", "~stage1.loss"]):
            c1 = first_stage_config(compose("config", overrides=["+experiment=splatfields3d_2stage", *extra]))
            for key in ("model", "optim", "strategy", "init", "loss", "method", "trainer"):
                mine, theirs = (OmegaConf.to_container(OmegaConf.select(c, key), resolve=True) if key != "method"
                                else c[key] for c in (c1, gs))
                if key == "model":  # field=none / flow=none leave empty placeholders that the gs3d model ignores
                    assert theirs.pop("flow") == {} and theirs.pop("network") == {"backbone": {}}
                assert mine == theirs, (key, extra)


@pytest.mark.parametrize("choice", ["sfm", "box"])
def test_an_initialiser_for_the_second_stage_is_refused_naming_the_first_stages(choice):
    from hydra import compose, initialize_config_module

    from src.init.stage1 import check_second_stage_init
    from src.utils.validate import ConfigValueError

    with initialize_config_module("conf", version_base="1.3"):
        chosen = compose("config", overrides=["+experiment=splatfields3d_mip", f"init={choice}"])
        first = compose("config", overrides=["+experiment=splatfields3d_mip", f"init@stage1.init={choice}"])
        single = compose("config", overrides=["+experiment=gs3d", f"init={choice}"])
    with pytest.raises(ConfigValueError, match=rf"init={choice}: .*two-stage.*init@stage1.init={choice}$"):
        check_second_stage_init(chosen, choice)
    check_second_stage_init(first, "from_run")   # the first stage's own initialiser: fine
    check_second_stage_init(single, choice)      # one stage: the run's initialiser
