"""Tests of the table/chart reporting (`python -m src.tables`) on synthetic sweep directories."""

from __future__ import annotations

import csv
import io
import json
import re
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from src.reporting import make_report, make_tables, paper_numbers
from src.reporting.aggregate import ReportSpec
from src.reporting.chart import Point, chart_data, chart_from_table_md, make_curves, pareto_front
from src.reporting.table_md import parse_cell, parse_tables
from src.tables import main

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO.parent / "shared" / "paper" / "splatfields_supplementary.txt"


def write_run(
    root: Path,
    subdir: str,
    *,
    method: str = "gs3d",
    n_views: int = 8,
    seed: int = 0,
    status: str = "ok",
    scene: str = "lego",
    reason: str | None = None,
    error: str | None = None,
    dataset: str = "blender",
    **metrics: float,
) -> Path:
    """Write a fake run record ``root/subdir/metrics.json`` following the metrics.json contract."""
    run_dir = root / subdir
    run_dir.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {
        "status": status,
        "error": error,
        "reason": reason,
        "experiment": method,
        "method": method,
        "choices": {"model": method, "dataset": dataset, "rasterizer": "cpu"},
        "overrides": [f"dataset.n_views={n_views}", f"seed={seed}", f"dataset.scene={scene}"],
        "keys": {"scene": scene, "n_views": n_views, "seed": seed, "iterations": 3000},
        "metrics": metrics,
        "views": [2, 17, 45],
        "env": {"git_sha": "abc", "torch": "2.13.0", "device": "cpu"},
    }
    (run_dir / "metrics.json").write_text(json.dumps(record), encoding="utf-8")
    return run_dir


