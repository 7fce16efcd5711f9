"""dataset=colmap, the LLFF sparse split, init=sfm and python -m src.data.sfm.

The COLMAP models are built with pycolmap from a shipped scene's ground truth (``tests/colmap_models.py``:
``data/static/plant``'s first 40 training frames, its images, points of its ``gt_points.npz``), written in
binary and in text form and read back with ``dataset=colmap``. The photos-to-model test renders 12 views of a
textured toy room (a ray caster below) and runs the structure from motion on them.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from src.core.cameras import Camera
from src.core.splats import RenderOutput
from src.data.base import DatasetError, View
from src.data.blender import frame_camera
from src.data.colmap import ColmapDataset, llff_split, spread
from src.data.images import read_image, write_png
from src.init import SfmInit
from src.losses.objective import SplatLoss
from tests.alignment import similarity_residual
from tests.cli_runs import one_error_line, run_cli
from tests.colmap_models import GREEN, N_IMAGES, SIZE, gt_points, image_name, plant_frames, write_model


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("colmap")
    return {fmt: write_model(base / fmt, fmt) for fmt in ("bin", "txt")}


def blender_cameras() -> dict[str, Camera]:
    """Plant's cameras as the Blender reader makes them (world units), by image stem."""
    frames, fov = plant_frames()
    return {Path(image_name(k)).stem: frame_camera(fr, fov, SIZE, SIZE, name=Path(image_name(k)).stem)
            for k, fr in enumerate(frames)}


# -- the reader ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_poses_and_intrinsics_round_trip(models, fmt):
    """A 3D point projects to the same pixel through the Blender reader's and the COLMAP reader's camera."""
    scene = ColmapDataset(str(models[fmt]), n_views=None, n_val=None).load()
    assert len(scene.train) == 35 and len(scene.test) == 5 and scene.val == []
    center = torch.tensor(scene.normalisation["center"], dtype=torch.float64)
    scale = scene.normalisation["scale"]
    world = torch.from_numpy(gt_points(200, seed=1))                  # [200, 3]
    blender = blender_cameras()
    for v in (*scene.train, *scene.test):
        ref = blender[v.camera.name]
        uv_ref, z_ref = ref.to(dtype=torch.float64).project(world)
        uv, z = v.camera.to(dtype=torch.float64).project(scale * (world - center))
        assert (z_ref > 0).all()
        assert float((uv - uv_ref).abs().max()) < 2e-3, v.camera.name
        assert torch.allclose(z, scale * z_ref, rtol=1e-4)
        assert (v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy) == pytest.approx((ref.fx, ref.fy, 50.0, 50.0))
        assert v.mask is None and v.image.shape == (SIZE, SIZE, 3)


def test_unnormalised_pose_is_the_blender_pose_in_opencv(models):
    scene = ColmapDataset(str(models["bin"]), n_views=3, normalise=False).load()
    blender = blender_cameras()
    for v in scene.train:
        assert torch.allclose(v.camera.world_to_cam, blender[v.camera.name].world_to_cam, atol=1e-5)


def test_normalisation_is_the_camera_sphere_of_the_training_views(models):
    scene = ColmapDataset(str(models["bin"]), n_views=6).load()
    centres = torch.stack([v.camera.center.double() for v in scene.train])
    assert float(centres.mean(0).abs().max()) < 1e-5
    assert float(centres.norm(dim=1).max()) == pytest.approx(1 / 1.1, rel=1e-5)
    assert scene.extent == pytest.approx(1.0, rel=1e-5)
    rec = pycolmap.Reconstruction(str(models["bin"] / "sparse" / "0"))
    raw = torch.tensor(np.stack([p.xyz for p in rec.points3D.values()]))
    expected = scene.normalisation["scale"] * (raw - torch.tensor(scene.normalisation["center"], dtype=torch.float64))
    assert torch.allclose(scene.meta["points"].double(), expected, atol=1e-5)
    assert torch.allclose(scene.meta["point_colors"], torch.tensor(GREEN) / 255.0)


