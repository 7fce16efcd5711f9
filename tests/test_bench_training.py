"""``python -m src.bench training`` runs end to end and writes the JSON contract (no timing assertions)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from src.bench.training import DEFAULT_OUT, PARTS, SPLIT, faster_row, main, output_path


def _tiny_bench(tmp_path, capsys, n_splats: int, *variant: str) -> list[dict]:
    """The rows of a one-step bench of gs3d and splatfields3d at 32 px with a variant option."""
    out = tmp_path / "bench.json"
    code = main(["--methods", "gs3d,splatfields3d", "--sizes", str(n_splats), "--iters", "1", "--warmup", "0",
                 "--width", "32", "--fps-width", "32", *variant, "--out", str(out)])
    assert code == 0, capsys.readouterr().out
    assert (tmp_path / "bench.png").stat().st_size > 0  # the split chart beside the JSON
    return json.loads(out.read_text())["rows"]


def test_training_chart_redraws_an_earlier_result_and_names_a_bad_file(tmp_path, capsys):
    split = dict(generator_fwd=10.0, heads_fwd=20.0, rasterizer=5.0, heads_bwd=40.0, generator_bwd=20.0, optimizer=2.0)
    common = dict(n_splats=1000, n_params=10, ms=dict.fromkeys(PARTS, 1.0), peak_mem_mb=1.0, fps_baked=1.0,
                  precision="float32", generator_flops=0)
    rows = [dict(common, method="gs3d", iter_ms=4.0, split={**split, "heads_fwd": 0.5}, flops=0, flop_floor_ms=0.0),
            dict(common, method="splatfields3d", iter_ms=100.0, split=split, ratio_vs_gs3d=25.0, flops=9e9,
                 flop_floor_ms=30.0, x_flop_floor=3.3),
            dict(method="splatfields3d", n_splats=1000, error="killed")]
    src = tmp_path / "old.json"
    src.write_text(json.dumps({"rows": rows, "settings": {"peaks": {}}}))
    assert main(["--from-json", str(src), "--chart", str(tmp_path / "c.png")]) == 0
    assert (tmp_path / "c.png").stat().st_size > 0 and "x 3DGS" in capsys.readouterr().out
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"rows": [{"method": "gs3d"}]}))
    with pytest.raises(SystemExit) as exc:
        main(["--from-json", str(bad)])
    assert exc.value.code == 2 and f"--from-json {bad}: rows[0] lacks n_splats, n_params, ms" in capsys.readouterr().err


def test_training_bench_writes_rows_per_method_and_head_width(tmp_path, capsys):
    rows = _tiny_bench(tmp_path, capsys, 400, "--head-widths", "32")
    assert [(r["method"], r["head_width"]) for r in rows] == [("gs3d", None), ("splatfields3d", 128),
                                                             ("splatfields3d", 32)]
    for r in rows:
        assert r["n_splats"] == 400 and set(r["ms"]) == set(PARTS)
        assert r["iter_ms"] > 0 and r["fps_baked"] > 0 and r["peak_mem_mb"] > 0
        assert r["ratio_vs_gs3d"] > 0
    assert rows[2]["n_params"] < rows[1]["n_params"]  # narrower heads, fewer parameters
    assert rows[0]["backbone_ms"] is None and rows[1]["backbone_ms"] > 0  # the tri-plane CNN alone
    assert "x 3DGS" in capsys.readouterr().out


def test_training_bench_times_a_smaller_tri_plane_beside_the_configured_one(tmp_path, capsys):
    rows = _tiny_bench(tmp_path, capsys, 300, "--plane-blocks", "1,3")
    # the configured size (3 blocks: 80 px at scale=cpu) is timed once; 1 block (20 px) adds a row; gs3d has none
    assert [(r["method"], r["plane_blocks"]) for r in rows] == [("gs3d", None), ("splatfields3d", 3),
                                                               ("splatfields3d", 1)]
    assert rows[2]["overrides"] == ["field_budget.triplane_up_blocks=1"] and rows[1]["overrides"] == []
    assert [r["plane_px"] for r in rows] == [None, 80, 20]
    assert rows[2]["generator_flops"] < rows[1]["generator_flops"] / 4  # 20 px planes: fewer than 1/4 of the FLOPs
    assert "20px" in capsys.readouterr().out


def test_flop_counter_matches_hand_count_from_layer_shapes():
    import torch

    from src.bench.flops import count_flops, floor_ms
    from src.fields.mlp import FieldMLP

    n = 7
    mlp = FieldMLP(5, 2, n_layers=3, width=4, skips=(2,))  # linears 5->4, 4->4, (5+4)->2
    x = torch.randn(n, 5, requires_grad=True)
    flops = count_flops(lambda: mlp(x).sum().backward())
    # each linear: forward, grad of input, grad of weight = 3 products of 2·N·in·out FLOPs
    assert flops == {"total": 3 * 2 * n * (5 * 4 + 4 * 4 + 9 * 2), "conv": 0, "matmul": 3 * 2 * n * 54}
    conv = torch.nn.Conv2d(2, 3, 3, padding=1)
    img = torch.randn(1, 2, 5, 5, requires_grad=True)
    flops = count_flops(lambda: conv(img).sum().backward())
    assert flops == {"total": 3 * 2 * 25 * 2 * 3 * 9, "conv": 3 * 2 * 25 * 2 * 3 * 9, "matmul": 0}
    assert floor_ms({"conv": 2e9, "matmul": 1e9}, {"conv_gflops": 100.0, "matmul_gflops": 50.0}) == 40.0


def test_training_bench_reports_flop_floor_and_split(tmp_path):
    out = tmp_path / "bench.json"
    assert main(["--methods", "gs3d,splatfields3d_mip", "--sizes", "300", "--iters", "1", "--warmup", "0",
                 "--width", "32", "--fps-width", "32", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["settings"]["peaks"]["float32"]["matmul_gflops"] > 0
    gs, sf = data["rows"]
    assert gs["flops"] == 0 and gs["x_flop_floor"] is None
    assert sf["flops"] > sf["generator_flops"] > 0 and sf["flop_floor_ms"] > 0 and sf["x_flop_floor"] > 0
    assert set(sf["split"]) == set(SPLIT) and sf["generator_ms"] > 0


def test_default_output_path():
    assert str(DEFAULT_OUT) == "sweeps/results/bench/training.json"


@pytest.mark.parametrize("groups", [1, 3])
def test_grouped_convolution_flops_match_a_hand_count(groups):
    """Forward + both gradients of a (grouped) 3x3 conv: 3 x 2 x outputs x (C_in / groups) x 9."""
    import torch

    from src.bench.flops import count_flops

    conv = torch.nn.Conv2d(96, 96, 3, padding=1, groups=groups, bias=False)
    x = torch.randn(1, 96, 20, 20, requires_grad=True)
    counted = count_flops(lambda: conv(x).sum().backward())
    assert counted["conv"] == 3 * 2 * (96 * 20 * 20) * (96 // groups) * 9


@pytest.mark.parametrize("with_r", [False, True])
def test_fused_linear_relu_flops_match_a_hand_count(with_r):
    """The heads' fused hidden layer (oneDNN forward, hand-written backward): 3 x 2 x N x in x out."""
    import torch

    from src.bench.flops import count_flops
    from src.fields.linear_relu import linear_relu

    n, d_in, d_out = 50, 16, 24
    h = torch.randn(n, d_in, requires_grad=True)
    w = torch.randn(d_out, d_in, requires_grad=True)
    b = None if with_r else torch.randn(d_out, requires_grad=True)
    r = torch.randn(n, d_out, requires_grad=True) if with_r else None
    counted = count_flops(lambda: linear_relu(h, w, b, r).sum().backward())
    assert counted == {"total": 3 * 2 * n * d_in * d_out, "conv": 0, "matmul": 3 * 2 * n * d_in * d_out}