def md_row(text: str, label: str) -> list[str]:
    """Cells of the first Markdown table row whose first cell is ``label``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] == label:
            return cells
    raise AssertionError(f"no row {label!r} in:\n{text}")


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    """3 methods × 2 view counts × 3 seeds; one failed seed and one all-failed cell."""
    root = tmp_path / "sweep"
    psnr = {"splatfields3d": 25.0, "gs3d": 23.0, "mip3dgs": 22.0}
    job = 0
    for method, base in psnr.items():
        for n_views in (4, 8):
            for seed in range(3):
                kwargs: dict[str, Any] = dict(method=method, n_views=n_views, seed=seed)
                if method == "mip3dgs" and n_views == 8:  # every seed of this cell fails
                    write_run(root, str(job), status="failed", error="Traceback (most recent call last):\n  boom",
                              **kwargs)  # fmt: skip
                elif method == "gs3d" and n_views == 4 and seed == 2:
                    write_run(root, str(job), status="failed", reason="divergence: non-finite loss at iter 1234",
                              **kwargs)  # fmt: skip
                else:
                    write_run(root, str(job), psnr=base + n_views / 4 + seed * 0.1, ssim=0.8 + seed * 0.01,
                              train_s=100.0 + seed, n_splats=1000, n_params=50, iter_ms=10.0 + seed,
                              **kwargs)  # fmt: skip
                job += 1
    return root


def test_mean_and_sample_std_over_seeds(tmp_path: Path) -> None:
    for seed, value in enumerate([20.0, 21.0, 23.0]):
        write_run(tmp_path, f"job{seed}", seed=seed, psnr=value, ssim=0.9)
    text = make_tables([tmp_path], {"metrics": ["psnr"]})
    expected = f"{statistics.fmean([20, 21, 23]):.2f} ± {statistics.stdev([20, 21, 23]):.2f} (n=3)"
    assert expected == "21.33 ± 1.53 (n=3)"
    assert md_row(text, "gs3d")[1] == f"**{expected.split(' ')[0]}**" + expected[5:]

    report = make_report([tmp_path], {"metrics": ["psnr"]})
    cell = report.tables[0].cells[(("gs3d",), 0)]
    assert cell.mean == pytest.approx(64 / 3)
    assert cell.std == pytest.approx(statistics.stdev([20.0, 21.0, 23.0]))
    assert cell.n == 3


def test_single_run_has_no_std(tmp_path: Path) -> None:
    write_run(tmp_path, "a", psnr=20.0)
    assert md_row(make_tables([tmp_path], {"metrics": ["psnr"]}), "gs3d")[1] == "**20.00** (n=1)"


def test_ranking_marks_first_second_third(tmp_path: Path) -> None:
    for i, (method, psnr) in enumerate([("a", 20.0), ("b", 24.0), ("c", 22.0), ("d", 23.0)]):
        write_run(tmp_path, str(i), method=method, psnr=psnr, iter_ms=psnr)
    text = make_tables([tmp_path], {"metrics": ["psnr", "iter_ms"]})
    psnr_table, ms_table = text.split("### ")[1:3]
    assert md_row(psnr_table, "b")[1].startswith("**24.00**")
    assert md_row(psnr_table, "d")[1].startswith("_23.00_")
    assert md_row(psnr_table, "c")[1].startswith("22.00³")
    assert md_row(psnr_table, "a")[1].startswith("20.00 ")
    # iter_ms: lower is better, so the order flips
    assert md_row(ms_table, "a")[1].startswith("**20.0**")
    assert md_row(ms_table, "c")[1].startswith("_22.0_")
    assert md_row(ms_table, "d")[1].startswith("23.0³")
    # the report block can flip a direction
    text = make_tables([tmp_path], {"metrics": ["psnr"], "higher_is_better": {"psnr": False}})
    assert md_row(text, "a")[1].startswith("**20.00**")


def test_failed_runs_dash_failure_rate_and_listing(sweep: Path) -> None:
    text = make_tables([sweep], {"metrics": ["psnr"]})
    header = md_row(text, "method")
    assert header == ["method", "n_views=4", "n_views=8", "failed", "seed std"]
    mip = md_row(text, "mip3dgs")
    assert mip[2] == "–"  # all seeds of (mip3dgs, 8 views) failed
    assert mip[1] == "23.10³ ± 0.10 (n=3)"  # the other cell is still aggregated (3rd best at 4 views)
    assert mip[3] == "3/6"
    gs = md_row(text, "gs3d")
    assert gs[1] == "_24.05_ ± 0.07 (n=2, 1 failed)"  # the failed seed is excluded from the mean
    assert gs[3] == "1/6"
    assert md_row(text, "splatfields3d")[3] == "0/6"
    assert "Failed / unfinished runs (4 of 18)" in text
    failed_lines = [line for line in text.splitlines() if "failed:" in line]
    assert len(failed_lines) == 4
    assert any(
        "method=gs3d, n_views=4, seed=2" in line
        and "divergence: non-finite loss at iter 1234" in line
        and str(sweep / "8") in line
        for line in failed_lines
    )
    # only the first line of a traceback is shown
    assert any("failed: Traceback (most recent call last):" in line for line in failed_lines)
    assert "boom" not in text


def test_stability_is_mean_seed_std(sweep: Path) -> None:
    report = make_report([sweep], {"metrics": ["psnr"]})
    table = report.tables[0]
    stds = [statistics.stdev([25.0 + v / 4 + s * 0.1 for s in range(3)]) for v in (4, 8)]
    assert table.stability[("splatfields3d",)] == pytest.approx(statistics.fmean(stds))
    assert table.failures[("mip3dgs",)] == (3, 6)


def test_markdown_tex_csv_render(sweep: Path) -> None:
    md = make_tables([sweep], {"metrics": ["psnr", "ssim"], "title": "View sweep"})
    assert md.count("### View sweep") == 2 and "— psnr (↑)" in md and "— ssim (↑)" in md

    tex = make_tables([sweep], {"metrics": ["psnr"], "title": "View sweep"}, fmt="tex")
    assert r"\newcommand{\first}[1]" in tex and r"\newcommand{\third}[1]" in tex
    assert r"\begin{tabular}{lcccc}" in tex and r"\toprule" in tex and r"\bottomrule" in tex
    assert r"\first{26.10}" in tex  # splatfields3d at 4 views: mean of 26.0, 26.1, 26.2
    assert r"\second{" in tex and r"\third{" in tex
    assert "mip3dgs & " in tex and " -- " in tex  # the all-failed cell
    assert "% Failed / unfinished runs:" in tex

    rows = list(csv.DictReader(io.StringIO(make_tables([sweep], {"metrics": ["psnr"]}, fmt="csv"))))
    assert len(rows) == 6
    by_key = {(r["method"], r["keys.n_views"]): r for r in rows}
    best = by_key[("splatfields3d", "4")]
    assert best["rank"] == "1" and float(best["mean"]) == pytest.approx(26.1) and best["n"] == "3"
    assert by_key[("mip3dgs", "8")]["mean"] == "" and by_key[("mip3dgs", "8")]["n_failed"] == "3"
    assert by_key[("gs3d", "4")]["rank"] == "2" and by_key[("mip3dgs", "4")]["rank"] == "3"


def test_no_cols_gives_one_column_per_metric(sweep: Path) -> None:
    text = make_tables([sweep], {"cols": [], "metrics": ["psnr", "train_s"]})
    assert md_row(text, "method") == ["method", "psnr", "train_s", "failed"]
    # train_s: lower is better; gs3d lost its slowest seed (seed 2) at 4 views, so it is fastest
    assert md_row(text, "gs3d")[2].startswith("**100.8**")


def test_directory_names_are_not_parsed(tmp_path: Path) -> None:
    write_run(tmp_path, "method=gs3d,n_views=12/seed=7", method="splatfields3d", n_views=4, seed=0, psnr=25.0)
    write_run(tmp_path, "n_views=4/gs3d", method="splatfields3d", n_views=4, seed=1, psnr=27.0)
    write_run(tmp_path, "splatfields3d/n_views=4/deep/er", method="gs3d", n_views=12, seed=0, psnr=20.0)
    text = make_tables([tmp_path], {"metrics": ["psnr"]})
    assert md_row(text, "method")[1:3] == ["n_views=4", "n_views=12"]
    assert md_row(text, "splatfields3d")[1:3] == ["**26.00** ± 1.41 (n=2)", "–"]
    assert md_row(text, "gs3d")[1:3] == ["–", "**20.00** (n=1)"]


def test_malformed_and_incomplete_records_are_reported(tmp_path: Path) -> None:
    write_run(tmp_path, "good", psnr=21.0)
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "metrics.json").write_text('{"status": "ok", "metrics": {', encoding="utf-8")
    (tmp_path / "nokeys").mkdir()
    (tmp_path / "nokeys" / "metrics.json").write_text(json.dumps({"status": "ok", "method": "x"}))
    (tmp_path / "badstatus").mkdir()
    (tmp_path / "badstatus" / "metrics.json").write_text(json.dumps({"status": "done"}))
    write_run(tmp_path, "noviews", psnr=30.0)
    data = json.loads((tmp_path / "noviews" / "metrics.json").read_text())
    del data["keys"]["n_views"]
    (tmp_path / "noviews" / "metrics.json").write_text(json.dumps(data))

    text = make_tables([tmp_path], {"metrics": ["psnr"]})
    assert md_row(text, "gs3d")[1] == "**21.00** (n=1)"  # the good run is still tabulated
    skipped = text.split("**Skipped files:**")[1]
    assert f"{tmp_path / 'broken' / 'metrics.json'}: malformed JSON" in skipped
    assert f"{tmp_path / 'nokeys' / 'metrics.json'}: status 'ok' but missing key(s) 'keys', 'metrics'" in skipped
    assert "status 'done' is not one of ok, failed, running" in skipped
    assert f"{tmp_path / 'noviews' / 'metrics.json'}: lacks 'keys.n_views'" in skipped


def test_reruns_across_sweeps_count_once(tmp_path: Path) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    write_run(first, "0", seed=0, psnr=20.0)
    write_run(first, "1", seed=1, status="failed", reason="divergence: non-finite loss at iter 10")
    write_run(second, "0", seed=1, psnr=22.0)  # the re-run of the failed job
    text = make_tables([first, second], {"metrics": ["psnr"]})
    assert md_row(text, "gs3d")[1:3] == ["**21.00** ± 1.41 (n=2)", "0/2"]
    assert "superseded" in text and "Failed / unfinished" not in text


def test_report_block_from_multirun_yaml_and_nested_runs(tmp_path: Path) -> None:
    (tmp_path / "multirun.yaml").write_text(
        "hydra:\n  sweep: {dir: '${now:%Y}'}\n"
        "report:\n  title: 'Flow ablation'\n  rows: [method, keys.flow]\n  cols: [keys.scene]\n"
        "  metrics: [ssim]\n",
        encoding="utf-8",
    )
    for i, (flow, scene, ssim) in enumerate([("dct", "dancer", 0.9), ("se3", "dancer", 0.8), ("dct", "model", 0.7)]):
        run = write_run(tmp_path / "runs" / str(i) / "nested", "job", method="splatfields4d", scene=scene, ssim=ssim)
        data = json.loads((run / "metrics.json").read_text())
        data["keys"]["flow"] = flow
        (run / "metrics.json").write_text(json.dumps(data))
    text = make_tables([tmp_path])
    assert text.startswith("### Flow ablation — ssim (↑)")
    assert md_row(text, "method") == ["method", "flow", "scene=dancer", "scene=model", "failed", "seed std"]
    assert md_row(text, "splatfields4d")[1:4] == ["dct", "**0.900** (n=1)", "**0.700** (n=1)"]


def test_report_spec_rejects_bad_types() -> None:
    with pytest.raises(ValueError, match=r"report\.rows"):
        ReportSpec.from_mapping({"rows": [1, 2]})
    with pytest.raises(ValueError, match=r"report\.higher_is_better"):
        ReportSpec.from_mapping({"higher_is_better": ["psnr"]})
    spec = ReportSpec.from_mapping({"cols": None, "quoted": True})
    assert spec.cols == () and spec.quoted == "auto" and spec.rows == ("method",)


def test_quoted_rows_for_systems_not_run(sweep: Path) -> None:
    text = make_tables([sweep], {"metrics": ["psnr", "ssim"], "quoted": "C.1"})
    psnr, ssim = text.split("### ")[1:3]
    label = "SuGaR [22] (quoted, supplementary Tab. C.1, column Toy)"
    assert md_row(psnr, label)[1:5] == ["16.96", "21.91", "", ""]  # Toy (= lego) at 4 and 8 views
    assert md_row(ssim, "SuGaR [22] (quoted, supplementary Tab. C.2, column Toy; SSIM ×100)")[1:3] == [
        "72.07",
        "82.04",
    ]
    # systems that were run (gs3d = 3DGS, splatfields3d, mip3dgs = Mip3DGS) are not quoted
    for system in ("3DGS [29]", "SplatFields3D", "Mip3DGS [91]"):
        assert f"| {system} (quoted" not in text
    assert "| 3DGS w. L_Moran (quoted" in text
    # quoted rows are never ranked
    assert "**16.96**" not in text and "_21.91_" not in text


def test_quoted_mean_column_and_paper_dash(tmp_path: Path) -> None:
    for i, scene in enumerate(["lego", "ship"]):
        write_run(tmp_path, str(i), method="splatfields3d", n_views=4, scene=scene, psnr=19.0)
    text = make_tables([tmp_path], {"metrics": ["psnr"]}, quoted="auto")
    assert md_row(text, "SparseNeRF [75] (quoted, supplementary Tab. C.1, column mean)")[1] == "–"  # "-"
    assert md_row(text, "3DGS [29] (quoted, supplementary Tab. C.1, column mean)")[1] == "17.37"
    assert "runs span several scenes" in text


def test_quoted_rows_per_scene_column(tmp_path: Path) -> None:
    write_run(tmp_path, "a", method="splatfields3d", n_views=6, scene="hotdog", psnr=26.0)
    write_run(tmp_path, "b", method="splatfields3d", n_views=6, scene="lego", psnr=22.0)
    text = make_tables([tmp_path], {"cols": ["keys.scene"], "metrics": ["psnr"]}, quoted="C.1")
    assert md_row(text, "method")[1:3] == ["scene=hotdog", "scene=lego"]
    assert md_row(text, "2DGS [25] (quoted, supplementary Tab. C.1)")[1:3] == ["23.85", "19.38"]


def test_cli_writes_table_and_chart(sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main([str(sweep), "--format", "csv", "--metrics", "psnr", "--out", str(out), "--chart"]) == 0
    printed = capsys.readouterr().out
    table = (out / "table.csv").read_text(encoding="utf-8")
    assert table.startswith("table,metric,method,keys.n_views,mean,")
    assert table in printed
    png, svg = out / "chart.png", out / "chart.svg"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 1000
    assert svg.read_text(encoding="utf-8").lstrip().startswith("<?xml")
    assert f"wrote {png}" in printed and f"wrote {svg}" in printed


def test_cli_chart_defaults_to_first_sweep_dir(sweep: Path) -> None:
    assert main([str(sweep), "--chart"]) == 0
    assert (sweep / "chart.png").stat().st_size > 0 and (sweep / "chart.svg").exists()


def test_cli_overrides_and_empty_dir(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty)]) == 2
    assert f"no metrics.json under {empty}" in capsys.readouterr().err
    assert main([str(tmp_path / "missing")]) == 2

    write_run(tmp_path / "s", "0", psnr=20.0, ssim=0.8)
    assert main([str(tmp_path / "s"), "--cols=", "--metrics", "psnr,ssim", "--rows", "keys.scene"]) == 0
    assert md_row(capsys.readouterr().out, "scene") == ["scene", "psnr", "ssim", "failed"]

    (tmp_path / "bad" / "0").mkdir(parents=True)
    (tmp_path / "bad" / "0" / "metrics.json").write_text("not json")
    assert main([str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "malformed JSON" in err and "could not be read" in err and len(err.strip().splitlines()) == 1


def test_cli_subprocess(sweep: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "src.tables", str(sweep), "--format", "md", "--quoted"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "| splatfields3d | **26.10** ± 0.10 (n=3) |" in result.stdout
    assert "(quoted, supplementary Tab. C.1, column Toy)" in result.stdout


def test_pareto_front() -> None:
    pts = [Point("a", "", x, 0, y, 0, 1) for x, y in [(1, 20), (2, 19), (3, 25), (4, 24), (5, 26)]]
    assert [(p.x, p.y) for p in pareto_front(pts)] == [(1, 20), (3, 25), (5, 26)]
    # higher x is better (e.g. FPS): the front runs from the fastest to the most accurate
    assert [(p.x, p.y) for p in pareto_front(pts, x_lower_is_better=False)] == [(5, 26)]


def test_chart_without_cost_metrics_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_run(tmp_path, "0", psnr=20.0)
    assert main([str(tmp_path), "--chart"]) == 2
    assert "nothing to chart" in capsys.readouterr().err


def _clean_label(label: str) -> str:
    return label.replace("<i>", "").replace("</i>", "").replace(r"\mathcal{L}_{Moran}", "L_Moran").strip()


def _section(text: str, ref: str) -> list[str]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"Table {ref}:"))
    end = next(i for i in range(start + 1, len(lines)) if re.match(r"Table C\.\d:|References", lines[i]))
    return lines[start:end]


# Tab. C.6 is transposed in the paper: one printed row per metric, one column per view count.
_C6_LABELS = {"psnr_train": "Train PSNR", "psnr": "Test PSNR", "delta_psnr": "Δ PSNR", "moran_rgb": "Moran RGB",
              "moran_opacity": "Moran Opacity", "moran_cov": "Moran Covariance"}  # fmt: skip


@pytest.mark.skipif(not PAPER.exists(), reason="supplementary text not available")
def test_paper_numbers_match_supplementary_text() -> None:
    """Every stored row appears verbatim in its table, under the right view-count / metric header."""
    text = PAPER.read_text(encoding="utf-8")
    for table in paper_numbers.TABLES:
        data_lines: dict[tuple[Any, str], tuple[str, ...]] = {}  # (views or block header, label) → fields
        context = None
        for line in _section(text, table.ref):
            fields = [f.strip() for f in line.rstrip().split("\t")]
            heading = re.match(r"\s*(\d+) Input Views", line)
            if heading:
                context = int(heading.group(1))
            elif "Resources" in fields:
                context = fields[3]
            elif fields[0] and len(fields) > 4:
                data_lines[(context, _clean_label(fields[0]))] = tuple(re.sub(r"</?u>", "", f) for f in fields if f)
        n_rows = 0
        for system, per_views in table.rows.items():
            for views, values in per_views.items():
                n_rows += 1
                printed = tuple("-" if v is None else f"{v:.{table.decimals}f}" for v in values)
                if table.ref == "C.6":
                    header = data_lines[(None, "#Views")]
                    row = next(v for (_, label), v in data_lines.items() if label.startswith(_C6_LABELS[table.metric]))
                    assert (row[header.index(str(views))],) == printed, (table.metric, views)
                    continue
                if table.ref == "C.4":
                    block = {"lpips": "LPIPS", "psnr": "PSNR", "ssim": "SSIM"}[table.metric]
                    key = next(k for k in data_lines if k[1] == system and str(k[0]).startswith(block))
                else:
                    key = (None if table.ref == "C.3" else views, system)
                assert data_lines[key][-len(printed) :] == printed, (table.ref, system, views)
        if table.ref in ("C.1", "C.2", "C.5"):
            assert n_rows == len(data_lines), table.ref


def test_in_memory_records_running_and_nan(tmp_path: Path) -> None:
    base = {"method": "gs3d", "keys": {"n_views": 4, "seed": 0}, "choices": {}, "overrides": []}
    records = [
        {**base, "status": "ok", "metrics": {"psnr": 20.0}},
        {**base, "status": "ok", "keys": {"n_views": 4, "seed": 1}, "metrics": {"psnr": float("nan")}},
        {**base, "status": "running", "keys": {"n_views": 4, "seed": 2}},
        {"status": "ok", "method": "gs3d"},  # invalid: no keys / metrics
    ]
    text = make_tables(records, ReportSpec(metrics=("psnr",)))
    assert md_row(text, "gs3d")[1:3] == ["**20.00** (n=1)", "0/3"]
    assert "1 ok run(s) have no finite value for metric 'psnr'" in text
    assert "n_views=4, seed=2 — running" in text
    assert "<record 3>: status 'ok' but missing key(s) 'keys', 'metrics'" in text


def test_ranks_are_per_scene_when_scene_is_a_row_key(tmp_path: Path) -> None:
    # scene B is easier: without per-scene ranking both B rows would outrank both A rows
    for i, (method, scene, psnr) in enumerate([("a", "A", 20.0), ("b", "A", 21.0), ("a", "B", 30.0),
                                                ("b", "B", 29.0)]):
        write_run(tmp_path, str(i), method=method, scene=scene, psnr=psnr)
    text = make_tables([tmp_path], {"metrics": ["psnr"], "rows": ["method", "keys.scene"]})
    cells = {(r[0], r[1]): r[2] for r in (line.strip("|").split("|") for line in text.splitlines()
                                          if line.startswith("| a |") or line.startswith("| b |"))
             for r in [[c.strip() for c in r]]}
    assert cells[("b", "A")].startswith("**21.00**") and cells[("a", "A")].startswith("_20.00_")
    assert cells[("a", "B")].startswith("**30.00**") and cells[("b", "B")].startswith("_29.00_")


def test_chart_training_time_includes_first_stage_and_capacity_search():
    from src.reporting.chart import _train_time
    from src.reporting.collect import RunRecord

    plain = RunRecord({"status": "ok", "metrics": {"train_s": 10.0}})
    full = RunRecord({"status": "ok", "metrics": {"train_s": 10.0, "stage1_train_s": 5.0, "capacity_search_s": 2.5}})
    assert _train_time(plain) == 10.0 and _train_time(full) == 17.5


def test_chart_panels_per_scene_and_failed_runs(sweep: Path) -> None:
    from src.reporting import load

    write_run(sweep, "other_scene", scene="ship", psnr=30.0, train_s=50.0)
    data = chart_data(load([sweep]).records, ReportSpec())
    assert {p.panel for p in data.points["psnr"]} == {"lego", "ship"}
    gs = next(p for p in data.points["psnr"] if p.row == "gs3d" and p.col == "n_views=4" and p.panel == "lego")
    assert gs.n == 2 and gs.x == pytest.approx(100.5) and gs.y == pytest.approx(24.05)
    assert data.failed["gs3d"] == (1, 7) and data.failed["mip3dgs"] == (3, 6)
    assert sum(1 for panel, _, _ in data.failed_x if panel == "lego") == 4


def test_chart_scene_as_row_key_is_a_panel_not_a_method(tmp_path: Path) -> None:
    from src.reporting import load

    for i, scene in enumerate(("a", "b")):
        write_run(tmp_path, str(i), scene=scene, psnr=20.0 + i, train_s=10.0)
    data = chart_data(load([tmp_path]).records, ReportSpec(rows=("method", "keys.scene")))
    assert sorted((p.panel, p.row) for p in data.points["psnr"]) == [("a", "gs3d"), ("b", "gs3d")]


def test_learning_curves_only_with_a_curve(sweep: Path, tmp_path: Path) -> None:
    from src.reporting import load

    assert make_curves(load([sweep]).records, ReportSpec(), tmp_path / "none") == []
    run = write_run(tmp_path / "c", "0", psnr=20.0, train_s=10.0)
    record = json.loads((run / "metrics.json").read_text())
    record["curve"] = [{"iteration": i * 100, "wall_s": 1.0 + i, "psnr": 15.0 + i} for i in range(5)]
    (run / "metrics.json").write_text(json.dumps(record))
    failed = write_run(tmp_path / "c", "1", seed=1, status="failed", reason="divergence")
    record = json.loads((failed / "metrics.json").read_text())
    record["curve"] = [{"iteration": 0, "wall_s": 1.0, "psnr": 14.0}, {"iteration": 100, "wall_s": 2.0,
                                                                        "psnr": float("nan")}]
    (failed / "metrics.json").write_text(json.dumps(record))
    out = tmp_path / "out"
    assert main([str(tmp_path / "c"), "--chart", "--out", str(out)]) == 0
    assert (out / "curves.png").stat().st_size > 1000 and (out / "curves.svg").exists()
    assert (out / "chart.png").exists()


def test_table_md_round_trip_and_chart_from_table(sweep: Path, tmp_path: Path) -> None:
    text = make_tables([sweep], {"metrics": ["psnr", "train_s"]})
    tables = {t.metric: t for t in parse_tables(text)}
    assert set(tables) == {"psnr", "train_s"} and tables["psnr"].higher_is_better
    assert not tables["train_s"].higher_is_better
    psnr = tables["psnr"]
    assert psnr.key_names == ("method",) and psnr.cols == ("n_views=4", "n_views=8")
    cell = psnr.cell(("splatfields3d",), "n_views=8")
    assert cell is not None and cell.mean == pytest.approx(27.1) and cell.n == 3
    assert psnr.cell(("mip3dgs",), "n_views=8") is None
    data = chart_from_table_md(text)
    assert data.failed["mip3dgs"] == (3, 6) and len(data.points["psnr"]) == 5
    assert parse_cell("_15.83_ ± 0.04 (n=2)") == parse_cell("15.83³ ± 0.04 (n=2)")
    assert parse_cell("–") is None
    with pytest.raises(ValueError, match="nothing to chart"):
        chart_from_table_md(make_tables([sweep], {"metrics": ["psnr"]}))


def test_bare_out_writes_to_the_sweeps_results_name(sweep: Path, monkeypatch: pytest.MonkeyPatch,
                                                    tmp_path: Path) -> None:  # fmt: skip
    import src.tables

    monkeypatch.setattr(src.tables, "RESULTS_ROOT", tmp_path / "results")
    assert main([str(sweep), "--out"]) == 2  # no multirun.yaml: no name
    (sweep / "multirun.yaml").write_text("hydra:\n  job:\n    config_name: blender_views\n")
    assert main([str(sweep), "--out", "--metrics", "psnr"]) == 0
    assert (tmp_path / "results" / "blender_views" / "table.md").exists()
