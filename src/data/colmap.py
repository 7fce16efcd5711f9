"""COLMAP sparse-model reader: a capture of one's own photos (``dataset=colmap``).

Layout of ``dataset.root``: ``images/`` (the photos, named as the model lists them; sub-folders allowed)
and the model in ``sparse/0/`` or ``sparse/``: ``cameras``, ``images`` and ``points3D``, all ``.bin``
(preferred when both exist) or all ``.txt``, as COLMAP writes them. Optional ``images_<N>/`` holds the
photos downscaled N times and is read for ``dataset.downscale=N``. Read through pycolmap (the optional
extra ``colmap``: ``pip install -e ".[colmap]"``); ``python -m src.data.sfm`` builds such a folder.

Conventions:

* Cameras: COLMAP's ``Image.cam_from_world()`` is the OpenCV world-to-camera transform (x right, y
  down, z forward), the same as :attr:`src.core.cameras.Camera.world_to_cam`, and is taken as is. Pixel
  coordinates agree as well: both put the centre of pixel (row i, column j) at (j + 0.5, i + 0.5).
* Camera models: ``PINHOLE`` (fx, fy, cx, cy) and ``SIMPLE_PINHOLE`` (f, cx, cy). Any model with lens
  distortion is refused: undistort first (``python -m src.data.sfm --undistort``).
* Images: the stored 8-bit sRGB values as [H, W, 3] float in [0, 1] (not linearised, as every reader
  here); an alpha channel, if any, is composited on the background. No masks: ``View.mask`` is None.
* Split (the LLFF / few-view protocol): the registered images sorted by name; every ``llff_hold``-th
  (indices 0, 8, 16, ...) is a test view; the ``n_views`` training views are
  ``round(linspace(0, len(rest) - 1, n_views))`` of the rest (Python's ``round``, as the few-view papers'
  code); ``n_val`` validation views are spread the same way over the rest's images not used for
  training, never over test views. ``Scene.view_ids`` are the training views' indices into the rest.
* Normalisation: from the training cameras' centres (:func:`src.data.normalise.fit_camera_normalisation`):
  x' = (x - their mean) / (1.1 x the largest distance of one from it); the model's 3D points get the same
  transform and are kept in ``Scene.meta["points"]`` ([P, 3]) with their colours in
  ``Scene.meta["point_colors"]`` ([P, 3], sRGB in [0, 1]) for ``init=sfm``. The content of an unbounded
  capture extends beyond [-1, 1]^3 (no contraction).
* Background: the photos cover every pixel, so the background colour only fills what no splat covers
  in a render; black by default (3DGS's choice for real scenes).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from src.core.cameras import Camera
from src.data.base import DatasetError, DatasetReader, Scene, View
from src.data.blender import parse_background
from src.data.detect import check_root, detect_format
from src.data.dnerf import scene_meta, strided
from src.data.images import composite, read_image, resize_premultiplied
from src.data.normalise import cameras_extent, fit_camera_normalisation, normalise_camera
from src.data.validate import check_int, check_number, check_pose, check_size, inside_root

log = logging.getLogger(__name__)

MODEL_FILES = ("cameras", "images", "points3D")
#: Files pycolmap 4 also reads when present (rigs and frames of the newer model layout).
EXTRA_MODEL_FILES = ("rigs", "frames")
MODEL_EXTENSIONS = (".bin", ".txt")
MODEL_FOLDERS = ("sparse/0", "sparse")
SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
INSTALL_HINT = 'pip install -e ".[colmap]"'


def import_pycolmap() -> ModuleType:
    """The pycolmap module, or DatasetError saying how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise DatasetError(f"dataset=colmap needs pycolmap, which is not installed: {INSTALL_HINT}") from None
    return pycolmap


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera of the model: focal lengths and principal point in pixels of a width x height image."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass(frozen=True)
class Entry:
    """One registered image of the model.

    Attributes:
        name: file name relative to ``images/`` as the model lists it.
        image_id, camera_id: COLMAP's ids.
        world_to_cam: [4, 4] float64, OpenCV world-to-camera (COLMAP's ``cam_from_world``).
    """

    name: str
    image_id: int
    camera_id: int
    world_to_cam: Tensor


