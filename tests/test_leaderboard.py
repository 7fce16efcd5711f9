"""Tests of the leaderboard (``python -m src.tables DIR --leaderboard``) on synthetic run records."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from src.reporting import load
from src.reporting.collect import RunRecord
from src.reporting.leaderboard import (
    Entry,
    Leaderboard,
    build_leaderboard,
    interpolate,
    method_label,
    pareto_staircase,
    render_markdown,
    to_json,
)
from src.tables import main

REPO = Path(__file__).resolve().parents[1]
REF = "splatfields3d_mip"


def write_run(
    root: Path,
    name: str,
    *,
    experiment: str = "gs3d",
    sparse: str = "none",
    scene: str = "a",
    seed: int = 0,
    budget: int = 1,
    status: str = "ok",
    psnr: float = 20.0,
    ssim: float = 0.8,
    train_s: float = 100.0,
    stage1_s: float | None = None,
    curve: Sequence[tuple[float, float]] = ((50.0, 18.0), (100.0, 19.0)),
    split: str | None = "val",
    reason: str | None = None,
) -> Path:
    """Write ``root/name/metrics.json``: a record as ``src.run`` writes it for the fair-budget sweep."""
    metrics: dict[str, float] = {"psnr": psnr, "ssim": ssim, "train_s": train_s} if status == "ok" else {}
    if stage1_s is not None and status == "ok":
        metrics["stage1_train_s"] = stage1_s
    record: dict[str, Any] = {
        "status": status, "reason": reason, "error": None, "experiment": experiment, "method": experiment,
        "choices": {"sparse": sparse, "dataset": "blender"},
        "keys": {"scene": scene, "n_views": 4, "seed": seed, "iterations": 1500 * budget, "budget_scale": budget},
        "metrics": metrics,
    }  # fmt: skip
    if status == "ok" and curve:
        record["curve"] = [{"iteration": 250 * (i + 1), "wall_s": t, "psnr": y} for i, (t, y) in enumerate(curve)]
        record["curve_split"] = split
    run_dir = root / name
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "metrics.json").write_text(json.dumps(record), encoding="utf-8")
    return run_dir


def board_of(root: Path, reference: str = REF) -> Leaderboard:
    return build_leaderboard(load([root]).records, reference)


def entry(board: Leaderboard, method: str) -> Entry:
    return next(e for e in board.entries if e.method == method)


def method_json(board: Leaderboard, method: str) -> dict[str, Any]:
    return next(m for m in to_json(board)["methods"] if m["method"] == method)


def table_row(text: str, method: str) -> list[str]:
    """The cells of the first Markdown table row whose method cell is ``method``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and method in cells[:2]:
            return cells
    raise AssertionError(f"no row for {method} in\n{text}")


def test_budget_is_chosen_on_validation_even_when_test_prefers_the_other(tmp_path: Path) -> None:
    for scene in ("a", "b"):
        write_run(tmp_path, f"x1_{scene}", scene=scene, budget=1, psnr=25.0, curve=((50, 18.0), (100, 20.0)))
        write_run(tmp_path, f"x2_{scene}", scene=scene, budget=2, psnr=22.0, curve=((100, 18.0), (200, 21.0)))
    board = board_of(tmp_path)
    gs = entry(board, "gs3d")
    assert gs.chosen is not None and gs.chosen.label() == "×2"
    data = method_json(board, "gs3d")
    assert data["chosen_budget"]["value"] == 2
    assert data["test_psnr"]["mean"] == pytest.approx(22.0)
    assert data["val_psnr_by_budget"]["budget_scale=1"]["val_psnr"] == pytest.approx(20.0)
    assert data["val_psnr_by_budget"]["budget_scale=2"]["val_psnr"] == pytest.approx(21.0)
    row = table_row(render_markdown(board), "gs3d")
    assert row[3].startswith("×2") and row[5] == "22.00"


