"""A COLMAP model built with pycolmap from a shipped scene's ground truth, for the readers' tests.

``data/static/plant``'s first 40 training frames (Blender / OpenGL camera-to-world turned into OpenCV
world-to-camera), its images copied into ``images/``, 3D points sampled from its ``gt_points.npz``; written in
binary or text form.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pycolmap

REPO = Path(__file__).resolve().parents[1]
PLANT = REPO / "data" / "static" / "plant"
N_IMAGES = 40          # plant frames in the test model: 5 test views (0, 8, ..., 32), 35 in the training pool
SIZE = 100             # plant's images are 100 x 100 px
GREEN = (30, 200, 60)  # the colour given to every model point


# -- a COLMAP model from plant's ground truth ---------------------------------------------------------------
def plant_frames() -> tuple[list[dict], float]:
    """The first N_IMAGES frames of plant's transforms_train.json and its camera_angle_x."""
    data = json.loads((PLANT / "transforms_train.json").read_text())
    return data["frames"][:N_IMAGES], float(data["camera_angle_x"])


def image_name(k: int) -> str:
    return f"r_{k:03d}.png"


def gt_points(n: int, seed: int = 0) -> np.ndarray:
    """[n, 3] float64 points of plant's rendered geometry (world coordinates)."""
    pts = np.load(PLANT / "gt_points.npz")["points"].astype(np.float64)
    return pts[np.random.default_rng(seed).choice(len(pts), n, replace=False)]


def write_model(root: Path, fmt: str = "bin", camera_model: str = "PINHOLE", n_points: int = 300,
                folder: str = "sparse/0", names: list[str] | None = None, copy_images: bool = True) -> Path:
    """A COLMAP model of plant's first N_IMAGES frames in ``root`` (``images/`` + ``folder``); returns root.

    Each Blender camera-to-world (OpenGL axes) becomes an OpenCV world-to-camera: inv(c2w @ diag(1, -1, -1, 1)).
    """
    frames, fov = plant_frames()
    focal = 0.5 * SIZE / math.tan(0.5 * fov)
    params = {"PINHOLE": [focal, focal, SIZE / 2, SIZE / 2], "SIMPLE_PINHOLE": [focal, SIZE / 2, SIZE / 2],
              "SIMPLE_RADIAL": [focal, SIZE / 2, SIZE / 2, 0.02]}[camera_model]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model=camera_model, width=SIZE, height=SIZE,
                                                    params=params))
    names = names or [image_name(k) for k in range(len(frames))]
    (root / "images").mkdir(parents=True, exist_ok=True)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    for k, (frame, name) in enumerate(zip(frames, names, strict=True)):
        if copy_images:
            shutil.copy(PLANT / (frame["file_path"].removeprefix("./") + ".png"), root / "images" / image_name(k))
        w2c = np.linalg.inv(np.asarray(frame["transform_matrix"], dtype=np.float64) @ flip)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=k + 1),
                                         pycolmap.Rigid3d(w2c[:3]))
    for p in gt_points(n_points):
        rec.add_point3D(p, pycolmap.Track(), np.array(GREEN, dtype=np.uint8))
    (root / folder).mkdir(parents=True, exist_ok=True)
    (rec.write_binary if fmt == "bin" else rec.write_text)(str(root / folder))
    return root