# -- the model files ---------------------------------------------------------------------------------
def find_model(root: Path) -> tuple[Path, str]:
    """(folder, extension) of the COLMAP model under ``root``: ``sparse/0`` first, then ``sparse``.

    Raises:
        DatasetError naming what is missing (a folder holding only some of the three files is named
        with the missing ones), or if a model file resolves outside ``root``.
    """
    partial: tuple[Path, str, list[str]] | None = None
    for sub in MODEL_FOLDERS:
        folder = root / sub
        if not folder.is_dir():
            continue
        for ext in MODEL_EXTENSIONS:
            present = [n for n in MODEL_FILES if (folder / f"{n}{ext}").is_file()]
            if len(present) == len(MODEL_FILES):
                for name in MODEL_FILES + EXTRA_MODEL_FILES:
                    path = folder / f"{name}{ext}"
                    if path.exists():
                        inside_root(root, path, str(folder), "COLMAP model file", f"{sub}/{name}{ext}")
                return folder, ext
            if present and partial is None:
                partial = (folder, ext, present)
    if partial is not None:
        folder, ext, present = partial
        missing = [f"{n}{ext}" for n in MODEL_FILES if n not in present]
        raise DatasetError(f"{folder}: COLMAP model without {', '.join(missing)} (found "
                           f"{', '.join(p + ext for p in present)}); a model needs cameras, images and points3D, "
                           "all .bin or all .txt")
    found = detect_format(root)
    hint = f"; it looks like a '{found}' dataset: use dataset={found}" if found not in (None, "colmap") else ""
    raise DatasetError(f"{root}: no COLMAP model: expected sparse/0/{{cameras,images,points3D}}.bin (or .txt, or "
                       "the same in sparse/) beside images/; build one from photos with "
                       f"`python -m src.data.sfm PHOTOS_DIR OUT_DIR`{hint}")


def read_model(folder: Path, ext: str) -> object:
    """The pycolmap ``Reconstruction`` in ``folder`` (binary or text by ``ext``); DatasetError if unreadable."""
    pycolmap = import_pycolmap()
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if ext == ".bin" else rec.read_text)(str(folder))
    except Exception as e:  # pycolmap raises ValueError, IndexError or RuntimeError for malformed files
        text = str(e).strip().splitlines()
        reason = text[0] if text else type(e).__name__
        raise DatasetError(f"{folder}: pycolmap cannot read the COLMAP model ({reason}); "
                           f"expected cameras, images and points3D{ext} as COLMAP writes them") from None
    return rec


def camera_intrinsics(camera: object, where: str, root: Path) -> Intrinsics:
    """The :class:`Intrinsics` of a pycolmap camera; DatasetError for a model with distortion or bad values.

    Args:
        camera: ``pycolmap.Camera``.
        where: the cameras file, for messages.
        root: ``dataset.root``, named in the undistortion command of the message.
    """
    cid, model = int(camera.camera_id), camera.model.name
    if model not in SUPPORTED_MODELS:
        raise DatasetError(
            f"{where}: camera {cid} has model {model}; dataset=colmap takes {' and '.join(SUPPORTED_MODELS)} "
            f"cameras only (no lens distortion): undistort first with `python -m src.data.sfm --undistort {root} "
            f"{root}_undistorted` (or `colmap image_undistorter`) and set dataset.root to the result")
    field = f"camera {cid}"
    fx = check_number(camera.focal_length_x, where, f"{field}.fx", "a focal length > 0", lambda x: x > 0)
    fy = check_number(camera.focal_length_y, where, f"{field}.fy", "a focal length > 0", lambda x: x > 0)
    width = check_int(camera.width, where, f"{field}.width", minimum=1)
    height = check_int(camera.height, where, f"{field}.height", minimum=1)
    cx = check_number(camera.principal_point_x, where, f"{field}.cx", f"a principal point in (0, {width})",
                      lambda x: 0 < x < width)
    cy = check_number(camera.principal_point_y, where, f"{field}.cy", f"a principal point in (0, {height})",
                      lambda x: 0 < x < height)
    return Intrinsics(fx, fy, cx, cy, width, height)