def test_llff_split_indices():
    split = llff_split(N_IMAGES, 3, n_val=2)
    assert split.test == [0, 8, 16, 24, 32]
    assert split.rest == [i for i in range(N_IMAGES) if i % 8]
    assert split.train == [0, 17, 34]                                # round(linspace(0, 34, 3))
    assert split.val == [1, 33] and not set(split.val) & set(split.train)
    assert llff_split(N_IMAGES, 6).train == [0, 7, 14, 20, 27, 34]   # 6.8, 13.6, 20.4, 27.2 rounded
    assert llff_split(N_IMAGES, 9).train == [0, 4, 8, 13, 17, 21, 26, 30, 34]  # 8.5 -> 8, 25.5 -> 26 (Python round)
    assert spread(10, None) == list(range(10)) and spread(10, 0) == [] and spread(10, 1) == [0]
    with pytest.raises(DatasetError, match="n_views=36 must be between 1 and the 35"):
        llff_split(N_IMAGES, 36)
    with pytest.raises(DatasetError, match="leave no training view"):
        llff_split(1, 1)


def test_scene_records_the_split(models):
    scene = ColmapDataset(str(models["txt"]), n_views=3, n_val=2).load()
    assert scene.view_ids == [0, 17, 34]
    assert [v.camera.name for v in scene.train] == ["r_001", "r_020", "r_039"]
    assert [v.camera.name for v in scene.val] == ["r_002", "r_038"]
    assert [v.camera.name for v in scene.test] == ["r_000", "r_008", "r_016", "r_024", "r_032"]
    assert [v.image_id for v in scene.test] == [0, 1, 2, 3, 4]
    assert scene.meta["test_names"] == [image_name(k) for k in (0, 8, 16, 24, 32)]
    assert torch.equal(scene.background, torch.zeros(3))
    assert [v.camera.name for v in ColmapDataset(str(models["txt"]), n_views=3, n_test=2).load().test] == \
        ["r_000", "r_016"]


