"""Command-line tools validate their arguments first: one line listing the valid choices, exit code 2."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    """A sweep directory holding one finished run record."""
    run = tmp_path / "sweep" / "0"
    run.mkdir(parents=True)
    record = {"status": "ok", "method": "gs3d", "experiment": "gs3d", "keys": {"scene": "s", "n_views": 4, "seed": 0},
              "metrics": {"psnr": 20.0, "ssim": 0.8}}
    (run / "metrics.json").write_text(json.dumps(record))
    return tmp_path / "sweep"


@pytest.mark.parametrize("flag,value,needle", [
    ("--rows", "nosuchkey", "--rows: no run has nosuchkey; choose from: "),
    ("--cols", "keys.nope", "--cols: no run has keys.nope; choose from: "),
    ("--metrics", "nope", "--metrics: no run has nope; choose from: psnr, ssim"),
])
def test_tables_unknown_key_lists_choices(sweep, flag, value, needle):
    p = cli("src.tables", str(sweep), flag, value)
    assert p.returncode == 2, p.stderr
    assert needle in p.stderr and "Traceback" not in p.stderr
    if flag != "--metrics":
        assert "keys.n_views" in p.stderr and "method" in p.stderr  # the valid choices are listed


def test_tables_valid_keys_still_work(sweep):
    p = cli("src.tables", str(sweep), "--rows", "method", "--cols", "keys.n_views")
    assert p.returncode == 0, p.stderr
    assert "| gs3d |" in p.stdout


@pytest.mark.parametrize("sub,args,needle", [
    ("rasterizer", ["--reps", "0"], "--reps 0: expected a positive number"),
    ("rasterizer", ["--reps", "-3"], "--reps -3: expected a positive number"),
    ("rasterizer", ["--scenes", "nosuch"], "--scenes: unknown scene 'nosuch'; choose from: cube, object"),
    ("training", ["--methods", "nosuch"],
     "--methods: unknown method(s) nosuch; choose from: gs3d, mip_splatting, splatfields3d"),
    ("training", ["--methods", "gs3d,nope"], "unknown method(s) nope"),
    ("training", ["--sizes", "10k"], "--sizes '10k': expected comma-separated positive splat counts"),
    ("training", ["--iters", "0"], "--iters 0: expected a positive number"),
    ("training", ["--repeat", "0"], "--repeat 0: expected 1 or more measurements per row"),
    ("training", ["--head-widths", "-4"], "--head-widths '-4': expected comma-separated positive widths"),
    ("training", ["--plane-blocks", "two"], "--plane-blocks 'two': expected comma-separated positive up-sampling"),
    ("training", ["--plane-blocks", "0"], "--plane-blocks '0': expected comma-separated positive up-sampling"),
    ("training", ["--rasterizer", "vulkan"], "--rasterizer 'vulkan': choose from: auto, cpu, torch_ref, gsplat"),
    ("training", ["--head-kernel", "maybe"], "--head-kernel 'maybe': choose on or off"),
])
def test_bench_bad_arguments_fail_at_once(sub, args, needle):
    p = cli("src.bench", sub, *args)
    assert p.returncode == 2 and needle in p.stderr, p.stderr


def test_bench_unknown_subcommand():
    p = cli("src.bench", "nosuch")
    assert p.returncode == 2 and "rasterizer" in p.stdout + p.stderr


def test_run_device_is_checked_before_anything_is_written(monkeypatch, tmp_path):
    """device names a device that exists here: one-line errors naming ``device``, exit code 2."""
    import torch

    from src.run import resolve_device
    from src.utils.validate import ConfigValueError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for name, needle in (("tpu", "device='tpu': expected auto, cpu, cuda or cuda:N"),
                         ("cuda", "device=cuda: no CUDA GPU is visible"), ("meta", "expected auto, cpu")):
        with pytest.raises(ConfigValueError, match=re.escape(needle)):
            resolve_device(name)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ConfigValueError, match=re.escape("device=cuda:3: only 1 CUDA GPU(s) visible")):
        resolve_device("cuda:3")
    assert resolve_device("cpu") == torch.device("cpu") and resolve_device("cuda:0") == torch.device("cuda:0")


def test_run_on_a_missing_gpu_exits_2_and_writes_nothing(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    p = cli("src.run", "device=cuda", f"hydra.run.dir={tmp_path / 'run'}")
    assert p.returncode == 2 and "error: device=cuda: no CUDA GPU is visible" in p.stderr, p.stderr
    assert not (tmp_path / "run" / "metrics.json").exists()
