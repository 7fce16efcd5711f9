"""The shipped photo capture ``data/captures/room``: its COLMAP model against the renderer's cameras.

The scene's 30 photos were rendered by ``tools/datagen/capture_scenes.py`` and reconstructed by the project's
own ``python -m src.data.sfm`` (docs/data.md). The model is read through ``dataset=colmap`` and its cameras
are compared with ``gt_cameras.json`` (OpenCV camera-to-world) after the similarity transform (Umeyama) of
the reconstructed camera centres onto the true ones.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from src.data.colmap import ColmapDataset
from tests.alignment import camera_errors, rotation_angle_deg
from tests.cli_runs import run_cli

REPO = Path(__file__).resolve().parents[1]
ROOM = REPO / "data" / "captures" / "room"

MAX_POSITION_ERROR = 0.02   # of the cameras' extent (the largest distance of a centre from their mean)
MAX_ROTATION_ERROR = 2.0    # degrees, in the frame of the centres' similarity transform
MAX_RELATIVE_ROTATION = 1.0  # degrees, between any two cameras (needs no alignment)
MAX_FOCAL_ERROR = 0.01      # relative


def truth() -> dict:
    """gt_cameras.json: intrinsics and OpenCV camera-to-world matrices of the rendered photos."""
    return json.loads((ROOM / "gt_cameras.json").read_text())


@pytest.fixture(scope="module")
def reconstruction():
    """(found camera-to-world [N, 4, 4], true camera-to-world [N, 4, 4], the first photo's camera, the scene), the
    poses in gt_cameras.json's order, the model read unnormalised (world units of the reconstruction)."""
    gt = truth()
    scene = ColmapDataset(str(ROOM), n_views=None, normalise=False).load()
    cams = {v.camera.name: v.camera for v in (*scene.train, *scene.test)}
    names = [Path(f["file"]).stem for f in gt["frames"]]
    assert sorted(cams) == sorted(names), "every photo must be registered"
    found = torch.stack([torch.linalg.inv(cams[n].world_to_cam.double()) for n in names])
    true = torch.tensor([f["c2w"] for f in gt["frames"]], dtype=torch.float64)
    return found, true, cams[names[0]], scene


def test_every_photo_is_registered_with_the_rendered_intrinsics(reconstruction):
    _, true, cam, scene = reconstruction
    gt = truth()
    assert len(true) == 30 and scene.meta["n_images"] == 30
    assert (cam.width, cam.height) == (gt["width"], gt["height"])
    assert (cam.cx, cam.cy) == pytest.approx((gt["cx"], gt["cy"]))
    assert cam.fx == cam.fy and cam.fx == pytest.approx(gt["fx"], rel=MAX_FOCAL_ERROR)
    assert scene.meta["points"].shape[0] > 1000


def test_cameras_agree_with_the_renderer_up_to_a_similarity(reconstruction):
    found, true, _, _ = reconstruction
    rot_err, pos_err = camera_errors(found, true)
    rel = rotation_angle_deg(
        (true[:, None, :3, :3].transpose(-1, -2) @ true[None, :, :3, :3]).transpose(-1, -2)
        @ (found[:, None, :3, :3].transpose(-1, -2) @ found[None, :, :3, :3]))
    line = (f"captures/room: rotation error {float(rot_err.mean()):.2f}° mean, {float(rot_err.max()):.2f}° max; "
            f"relative rotation between cameras {float(rel.max()):.2f}° max; position error "
            f"{100 * float(pos_err.mean()):.2f} % mean, {100 * float(pos_err.max()):.2f} % max of the camera extent")
    print(line)
    assert float(pos_err.max()) < MAX_POSITION_ERROR, line
    assert float(rot_err.max()) < MAX_ROTATION_ERROR, line
    assert float(rel.max()) < MAX_RELATIVE_ROTATION, line


def test_alignment_detects_a_wrong_camera(reconstruction):
    """The check can fail: one camera turned by 5° and another moved by 5 % of the extent are both caught."""
    found, true, _, _ = reconstruction
    broken = found.clone()
    a = torch.deg2rad(torch.tensor(5.0, dtype=torch.float64))
    turn = torch.tensor([[1.0, 0.0, 0.0], [0.0, torch.cos(a), -torch.sin(a)], [0.0, torch.sin(a), torch.cos(a)]],
                        dtype=torch.float64)
    broken[3, :3, :3] = broken[3, :3, :3] @ turn
    spread = float((found[:, :3, 3] - found[:, :3, 3].mean(0)).norm(dim=1).max())
    broken[20, :3, 3] += 0.05 * spread * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    rot_err, pos_err = camera_errors(broken, true)
    assert float(rot_err[3]) > MAX_ROTATION_ERROR and float(pos_err[20]) > MAX_POSITION_ERROR


@pytest.mark.slow
def test_smoke_run_on_the_capture(tmp_path):
    out = tmp_path / "run"
    proc = run_cli("+experiment=gs3d", "dataset=colmap", f"dataset.root={ROOM}", "init=sfm", "dataset.n_views=3",
                   "threads=1", f"hydra.run.dir={out}", "+ci=smoke")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["status"] == "ok" and rec["choices"]["init"] == "sfm"
    assert rec["views"] == [0, 12, 25]   # round(linspace(0, 25, 3)) of the 26 non-test photos
    assert rec["image_size"] == [100, 75]  # +ci=smoke: downscale 4 of 400 x 300