def test_downscale_resizes_or_reads_images_n(models, tmp_path):
    full = ColmapDataset(str(models["bin"]), n_views=3).load()
    half = ColmapDataset(str(models["bin"]), n_views=3, downscale=2).load()
    cam, cam_half = full.train[0].camera, half.train[0].camera
    assert half.train[0].image.shape == (50, 50, 3) and (cam_half.width, cam_half.height) == (50, 50)
    assert (cam_half.fx, cam_half.cx) == pytest.approx((cam.fx / 2, cam.cx / 2))
    expected = torch.nn.functional.avg_pool2d(full.train[0].image.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
    assert torch.allclose(half.train[0].image, expected, atol=1e-6)
    root = tmp_path / "scene"
    shutil.copytree(models["bin"], root)
    (root / "images_2").mkdir()
    for p in (root / "images").iterdir():
        write_png(root / "images_2" / p.name, torch.full((50, 50, 3), 0.25))
    pre = ColmapDataset(str(root), n_views=3, downscale=2).load()
    assert pre.meta["image_folder"] == "images_2"
    assert torch.allclose(pre.train[0].image, torch.full((50, 50, 3), 64 / 255))
    assert (pre.train[0].camera.fx, pre.train[0].camera.cy) == pytest.approx((cam.fx / 2, cam.cy / 2))


def test_sparse_folder_without_0_is_read(tmp_path):
    root = write_model(tmp_path / "scene", "bin", camera_model="SIMPLE_PINHOLE", folder="sparse")
    scene = ColmapDataset(str(root), n_views=3).load()
    assert scene.meta["model"] == str(root / "sparse") and len(scene.train) == 3
    assert scene.train[0].camera.fx == scene.train[0].camera.fy


# -- init=sfm and the objective without masks ----------------------------------------------------------------
def test_init_sfm_returns_the_normalised_points(models):
    scene = ColmapDataset(str(models["bin"]), n_views=3).load()
    points = scene.meta["points"]
    everything = SfmInit(n_points=10_000)(scene, torch.Generator().manual_seed(0))
    assert torch.equal(everything, points) and everything.shape == (300, 3)
    some = SfmInit(n_points=50)(scene, torch.Generator().manual_seed(0))
    assert some.shape == (50, 3)
    assert bool(((some[:, None] - points[None]).abs().sum(-1) == 0).any(1).all())
    assert float(points.norm(dim=1).max()) < 5.0  # the plant lies among the cameras (unit ball)


def test_init_sfm_refuses_a_model_without_points_and_scenes_without_any(tmp_path):
    root = write_model(tmp_path / "scene", n_points=0)
    scene = ColmapDataset(str(root), n_views=3).load()
    with pytest.raises(DatasetError, match="the COLMAP model has no 3D points"):
        SfmInit()(scene, torch.Generator())
    scene.meta.pop("points")
    with pytest.raises(DatasetError, match="init=sfm needs the 3D points"):
        SfmInit()(scene, torch.Generator())


def test_no_mask_loss_without_masks():
    h = w = 8
    render = RenderOutput(color=torch.rand(h, w, 3), alpha=torch.rand(h, w), depth=torch.zeros(h, w),
                          means2d=torch.zeros(1, 2), radii=torch.zeros(1))
    cam = Camera(torch.eye(4), fx=8.0, fy=8.0, cx=4.0, cy=4.0, width=w, height=h)
    loss = SplatLoss(lambda_mask=0.1)
    unmasked = loss([render], [View(cam, torch.rand(h, w, 3), None, 0)], [])
    assert "mask" not in unmasked
    assert float(unmasked["total"]) == pytest.approx(0.8 * float(unmasked["l1"]) + 0.2 * float(unmasked["dssim"]))
    assert "mask" in loss([render], [View(cam, torch.rand(h, w, 3), torch.ones(h, w), 0)], [])


# -- bad input: one line naming the file ---------------------------------------------------------------------
def _drop_points_file(root: Path) -> None:
    (root / "sparse" / "0" / "points3D.bin").unlink()


def _no_model(root: Path) -> None:
    shutil.rmtree(root / "sparse")


def _missing_image(root: Path) -> None:
    (root / "images" / image_name(5)).unlink()


def _corrupt_images_file(root: Path) -> None:
    (root / "sparse" / "0" / "images.bin").write_bytes(b"\x05\x00\x00")


def _symlink_outside(root: Path) -> None:
    outside = root.parent / "elsewhere.png"
    shutil.copy(root / "images" / image_name(20), outside)
    (root / "images" / image_name(20)).unlink()
    os.symlink(outside, root / "images" / image_name(20))


@pytest.mark.parametrize("breaks,needle", [
    (_drop_points_file, "COLMAP model without points3D.bin (found cameras.bin, images.bin)"),
    (_no_model, "no COLMAP model: expected sparse/0/"),
    (_missing_image, f"image '{image_name(5)}' (image id 6) is listed in the model but missing"),
    (_corrupt_images_file, "pycolmap cannot read the COLMAP model"),
    (_symlink_outside, "outside dataset.root"),
])
def test_bad_model_or_images_are_one_line(tmp_path, breaks, needle):
    root = write_model(tmp_path / "scene")
    breaks(root)
    with pytest.raises(DatasetError) as info:
        ColmapDataset(str(root), n_views=3).load()
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_image_of_the_wrong_size_is_refused(tmp_path):
    root = write_model(tmp_path / "scene")
    write_png(root / "images" / image_name(20), torch.zeros(40, 40, 3))  # r_020: a training view at n_views=3
    with pytest.raises(DatasetError, match="image is 40x40 px but its camera in the model is 100x100"):
        ColmapDataset(str(root), n_views=3).load()


def test_image_name_leaving_the_root_is_refused(tmp_path):
    names = [image_name(k) for k in range(N_IMAGES)]
    names[3] = "../../outside/" + image_name(3)  # images/../../ = beside root
    root = write_model(tmp_path / "scene", names=names)
    (tmp_path / "outside").mkdir()
    shutil.copy(root / "images" / image_name(3), tmp_path / "outside" / image_name(3))
    needle = r"image 'images/\.\./\.\./outside/r_003\.png' resolves to .* outside dataset\.root"
    with pytest.raises(DatasetError, match=needle):
        ColmapDataset(str(root), n_views=3).load()


def test_camera_with_distortion_is_refused(tmp_path):
    root = write_model(tmp_path / "scene", camera_model="SIMPLE_RADIAL")
    with pytest.raises(DatasetError, match="camera 1 has model SIMPLE_RADIAL; dataset=colmap takes PINHOLE and "
                                           r"SIMPLE_PINHOLE cameras only .*python -m src\.data\.sfm --undistort"):
        ColmapDataset(str(root), n_views=3).load()


def test_missing_pycolmap_says_how_to_install(models, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)
    with pytest.raises(DatasetError, match=r'needs pycolmap, which is not installed: pip install -e "\.\[colmap\]"'):
        ColmapDataset(str(models["bin"]), n_views=3).load()


# -- end to end through the CLI ------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("experiment,fmt", [("gs3d", "bin"), ("gs3d", "txt"), ("mip_splatting", "bin")])
def test_smoke_run_on_a_colmap_model(models, tmp_path, experiment, fmt):
    out = tmp_path / "run"
    proc = run_cli(f"+experiment={experiment}", "dataset=colmap", f"dataset.root={models[fmt]}", "init=sfm",
                   "dataset.n_views=3", "threads=1", f"hydra.run.dir={out}", "+ci=smoke")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "ok" and rec["views"] == [0, 17, 34] and rec["choices"]["init"] == "sfm"
    assert rec["image_size"] == [25, 25]  # +ci=smoke: downscale 4
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(out / "tb"))
    ea.Reload()
    assert "loss/l1" in ea.Tags()["scalars"] and "loss/mask" not in ea.Tags()["scalars"]


