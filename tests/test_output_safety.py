"""Outputs are written safely and user mistakes get one clear line.

* one writer per output folder: a second ``src.tables --out OUT`` is refused (exit code 2) and OUT is
  left as it was;
* every file goes through one atomic writer with a unique temporary, and gets the mode a plain
  ``open(path, "w")`` would give it;
* the command lines (``src.tables``, ``src.view``, ``src.prune``, ``src.bench``, ``src.reporting.chart``)
  answer an ordinary mistake with one ``error:`` line naming the file or flag, exit code 2, no traceback,
  and without touching what exists.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import pytest
import torch
from matplotlib.figure import Figure

from src.core.splats import Splats
from src.io.ply import ply_bytes, write_ply
from src.utils.runlock import RunLock

REPO = Path(__file__).resolve().parents[1]
AS_ROOT = os.geteuid() == 0
ROOT_SKIP = "root may read and write any file, so a permission mistake cannot be made"


def cli(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    """Run ``python -m ARGS`` as a user would."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env=env)


def error_lines(stderr: str) -> list[str]:
    """The lines of ``stderr`` that are not Python warnings (which the tools do not control)."""
    return [line for line in stderr.splitlines() if line.strip() and "Warning" not in line
            and not line.startswith("  ")]


def assert_one_line_error(returncode: int, stderr: str, needle: str) -> None:
    """Exit code 2, one ``error:`` line holding ``needle``, no traceback."""
    assert "Traceback" not in stderr, stderr
    lines = error_lines(stderr)
    assert returncode == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert needle in lines[0], stderr


def call(main: Callable[[Sequence[str]], int], args: Sequence[str], capsys: pytest.CaptureFixture[str]
         ) -> tuple[int, str]:
    """Call a command line's ``main`` in this process: (exit code, stderr)."""
    try:
        code = main(list(args))
    except SystemExit as exc:
        code = exc.code
    return int(code or 0), capsys.readouterr().err


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def write_record(run_dir: Path, **metrics: float) -> Path:
    """A finished run's metrics.json."""
    run_dir.mkdir(parents=True, exist_ok=True)
    record = {"status": "ok", "method": "gs3d", "experiment": "gs3d",
              "keys": {"scene": "s", "n_views": 4, "seed": 0}, "metrics": {"psnr": 20.0, "ssim": 0.8, **metrics}}
    path = run_dir / "metrics.json"
    path.write_text(json.dumps(record))
    return path


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    """A sweep directory with two finished runs that can be charted (train_s recorded)."""
    write_record(tmp_path / "sweep" / "0", train_s=10.0)
    record = json.loads((tmp_path / "sweep" / "0" / "metrics.json").read_text())
    record["keys"]["seed"] = 1
    record["metrics"] = {"psnr": 21.0, "ssim": 0.82, "train_s": 12.0}
    (tmp_path / "sweep" / "1").mkdir()
    (tmp_path / "sweep" / "1" / "metrics.json").write_text(json.dumps(record))
    return tmp_path / "sweep"


def splats(n: int = 4) -> Splats:
    """A small valid splat set."""
    return Splats(means=torch.randn(n, 3, generator=torch.Generator().manual_seed(0)),
                  scales=torch.full((n, 3), 0.1), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
                  opacities=torch.full((n,), 0.5), colors=torch.full((n, 3), 0.5))


# -- one writer per output folder -------------------------------------------------------------------


