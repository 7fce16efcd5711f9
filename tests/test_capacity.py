"""Capacity search: held-out training views only, greedy growth with a stopping rule, config edits."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from omegaconf import OmegaConf

import src.run  # noqa: F401  (registers the ${half:} resolver of conf/model/splatfields.yaml)
from src.capacity import CapacitySearch


@dataclass
class _Cam:
    frame_id: int = 0


@dataclass
class _View:
    image_id: int
    camera: _Cam = field(default_factory=_Cam)


@dataclass
class _Scene:
    train: list
    test: list
    val: list
    background: torch.Tensor = field(default_factory=lambda: torch.ones(3))


def test_split_uses_only_training_views():
    scene = _Scene(train=[_View(i) for i in range(8)], test=[_View(100 + i) for i in range(5)], val=[])
    part, val = CapacitySearch(holdout_every=4).split(scene)
    ids_train = {v.image_id for v in part.train}
    ids_val = {v.image_id for v in val.train}
    assert ids_val == {7, 3} and ids_train == set(range(8)) - {7, 3}
    assert {v.image_id for v in part.test} == ids_val  # scored on held-out TRAINING views, never test views


def test_greedy_growth_stops_when_gain_is_small(monkeypatch):
    search = CapacitySearch(budgets=[1000, 2000, 4000, 8000], widths=[32, 64, 128], min_gain_db=0.1)
    psnr_by_budget = {1000: 20.0, 2000: 21.0, 4000: 21.05, 8000: 23.0}  # 4000 gains < 0.1 dB: stop at 2000
    psnr_by_width = {32: 21.0, 64: 21.5, 128: 21.55}

    def fake_score(cfg, part, out_dir, device, fit):
        w = cfg.model.network.color_width
        return {"val_psnr": psnr_by_width[w] if "width" in str(out_dir) else psnr_by_budget[cfg.schedule.max_splats]}

    monkeypatch.setattr(search, "_score", fake_score)
    cfg = OmegaConf.create({"schedule": {"max_splats": 50_000}, "init": {"n_points": 10_000}, "seed": 0,
                            "field_budget": {"head_width": 128},
                            "model": {"network": {"backbone": {"_target_": "src.fields.backbones.NoBackbone"},
                                                  "color_width": "${field_budget.head_width}",
                                                  "scale_width": "${half:${field_budget.head_width}}"}}})
    scene = _Scene(train=[_View(i) for i in range(8)], test=[], val=[])
    new_cfg, block = search.choose(cfg, scene, __import__("pathlib").Path("/tmp/cap_test"), "cpu", None)
    assert block["chosen"] == {"max_splats": 2000, "width": 64}
    assert new_cfg.schedule.max_splats == 2000 and new_cfg.init.n_points == 2000
    assert new_cfg.model.network.color_width == 64 and new_cfg.model.network.scale_width == 32
    assert [r.get("max_splats") for r in block["trace"][:3]] == [1000, 2000, 4000]


def test_models_without_fields_search_only_the_budget(monkeypatch):
    """3DGS carries an empty ``model.network`` placeholder (field=none): no width trials are run."""
    search = CapacitySearch(budgets=[1000, 2000], widths=[32, 64], min_gain_db=0.1)
    monkeypatch.setattr(search, "_score", lambda cfg, *a: {"val_psnr": float(cfg.schedule.max_splats) / 1000})
    cfg = OmegaConf.create({"schedule": {"max_splats": 50_000}, "init": {"n_points": 10_000}, "seed": 0,
                            "model": {"network": {"backbone": {}}, "flow": {}}})
    scene = _Scene(train=[_View(i) for i in range(8)], test=[], val=[])
    new_cfg, block = search.choose(cfg, scene, __import__("pathlib").Path("/tmp/cap_test"), "cpu", None)
    assert new_cfg.schedule.max_splats == 2000
    assert block["chosen"] == {"max_splats": 2000} and len(block["trace"]) == 2


def test_triplane_resolution_is_searched_last_and_single_candidates_cost_no_trial(monkeypatch):
    calls = []

    def fake_score(cfg, part, out_dir, device, fit):
        calls.append(out_dir.name)
        blocks = cfg.model.network.backbone.n_up_blocks  # follows field_budget.triplane_up_blocks
        return {"val_psnr": {2: 20.0, 3: 20.5}[blocks]}

    cfg = OmegaConf.create({"schedule": {"max_splats": 50_000}, "init": {"n_points": 10_000}, "seed": 0,
                            "field_budget": {"head_width": 128, "triplane_up_blocks": 3},
                            "model": {"network": {"backbone": {"_target_": "x",
                                                               "n_up_blocks": "${field_budget.triplane_up_blocks}"},
                                                  "color_width": "${field_budget.head_width}"}}})
    scene = _Scene(train=[_View(i) for i in range(8)], test=[], val=[])
    search = CapacitySearch(budgets=[1000], widths=[64], plane_blocks=[2, 3])
    monkeypatch.setattr(search, "_score", fake_score)
    new_cfg, block = search.choose(cfg, scene, __import__("pathlib").Path("/tmp/cap_test"), "cpu", None)
    assert calls == ["triplane_up_blocks_2", "triplane_up_blocks_3"]  # budget and width: one candidate each
    assert block["chosen"] == {"max_splats": 1000, "width": 64, "triplane_up_blocks": 3}
    assert new_cfg.model.network.backbone.n_up_blocks == 3 and new_cfg.model.network.color_width == 64


def test_capacity_auto_runs_end_to_end_and_records_its_choice(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "src.run", "+experiment=gs3d_auto", f"hydra.run.dir={out}", "+ci=smoke"],
                       cwd=repo, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    rec = json.loads((out / "metrics.json").read_text())
    chosen = rec["capacity"]["chosen"]
    assert rec["status"] == "ok" and rec["keys"]["max_splats"] == chosen["max_splats"]
    assert "width" not in chosen  # 3DGS has no fields to size
    assert rec["metrics"]["n_splats"] <= chosen["max_splats"] and rec["metrics"]["capacity_search_s"] > 0
    holdout = set(rec["capacity"]["holdout_views"])
    assert holdout and holdout < set(rec["views"])  # held out of the TRAINING views (rec["views"])


def test_two_stage_search_trains_its_own_first_stage_on_the_search_views(monkeypatch, tmp_path):
    """The trials' 3DGS first stage must not see the held-out views (nor depend on the trial length)."""
    import src.capacity as capacity

    seen = {}

    def fake_ensure(cfg, scene, device, fit):
        seen["run_dir"], seen["iterations"] = cfg.init.run_dir, cfg.stage1.iterations
        seen["views"] = [v.image_id for v in scene.train]

    monkeypatch.setattr(capacity, "ensure_first_stage", fake_ensure)
    search = CapacitySearch(budgets=[1000], widths=[64], search_iterations=10)
    monkeypatch.setattr(search, "_score", lambda *a: {"val_psnr": 1.0})
    cfg = OmegaConf.create({"schedule": {"max_splats": 50_000}, "init": {"n_points": 10_000, "run_dir": "/main/s1"},
                            "seed": 0, "trainer": {"iterations": 1500},
                            "stage1": {"auto": True, "iterations": "${trainer.iterations}"}})
    scene = _Scene(train=[_View(i) for i in range(8)], test=[], val=[])
    new_cfg, _ = search.choose(cfg, scene, tmp_path, "cpu", None)
    assert seen == {"run_dir": str(tmp_path / "stage1"), "iterations": 1500, "views": [0, 1, 2, 4, 5, 6]}
    assert new_cfg.init.run_dir == "/main/s1"  # the main run keeps the first stage of all training views