def test_a_choice_at_the_largest_budget_tried_is_marked(tmp_path: Path) -> None:
    """gs3d's validation PSNR still rises at its largest budget (x2): its row may sit below its converged one and
    says so; mip_splatting's peaks at x2 of x1 / x2 / x3 and is not marked."""
    for budget, val in ((1, 19.0), (2, 20.0)):
        write_run(tmp_path, f"gs_x{budget}", budget=budget, curve=((50, 18.0), (100, val)))
    for budget, val in ((1, 19.0), (2, 20.5), (3, 20.2)):
        write_run(tmp_path, f"mip_x{budget}", experiment="mip_splatting", budget=budget, curve=((50, 18.0), (100, val)))
    board = board_of(tmp_path)
    assert entry(board, "gs3d").chose_largest() and not entry(board, "mip_splatting").chose_largest()
    text = render_markdown(board)
    assert table_row(text, "gs3d")[3].startswith("×2↑") and table_row(text, "mip_splatting")[3].startswith("×2 ")
    assert method_json(board, "gs3d")["chosen_is_largest_tried"] is True
    assert method_json(board, "mip_splatting")["chosen_is_largest_tried"] is False


def test_equal_validation_scores_go_to_the_cheaper_budget(tmp_path: Path) -> None:
    write_run(tmp_path, "a_first", budget=2, psnr=24.0, curve=((100, 18.0), (200, 20.0)))
    write_run(tmp_path, "b_second", budget=1, psnr=21.0, curve=((50, 17.0), (100, 20.0)))
    gs = entry(board_of(tmp_path), "gs3d")
    assert gs.chosen is not None and gs.chosen.key == "budget_scale" and gs.chosen.value == 1
    assert gs.stat("psnr").mean == pytest.approx(21.0)


def test_budgets_are_compared_on_the_seeds_they_share(tmp_path: Path) -> None:
    """x1 ran seeds 0 and 1, x2 seed 0 only: x2 wins on seed 0 (19.5 against 19.0), and x1's lucky seed 1 (22.0)
    must not decide; over all of its seeds x1 scores 20.5, which its cell shows."""
    for scene in ("a", "b"):
        write_run(tmp_path, f"x1_s0_{scene}", scene=scene, budget=1, curve=((50, 18.0), (100, 19.0)))
        write_run(tmp_path, f"x1_s1_{scene}", scene=scene, seed=1, budget=1, curve=((50, 18.0), (100, 22.0)))
        write_run(tmp_path, f"x2_s0_{scene}", scene=scene, budget=2, curve=((100, 18.0), (200, 19.5)))
    board = board_of(tmp_path)
    gs = entry(board, "gs3d")
    assert gs.chosen is not None and gs.chosen.value == 2
    assert {b.value: sc.score for b, sc in gs.scores.items()} == {1: pytest.approx(20.5), 2: pytest.approx(19.5)}
    text = render_markdown(board)
    assert "×2 against ×1 on the runs both have (a, b; seed 0): 19.50 vs 19.00" in text
    assert "×1: 20.50 · **×2: 19.50 (seed 0)**" in text


def test_a_budget_on_fewer_seeds_does_not_change_the_others_comparison(tmp_path: Path) -> None:
    """x1 and x2 ran seeds 0 and 1 and x2 is better over both (19.7 against 19.5) though worse on seed 0; x3 ran
    seed 0 only and is worse than x2 there. Comparing all three on seed 0 alone would choose x1; the choice is x2."""
    finals = {1: (19.0, 20.0), 2: (18.8, 20.6), 3: (18.7,)}
    for budget, values in finals.items():
        for seed, val in enumerate(values):
            write_run(tmp_path, f"x{budget}_s{seed}", seed=seed, budget=budget, curve=((50, 17.0), (100, val)))
    gs = entry(board_of(tmp_path), "gs3d")
    assert gs.chosen is not None and gs.chosen.value == 2
    assert not gs.chose_largest()
    assert method_json(board_of(tmp_path), "gs3d")["val_psnr_by_budget"]["budget_scale=3"]["seeds"] == ["0"]