@pytest.mark.slow
def test_cli_refusals_are_one_line(tmp_path):
    no_points = write_model(tmp_path / "no_points", n_points=0)
    proc = run_cli("+experiment=gs3d", "dataset=colmap", f"dataset.root={no_points}", "init=sfm", "threads=1",
                   f"hydra.run.dir={tmp_path / 'run1'}", "+ci=smoke")
    assert "the COLMAP model has no 3D points" in one_error_line(proc)
    radial = write_model(tmp_path / "radial", camera_model="SIMPLE_RADIAL")
    proc = run_cli("+experiment=gs3d", "dataset=colmap", f"dataset.root={radial}", "threads=1",
                   f"hydra.run.dir={tmp_path / 'run2'}", "+ci=smoke")
    assert "camera 1 has model SIMPLE_RADIAL" in one_error_line(proc)
    rec = json.loads((tmp_path / "run2" / "metrics.json").read_text())
    assert rec["status"] == "failed" and rec["reason"].startswith("invalid input")


# -- python -m src.data.sfm ----------------------------------------------------------------------------------
TOY_BOXES = [((-2.0, -2.0, -0.1), (2.0, 2.0, 0.0)),      # floor
             ((-2.0, 1.9, 0.0), (2.0, 2.0, 2.0)),        # back wall
             ((-0.5, -0.5, 0.0), (0.5, 0.5, 0.8)),       # two blocks
             ((0.7, 0.2, 0.0), (1.2, 0.9, 1.3))]
TOY_FOCAL, TOY_W, TOY_H = 170.0, 200, 150


def toy_texture(p: np.ndarray) -> np.ndarray:
    """[N, 3] colours in [0, 1] of world points [N, 3]: random sinusoids at four scales (blobs for SIFT)."""
    rng = np.random.default_rng(0)
    out = np.zeros((len(p), 3))
    for scale in (2.0, 5.0, 11.0, 23.0):
        freq, phase, mix = rng.normal(size=(3, 16)) * scale, rng.uniform(0, 2 * np.pi, 16), rng.normal(size=(16, 3))
        out += np.sin(p @ freq + phase) @ mix / 4.0
    return 1.0 / (1.0 + np.exp(-2.5 * out))


