"""A run never records what it did not do: checkpoints of other runs are refused, user mistakes are one
line with exit code 2 (and a record saying ``invalid input``), interruptions are recorded and resumable."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from src.run import unwritable
from src.trainer.identity import mismatch, shape_mismatch
from src.utils.hydra_cli import one_line
from tests.cli_runs import run_cli

REPO = Path(__file__).resolve().parents[1]
SMOKE = ("threads=1", "trainer.progress=false", "trainer.tensorboard=false", "+ci=smoke")


def error_lines(p: subprocess.CompletedProcess) -> list[str]:
    """stderr lines that are not log records (``[date][logger][LEVEL] - ...``) or library warnings."""
    return [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith("[")
            and "Warning" not in ln and not ln.startswith("  ")]


def assert_one_line(p: subprocess.CompletedProcess, *needles: str) -> str:
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    assert "Traceback" not in p.stderr, p.stderr[-2000:]
    lines = error_lines(p)
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def record(run_dir: Path) -> dict:
    return json.loads((run_dir / "metrics.json").read_text())


@pytest.fixture(scope="module")
def gs3d_checkpoint(tmp_path_factory) -> Path:
    """A finished ``+experiment=gs3d`` smoke run of monkey_cage (its checkpoint.pt is what gets copied)."""
    run_dir = tmp_path_factory.mktemp("gs3d") / "run"
    p = run_cli("+experiment=gs3d", f"hydra.run.dir={run_dir}", *SMOKE)
    assert p.returncode == 0, p.stderr[-2000:]
    return run_dir / "checkpoint.pt"


@pytest.mark.parametrize("args,needle", [
    (("+experiment=gs3d", "dataset.root=data/static/plant"), "its scene is 'monkey_cage', this run's is 'plant'"),
    (("+experiment=mip_splatting",), "its experiment is 'gs3d', this run's is 'mip_splatting'"),
    (("+experiment=gs3d", "dataset.n_views=4"), "training view count"),
    (("+experiment=gs3d", "model.sh_degree=0"), "model.sh_degree"),
])
def test_a_checkpoint_of_another_run_is_refused(gs3d_checkpoint, tmp_path, args, needle):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    shutil.copy(gs3d_checkpoint, run_dir / "checkpoint.pt")
    before = (run_dir / "checkpoint.pt").read_bytes()
    p = run_cli(*args, f"hydra.run.dir={run_dir}", *SMOKE)
    line = assert_one_line(p, "belongs to another run", needle, "trainer.resume=false")
    rec = record(run_dir)
    assert rec["status"] == "failed" and rec["reason"] == "invalid input: " + line[len("error: "):]
    assert (run_dir / "checkpoint.pt").read_bytes() == before  # nothing lost


def test_a_checkpoint_of_the_same_run_resumes(gs3d_checkpoint, tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    shutil.copy(gs3d_checkpoint, run_dir / "checkpoint.pt")
    p = run_cli("+experiment=gs3d", f"hydra.run.dir={run_dir}", *SMOKE)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "resumed from" in (run_dir / "run.log").read_text() and record(run_dir)["status"] == "ok"


def test_identity_tells_what_differs():
    base = {"experiment": "gs3d", "method": "gs3d", "model_class": "M", "scene": "a", "views": "f", "n_views": 4,
            "config": {"model.sh_degree": "1", "dataset.n_views": "4"}}
    assert mismatch(base, dict(base)) is None
    assert "carries no run identity" in mismatch(None, base)
    assert "its scene is 'a', this run's is 'b'" in mismatch(base, {**base, "scene": "b"})
    assert "training views" in mismatch(base, {**base, "views": "g"})
    other = {**base, "config": {"model.sh_degree": "3", "dataset.n_views": "4"}}
    assert mismatch(base, other) == "model.sh_degree is 1 there, 3 here"


def test_shapes_may_differ_only_in_the_splat_count():
    saved = {"means": torch.zeros(7, 3), "w": torch.zeros(4, 2)}
    assert shape_mismatch(saved, {"means": torch.zeros(5, 3), "w": torch.zeros(4, 2)}, 7, 5) is None
    assert "w has shape [4, 2] there, [8, 2] here" in shape_mismatch(
        saved, {"means": torch.zeros(5, 3), "w": torch.zeros(8, 2)}, 7, 5)
    assert "missing ['x']" in shape_mismatch(saved, {**saved, "x": torch.zeros(1)}, 7, 7)
    assert shape_mismatch({**saved, "means": torch.zeros(7, 3, 2)}, saved, 7, 7) is not None  # another layout
    assert shape_mismatch({"means": torch.zeros(7, 0, 3), "w": saved["w"]},
                          {"means": torch.zeros(5, 15, 3), "w": saved["w"]}, 7, 5) is None  # SH distilled away
    # buffers a model creates during training (LightGaussian's teacher) are the model's to load
    assert shape_mismatch({**saved, "teacher": torch.zeros(7, 3)}, saved, 7, 7) is None


@pytest.mark.parametrize("arg,needles", [
    ("+experiment=nosuch", ("Could not find 'experiment/nosuch'", "gs3d, gs3d_auto")),
    ("trainer.iteratons=5", ("trainer.iteratons",)),
    ("rasterizer=nosuch", ("rasterizer/nosuch", "auto, cpu, gsplat, torch_ref")),
])
def test_hydra_composition_errors_are_one_line_and_exit_2(tmp_path, arg, needles):
    args = (arg,) if arg.startswith("+experiment") else ("+experiment=gs3d", arg)
    p = run_cli(*args, f"hydra.run.dir={tmp_path / 'run'}", "+ci=smoke")
    assert_one_line(p, *needles)
    assert not (tmp_path / "run").exists()  # nothing was started


def test_one_line_lists_the_choices():
    text = ("In 'config': Could not find 'rasterizer/x'\n\nAvailable options in 'rasterizer':\n\tauto\n\tcpu\n"
            "Config search path:\n\tprovider=hydra, path=pkg://hydra.conf\n\n"
            "Set the environment variable HYDRA_FULL_ERROR=1 for a complete stack trace.\n")
    assert one_line(text) == ("In 'config': Could not find 'rasterizer/x'; "
                              "Available options in 'rasterizer': auto, cpu")


@pytest.mark.parametrize("arg,needle", [
    ("seed=1.5", "seed=1.5: expected an integer >= 0"),
    ("threads=-2", "threads=-2: expected a positive integer"),
    ("threads=0", "threads=0: expected a positive integer"),
    ("dataset.root=/nonexistent/scene", "dataset.root=/nonexistent/scene does not exist"),
])
def test_invalid_values_are_recorded_as_invalid_input(tmp_path, arg, needle):
    run_dir = tmp_path / "run"
    smoke = [a for a in SMOKE if not (arg.startswith("threads") and a.startswith("threads"))]
    p = run_cli("+experiment=gs3d", *smoke[:-1], arg, f"hydra.run.dir={run_dir}", "+ci=smoke")
    line = assert_one_line(p, needle)
    assert record(run_dir)["reason"] == "invalid input: " + line[len("error: "):]


def test_a_run_dir_that_cannot_be_written_is_one_line(tmp_path):
    in_the_way = tmp_path / "file"
    in_the_way.write_text("not a directory")
    p = run_cli("+experiment=gs3d", f"hydra.run.dir={in_the_way / 'run'}", *SMOKE)
    assert_one_line(p, "cannot create the run directory", "Not a directory", str(in_the_way))
    assert in_the_way.read_text() == "not a directory"


def test_a_full_disk_names_the_file_and_the_error(tmp_path):
    e = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / ".checkpoint.pt.x.tmp"))
    message = str(unwritable(e, tmp_path))
    assert "No space left on device" in message and ".checkpoint.pt.x.tmp" in message and "\n" not in message
    assert unwritable(OSError(errno.EIO, "I/O error"), tmp_path) is None  # not the user's doing: a traceback


def test_a_run_dir_of_another_job_is_refused_without_touching_it(gs3d_checkpoint, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(gs3d_checkpoint.parent, run_dir)
    rec = record(run_dir)
    rec["overrides"] = ["+experiment=gs3d", "seed=1"]
    (run_dir / "metrics.json").write_text(json.dumps(rec))
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file() and p.name != ".lock"}
    p = run_cli("+experiment=gs3d", f"hydra.run.dir={run_dir}", *SMOKE)
    assert_one_line(p, "holds another run")
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file() and p.name in before} == before


def _wait_for(path: Path, text: str, timeout: float = 120) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if path.is_file() and text in path.read_text(errors="replace"):
            return
        time.sleep(0.2)
    raise AssertionError(f"{text!r} never appeared in {path}")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_an_interrupted_run_is_recorded_and_resumes_to_the_same_result(tmp_path, signum):
    args = ["+experiment=gs3d", "dataset.n_views=4", "trainer.iterations=400", "trainer.log_every=10",
            "threads=1", "trainer.progress=false", "trainer.tensorboard=false", "eval.perceptual=false"]
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "src.run", *args, f"hydra.run.dir={run_dir}"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for(run_dir / "run.log", "iter 100/")
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, err[-2000:]
    rec = record(run_dir)
    done = rec["interrupted"]["checkpoint_iteration"]
    assert rec["status"] == "interrupted" and 100 <= done < 400
    assert rec["reason"] == (f"interrupted by {signal.Signals(signum).name}; checkpoint at iteration {done} "
                             f"({run_dir / 'checkpoint.pt'}); re-run the same command to resume")
    assert "Traceback" not in err
    resumed = run_cli(*args, f"hydra.run.dir={run_dir}")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert f"resumed from {run_dir / 'checkpoint.pt'} at iteration {done}" in (run_dir / "run.log").read_text()
    whole = run_cli(*args, f"hydra.run.dir={tmp_path / 'whole'}")
    assert whole.returncode == 0
    a, b = record(run_dir)["metrics"], record(tmp_path / "whole")["metrics"]
    assert (a["psnr"], a["ssim"], a["n_splats"]) == (b["psnr"], b["ssim"], b["n_splats"])


def test_files_are_left_readable_by_the_group(gs3d_checkpoint):
    umask = os.umask(0)
    os.umask(umask)
    for name in ("metrics.json", "checkpoint.pt", "splats.ply"):
        assert (gs3d_checkpoint.parent / name).stat().st_mode & 0o777 == 0o666 & ~umask, name


@pytest.mark.parametrize("value", ["abc", "0", "-1"])
def test_a_budget_scale_that_is_not_a_positive_number_is_one_line(tmp_path, value):
    """schedule.budget_scale feeds every ${times:...} of the scale's schedule: refused in one line naming it,
    before a record is written."""
    run_dir = tmp_path / "run"
    p = run_cli("+experiment=gs3d", f"schedule.budget_scale={value}", f"hydra.run.dir={run_dir}")
    assert_one_line(p, "schedule.budget_scale=", value, "expected a positive number")
    assert not (run_dir / "metrics.json").exists()
