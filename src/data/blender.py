"""NeRF-synthetic ("Blender") format reader.

Layout: ``transforms_{train,val,test}.json`` with ``camera_angle_x`` (horizontal FoV, radians) and
``frames`` [{``file_path`` (relative, extension optional), ``transform_matrix`` (4x4 camera-to-world,
Blender/OpenGL: camera looks along -z, +y up)}], RGBA images. Cameras are converted to OpenCV by
right-multiplying with diag(1, -1, -1, 1); focal = (W / 2) / tan(camera_angle_x / 2), principal point
at the image centre. Images are composited on the configured background; alpha becomes the mask.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import Tensor

from src.core.cameras import Camera, opengl_to_opencv
from src.data.base import DatasetError, DatasetReader, Scene, View, read_json
from src.data.images import composite, read_image, resize_premultiplied
from src.data.normalise import cameras_extent, fit_normalisation, normalise_camera
from src.data.validate import (
    check_fov,
    check_int,
    check_matrix,
    check_number,
    check_pose,
    check_size,
    inside_root,
    kind_of,
    shown,
)
from src.data.views import select_views

IMAGE_EXTENSIONS = (".png", ".exr", ".jpg", ".jpeg", "")


def parse_background(background: str | list[float] | tuple[float, ...]) -> Tensor:
    """[3] background colour from ``white``/``black``/``grey`` or three floats in [0, 1]."""
    names = {"white": [1.0, 1.0, 1.0], "black": [0.0, 0.0, 0.0], "grey": [0.5, 0.5, 0.5]}
    if isinstance(background, str):
        if background not in names:
            raise DatasetError(f"dataset.background={background!r}: expected one of {sorted(names)} or 3 floats")
        return torch.tensor(names[background])
    bg = torch.tensor([float(x) for x in background])
    if bg.shape != (3,):
        raise DatasetError(f"dataset.background must have 3 values, got {list(background)}")
    return bg


def check_frame(frame: object, index: int, path: Path) -> torch.Tensor:
    """Check one entry of a transforms JSON's ``frames``; returns its transform_matrix [4, 4] (float64).

    ``file_path`` must be a non-empty string naming a file inside the scene folder; ``transform_matrix``
    4x4 numbers forming a rigid transform; ``time`` (if present) a number; ``frame_id`` and
    ``camera_id`` (if present) integers. Errors name the file, the frame and the field.
    """
    where = f"{path}: frames[{index}]"
    if not isinstance(frame, dict):
        raise DatasetError(f"{where}={shown(frame)} is {kind_of(frame)}, expected an object with file_path and "
                           "transform_matrix")
    for key in ("file_path", "transform_matrix"):
        if key not in frame:
            raise DatasetError(f"{path}: frames[{index}] is missing key '{key}'")
    file_path = frame["file_path"]
    if not isinstance(file_path, str) or not file_path.strip():
        raise DatasetError(f"{where}.file_path={file_path!r}: expected a non-empty relative path (a string)")
    inside_root(path.parent, path.parent / file_path, where, "image", file_path)
    matrix = check_matrix(frame["transform_matrix"], str(path), f"frames[{index}].transform_matrix", (4, 4))
    check_pose(matrix, where, "transform_matrix")
    if "time" in frame:
        check_number(frame["time"], str(path), f"frames[{index}].time", "a time in [0, 1]")
    for key in ("frame_id", "camera_id"):
        if key in frame:
            check_int(frame[key], str(path), f"frames[{index}].{key}", minimum=None)
    return matrix


def load_transforms(path: Path) -> dict:
    """Read and validate a transforms JSON; errors name the file, the frame and the key.

    The JSON and every image it lists must lie inside the scene folder (the JSON's own folder).
    """
    inside_root(path.parent, path, str(path.parent), "transforms file", path.name)
    data = read_json(path, "transforms file")
    for key in ("camera_angle_x", "frames"):
        if key not in data:
            raise DatasetError(f"{path}: missing key '{key}'")
    if not isinstance(data["frames"], list) or not data["frames"]:
        raise DatasetError(f"{path}: 'frames' must be a non-empty list")
    for i, fr in enumerate(data["frames"]):
        check_frame(fr, i, path)
    check_fov(data["camera_angle_x"], str(path))
    return data


def resolve_image(root: Path, file_path: str, json_path: Path, index: int | None = None) -> Path:
    """The image file a frame's ``file_path`` refers to (trying the usual extensions), resolved.

    Raises:
        DatasetError if it is missing or lies (symlinks followed) outside ``root``; the message names
        ``json_path`` and the frame ``index``.
    """
    where = str(json_path) if index is None else f"{json_path}: frames[{index}]"
    base = root / file_path  # an absolute file_path replaces root: refused just below
    inside_root(root, base, where, "image", file_path)
    for ext in IMAGE_EXTENSIONS:
        cand = base.with_name(base.name + ext) if ext else base
        if cand.is_file():
            return inside_root(root, cand, where, "image", file_path)
    raise DatasetError(f"{json_path}: image '{file_path}' listed but not found (tried {base}.png/.exr/...)")


def frame_camera(frame: dict, fov_x: float, width: int, height: int, name: str) -> Camera:
    """OpenCV camera of a NeRF-synthetic frame (centred principal point, square pixels)."""
    c2w = opengl_to_opencv(torch.tensor(frame["transform_matrix"], dtype=torch.float64))
    f = 0.5 * width / math.tan(0.5 * fov_x)
    return Camera(
        world_to_cam=torch.linalg.inv(c2w).float(), fx=f, fy=f, cx=width / 2.0, cy=height / 2.0,
        width=width, height=height, time=float(frame.get("time", 0.0)), name=name,
        frame_id=int(frame.get("frame_id", 0)), camera_id=int(frame.get("camera_id", -1)),
    )


def read_split(root: Path, split: str, background: Tensor, downscale: float,
               indices: list[int] | None = None) -> tuple[list[View], dict]:
    """Views of ``transforms_<split>.json`` (only ``indices`` if given), plus the raw JSON."""
    json_path = root / f"transforms_{split}.json"
    data = load_transforms(json_path)
    fov_x = check_fov(data["camera_angle_x"], str(json_path))
    frames = data["frames"]
    wanted = range(len(frames)) if indices is None else indices
    views: list[View] = []
    size: tuple[int, int] | None = None
    first_path: Path | None = None
    for i in wanted:
        fr = frames[i]
        path = resolve_image(root, fr["file_path"], json_path, i)
        rgba = read_image(path)
        if size is None:
            size, first_path = tuple(rgba.shape[:2]), path
        elif tuple(rgba.shape[:2]) != size:
            raise DatasetError(
                f"{path}: image size {tuple(rgba.shape[:2])} differs from {first_path}'s {size}"
            )
        if rgba.shape[-1] not in (3, 4):
            raise DatasetError(f"{path}: expected RGB or RGBA, got {rgba.shape[-1]} channels")
        h, w = rgba.shape[:2]
        cam = frame_camera(fr, fov_x, w, h, name=Path(fr["file_path"]).name)
        if downscale != 1.0:
            th, tw = round(h / downscale), round(w / downscale)
            check_size(th, tw, str(path), downscale)
            if rgba.shape[-1] == 4:
                rgba = resize_premultiplied(rgba, (th, tw))
            else:
                rgba = torch.nn.functional.interpolate(rgba.permute(2, 0, 1)[None], (th, tw), mode="area")[0]
                rgba = rgba.permute(1, 2, 0)
            cam = cam.scaled(tw / w)
        rgb, alpha = composite(rgba, background)
        mask = alpha if rgba.shape[-1] == 4 else None
        views.append(View(camera=cam, image=rgb.contiguous(), mask=mask, image_id=i))
    return views, data


def camera_centres(root: Path, split: str = "train") -> Tensor:
    """[N, 3] camera centres of a split straight from its JSON (no images read)."""
    data = load_transforms(root / f"transforms_{split}.json")
    return torch.tensor([fr["transform_matrix"] for fr in data["frames"]], dtype=torch.float64)[:, :3, 3]


class BlenderDataset(DatasetReader):
    """Reader for NeRF-synthetic scenes with deterministic sparse training views.

    Args:
        root: scene folder holding ``transforms_*.json``.
        n_views: number of training views (K-means on camera centres); None = all.
        downscale: image downscale factor (2 = half resolution).
        background: ``white`` (default, as the paper), ``black``, ``grey`` or [r, g, b].
        view_seed: seed of the K-means view selection (0, as the reference code).
        n_test: keep only the first ``n_test`` test views, evenly strided (None = all).
        n_val: same for the validation split (0 = skip it).
        normalise: move and scale the scene so the training masks' visual hull fits [-0.9, 0.9]^3.
    """

    def __init__(self, root: str, n_views: int | None = None, downscale: float = 1.0,
                 background: str | list[float] = "white", view_seed: int = 0, n_test: int | None = None,
                 n_val: int | None = 0, normalise: bool = True) -> None:
        if root is None or str(root) in ("", "???"):
            raise DatasetError("dataset.root is not set: pass dataset.root=/path/to/scene")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise DatasetError(f"dataset.root={self.root} does not exist or is not a directory")
        if downscale <= 0:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0")
        self.n_views = n_views
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.view_seed = view_seed
        self.n_test = n_test
        self.n_val = n_val
        self.normalise = normalise

    @staticmethod
    def _strided(n_total: int, n_keep: int | None) -> list[int] | None:
        if n_keep is None or n_keep >= n_total:
            return None
        return sorted({round(i * n_total / n_keep) for i in range(n_keep)})

    def load(self) -> Scene:
        """Read the scene: selected training views, test (and val) views, normalised cameras."""
        from src.data.detect import check_format, detect_format

        if detect_format(self.root) not in (None, "blender"):
            check_format(self.root, "blender")  # names the format the folder looks like
        centres = camera_centres(self.root, "train").numpy()
        view_ids = select_views(centres, self.n_views, seed=self.view_seed)
        train, _ = read_split(self.root, "train", self.background, self.downscale, view_ids)
        test_json = load_transforms(self.root / "transforms_test.json")
        test, _ = read_split(self.root, "test", self.background, self.downscale,
                             self._strided(len(test_json["frames"]), self.n_test))
        val: list[View] = []
        if self.n_val != 0 and (self.root / "transforms_val.json").is_file():
            val_json = load_transforms(self.root / "transforms_val.json")
            val, _ = read_split(self.root, "val", self.background, self.downscale,
                                self._strided(len(val_json["frames"]), self.n_val))
        norm = {"center": [0.0, 0.0, 0.0], "scale": 1.0}
        if self.normalise:
            masks = [v.mask for v in train]
            if any(m is None for m in masks):
                raise DatasetError(f"{self.root}: normalisation needs RGBA training images (alpha masks)")
            center, scale = fit_normalisation([v.camera for v in train], masks,
                                              where=str(self.root / "transforms_train.json"))
            for v in (*train, *test, *val):
                v.camera = normalise_camera(v.camera, center, scale)
            norm = {"center": center.tolist(), "scale": scale}
        return Scene(
            name=self.root.name, train=train, val=val, test=test, background=self.background,
            view_ids=view_ids, n_frames=1, normalisation=norm,
            extent=cameras_extent([v.camera for v in train]),
            meta={"format": "blender", "root": str(self.root), "height": train[0].image.shape[0],
                  "width": train[0].image.shape[1]},
        )
