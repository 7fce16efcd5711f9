"""Reliability: bad input fails before training with one clear line, and nothing in a run dir is lost.

Every case asserts the message (which file or key, what was expected) and that the run directory holds
no half-written file afterwards. Security cases (a crafted checkpoint, nested ``_target_``\\s) also
assert that the code they carry did NOT run. The last cases cover failures during or after training:
a collapsed run is recorded as failed (never "ok"), a corrupt checkpoint is named with the way out,
and a second writer to a run directory is refused without touching the first one's files.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from src.data.base import DatasetError
from src.run import run
from src.trainer.trainer import CheckpointError
from src.utils.instantiate import ConfigError, build
from src.utils.runlock import RunDirLocked, RunLock
from src.utils.validate import ConfigValueError
from tests import format_writers as fw
from tests.cli_runs import run_cli
from tests.scenes import write_blender_scene

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")


# -- helpers ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene_root(tmp_path_factory) -> Path:
    """A small NeRF-synthetic-layout scene (48 px, 10 training views)."""
    return write_blender_scene(tmp_path_factory.mktemp("rel") / "scene", n_train=10, n_test=2, size=48)


def copy_scene(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def config(root: Path, *overrides: str, experiment: str = "gs3d"):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[
            f"+experiment={experiment}", f"dataset.root={root}", "+ci=smoke", "trainer.tensorboard=false",
            *overrides])


def assert_clean(run_dir: Path) -> None:
    """No temporary (half-written) file, and any metrics.json is complete JSON that is not 'ok'/'running'."""
    assert not list(run_dir.glob(".*.tmp")), list(run_dir.glob(".*.tmp"))
    metrics = run_dir / "metrics.json"
    if metrics.exists():
        assert json.loads(metrics.read_text())["status"] == "failed"


# -- camera / image files -----------------------------------------------------------------------------------
def _nan_pose(d):
    d["frames"][1]["transform_matrix"][0][3] = math.nan


def _scaled_pose(d):
    d["frames"][0]["transform_matrix"] = [[2 * x for x in row[:3]] + [row[3]] for row in
                                          d["frames"][0]["transform_matrix"][:3]] + [[0, 0, 0, 1]]


def _fov(value):
    def fn(d):
        d["camera_angle_x"] = value
    return fn


def _bad_last_row(d):
    d["frames"][0]["transform_matrix"][3] = [0, 0, 1, 1]


@pytest.mark.parametrize("split,edit,needle", [
    ("test", _nan_pose, r"transforms_test.json: frames\[1\].transform_matrix holds non-finite values"),
    ("train", _nan_pose, r"transforms_train.json: frames\[1\].transform_matrix holds non-finite values"),
    ("train", _scaled_pose, r"frames\[0\].transform_matrix is not a rigid transform"),
    ("test", _bad_last_row, r"frames\[0\].transform_matrix: last row"),
    ("train", _fov(0), r"transforms_train.json: camera_angle_x=0 must be a field of view"),
    ("test", _fov(3.5), r"transforms_test.json: camera_angle_x=3.5 must be a field of view"),
    ("train", _fov(-0.3), r"camera_angle_x=-0.3"),
    ("train", _fov("wide"), r"camera_angle_x='wide' is not a number"),
])
def test_bad_camera_file_fails_before_training(scene_root, tmp_path, split, edit, needle):
    root = copy_scene(scene_root, tmp_path / "scene")
    edit_json(root / f"transforms_{split}.json", edit)
    out = tmp_path / "run"
    with pytest.raises(DatasetError, match=needle) as info:
        run(config(root), out)
    assert "\n" not in str(info.value)
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "failed" and "invalid input" in rec["reason"]
    assert not (out / "checkpoint.pt").exists() and not (out / "splats.ply").exists()
    assert_clean(out)


def test_downscale_that_leaves_too_few_pixels(scene_root, tmp_path):
    out = tmp_path / "run"
    needle = r"train/r_\d+\.png: image is 0x0 px after dataset\.downscale=1000; at least 8 px"
    with pytest.raises(DatasetError, match=needle):
        run(config(scene_root, "dataset.downscale=1000"), out)
    assert_clean(out)


def test_neus_camera_file_with_nan(tmp_path):
    root = tmp_path / "owl"
    fw.write_owlii(root, n_cams=4, n_frames=2, size=(16, 12))
    npz = root / "cam_train_2" / "cameras_sphere.npz"
    import numpy as np

    with np.load(npz) as z:
        arrays = {k: z[k].copy() for k in z.files}
    arrays["world_mat_1"][0, 0] = np.nan
    np.savez(npz, **arrays)
    with pytest.raises(DatasetError, match=r"cam_train_2/cameras_sphere.npz: 'world_mat_1' holds non-finite"):
        run(config(root, "dataset=owlii", "dataset.downscale=1", experiment="splatfields4d"), tmp_path / "run")
    assert_clean(tmp_path / "run")


def test_image_that_does_not_match_its_intrinsics(tmp_path):
    """A DTU-layout scan whose principal point lies outside its (cropped) images."""
    import numpy as np

    root = tmp_path / "dtu"
    fw.write_dtu(root, n_images=30, size=(16, 12))
    npz = root / "cameras_sphere.npz"
    with np.load(npz) as z:
        arrays = {k: z[k].copy() for k in z.files}
    from src.data.owlii import decompose_projection

    for i in range(30):  # shift every principal point 40 px to the right (beyond the 16 px width)
        K, w2c = decompose_projection(arrays[f"world_mat_{i}"])
        K[0, 2] += 40.0
        arrays[f"world_mat_{i}"] = np.eye(4)
        arrays[f"world_mat_{i}"][:3] = K @ w2c[:3]
    np.savez(npz, **arrays)
    with pytest.raises(DatasetError, match=r"principal point .* lies outside the 16x12 image: the image does not "
                                           r"match its intrinsics"):
        run(config(root, "dataset=dtu", "dataset.downscale=1", "dataset.n_views=3"), tmp_path / "run")
    assert_clean(tmp_path / "run")


def test_more_views_than_available(scene_root, tmp_path):
    with pytest.raises(ValueError, match="n_views"):
        run(config(scene_root, "dataset.n_views=500"), tmp_path / "run")
    assert_clean(tmp_path / "run")


# -- config values ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("override,needle", [
    ("trainer.iterations=-5", "trainer.iterations=-5: expected a positive integer"),
    ("trainer.iterations=0", "trainer.iterations=0: expected a positive integer"),
    ("trainer.iterations=2.5", "trainer.iterations=2.5: expected a positive integer"),
    ("optim.lr.means.init=-0.001", "optim.lr.means.init=-0.001: expected a positive number"),
    ("optim.lr.opacities.init=0", "optim.lr.opacities.init=0: expected a positive number"),
    ("init.n_points=0", "init.n_points=0: expected a positive integer"),
    ("schedule.max_splats=-10", "schedule.max_splats=-10: expected a positive integer"),
    ("trainer.views_per_step=0", "trainer.views_per_step=0: expected a positive integer"),
    ("dataset.n_views=0", "dataset.n_views=0: expected a positive integer"),
])
def test_bad_config_value_fails_before_training(scene_root, tmp_path, override, needle):
    out = tmp_path / "run"
    with pytest.raises(ConfigValueError, match=needle.replace(".", r"\.")):
        run(config(scene_root, override), out)
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "failed" and needle in rec["error"]
    assert_clean(out)


def test_negative_network_learning_rate(scene_root, tmp_path):
    with pytest.raises(ConfigValueError, match=r"optim\.lr\.network\.init=-1"):
        run(config(scene_root, "optim.lr.network.init=-1", experiment="splatfields3d"), tmp_path / "run")


# -- code in configs and checkpoints --------------------------------------------------------------------------
@pytest.mark.parametrize("target", ["os.system", "builtins.exec", "torch.load", "src.run.torch.load",
                                    "subprocess.run", "src.utils.instantiate.importlib.import_module"])
def test_nested_target_is_refused_and_never_runs(tmp_path, target):
    marker = tmp_path / "pwned"
    cfg = {"_target_": "src.trainer.Trainer", "iterations": 1,
           "guard": {"evil": {"_target_": target, "_args_": [f"touch {marker}"]}}}
    with pytest.raises(ConfigError, match=r"guard\.evil: _target_ .* is not allowed") as info:
        build(cfg)
    assert "\n" not in str(info.value)
    assert not marker.exists()


def test_nested_target_from_the_command_line(scene_root, tmp_path):
    marker = tmp_path / "pwned"
    out = tmp_path / "run"
    p = run_cli("+experiment=gs3d", f"dataset.root={scene_root}", f"hydra.run.dir={out}", "+ci=smoke",
                "+loss.evil._target_=os.system", f"+loss.evil._args_=[touch {marker}]")
    assert p.returncode == 2, p.stderr[-2000:]
    assert "loss.evil: _target_ 'os.system' is not allowed" in p.stderr
    assert "Traceback" not in p.stderr
    assert not marker.exists()
    assert_clean(out)


class _Payload:
    """Pickles to a call of os.system: what a crafted checkpoint carries."""

    def __init__(self, cmd: str) -> None:
        self.cmd = cmd

    def __reduce__(self):
        return (os.system, (self.cmd,))


def test_crafted_checkpoint_does_not_run_code(scene_root, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    marker = tmp_path / "pwned"
    with open(out / "checkpoint.pt", "wb") as f:
        pickle.dump({"iteration": 1, "model": _Payload(f"touch {marker}")}, f)
    p = run_cli("+experiment=gs3d", f"dataset.root={scene_root}", f"hydra.run.dir={out}", "+ci=smoke")
    assert p.returncode == 2, p.stderr[-2000:]
    assert f"{out / 'checkpoint.pt'}: cannot read this checkpoint" in p.stderr
    assert "trainer.resume=false" in p.stderr
    assert not marker.exists()
    assert (out / "checkpoint.pt").is_file()  # the file is left for the user to inspect
    assert_clean(out)


def test_truncated_checkpoint_is_named_and_resume_false_starts_fresh(scene_root, tmp_path):
    out = tmp_path / "run"
    cfg = config(scene_root, "trainer.iterations=6", "trainer.ckpt_every=3")
    assert run(cfg, out)["status"] == "ok"
    data = (out / "checkpoint.pt").read_bytes()
    (out / "checkpoint.pt").write_bytes(data[: len(data) // 2])
    (out / "metrics.json").unlink()  # as after a kill: the run is not finished
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt: cannot read this checkpoint .*trainer\.resume=false"):
        run(cfg, out)
    assert_clean(out)
    rec = run(config(scene_root, "trainer.iterations=6", "trainer.ckpt_every=3", "trainer.resume=false"), out)
    assert rec["status"] == "ok"
    kept = list(out.glob("checkpoint.pt.*.old"))
    assert len(kept) == 1 and kept[0].read_bytes() == data[: len(data) // 2]  # set aside, not deleted
    assert torch.load(out / "checkpoint.pt", weights_only=True)["iteration"] == 5


def test_checkpoint_with_another_parameter_list_is_named(scene_root, tmp_path):
    """An optimiser state saved for another parameter list (e.g. an earlier network layout) is one clear error."""
    out = tmp_path / "run"
    cfg = config(scene_root, "trainer.iterations=6", "trainer.ckpt_every=3")
    assert run(cfg, out)["status"] == "ok"
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    groups = ck["optimizer"]["param_groups"]
    groups[0]["params"] = groups[0]["params"][:-1]  # one parameter fewer than the model has
    torch.save(ck, out / "checkpoint.pt")
    (out / "metrics.json").unlink()  # as after a kill: the run is not finished
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt: its optimiser state does not match .*resume=false"):
        run(cfg, out)
    assert_clean(out)


def test_checkpoint_holds_only_safe_types(scene_root, tmp_path):
    out = tmp_path / "run"
    assert run(config(scene_root, "trainer.iterations=3"), out)["status"] == "ok"
    ck = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=True)  # raises on any other type
    assert ck["iteration"] == 2 and isinstance(ck["np_rng"]["keys"], torch.Tensor)


# -- one writer per run directory ---------------------------------------------------------------------------
def test_second_writer_is_refused_and_changes_nothing(scene_root, tmp_path):
    out = tmp_path / "run"
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "config.yaml").write_text("the running job's config\n")
    (out / "metrics.json").write_text('{"status": "running"}\n')
    with RunLock(out):  # the first writer
        p = run_cli("+experiment=gs3d", f"dataset.root={scene_root}", f"hydra.run.dir={out}", "+ci=smoke")
        with pytest.raises(RunDirLocked, match="is in use by a running job"):
            run(config(scene_root), out)
    assert p.returncode == 2 and "is in use by a running job" in p.stderr, p.stderr[-2000:]
    assert (out / ".hydra" / "config.yaml").read_text() == "the running job's config\n"
    assert (out / "metrics.json").read_text() == '{"status": "running"}\n'
    assert not list(out.glob(".*.tmp"))


def test_lock_is_released_by_a_killed_holder(tmp_path):
    """flock locks die with their process (kill -9), so a killed run can be resumed."""
    code = f"from src.utils.runlock import RunLock; import time; RunLock({str(tmp_path)!r}).acquire(); " \
           "print('locked', flush=True); time.sleep(60)"
    holder = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(RunDirLocked):
            RunLock(tmp_path).acquire()
    finally:
        holder.kill()
        holder.wait()
    RunLock(tmp_path).acquire().release()


def test_extension_build_lock_left_by_a_killed_builder_is_cleared(tmp_path, monkeypatch):
    """A builder killed mid-compile leaves torch's file baton in the build directory; the next build
    must not wait for it forever (the kernel lock it takes first says no other builder is alive)."""
    from torch.utils import cpp_extension

    import src.kernels.build as _build

    monkeypatch.setenv("SPLATFIELDS_EXT_DIR", str(tmp_path))
    flags = _build.projection_compile_flags()
    build_dir = tmp_path / f"surfel_cpu_{_build.build_key(flags, _build.SURFEL_SOURCES)}"
    build_dir.mkdir()
    (build_dir / "lock").touch()  # the dead builder's baton
    seen = {}
    monkeypatch.setattr(cpp_extension, "load", lambda **kw: seen.update(
        baton=(Path(kw["build_directory"]) / "lock").exists(), dir=kw["build_directory"]))
    _build._load_unit("surfel_cpu", _build.SURFEL_SOURCES, [], flags, verbose=False)
    assert seen == {"baton": False, "dir": str(build_dir)}

# -- runs that collapse ----------------------------------------------------------------------------------------
def test_splats_flying_away_is_a_failed_run(scene_root, tmp_path):
    out = tmp_path / "run"
    p = run_cli("+experiment=gs3d", f"dataset.root={scene_root}", f"hydra.run.dir={out}", "+ci=smoke",
                "optim.lr.means.init=1e6")
    assert p.returncode == 1, p.stderr[-2000:]
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "failed" and rec["reason"].startswith("collapse:"), rec.get("reason")
    assert "run failed: collapse" in p.stdout
    assert_clean(out)


def test_empty_render_is_a_failed_run(scene_root, tmp_path):
    """Splats that are all transparent leave the background alone: flat renders fail the run."""
    out = tmp_path / "run"
    rec = run(config(scene_root, "trainer.iterations=2", "optim.lr.opacities.init=1e-12",
                     "model.init_opacity=1e-6"), out)
    assert rec["status"] == "failed" and "flat" in rec["reason"], rec.get("reason")


def test_psnr_no_better_than_the_background_is_a_failed_run(scene_root, tmp_path):
    """With gain_after lowered to the run's length, a barely trained run must beat the empty render by 30 dB."""
    rec = run(config(scene_root, "trainer.guard.gain_after=1", "trainer.guard.min_gain_db=30"), tmp_path / "run")
    assert rec["status"] == "failed" and "no better than an empty render" in rec["reason"], rec.get("reason")
    assert math.isfinite(json.loads((tmp_path / "run" / "metrics.json").read_text())["wall_s"])


def test_healthy_run_records_the_background_psnr(scene_root, tmp_path):
    rec = run(config(scene_root), tmp_path / "run")
    assert rec["status"] == "ok"
    assert rec["metrics"]["background_psnr"] < rec["metrics"]["psnr"]