def model_entries(rec: object, where: str) -> list[Entry]:
    """The registered images of ``rec`` (a pycolmap ``Reconstruction``) sorted by name; poses checked rigid."""
    entries, unposed = [], 0
    for image_id, image in rec.images.items():
        if not image.has_pose:
            unposed += 1
            continue
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3] = torch.from_numpy(np.asarray(image.cam_from_world().matrix(), dtype=np.float64))  # [3, 4]
        check_pose(w2c, f"{where}: image {image_id} ({image.name})", "cam_from_world")
        entries.append(Entry(str(image.name), int(image_id), int(image.camera_id), w2c))
    if unposed:
        log.warning("%s: %d image(s) without a pose (not registered) are left out", where, unposed)
    return sorted(entries, key=lambda e: e.name)


def model_points(rec: object) -> tuple[Tensor, Tensor]:
    """(xyz [P, 3] float64 world coordinates, rgb [P, 3] float32 sRGB in [0, 1]) of the model's 3D points."""
    points = list(rec.points3D.values())
    if not points:
        return torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3)
    xyz = torch.from_numpy(np.stack([np.asarray(p.xyz, dtype=np.float64) for p in points]))        # [P, 3]
    rgb = torch.from_numpy(np.stack([np.asarray(p.color, dtype=np.float32) for p in points])) / 255.0  # [P, 3]
    return xyz, rgb


# -- the split -----------------------------------------------------------------------------------------
def spread(n_total: int, n_keep: int | None) -> list[int]:
    """``round(linspace(0, n_total - 1, n_keep))`` (all of range(n_total) for None), the few-view papers' rule."""
    if n_keep is None:
        return list(range(n_total))
    if n_keep == 0 or n_total == 0:
        return []
    if n_keep == 1:
        return [0]
    picks = [round(float(x)) for x in np.linspace(0, n_total - 1, n_keep)]
    if n_keep > n_total or len(set(picks)) != n_keep:
        raise ValueError(f"cannot spread {n_keep} picks over {n_total} items")
    return picks


@dataclass(frozen=True)
class Split:
    """Indices of the LLFF sparse split of n images sorted by name.

    Attributes:
        test: indices into the sorted images (0, hold, 2 hold, ...).
        rest: indices into the sorted images of the others (the training pool).
        train, val: positions in ``rest`` of the training and validation views.
    """

    test: list[int]
    rest: list[int]
    train: list[int]
    val: list[int]


def llff_split(n_images: int, n_views: int | None, n_val: int | None = 0, hold: int = 8, where: str = "") -> Split:
    """The LLFF sparse split (module docstring); DatasetError if there are too few images for it."""
    test = list(range(0, n_images, hold))
    rest = [i for i in range(n_images) if i % hold != 0]
    if not rest:
        raise DatasetError(f"{where}: {n_images} registered image(s) leave no training view after holding out every "
                           f"{hold}th for testing; the split needs at least 2")
    if n_views is not None and not 1 <= n_views <= len(rest):
        raise DatasetError(f"dataset.n_views={n_views} must be between 1 and the {len(rest)} training images ({where}: "
                           f"{n_images} registered, every {hold}th held out for testing)")
    train = spread(len(rest), n_views)
    left = [k for k in range(len(rest)) if k not in train]
    if n_val is not None and n_val > len(left):
        log.warning("%s: dataset.n_val=%d but only %d training-pool image(s) are left after the %d training views: "
                    "all of them are validation views", where, n_val, len(left), len(train))
        n_val = len(left)
    val = [left[k] for k in spread(len(left), n_val)]
    return Split(test=test, rest=rest, train=train, val=val)


