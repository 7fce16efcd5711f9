"""Learning curves: held-out PSNR against iteration and training time in metrics.json ``curve``."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from src.run import run
from tests.scenes import write_blender_scene

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")


def test_curve_is_recorded_every_k_iterations(tmp_path):
    root = write_blender_scene(tmp_path / "scene", n_train=8, n_test=3, size=32)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "+experiment=gs3d", f"dataset.root={root}", "+ci=smoke", "dataset.downscale=1", "trainer.iterations=12",
            "eval.curve_every=5", "eval.curve_views=2", "trainer.tensorboard=false"])
    rec = run(cfg, tmp_path / "run")
    assert rec["status"] == "ok"
    curve = rec["curve"]
    assert [p["iteration"] for p in curve] == [5, 10, 12]
    assert all(math.isfinite(p["psnr"]) for p in curve)
    walls = [p["wall_s"] for p in curve]
    assert walls == sorted(walls) and walls[-1] <= rec["metrics"]["train_s"] + 1e-6
    assert rec["curve_split"] == "test"  # this scene has no validation split
    # the last point scores the final model on 2 of the test views: within the range of the full test score
    assert abs(curve[-1]["psnr"] - rec["metrics"]["psnr"]) < 5


def test_no_curve_by_default(tmp_path):
    root = write_blender_scene(tmp_path / "scene", n_train=8, n_test=2, size=32)
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "+experiment=gs3d", f"dataset.root={root}", "+ci=smoke", "dataset.downscale=1", "trainer.iterations=3",
            "trainer.tensorboard=false"])
    assert "curve" not in run(cfg, tmp_path / "run")
