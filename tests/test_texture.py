"""The texture measure of a scene's images (src/data/texture.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from src.data.base import DatasetError
from src.data.images import write_png
from src.data.texture import image_texture_energy, main, texture_energy


def _object(pattern: np.ndarray) -> np.ndarray:
    """[32, 32, 4] RGBA: ``pattern`` [32, 32] as grey on an opaque 20 x 20 square, transparent around it."""
    rgba = np.zeros((32, 32, 4))
    rgba[..., :3] = pattern[..., None]
    rgba[6:26, 6:26, 3] = 1.0
    return rgba


def _checker() -> np.ndarray:
    """[32, 32] 0/1 checkerboard of 2-pixel cells."""
    return ((np.indices((32, 32)).sum(0) // 2) % 2).astype(float)


def test_checkerboard_scores_above_flat_and_silhouette_is_not_counted():
    flat = _object(np.full((32, 32), 0.3))
    checker = _object(_checker())
    e_flat, frac = image_texture_energy(flat)
    e_checker, _ = image_texture_energy(checker)
    assert e_flat == pytest.approx(0.0, abs=1e-12)  # the dark square's edge on white lies outside the eroded mask
    assert frac == pytest.approx(16 * 16 / 32**2)  # 20 x 20 shrunk by 2 pixels on every side
    assert e_checker > 0.1
    e_no_erosion, _ = image_texture_energy(flat, erode=0)
    assert e_no_erosion > 0.0  # without erosion the silhouette's edge counts


def test_empty_object_and_bad_shape():
    empty = np.zeros((8, 8, 4))
    energy, fraction = image_texture_energy(empty)
    assert np.isnan(energy) and fraction == 0.0
    with pytest.raises(ValueError, match=r"\[H, W, 4\]"):
        image_texture_energy(np.zeros((8, 8, 3)))


def test_scene_mean_and_cli(tmp_path, capsys):
    frames = []
    for i, pattern in enumerate([np.full((32, 32), 0.5), _checker()]):
        write_png(tmp_path / "train" / f"r_{i}.png", torch.from_numpy(_object(pattern)).float())
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": np.eye(4).tolist()})
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    stats = texture_energy(tmp_path)
    per_image = [image_texture_energy(_object(np.full((32, 32), 0.5)))[0],
                 image_texture_energy(_object(_checker()))[0]]
    assert stats["images"] == 2
    assert stats["texture_energy"] == pytest.approx(np.mean(per_image), abs=1e-2)  # 8-bit PNG rounding
    assert main([str(tmp_path)]) == 0
    assert str(tmp_path) in capsys.readouterr().out


def test_missing_split_names_the_file(tmp_path, capsys):
    with pytest.raises(DatasetError, match=r"transforms_val\.json"):
        texture_energy(tmp_path, split="val")
    assert main([str(tmp_path)]) == 2
    assert "transforms_train.json" in capsys.readouterr().err


def test_frame_without_file_path_names_the_field(tmp_path):
    frame = {"transform_matrix": np.eye(4).tolist()}
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [frame]}))
    with pytest.raises(DatasetError, match=r"frames\[0\] is missing key 'file_path'"):
        texture_energy(tmp_path)
