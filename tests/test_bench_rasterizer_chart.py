"""The rasterizer benchmark's chart and its --from-json mode (no timing runs: synthetic results)."""

from __future__ import annotations

import json

import pytest

from src.bench.rasterizer import main
from src.bench.rasterizer_chart import make_rasterizer_chart


def _result() -> dict:
    rows = []
    for scene in ("cube", "object"):
        for width, n in ((100, 10_000), (200, 50_000)):
            floor = 0.1 * width / 100
            ms = {"cpu": 25 * floor, "torch_ref": 4000 * floor} if n == 10_000 else {"cpu": 40 * floor}
            rows.append({"scene": scene, "width": width, "n_splats": n, "ms": ms,
                         "ms_min": dict(ms), "speedup_vs_ref": None, "floor_ms": floor,
                         "x_floor": {k: v / floor for k, v in ms.items()}, "traffic_floor_ms": 0.05,
                         "x_bound": {k: v / floor for k, v in ms.items()}, "grad_rel_err": None,
                         "contrib_pairs": 1000, "eval_pairs_fwd": 2000, "eval_pairs_bwd": 2000})
    return {"peak_gflops": 300.0, "copy_gbps": 25.0, "rows": rows}


def test_chart_is_written_as_png(tmp_path):
    out = make_rasterizer_chart(_result(), tmp_path / "bench.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("*.tmp"))  # renamed into place


def test_chart_of_an_empty_result_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="no rows"):
        make_rasterizer_chart({"rows": []}, tmp_path / "x.png")


def test_from_json_prints_the_table_and_charts(tmp_path, capsys):
    src = tmp_path / "r.json"
    src.write_text(json.dumps(_result()))
    assert main(["--from-json", str(src), "--chart", str(tmp_path / "c.png")]) == 0
    out = capsys.readouterr().out
    assert "| cube | 100 | 10k |" in out and "traffic floor ms" in out
    assert (tmp_path / "c.png").stat().st_size > 0


def test_from_json_names_a_bad_file(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{\"no_rows\": 1}")
    with pytest.raises(SystemExit):
        main(["--from-json", str(bad)])
    assert "bad.json" in capsys.readouterr().err


def test_from_json_names_the_row_and_missing_key(tmp_path, capsys):
    bad = tmp_path / "partial.json"
    res = _result()
    del res["rows"][1]["floor_ms"]
    bad.write_text(json.dumps(res))
    with pytest.raises(SystemExit):
        main(["--from-json", str(bad)])
    err = capsys.readouterr().err
    assert "partial.json" in err and "rows[1]" in err and "floor_ms" in err
