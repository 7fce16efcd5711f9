"""Blender/NeRF-synthetic reader: camera conventions, view selection, bad inputs."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

from src.data.base import DatasetError
from src.data.blender import BlenderDataset
from src.data.views import select_views
from tests.scenes import hemisphere_c2w_gl, write_blender_scene


def test_known_point_lands_on_the_right_pixel(tmp_path):
    """A 3D point projected with the OpenGL formula lands where the loaded OpenCV camera puts it."""
    root = write_blender_scene(tmp_path / "s", n_train=4, n_test=1, size=32)
    ds = BlenderDataset(str(root), normalise=False, n_test=1)
    scene = ds.load()
    data = json.loads((root / "transforms_train.json").read_text())
    fov = data["camera_angle_x"]
    p = torch.tensor([0.3, -0.2, 0.25], dtype=torch.float64)
    for v in scene.train:
        c2w = torch.tensor(data["frames"][v.image_id]["transform_matrix"], dtype=torch.float64)
        pc = torch.linalg.inv(c2w) @ torch.cat([p, torch.ones(1, dtype=torch.float64)])
        # OpenGL: camera looks along -z, +y up; image row grows downwards; pixel centres at +0.5
        f = 16 / math.tan(fov / 2)
        u = f * pc[0] / -pc[2] + 16
        vv = -f * pc[1] / -pc[2] + 16
        uv, z = v.camera.project(p[None].float())
        assert z[0] > 0
        assert abs(float(uv[0, 0]) - float(u)) < 1e-3 and abs(float(uv[0, 1]) - float(vv)) < 1e-3


def test_normalisation_puts_hull_in_unit_cube(tmp_path):
    root = write_blender_scene(tmp_path / "s", n_train=8, n_test=1, size=32)
    scene = BlenderDataset(str(root), n_test=1).load()
    assert 0 < scene.normalisation["scale"]
    # the random-splat object (spread 0.35) sits near the origin, so the hull box is modest
    c = torch.tensor(scene.normalisation["center"])
    assert c.abs().max() < 0.5
    assert scene.extent > 1.0


def test_view_selection_is_deterministic_sorted_and_spread():
    c2w = hemisphere_c2w_gl(100, seed=3)
    centres = torch.stack([m[:3, 3] for m in c2w]).numpy()
    a = select_views(centres, 6, seed=0)
    b = select_views(centres, 6, seed=0)
    assert a == b and a == sorted(a) and len(set(a)) == 6
    chosen = centres[a]
    d = np.linalg.norm(chosen[:, None] - chosen[None], axis=-1) + np.eye(6) * 1e9
    assert d.min() > 1.0  # spread out on a radius-4 hemisphere
    assert select_views(centres, None) == list(range(100))


def test_downscale_scales_intrinsics(tmp_path):
    root = write_blender_scene(tmp_path / "s", n_train=4, n_test=1, size=32)
    full = BlenderDataset(str(root), normalise=False, n_test=1).load()
    half = BlenderDataset(str(root), normalise=False, n_test=1, downscale=2).load()
    assert half.train[0].image.shape == (16, 16, 3)
    assert math.isclose(half.train[0].camera.fx, full.train[0].camera.fx / 2)
    p = torch.tensor([[0.1, 0.2, -0.1]])
    assert torch.allclose(half.train[0].camera.project(p)[0], full.train[0].camera.project(p)[0] / 2, atol=1e-4)


def test_background_compositing(tmp_path):
    root = write_blender_scene(tmp_path / "s", n_train=4, n_test=1, size=32)
    white = BlenderDataset(str(root), normalise=False, n_test=1).load().train[0]
    black = BlenderDataset(str(root), normalise=False, n_test=1, background="black").load().train[0]
    bg = white.mask < 1e-6
    assert bg.any()
    assert torch.allclose(white.image[bg], torch.ones(3))
    assert torch.allclose(black.image[bg], torch.zeros(3))


# -- bad input ------------------------------------------------------------------------------
@pytest.fixture
def scene_dir(tmp_path):
    return write_blender_scene(tmp_path / "bad", n_train=5, n_test=2, size=16)


def test_missing_root():
    with pytest.raises(DatasetError, match=r"dataset\.root"):
        BlenderDataset(None)
    with pytest.raises(DatasetError, match="does not exist"):
        BlenderDataset("/nonexistent/scene")


def test_missing_transforms(scene_dir):
    (scene_dir / "transforms_train.json").unlink()
    with pytest.raises(DatasetError, match=r"transforms_train\.json"):
        BlenderDataset(str(scene_dir)).load()


def test_malformed_json_and_missing_key(scene_dir):
    p = scene_dir / "transforms_test.json"
    p.write_text("{not json")
    with pytest.raises(DatasetError, match=r"transforms_test\.json.*malformed"):
        BlenderDataset(str(scene_dir)).load()
    p.write_text(json.dumps({"frames": [{"file_path": "./test/r_0", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(DatasetError, match="camera_angle_x"):
        BlenderDataset(str(scene_dir)).load()
    p.write_text(json.dumps({"camera_angle_x": 0.7, "frames": [{"file_path": "./test/r_0"}]}))
    with pytest.raises(DatasetError, match=r"frames\[0\].*transform_matrix"):
        BlenderDataset(str(scene_dir)).load()


def test_listed_image_absent(scene_dir):
    (scene_dir / "test" / "r_1.png").unlink()
    with pytest.raises(DatasetError, match=r"test/r_1.*not found"):
        BlenderDataset(str(scene_dir)).load()


def test_images_of_different_sizes(scene_dir, tmp_path):
    other = write_blender_scene(tmp_path / "other", n_train=1, n_test=1, size=20)
    shutil.copy(other / "test" / "r_0.png", scene_dir / "test" / "r_1.png")
    with pytest.raises(DatasetError, match="differs"):
        BlenderDataset(str(scene_dir)).load()


@pytest.mark.parametrize("n", [0, 6, -1])
def test_n_views_out_of_range(scene_dir, n):
    with pytest.raises(ValueError, match="n_views"):
        BlenderDataset(str(scene_dir), n_views=n).load()


def test_nan_in_image(scene_dir):
    data = json.loads((scene_dir / "transforms_test.json").read_text())
    data["frames"][0]["file_path"] = "./test/nan"
    (scene_dir / "transforms_test.json").write_text(json.dumps(data))
    arr = np.full((16, 16, 4), 0.5, np.float32)
    arr[3, 4, 1] = np.nan
    out = oiio.ImageOutput.create(str(scene_dir / "test" / "nan.exr"))
    out.open(str(scene_dir / "test" / "nan.exr"), oiio.ImageSpec(16, 16, 4, oiio.FLOAT))
    out.write_image(arr)
    out.close()
    with pytest.raises(DatasetError, match=r"nan\.exr.*NaN"):
        BlenderDataset(str(scene_dir)).load()