def test_repeated_rows_keep_their_fastest_run(tmp_path, capsys):
    rows = _tiny_bench(tmp_path, capsys, 300, "--repeat", "2")
    assert [r["method"] for r in rows] == ["gs3d", "splatfields3d"]
    for r in rows:
        assert len(r["iter_ms_runs"]) == 2 and r["iter_ms"] == min(r["iter_ms_runs"])
        assert r["ratio_vs_gs3d"] == r["iter_ms"] / rows[0]["iter_ms"]  # ratios from the kept runs


def test_faster_row_never_keeps_a_failed_run():
    ok, slow, failed = {"iter_ms": 80.0, "k": "a"}, {"iter_ms": 100.0, "k": "b"}, {"error": "killed"}
    assert faster_row(slow, ok) == {**ok, "iter_ms_runs": [100.0, 80.0]}
    assert faster_row(faster_row(slow, ok), failed)["iter_ms_runs"] == [100.0, 80.0]
    assert faster_row(failed, slow) == {**slow, "iter_ms_runs": [100.0]}
    assert "error" in faster_row(failed, failed)


def test_a_quick_run_does_not_replace_the_kept_result():
    assert output_path(None, quick=False) == DEFAULT_OUT
    assert output_path(None, quick=True) is None  # --quick prints only
    assert output_path(Path("x.json"), quick=True) == Path("x.json")


def test_device_argument_is_checked_before_any_work(capsys, monkeypatch):
    """--device names cpu or cuda; cuda needs a GPU; gsplat needs --device cuda (one-line errors, exit 2)."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for argv, message in ((["--device", "tpu"], "--device 'tpu': choose cpu or cuda"),
                          (["--device", "cuda"], "--device cuda: no CUDA GPU on this machine"),
                          (["--rasterizer", "gsplat"], "--rasterizer gsplat needs --device cuda")):
        with pytest.raises(SystemExit) as exc:
            main(["--quick", *argv])
        assert exc.value.code == 2 and message in capsys.readouterr().err


def test_rows_name_their_device(tmp_path, capsys):
    assert {r["device"] for r in _tiny_bench(tmp_path, capsys, 300)} == {"cpu"}