def test_a_budget_on_fewer_scenes_says_so(tmp_path: Path) -> None:
    for scene in ("a", "b"):
        write_run(tmp_path, f"x1_{scene}", scene=scene, budget=1, curve=((50, 17.0), (100, 19.0)))
    write_run(tmp_path, "x2_a", scene="a", budget=2, curve=((50, 17.0), (100, 19.5)))
    assert "×1: 19.00 · **×2: 19.50 (1 of 2 scenes)**" in render_markdown(board_of(tmp_path))


def test_a_run_without_a_validation_curve_cannot_be_selected(tmp_path: Path) -> None:
    write_run(tmp_path, "x1", budget=1, curve=((50, 18.0), (100, 19.0)))
    write_run(tmp_path, "x2", budget=2, psnr=30.0, curve=((100, 25.0), (200, 29.0)), split="test")
    board = board_of(tmp_path)
    gs = entry(board, "gs3d")
    assert gs.chosen is not None and gs.chosen.value == 1
    assert gs.scores[next(b for b in gs.scores if b.value == 2)].score is None
    assert "×2: 1 ok run(s) without a validation curve" in render_markdown(board)


def test_test_psnr_std_is_over_seeds_of_the_scene_mean(tmp_path: Path) -> None:
    for seed, (pa, pb) in enumerate(((20.0, 22.0), (21.0, 25.0))):
        write_run(tmp_path, f"s{seed}a", scene="a", seed=seed, psnr=pa)
        write_run(tmp_path, f"s{seed}b", scene="b", seed=seed, psnr=pb)
    stat = entry(board_of(tmp_path), "gs3d").stat("psnr")
    assert stat.mean == pytest.approx(22.0)
    assert stat.std == pytest.approx(statistics.stdev([21.0, 23.0]))  # each seed's mean over the two scenes
    assert stat.n_seeds == 2


def test_interpolate_on_a_curve() -> None:
    curve = [(100.0, 18.0), (200.0, 20.0)]
    assert interpolate(curve, 150.0) == (pytest.approx(19.0), False)
    assert interpolate(curve, 100.0) == (18.0, False)
    assert interpolate(curve, 250.0) == (20.0, True)
    assert interpolate(curve, 50.0) == (None, False)


def write_reference(root: Path) -> None:
    """The reference: 100 s second stage + 50 s first stage = 150 s total training time."""
    write_run(root, "ref", experiment=REF, train_s=100.0, stage1_s=50.0, psnr=23.0, curve=((50, 19.0), (100, 21.0)))


def test_equal_time_interpolates_at_the_reference_time(tmp_path: Path) -> None:
    write_reference(tmp_path)
    write_run(tmp_path, "gs", train_s=200.0, curve=((100, 18.0), (200, 20.0)))
    board = board_of(tmp_path)
    assert board.ref_times[4] == pytest.approx(150.0)
    at = entry(board, "gs3d").at_ref
    assert at is not None and at.value == pytest.approx(19.0) and not at.past_end
    assert table_row(render_markdown(board), "gs3d")[8] == "19.00"
    assert method_json(board, "gs3d")["equal_time_val_psnr"]["value"] == pytest.approx(19.0)


def test_equal_time_past_the_end_is_flagged(tmp_path: Path) -> None:
    write_reference(tmp_path)
    write_run(tmp_path, "gs", train_s=100.0, curve=((50, 18.0), (100, 19.5)))
    board = board_of(tmp_path)
    at = entry(board, "gs3d").at_ref
    assert at is not None and at.value == pytest.approx(19.5) and at.past_end
    assert table_row(render_markdown(board), "gs3d")[8] == "19.50†"
    ref = entry(board, REF).at_ref  # the reference at its own training time has not ended
    assert ref is not None and ref.value == pytest.approx(21.0) and not ref.past_end


def test_equal_time_adds_the_first_stage_to_the_curve(tmp_path: Path) -> None:
    write_reference(tmp_path)
    write_run(tmp_path, "two_stage", experiment="splatfields3d", train_s=100.0, stage1_s=50.0,
              curve=((50, 18.0), (150, 20.0)))  # fmt: skip
    board = board_of(tmp_path)
    at = entry(board, "splatfields3d").at_ref
    assert at is not None and at.value == pytest.approx(19.0) and not at.past_end
    assert entry(board, "splatfields3d").train_s() == pytest.approx(150.0)