def toy_render(cam: Camera) -> torch.Tensor:
    """[H, W, 3] ray-cast image of the toy room (boxes, textured by position; grey sky) through ``cam``."""
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    rays_cam = np.stack([(j - cam.cx) / cam.fx, (i - cam.cy) / cam.fy, np.ones_like(j)], -1).reshape(-1, 3)
    w2c = cam.world_to_cam.double().numpy()
    rays = rays_cam @ w2c[:3, :3]                                      # [HW, 3] world directions
    origin = -w2c[:3, :3].T @ w2c[:3, 3]
    t_hit = np.full(len(rays), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi in TOY_BOXES:
            t0, t1 = (np.array(lo) - origin) / rays, (np.array(hi) - origin) / rays
            near, far = np.nanmax(np.minimum(t0, t1), axis=1), np.nanmin(np.maximum(t0, t1), axis=1)
            t_hit = np.where((near <= far) & (near > 0) & (near < t_hit), near, t_hit)
    hit = np.isfinite(t_hit)
    colour = np.where(hit[:, None], toy_texture(origin + rays * np.where(hit, t_hit, 0.0)[:, None]), 0.6)
    return torch.from_numpy(colour.reshape(cam.height, cam.width, 3)).float().contiguous()


def toy_cameras(n: int = 12) -> list[Camera]:
    """``n`` cameras on an arc of 70 degrees looking at the blocks (a forward-facing capture)."""
    from src.core.cameras import look_at

    cams = []
    for k in range(n):
        a = math.radians(-35 + 70 * k / (n - 1))
        eye = torch.tensor([4.5 * math.sin(a), -4.5 * math.cos(a), 2.2], dtype=torch.float64)
        w2c = look_at(eye, torch.tensor([0.0, 0.3, 0.5], dtype=torch.float64))
        cams.append(Camera(w2c, fx=TOY_FOCAL, fy=TOY_FOCAL, cx=TOY_W / 2, cy=TOY_H / 2, width=TOY_W, height=TOY_H))
    return cams


@pytest.mark.slow
def test_sfm_registers_every_photo_and_recovers_the_cameras(tmp_path):
    photos = tmp_path / "photos"
    cams = toy_cameras()
    for k, cam in enumerate(cams):
        write_png(photos / f"{k:03d}.png", toy_render(cam))
    out = tmp_path / "capture"
    proc = run_cli(str(photos), str(out), "--threads", "1", module="src.data.sfm", timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "registered 12 of 12 photos" in proc.stdout and "[3/3] incremental mapping" in proc.stdout
    scene = ColmapDataset(str(out), n_views=None, normalise=False).load()
    assert len(scene.train) + len(scene.test) == 12 and scene.meta["points"].shape[0] > 100
    got = {v.camera.name: v.camera for v in (*scene.train, *scene.test)}
    truth = torch.stack([cams[int(name)].center for name in sorted(got)])
    found = torch.stack([got[name].center.double() for name in sorted(got)])
    spread_m = float((truth - truth.mean(0)).norm(dim=1).max())
    assert similarity_residual(found, truth) < 0.02 * spread_m
    assert got["000"].fx == pytest.approx(TOY_FOCAL, rel=0.03) and got["000"].fx == got["000"].fy
    again = run_cli(str(photos), str(out), "--threads", "1", module="src.data.sfm")
    assert "already holds a COLMAP model" in one_error_line(again)


@pytest.mark.slow
def test_sfm_on_unrelated_photos_fails_in_one_line(tmp_path):
    photos = tmp_path / "photos"
    write_png(photos / "a.png", toy_render(toy_cameras()[0]))
    write_png(photos / "b.png", torch.from_numpy(np.random.default_rng(1).random((TOY_H, TOY_W, 3))).float())
    proc = run_cli(str(photos), str(tmp_path / "out"), "--threads", "1", module="src.data.sfm")
    line = one_error_line(proc)
    assert "the reconstruction failed: it registered none of the 2 photos" in line and "no model written" in line
    assert not (tmp_path / "out" / "sparse" / "0").exists()


def test_sfm_refuses_photos_of_different_sizes(tmp_path):
    photos = tmp_path / "photos"
    write_png(photos / "a.png", torch.zeros(30, 40, 3))
    write_png(photos / "b.png", torch.zeros(40, 40, 3))
    line = one_error_line(run_cli(str(photos), str(tmp_path / "out"), module="src.data.sfm"))
    assert "b.png: 40x40 px, but a.png is 40x30 px" in line


def test_undistort_turns_a_radial_model_into_one_the_reader_takes(tmp_path):
    radial = write_model(tmp_path / "radial", camera_model="SIMPLE_RADIAL")
    out = tmp_path / "undistorted"
    proc = run_cli("--undistort", str(radial), str(out), "--threads", "1", module="src.data.sfm")
    assert proc.returncode == 0, proc.stderr[-2000:]
    scene = ColmapDataset(str(out), n_views=3).load()
    assert scene.meta["model"] == str(out / "sparse") and len(scene.test) == 5
    assert read_image(out / "images" / image_name(0)).shape[:2] == (scene.test[0].camera.height,
                                                                    scene.test[0].camera.width)