# -- the images ------------------------------------------------------------------------------------------
def image_folder(root: Path, downscale: float) -> tuple[str, bool]:
    """(folder name, prescaled): ``images_N`` if downscale is an integer N > 1 and ``root/images_N`` exists."""
    n = round(downscale)
    if downscale > 1 and math.isclose(downscale, n) and (root / f"images_{n}").is_dir():
        return f"images_{n}", True
    return "images", False


def image_file(root: Path, folder: str, entry: Entry, where: str) -> Path:
    """The file of ``entry`` in ``root/folder``, resolved inside ``root``; DatasetError if missing."""
    path = inside_root(root, root / folder / entry.name, where, "image", f"{folder}/{entry.name}")
    if not path.is_file():
        raise DatasetError(f"{where}: image '{entry.name}' (image id {entry.image_id}) is listed in the model but "
                           f"missing: {root / folder / entry.name}")
    return path


def view_name(name: str) -> str:
    """A camera name for logs and render files: the image name without extension, '/' replaced by '_'."""
    return Path(name).with_suffix("").as_posix().replace("/", "_")


def load_rgb(path: Path, background: Tensor) -> Tensor:
    """[H, W, 3] float in [0, 1] of an image file (grey repeated, alpha composited on ``background``)."""
    img = read_image(path)  # [H, W, C]
    channels = img.shape[-1]
    if channels == 1:
        return img.expand(*img.shape[:2], 3).contiguous()
    if channels == 3:
        return img
    if channels == 4:
        return composite(img, background)[0].contiguous()
    raise DatasetError(f"{path}: expected a grey, RGB or RGBA image, got {channels} channels")


def sized_image(path: Path, intr: Intrinsics, prescaled: bool, downscale: float,
                background: Tensor) -> tuple[Tensor, float, float]:
    """(image [h, w, 3], sx, sy): the image at the requested scale and its scale factors from the model's camera.

    ``prescaled`` images (``images_N/``) must be the model's size / N to within a pixel; full-size images
    the model's size exactly (then area-resized by ``downscale``).
    """
    raw = read_image(path)
    h, w = raw.shape[:2]
    if prescaled:
        if abs(w - intr.width / downscale) > 1 or abs(h - intr.height / downscale) > 1:
            raise DatasetError(f"{path}: image is {w}x{h} px; its camera is {intr.width}x{intr.height}, so images_"
                               f"{round(downscale)}/ should hold {intr.width / downscale:.0f}x"
                               f"{intr.height / downscale:.0f} px images")
        return load_rgb(path, background), w / intr.width, h / intr.height
    if (w, h) != (intr.width, intr.height):
        raise DatasetError(f"{path}: image is {w}x{h} px but its camera in the model is {intr.width}x{intr.height}; "
                           "the photos must be the ones the model was built from (or undistorted with it)")
    if downscale == 1.0:
        return load_rgb(path, background), 1.0, 1.0
    th, tw = round(h / downscale), round(w / downscale)
    check_size(th, tw, str(path), downscale)
    if raw.shape[-1] == 4:
        img = composite(resize_premultiplied(raw, (th, tw)), background)[0]
    else:
        rgb = load_rgb(path, background)
        img = F.interpolate(rgb.permute(2, 0, 1)[None], (th, tw), mode="area")[0].permute(1, 2, 0)
    return img.contiguous(), tw / w, th / h


def read_view(root: Path, folder: str, prescaled: bool, entry: Entry, intr: Intrinsics, downscale: float,
              background: Tensor, index: int, where: str) -> View:
    """The :class:`View` of ``entry``: its image and OpenCV camera (float64 pose, world units)."""
    image, sx, sy = sized_image(image_file(root, folder, entry, where), intr, prescaled, downscale, background)
    cam = Camera(world_to_cam=entry.world_to_cam.clone(), fx=intr.fx * sx, fy=intr.fy * sy, cx=intr.cx * sx,
                 cy=intr.cy * sy, width=int(image.shape[1]), height=int(image.shape[0]), name=view_name(entry.name))
    return View(camera=cam, image=image, mask=None, image_id=index)


