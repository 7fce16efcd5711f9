"""``python -m src.bench training`` runs end to end and writes the JSON contract (no timing assertions)."""

from __future__ import annotations

import json

from src.bench.training import PARTS, main


def test_training_bench_writes_rows_per_method_and_head_width(tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = main(["--methods", "gs3d,splatfields3d", "--sizes", "400", "--iters", "1", "--warmup", "0",
                 "--width", "32", "--fps-width", "32", "--head-widths", "32", "--out", str(out)])
    assert code == 0, capsys.readouterr().out
    rows = json.loads(out.read_text())["rows"]
    assert [(r["method"], r["head_width"]) for r in rows] == [("gs3d", None), ("splatfields3d", 128),
                                                             ("splatfields3d", 32)]
    for r in rows:
        assert r["n_splats"] == 400 and set(r["ms"]) == set(PARTS)
        assert r["iter_ms"] > 0 and r["fps_baked"] > 0 and r["peak_mem_mb"] > 0
        assert r["ratio_vs_gs3d"] > 0
    assert rows[2]["n_params"] < rows[1]["n_params"]  # narrower heads, fewer parameters
    assert rows[0]["backbone_ms"] is None and rows[1]["backbone_ms"] > 0  # the tri-plane CNN alone
    assert "x 3DGS" in capsys.readouterr().out
