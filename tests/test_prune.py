"""``python -m src.prune``: significance pruning of a finished run's baked splat set."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from src.io.ply import read_ply
from src.prune import main, prune_run

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("prune") / "run"
    p = subprocess.run([sys.executable, "-m", "src.run", "+experiment=gs3d", f"hydra.run.dir={out}", "+ci=smoke"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return out


def test_unpruned_row_reproduces_the_evaluators_baked_psnr(smoke_run):
    rec = prune_run(smoke_run, [0.5, 0.25], max_loss_db=0.2, write=True)
    metrics = json.loads((smoke_run / "metrics.json").read_text())["metrics"]
    base = rec["rows"][0]
    assert base["keep"] == 1.0 and base["n_splats"] == metrics["n_splats"]
    assert base["psnr"] == pytest.approx(metrics["baked_psnr"], abs=1e-6)  # same protocol as the evaluator
    assert [r["n_splats"] for r in rec["rows"][1:]] == [round(0.5 * base["n_splats"]), round(0.25 * base["n_splats"])]
    assert rec["selected_on"] == "training views"
    assert rec["chosen"] is base or rec["chosen"]["train_loss_db"] <= 0.2
    assert json.loads((smoke_run / "pruning.json").read_text())["chosen"] == rec["chosen"]
    assert read_ply(smoke_run / "splats_pruned.ply").splats.n == rec["chosen"]["n_splats"]


def test_chosen_model_respects_the_training_view_loss_bound(smoke_run):
    rec = prune_run(smoke_run, [0.9, 0.5, 0.1], max_loss_db=0.0)
    assert rec["chosen"].get("train_loss_db", 0.0) <= 0.0
    loose = prune_run(smoke_run, [0.9, 0.5, 0.1], max_loss_db=1e9)
    assert loose["chosen"]["keep"] == 0.1  # any loss allowed: the smallest model


def test_cli_names_a_missing_run_file(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "config.yaml: missing" in capsys.readouterr().err


@pytest.mark.parametrize("text, expected", [("dataset: [unclosed\n", "unreadable run config"),
                                            ("seed: 0\n", "lacks dataset, rasterizer")])
def test_cli_names_a_malformed_run_config(tmp_path, capsys, text, expected):
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_text(text)
    (tmp_path / "splats.ply").write_bytes(b"ply\n")
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "config.yaml" in err and expected in err and len(err.strip().splitlines()) == 1