# -- the reader --------------------------------------------------------------------------------------------
class ColmapDataset(DatasetReader):
    """Reader for a COLMAP sparse model beside its photos, with the LLFF sparse-view split.

    Args:
        root: capture folder holding ``images/`` and ``sparse/0/`` (or ``sparse/``).
        n_views: training views spread evenly over the non-test images (3 / 6 / 9 in the few-view
            literature); None = all of them.
        downscale: image downscale factor N (``images_N/`` when present, else resized from ``images/``).
        background: colour of what no splat covers (``black`` default, ``white``, ``grey`` or [r, g, b]).
        llff_hold: every ``llff_hold``-th image by name is a test view (LLFF: 8).
        n_test: keep ``n_test`` evenly strided test views (None = all).
        n_val: validation views from the non-test images left after the training views (0 = none,
            None = all of them).
        normalise: put the training camera centres into the unit ball (module docstring).
    """

    def __init__(self, root: str, n_views: int | None = 3, downscale: float = 1.0,
                 background: str | list[float] = "black", llff_hold: int = 8, n_test: int | None = None,
                 n_val: int | None = 0, normalise: bool = True) -> None:
        self.root = check_root(root)
        if downscale <= 0:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0")
        if llff_hold < 2:
            raise DatasetError(f"dataset.llff_hold={llff_hold} must be >= 2 (every llff_hold-th image is a test view)")
        self.n_views = n_views
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.llff_hold = int(llff_hold)
        self.n_test = n_test
        self.n_val = n_val
        self.normalise = normalise

    def load(self) -> Scene:
        """Read the model and the split's images; cameras and 3D points normalised together."""
        folder, ext = find_model(self.root)
        rec = read_model(folder, ext)
        images_file = str(folder / f"images{ext}")
        entries = model_entries(rec, images_file)
        if not entries:
            raise DatasetError(f"{images_file}: the model registers no image")
        cameras_file = str(folder / f"cameras{ext}")
        intr = {cid: camera_intrinsics(rec.cameras[cid], cameras_file, self.root)
                for cid in sorted({e.camera_id for e in entries})}
        image_dir, prescaled = image_folder(self.root, self.downscale)
        for e in entries:  # every listed image, before any is read
            image_file(self.root, image_dir, e, images_file)
        split = llff_split(len(entries), self.n_views, self.n_val, self.llff_hold, images_file)
        test_ids = [split.test[k] for k in strided(len(split.test), self.n_test)]

        def views(indices: list[int], positions: list[int]) -> list[View]:
            """Views of the sorted entries ``indices``, numbered by ``positions`` within their split."""
            return [read_view(self.root, image_dir, prescaled, entries[i], intr[entries[i].camera_id], self.downscale,
                              self.background, p, images_file) for i, p in zip(indices, positions, strict=True)]

        train = views([split.rest[k] for k in split.train], split.train)
        val = views([split.rest[k] for k in split.val], split.val)
        test = views(test_ids, [split.test.index(i) for i in test_ids])
        points, colors = model_points(rec)
        norm = {"center": [0.0, 0.0, 0.0], "scale": 1.0}
        if self.normalise:
            center, scale = fit_camera_normalisation([v.camera for v in train], where=images_file)
            for v in (*train, *val, *test):
                v.camera = normalise_camera(v.camera, center, scale)
            points = scale * (points - center)
            norm = {"center": center.tolist(), "scale": scale}
        for v in (*train, *val, *test):
            v.camera = v.camera.to(dtype=torch.float32)
        names = [e.name for e in entries]
        meta = scene_meta("colmap", self.root, train, model=str(folder), n_images=len(entries), image_folder=image_dir,
                          train_names=[names[split.rest[k]] for k in split.train],
                          val_names=[names[split.rest[k]] for k in split.val], test_names=[names[i] for i in test_ids],
                          points=points.to(torch.float32), point_colors=colors,
                          points_file=str(folder / f"points3D{ext}"))
        return Scene(name=self.root.name, train=train, val=val, test=test, background=self.background,
                     view_ids=list(split.train), n_frames=1, normalisation=norm,
                     extent=cameras_extent([v.camera for v in train]), meta=meta)