def test_equal_time_before_the_first_point_is_a_dash(tmp_path: Path) -> None:
    write_reference(tmp_path)
    write_run(tmp_path, "slow", train_s=400.0, curve=((200, 18.0), (400, 20.0)))
    board = board_of(tmp_path)
    assert entry(board, "gs3d").at_ref.value is None  # type: ignore[union-attr]
    assert table_row(render_markdown(board), "gs3d")[8] == "–"


def test_within_the_reference_time_is_the_best_budget_that_fits(tmp_path: Path) -> None:
    """The reference takes 150 s. gs3d's x4 (400 s) is its board choice; of the budgets that fit, x2 (140 s) beats
    x1 (60 s) on validation although x1 has the better test PSNR, and x3 (160 s) does not fit."""
    write_reference(tmp_path)
    for budget, t, val, test in ((1, 60.0, 19.0, 22.0), (2, 140.0, 19.5, 21.0), (3, 160.0, 20.0, 21.5),
                                 (4, 400.0, 20.5, 23.0)):  # fmt: skip
        for seed in (0, 1):
            write_run(tmp_path, f"gs_x{budget}_s{seed}", budget=budget, seed=seed, train_s=t, psnr=test + 0.1 * seed,
                      curve=((t / 2, 18.0), (t, val)))  # fmt: skip
    write_run(tmp_path, "slow", experiment="mip_splatting", budget=2, train_s=300.0, curve=((150, 18.0), (300, 20.0)))
    board = board_of(tmp_path)
    gs = entry(board, "gs3d")
    assert gs.chosen is not None and gs.chosen.value == 4
    w = gs.within_ref
    assert w is not None and w.budget.value == 2 and w.time_s == pytest.approx(150.0)
    assert w.val_psnr == pytest.approx(19.5) and w.train_s == pytest.approx(140.0)
    assert w.test_psnr.mean == pytest.approx(21.05) and w.test_psnr.std == pytest.approx(0.1 / 2**0.5)
    assert table_row(render_markdown(board), "gs3d")[9] == "21.05 ± 0.07 (×2)"
    data = method_json(board, "gs3d")["within_ref_time"]
    assert data["budget"] == "×2" and data["test_psnr"]["mean"] == pytest.approx(21.05)
    assert entry(board, "mip_splatting").within_ref is None  # no budget tried fits
    assert table_row(render_markdown(board), "mip_splatting")[9] == "–"
    assert method_json(board, "mip_splatting")["within_ref_time"] is None
    ref = entry(board, REF).within_ref  # the reference fits its own time
    assert ref is not None and ref.test_psnr.mean == pytest.approx(23.0)


def test_pareto_staircase_of_hand_made_points() -> None:
    points = [(4.0, 12.0), (1.0, 10.0), (2.0, 9.0), (3.0, 11.0), (3.0, 12.0), (5.0, 13.0), (6.0, 12.5)]
    assert pareto_staircase(points) == [(1.0, 10.0), (3.0, 12.0), (5.0, 13.0)]


def test_the_best_method_at_every_budget_is_named(tmp_path: Path) -> None:
    """A fast method holds the front until a slow one passes it; a point of the slow one below the fast one's best
    does not end the fast one's stretch, and the slow one's stretch starts where it first leads."""
    write_run(tmp_path, "fast", experiment="dropgaussian", curve=((1.0, 17.0), (5.0, 19.0), (10.0, 19.2)))
    write_run(tmp_path, "slow", experiment="mip_splatting", curve=((8.0, 18.0), (50.0, 19.5), (100.0, 20.0)))
    board = board_of(tmp_path)
    front = to_json(board)["front_by_time"]["4"]
    assert [(s["method"], s["from_s"], s["to_s"], s["val_psnr"]) for s in front] == [
        ("dropgaussian (×1↑)", 1.0, 10.0, 19.2), ("mip_splatting (×1↑)", 50.0, 100.0, 20.0)]  # fmt: skip
    assert "from 1.0 s dropgaussian (×1↑) (19.20 dB at 10.0 s) · from 50.0 s mip_splatting" in render_markdown(board)