def test_second_tables_writer_is_refused_and_out_is_untouched(sweep: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = cli("src.tables", str(sweep), "--out", str(out), "--chart")
    assert first.returncode == 0, first.stderr
    before = snapshot(out)
    assert {"table.md", "chart.png", "chart.svg"} <= set(before)
    with RunLock(out):
        held = (out / ".lock").read_bytes()
        second = cli("src.tables", str(sweep), "--out", str(out), "--chart", "--format", "csv")
        assert (out / ".lock").read_bytes() == held
    assert_one_line_error(second.returncode, second.stderr, f"error: {out} is being written by pid {os.getpid()}")
    assert second.stdout == ""
    assert snapshot(out) == {**before, ".lock": held}


def test_chart_cli_is_refused_while_the_folder_is_written(sweep: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    from src.reporting.chart import main as chart_main
    from src.tables import main as tables_main

    out = tmp_path / "out"
    assert tables_main([str(sweep), "--out", str(out), "--metrics", "psnr,train_s"]) == 0
    capsys.readouterr()
    before = snapshot(out)
    with RunLock(out):
        code, err = call(chart_main, ["--from-table", str(out / "table.md")], capsys)
    assert_one_line_error(code, err, f"{out} is being written by")
    assert {k: v for k, v in snapshot(out).items() if k != ".lock"} == {k: v for k, v in before.items() if k != ".lock"}


# -- unique temporaries through the one atomic writer ----------------------------------------------------


def test_every_output_goes_through_unique_temporaries(sweep: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from src.tables import main as tables_main

    names: list[str] = []
    real_mkstemp = tempfile.mkstemp

    def spy_mkstemp(*args, **kwargs):
        fd, name = real_mkstemp(*args, **kwargs)
        names.append(name)
        return fd, name

    def no_paths(self, fname, *args, **kwargs):
        assert not isinstance(fname, str | Path), f"savefig to the fixed name {fname}"
        return real_savefig(self, fname, *args, **kwargs)

    real_savefig = Figure.savefig
    monkeypatch.setattr(tempfile, "mkstemp", spy_mkstemp)
    monkeypatch.setattr(Figure, "savefig", no_paths)
    out = tmp_path / "out"
    for _ in range(2):
        assert tables_main([str(sweep), "--out", str(out), "--chart"]) == 0
    capsys.readouterr()
    assert len(names) == 8 and len(set(names)) == 8  # table.md, runs.jsonl.gz, chart.png, chart.svg, twice
    assert sorted(p.name for p in out.iterdir()) == [".lock", "chart.png", "chart.svg", "runs.jsonl.gz", "table.md"]


def test_bench_charts_go_through_the_atomic_writer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from src.bench.training_chart import make_training_chart

    written: list[Path] = []
    import src.reporting.chart as chart

    monkeypatch.setattr(chart, "atomic_write_bytes", lambda path, data: written.append(Path(path)))
    row = {"method": "gs3d", "n_splats": 10_000, "iter_ms": 10.0, "flop_floor_ms": 1.0, "x_flop_floor": 10.0,
           "split": {"generator_fwd": 0.0, "heads_fwd": 0.0, "rasterizer": 8.0, "heads_bwd": 0.0,
                     "generator_bwd": 0.0, "optimizer": 2.0}}
    assert make_training_chart({"rows": [row], "settings": {}}, tmp_path / "t.png") == tmp_path / "t.png"
    assert written == [tmp_path / "t.png"] and not list(tmp_path.iterdir())


# -- file modes --------------------------------------------------------------------------------------------


MODE_PROBE = """
import os, sys
from pathlib import Path
os.umask(int(sys.argv[1], 8))
from src.utils.record import atomic_write_bytes, write_json
d = Path(sys.argv[2])
write_json(d / "metrics.json", {"status": "ok"})
atomic_write_bytes(d / "checkpoint.pt", b"x")
with open(d / "plain.txt", "w") as f:
    f.write("x")
(d / "kept.json").write_text("{}")
os.chmod(d / "kept.json", 0o640)
write_json(d / "kept.json", {"a": 1})
names = ("metrics.json", "checkpoint.pt", "plain.txt", "kept.json")
print(" ".join(oct(os.stat(d / n).st_mode & 0o777) for n in names))
"""


@pytest.mark.parametrize("umask,mode", [("022", "0o644"), ("002", "0o664")])
def test_atomic_files_get_the_mode_of_a_plain_open(tmp_path: Path, umask: str, mode: str) -> None:
    p = subprocess.run([sys.executable, "-c", MODE_PROBE, umask, str(tmp_path)], cwd=REPO, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == [mode, mode, mode, "0o640"]  # a replaced file keeps its own mode
    assert sorted(x.name for x in tmp_path.iterdir()) == ["checkpoint.pt", "kept.json", "metrics.json", "plain.txt"]


def test_umask_is_read_without_changing_it() -> None:
    from src.utils.record import process_umask

    old = os.umask(0o027)
    try:
        assert process_umask() == 0o027 and process_umask() == 0o027
    finally:
        os.umask(old)


# -- src.tables mistakes ---------------------------------------------------------------------------------


@pytest.mark.parametrize("content,needle", [
    ("{not json", "malformed JSON"),
    ("[1, 2]", "top level is list, expected a JSON object"),
    ('{"status": "ok"}', "status 'ok' but missing key(s) 'method', 'keys', 'metrics'"),
])
def test_tables_unusable_record_is_one_line(tmp_path: Path, content: str, needle: str) -> None:
    (tmp_path / "s" / "0").mkdir(parents=True)
    (tmp_path / "s" / "0" / "metrics.json").write_text(content)
    p = cli("src.tables", str(tmp_path / "s"), "--out", str(tmp_path / "out"))
    assert_one_line_error(p.returncode, p.stderr, needle)
    assert "metrics.json" in p.stderr and not (tmp_path / "out").exists()


@pytest.mark.parametrize("make,needle", [
    (lambda t: t / "nope", "no such directory"),
    (lambda t: (t / "file.txt").write_text("x") and t / "file.txt", "is a file; expected a sweep directory"),
])
def test_tables_sweep_dir_mistakes(tmp_path: Path, capsys: pytest.CaptureFixture[str], make, needle: str) -> None:
    from src.tables import main as tables_main

    path = make(tmp_path)
    code, err = call(tables_main, [str(path)], capsys)
    assert_one_line_error(code, err, f"{path}: {needle}")


def test_tables_out_blocked_by_a_file(sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from src.tables import main as tables_main

    blocker = tmp_path / "out"
    blocker.write_text("keep me")
    code, err = call(tables_main, [str(sweep), "--out", str(blocker), "--chart"], capsys)
    assert_one_line_error(code, err, f"{blocker}: a file is in the way, expected a directory")
    assert blocker.read_text() == "keep me"


@pytest.mark.parametrize("args,needle", [
    (["--format", "pdf"], "argument --format: invalid choice: 'pdf'"),
    (["--chart", "--metrics", "psnr"], None),
])
def test_tables_flag_mistakes(sweep: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                              needle: str | None) -> None:
    from src.tables import main as tables_main

    code, err = call(tables_main, [str(sweep), *args], capsys)
    if needle is None:  # a valid call, for contrast
        assert code == 0, err
    else:
        assert_one_line_error(code, err, needle)


def test_tables_chart_failure_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from src.tables import main as tables_main

    write_record(tmp_path / "s" / "0")  # no train_s: nothing to chart
    code, err = call(tables_main, [str(tmp_path / "s"), "--out", str(tmp_path / "out"), "--chart"], capsys)
    assert_one_line_error(code, err, "--chart: nothing to chart")
    assert not (tmp_path / "out").exists()


def test_tables_malformed_multirun_yaml_is_one_skipped_line(sweep: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from src.tables import main as tables_main

    (sweep / "multirun.yaml").write_text(": : [\n")
    code, err = call(tables_main, [str(sweep)], capsys)
    assert code == 0
    assert error_lines(err) == [f"skipped {sweep / 'multirun.yaml'}: cannot read YAML: expected <block end>, "
                                "but found ':' at line 1 column 1"]


@pytest.mark.skipif(AS_ROOT, reason=ROOT_SKIP)
def test_tables_unreadable_record_and_read_only_out(sweep: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from src.tables import main as tables_main

    locked = tmp_path / "locked"
    write_record(locked / "0").chmod(0)
    code, err = call(tables_main, [str(locked)], capsys)
    assert_one_line_error(code, err, "cannot read")
    read_only = tmp_path / "ro"
    read_only.mkdir()
    read_only.chmod(0o555)
    code, err = call(tables_main, [str(sweep), "--out", str(read_only / "out")], capsys)
    assert_one_line_error(code, err, "Permission denied")
    assert not list(read_only.iterdir())


# -- src.view and src.prune mistakes -------------------------------------------------------------------------


@pytest.fixture
def runs(tmp_path: Path) -> Path:
    """Run directories with the usual problems (a config that passes the first checks where one is needed)."""
    for name in ("empty", "junk", "nan", "noply"):
        (tmp_path / name / ".hydra").mkdir(parents=True)
        (tmp_path / name / ".hydra" / "config.yaml").write_text("dataset: {a: 1}\nrasterizer: {b: 1}\n")
    (tmp_path / "empty" / "splats.ply").write_bytes(b"")
    (tmp_path / "junk" / "splats.ply").write_bytes(bytes(range(256)) * 4)
    bad = splats()
    bad.means[1, 2] = float("inf")
    (tmp_path / "nan" / "splats.ply").write_bytes(ply_bytes(bad))
    (tmp_path / "afile").write_text("x")
    return tmp_path


VIEW_CASES = [
    ("nope", [], "nope: no such run directory"),
    ("afile", [], "afile: not a run directory or a .ply file"),
    ("noply", [], "noply: no splats.ply and no frames/frames.json"),
    ("empty", [], "empty/splats.ply: "),
    ("junk", [], "junk/splats.ply: malformed PLY"),
    ("nan", [], "nan/splats.ply: vertex property 'z' is not finite at vertex 1"),
    ("nan", ["--port", "-1"], "--port: -1 is out of range; expected 0..65535"),
    ("nan", ["--port", "http"], "--port: 'http' is not a port number"),
    ("nan", ["--frame", "1.5"], "--frame: invalid int value: '1.5'"),
]


@pytest.mark.parametrize("name,args,needle", VIEW_CASES)
def test_view_mistakes(runs: Path, capsys: pytest.CaptureFixture[str], name: str, args: list[str],
                       needle: str) -> None:
    from src.view import main as view_main

    code, err = call(view_main, [str(runs / name), *args], capsys)
    assert_one_line_error(code, err, needle)


PRUNE_CASES = [
    ("nope", [], "nope: does not exist; expected a finished run directory"),
    ("afile", [], "afile: is a file; expected a finished run directory"),
    ("noply", [], "noply/splats.ply: missing"),
    ("junk", [], "junk/splats.ply: malformed PLY"),
    ("nan", [], "nan/splats.ply: vertex property 'z' is not finite at vertex 1"),
    ("nan", ["--keep", "half"], "--keep: 'half': expected comma-separated fractions in (0, 1)"),
    ("nan", ["--keep", "0"], "--keep: '0': expected comma-separated fractions in (0, 1)"),
    ("nan", ["--max-loss-db", "-0.5"], "--max-loss-db: '-0.5': expected a finite number of 0 or more"),
    ("nan", ["--max-loss-db", "inf"], "--max-loss-db: 'inf': expected a finite number of 0 or more"),
    ("nan", ["--volume-power", "yes"], "--volume-power: 'yes': expected a finite number of 0 or more"),
]


@pytest.mark.parametrize("name,args,needle", PRUNE_CASES)
def test_prune_mistakes(runs: Path, capsys: pytest.CaptureFixture[str], name: str, args: list[str],
                        needle: str) -> None:
    from src.prune import main as prune_main

    before = snapshot(runs)
    code, err = call(prune_main, [str(runs / name), *args], capsys)
    assert_one_line_error(code, err, needle)
    assert snapshot(runs) == before


def test_prune_names_the_config_of_an_unbuildable_dataset(runs: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from src.prune import main as prune_main

    run = runs / "ok"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("dataset: {_target_: os.system}\nrasterizer: {_target_: os.system}\n")
    write_ply(run / "splats.ply", splats())
    code, err = call(prune_main, [str(run)], capsys)
    assert_one_line_error(code, err, f"{run / '.hydra' / 'config.yaml'}: dataset: ")
    assert not (run / "pruning.json").exists()


def test_view_and_prune_from_a_shell(runs: Path) -> None:
    for module in ("src.view", "src.prune"):
        p = cli(module, str(runs / "nan"))
        assert_one_line_error(p.returncode, p.stderr, "splats.ply: vertex property 'z' is not finite")


# -- src.bench and src.reporting.chart mistakes --------------------------------------------------------------


@pytest.fixture
def files(tmp_path: Path) -> Path:
    """Files a user might pass by mistake."""
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "rows.json").write_text('{"rows": 5}')
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    return tmp_path


BENCH_CASES = [
    (["--from-json", "list.json"], "top level is list; expected a JSON object with 'rows'"),
    (["--from-json", "rows.json"], "expected a"),
    (["--from-json", "adir"], "Is a directory"),
    (["--quick", "--out", "adir"], "--out: {t}/adir: is a directory; expected a file name"),
    (["--quick", "--out", "afile/r.json"], "--out: {t}/afile: is a file; expected a folder to hold r.json"),
    (["--quick", "--chart", "adir"], "--chart: {t}/adir: is a directory"),
]


@pytest.mark.parametrize("sub", ["rasterizer", "training"])
@pytest.mark.parametrize("args,needle", BENCH_CASES)
def test_bench_mistakes(files: Path, capsys: pytest.CaptureFixture[str], sub: str, args: list[str],
                        needle: str) -> None:
    from src.bench.__main__ import main as bench_main

    args = [str(files / a) if (files / a.split("/")[0]).exists() else a for a in args]
    before = snapshot(files)
    code, err = call(bench_main, [sub, *args], capsys)
    assert_one_line_error(code, err, needle.format(t=files))
    assert snapshot(files) == before


@pytest.mark.parametrize("args,needle", [
    (["--ref-max-s", "-1"], "--ref-max-s -1.0: expected a finite limit of 0 or more"),
    (["--ref-max-gb", "nan"], "--ref-max-gb nan: expected a finite limit of 0 or more"),
    (["--reps", "true"], "argument --reps: invalid int value: 'true'"),
])
def test_bench_rasterizer_numeric_flags(capsys: pytest.CaptureFixture[str], args: list[str], needle: str) -> None:
    from src.bench.__main__ import main as bench_main

    code, err = call(bench_main, ["rasterizer", *args], capsys)
    assert_one_line_error(code, err, needle)


def test_bench_mistake_from_a_shell(files: Path) -> None:
    p = cli("src.bench", "training", "--iters", "ten")
    assert_one_line_error(p.returncode, p.stderr, "argument --iters: invalid int value: 'ten'")


@pytest.mark.parametrize("make,needle", [
    (lambda t: t / "missing.md", "No such file or directory"),
    (lambda t: (t / "t.md").write_text("# no tables\n") and t / "t.md", "nothing to chart"),
])
def test_chart_cli_mistakes(tmp_path: Path, capsys: pytest.CaptureFixture[str], make, needle: str) -> None:
    from src.reporting.chart import main as chart_main

    code, err = call(chart_main, ["--from-table", str(make(tmp_path))], capsys)
    assert_one_line_error(code, err, needle)
