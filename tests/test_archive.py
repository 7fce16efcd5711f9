"""Tests of run archives (``runs.jsonl.gz`` beside a board): a board rebuilt from one equals the board built from
the run directories, extends with new sweeps, and bad input is named, not swallowed."""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import pytest

from src.reporting import load
from src.reporting.archive import ARCHIVE_NAME, archive_bytes, is_archive
from src.tables import main
from tests.test_leaderboard import write_reference, write_run


def make_sweep(root: Path) -> Path:
    write_reference(root)
    write_run(root, "gs1", budget=1, psnr=21.0)
    write_run(root, "gs2", budget=2, psnr=22.0, train_s=200.0, curve=((100, 18.0), (200, 19.5)))
    write_run(root, "gs_bad", budget=2, scene="b", status="failed", reason="out of memory")
    return root


def board(sources: list[Path], out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    assert main([*map(str, sources), "--leaderboard", "--out", str(out)]) == 0
    capsys.readouterr()
    return (out / "leaderboard.md").read_text(encoding="utf-8")


def test_records_survive_the_round_trip(tmp_path: Path) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    os.utime(sweep / "gs1" / "metrics.json", (1_000.0, 1_000.0))
    records = load([sweep]).records
    path = tmp_path / ARCHIVE_NAME
    path.write_bytes(archive_bytes(records))
    back = load([path]).records
    by_data = lambda rs: sorted((json.dumps(r.data, sort_keys=True), r.mtime) for r in rs)  # noqa: E731
    assert by_data(back) == by_data(records) and len(back) == 4
    assert all(r.path.startswith(f"{path}#") for r in back)
    assert any(r.mtime == 1_000.0 for r in back)


def test_the_same_records_give_the_same_bytes(tmp_path: Path) -> None:
    records = load([make_sweep(tmp_path / "sweep")]).records
    data = archive_bytes(records)
    assert data == archive_bytes(list(reversed(records)))
    assert data[4:8] == b"\0\0\0\0"  # gzip header: no timestamp
    lines = gzip.decompress(data).decode("utf-8").splitlines()
    assert [json.loads(line)["path"] for line in lines] == sorted(json.loads(line)["path"] for line in lines)


def test_a_board_rebuilt_from_its_archive_is_the_same(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    first = board([sweep], tmp_path / "first", capsys)
    archive = tmp_path / "first" / ARCHIVE_NAME
    assert archive.is_file() and is_archive(archive)
    again = board([archive], tmp_path / "again", capsys)
    assert again != first and again.replace(f"{archive}#", "") == first  # the failed run's folder names the archive
    js = [json.loads((tmp_path / d / "leaderboard.json").read_text(encoding="utf-8")) for d in ("first", "again")]
    assert js[0]["methods"] == js[1]["methods"] and js[0]["lead"] == js[1]["lead"]
    assert "out of memory" in again  # failed runs are kept with their reason


def test_an_archive_extends_with_a_new_sweep_and_a_rerun_counts_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    board([sweep], tmp_path / "first", capsys)
    new = tmp_path / "new"
    write_run(new, "gs4", budget=4, psnr=23.0, train_s=400.0, curve=((200, 19.0), (400, 20.5)))
    write_run(new, "gs_bad", budget=2, scene="b", psnr=21.5, train_s=200.0,
              curve=((100, 18.0), (200, 19.4)))  # the failed run, re-run: ok now  # fmt: skip
    board([tmp_path / "first" / ARCHIVE_NAME, new], tmp_path / "both", capsys)
    data = json.loads((tmp_path / "both" / "leaderboard.json").read_text(encoding="utf-8"))
    gs = next(m for m in data["methods"] if m["method"] == "gs3d")
    assert gs["chosen_budget"]["value"] == 4
    at_2 = gs["val_psnr_by_budget"]["budget_scale=2"]
    assert at_2["runs"] == 2 and at_2["failed"] == 0
    rebuilt = load([tmp_path / "both" / ARCHIVE_NAME]).records
    assert len(rebuilt) == 6  # the archive keeps every run read; duplicates are resolved when a board is built


def test_bad_lines_are_named_and_the_rest_is_read(tmp_path: Path) -> None:
    good = load([make_sweep(tmp_path / "sweep")]).records
    lines = gzip.decompress(archive_bytes(good)).decode("utf-8").splitlines()
    lines[1] = "{not json"
    lines.insert(2, json.dumps({"path": "x", "mtime": "yesterday", "record": {"status": "ok"}}))
    lines.append(json.dumps({"path": "y", "mtime": 0, "record": {"status": "ok", "method": "m"}}))
    path = tmp_path / "runs.jsonl"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    collection = load([path])
    assert len(collection.records) == 3
    problems = [str(p) for p in collection.problems]  # the lines first, then the records
    assert f"{path}:2: malformed JSON" in problems[0]
    assert f"{path}:3: 'mtime' is str, expected a number" == problems[1]
    assert problems[2].startswith(f"{path}#y: status 'ok' but missing key(s) 'keys', 'metrics'")


def test_an_unreadable_archive_is_exit_2_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = archive_bytes(load([make_sweep(tmp_path / "sweep")]).records)
    broken = tmp_path / "broken.jsonl.gz"
    broken.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    assert main([str(broken), "--leaderboard", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {broken}: cannot read the run archive") and err.count("\n") == 1
    assert main([str(tmp_path / "missing.jsonl.gz"), "--leaderboard"]) == 2
    assert "missing.jsonl.gz: cannot read the run archive" in capsys.readouterr().err
    assert not out.exists()


def test_tables_with_out_keep_their_runs_too(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    out = tmp_path / "out"
    assert main([str(sweep), "--metrics", "psnr", "--out", str(out)]) == 0
    first = capsys.readouterr().out
    assert main([str(out / ARCHIVE_NAME), "--metrics", "psnr"]) == 0
    again = capsys.readouterr().out
    assert "out of memory" in again and again.replace(f"{out / ARCHIVE_NAME}#", "") == first


def test_a_chart_from_an_archive_needs_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    out = tmp_path / "out"
    assert main([str(sweep), "--metrics", "psnr", "--out", str(out)]) == 0
    capsys.readouterr()
    archive = out / ARCHIVE_NAME
    before = sorted(p.name for p in out.iterdir())
    assert main([str(archive), "--metrics", "psnr", "--chart"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --chart: {archive} is a run archive") and "pass --out DIR" in err
    assert sorted(p.name for p in out.iterdir()) == before


def test_tables_read_an_archive_once(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    path = tmp_path / ARCHIVE_NAME
    path.write_bytes(archive_bytes(load([sweep]).records))
    calls: list[Path] = []
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda p: (calls.append(p) if p == path else None) or real(p))
    assert main([str(path), "--leaderboard", "--out", str(tmp_path / "board")]) == 0
    capsys.readouterr()
    assert calls == [path]