def test_a_failed_run_is_a_dash_with_its_reason(tmp_path: Path) -> None:
    write_run(tmp_path, "ok_a", scene="a", psnr=21.0)
    write_run(tmp_path, "bad_b", scene="b", status="failed", reason="diverged: loss is NaN at step 300")
    board = board_of(tmp_path)
    text = render_markdown(board)
    scene_row = [line for line in text.splitlines() if line.startswith("| gs3d | ×1")][-1]
    assert scene_row.endswith("| 21.00 | –[1] |")
    assert "- [1] gs3d, 4 views, ×1, scene=b, seed=0 — failed: diverged: loss is NaN at step 300 —" in text
    assert table_row(text, "gs3d")[-1] == "2 / 1"
    assert to_json(board)["failed_runs"][0]["reason"] == "diverged: loss is NaN at step 300"


def test_the_lead_of_the_reference(tmp_path: Path) -> None:
    write_reference(tmp_path)
    write_run(tmp_path, "gs", psnr=22.5, train_s=75.0)
    write_run(tmp_path, "gs_dropout", sparse="dropout", psnr=21.0, train_s=60.0)
    lead = to_json(board_of(tmp_path))["lead"][0]
    assert lead["other"] == "gs3d"
    assert lead["lead_db"] == pytest.approx(0.5)
    assert lead["time_ratio"] == pytest.approx(2.0)


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "src.tables", *args], cwd=REPO, capture_output=True, text=True,
                          check=False, timeout=300)  # fmt: skip


def test_cli_end_to_end(tmp_path: Path) -> None:
    sweep, out = tmp_path / "sweep", tmp_path / "out"
    write_reference(sweep)
    write_run(sweep, "gs1", budget=1, psnr=21.0)
    write_run(sweep, "gs2", budget=2, psnr=22.0, train_s=200.0, curve=((100, 18.0), (200, 19.5)))
    write_run(sweep, "gs_bad", budget=2, scene="b", status="failed", reason="out of memory")
    result = run_cli(str(sweep), "--leaderboard", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "| 1 | splatfields3d_mip | 4 |" in result.stdout
    for name in ("leaderboard.md", "leaderboard.json", "leaderboard_curves.png", "leaderboard_curves.svg"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert (out / "leaderboard_curves.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((out / "leaderboard.json").read_text(encoding="utf-8"))
    gs = next(m for m in data["methods"] if m["method"] == "gs3d")
    assert gs["chosen_budget"]["value"] == 2 and data["reference"]["method"] == REF
    assert "out of memory" in (out / "leaderboard.md").read_text(encoding="utf-8")


def test_cli_bad_reference_is_one_line(tmp_path: Path) -> None:
    write_reference(tmp_path)
    write_run(tmp_path, "gs", psnr=21.0)
    result = run_cli(str(tmp_path), "--leaderboard", "--reference", "nerf", "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: --reference nerf")
    assert "gs3d" in result.stderr and REF in result.stderr
    assert not (tmp_path / "out" / "leaderboard.md").exists()


def test_reference_without_leaderboard_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_run(tmp_path, "gs")
    assert main([str(tmp_path), "--reference", "gs3d"]) == 2
    assert capsys.readouterr().err.strip() == "error: --reference needs --leaderboard"


def test_method_label_names_the_ingredients_of_both_stages() -> None:
    def label(choices: dict[str, str]) -> str:
        return method_label(RunRecord({"experiment": "splatfields3d_mip", "choices": choices}))

    assert label({"sparse": "none"}) == "splatfields3d_mip"
    assert label({"sparse": "dropout_few_views", "sparse@stage1.sparse": "none"}) == \
        "splatfields3d_mip + dropout_few_views"
    assert label({"sparse": "dropout_few_views", "sparse@stage1.sparse": "dropout"}) == \
        "splatfields3d_mip + dropout_few_views (first stage + dropout)"
