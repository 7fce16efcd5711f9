"""OwlII reader in the ResFields / NeuS layout, plus the NeuS/IDR camera helpers DTU shares.

Layout: ``<root>/cam_train_<k>/`` (training cameras) and ``<root>/cam_test*/`` (held-out cameras),
each with ``rgb/*.png`` (or ``image/*.png``), ``mask/*.png`` and ``cameras_sphere.npz`` holding, for
the i-th image of the folder (sorted file names, the NeuS convention), ``world_mat_i`` = K [R | t]
(OpenCV: world -> pixels, 3x4 or padded 4x4) and ``scale_mat_i`` (maps the unit sphere onto a sphere
around the object: x_world = scale_mat @ x_unit). ``P = world_mat @ scale_mat`` is decomposed (RQ,
:func:`decompose_projection`) into K and the OpenCV world-to-camera pose of the unit-sphere frame.

Normalisation: the data is already normalised by ``scale_mat`` (the object is inside the unit sphere,
hence inside [-1, 1]^3), so no visual-hull fit is done; ``Scene.normalisation`` records the
equivalent similarity (center = scale_mat[:3, 3], scale = 1 / scale_mat[0, 0]).

Time: frame index / (n_frames - 1), frame id = index of the image in its sorted folder. The frames are
the first ``frames`` images of every camera folder (all folders must hold the same number).
"""

from __future__ import annotations

import logging
import re
import zipfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from src.core.cameras import Camera
from src.data.base import DatasetError, DatasetReader, Scene, View
from src.data.blender import parse_background
from src.data.detect import check_format, check_root
from src.data.dnerf import scene_meta, strided
from src.data.images import read_image
from src.data.normalise import cameras_extent
from src.data.validate import check_array, check_size, inside_root
from src.data.views import select_views

log = logging.getLogger(__name__)

#: ResFields' 4-view OwlII protocol (``n_views=4``).
OWLII_4_VIEWS = ["cam_train_1", "cam_train_3", "cam_train_6", "cam_train_8"]
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
COMPOSITE_MODES = ("premultiplied", "straight", "none")


# -- NeuS / IDR cameras --------------------------------------------------------------------------
def rq3(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RQ decomposition of a 3x3 matrix: M = K @ R, K upper-triangular with positive diagonal, R orthogonal."""
    flip = np.eye(3)[::-1]  # reverses rows / columns
    q, r = np.linalg.qr((flip @ M).T)
    K = flip @ r.T @ flip
    R = flip @ q.T
    signs = np.diag(np.sign(np.where(np.diag(K) == 0, 1.0, np.diag(K))))
    return K @ signs, signs @ R


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 (or padded 4x4) projection P ~ K [R | t] into K [3, 3] (K[2, 2] = 1) and w2c [4, 4].

    OpenCV convention: the camera looks along +z (points in front have positive depth), x right,
    y down. P is defined up to scale, including sign: if det(R) < 0 the sign of P is flipped.
    """
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    K, R = rq3(P[:, :3])
    p4 = P[:, 3].copy()
    if np.linalg.det(R) < 0:
        R, p4 = -R, -p4
    t = np.linalg.solve(K, p4)
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    return K / K[2, 2], w2c


def load_npz(path: Path, root: Path | None = None) -> dict[str, np.ndarray]:
    """All arrays of an npz file (DatasetError naming the file if missing, unreadable or outside ``root``)."""
    if root is not None:
        inside_root(root, path, str(path.parent), "camera file", path.name)
    if not path.is_file():
        raise DatasetError(f"camera file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise DatasetError(f"cannot read {path}: {e}") from e


def check_projection(world: np.ndarray, scale: np.ndarray, npz_path: Path, i: int) -> np.ndarray:
    """``P = world_mat_i @ scale_mat_i`` [4, 4], checked to be a pinhole projection.

    Raises:
        DatasetError unless scale_mat_i has a positive scale and P a full-rank 3x3 block.
    """
    S = np.eye(4)
    S[: scale.shape[0]] = scale
    det_s = float(np.linalg.det(S[:3, :3]))
    if not det_s > 0:
        raise DatasetError(f"{npz_path}: 'scale_mat_{i}' has a 3x3 block with determinant {det_s:.4g}, expected a "
                           "positive scale (x_world = scale_mat @ x_unit)")
    W = np.eye(4)
    W[:3] = world[:3]
    P = W @ S
    block = P[:3, :3]
    if abs(float(np.linalg.det(block))) <= 1e-12 * max(float(np.abs(block).max()), 1e-300) ** 3:
        raise DatasetError(f"{npz_path}: 'world_mat_{i}' @ 'scale_mat_{i}' has a singular 3x3 block, expected a "
                           "pinhole projection K [R | t] with positive focal lengths")
    return P


def neus_cameras(npz_path: Path, n_images: int, folder: Path,
                 root: Path | None = None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(K [3, 3], w2c [4, 4] in the unit-sphere frame, scale_mat [4, 4]) of images 0..n_images-1.

    ``root``: the dataset folder the npz file must lie in (default: ``folder``).
    """
    cams = load_npz(npz_path, folder if root is None else root)
    mats: dict[str, np.ndarray] = {}
    for i in range(n_images):
        for key in (f"world_mat_{i}", f"scale_mat_{i}"):
            if key not in cams:
                raise DatasetError(f"{npz_path}: missing '{key}' (needed for image {i} of {folder})")
            mats[key] = check_array(cams[key], str(npz_path), key, ((4, 4), (3, 4)))
    n_mats = len([k for k in cams if re.fullmatch(r"world_mat_\d+", k)])
    if n_mats != n_images:
        raise DatasetError(f"{npz_path}: {n_mats} world_mat_* entries but {n_images} images in {folder} "
                           "(cameras and images must match one to one)")
    out = []
    for i in range(n_images):
        P = check_projection(mats[f"world_mat_{i}"], mats[f"scale_mat_{i}"], npz_path, i)
        K, w2c = decompose_projection(P)
        S = np.eye(4)
        S[: mats[f"scale_mat_{i}"].shape[0]] = mats[f"scale_mat_{i}"]
        out.append((K, w2c, S))
    return out


def scale_mat_normalisation(S: np.ndarray, where: str) -> dict:
    """``{"center", "scale"}`` equivalent to the unit-sphere frame x_unit = S^-1 x_world (S a similarity)."""
    A = S[:3, :3]
    r = float(np.cbrt(abs(np.linalg.det(A))))
    if not np.allclose(A, r * np.eye(3), rtol=1e-5, atol=1e-8 * max(r, 1.0)):
        log.warning("%s: scale_mat is not an isotropic scale + translation; Scene.normalisation records "
                    "its mean scale only", where)
    return {"center": S[:3, 3].tolist(), "scale": 1.0 / r}


def skew_warning(K: np.ndarray, where: str) -> None:
    if abs(K[0, 1]) > 1e-3 * abs(K[0, 0]):
        log.warning("%s: intrinsics have skew %.4g, which the pinhole Camera ignores", where, K[0, 1])


# -- images --------------------------------------------------------------------------------------
def list_images(folder: Path) -> list[Path]:
    """Image files of ``folder`` in sorted-name order."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []


def _area_resize(x: Tensor, size: tuple[int, int]) -> Tensor:
    """[H, W, C] -> [h, w, C] area resampling."""
    return F.interpolate(x.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)


def load_rgb_mask(image_path: Path, mask_path: Path | None, background: Tensor, downscale: float,
                  composite: str = "premultiplied") -> tuple[Tensor, Tensor | None, tuple[int, int]]:
    """(rgb [h, w, 3] on ``background``, mask [h, w] or None, original (H, W)) of one view.

    ``composite``: how the stored RGB relates to the mask: ``premultiplied`` (RGB rendered over black,
    e.g. this project's renders: out = rgb + bg * (1 - m)), ``straight`` (ResFields/NeuS formula:
    out = rgb * m + bg * (1 - m)) or ``none`` (keep the image as stored). An RGBA image without a
    mask file uses its alpha as mask, composited as straight alpha.
    """
    if composite not in COMPOSITE_MODES:
        raise DatasetError(f"dataset.composite={composite!r}: expected one of {COMPOSITE_MODES}")
    img = read_image(image_path)
    if img.shape[-1] not in (1, 3, 4):
        raise DatasetError(f"{image_path}: expected a grey, RGB or RGBA image, got {img.shape[-1]} channels")
    if img.shape[-1] == 1:
        img = img.expand(-1, -1, 3)
    mask = None
    mode = composite
    if mask_path is not None:
        m = read_image(mask_path)
        if m.shape[:2] != img.shape[:2]:
            raise DatasetError(f"{mask_path}: mask size {tuple(m.shape[:2])} differs from {image_path.name}'s "
                               f"{tuple(img.shape[:2])}")
        mask = m[..., 0]
    elif img.shape[-1] == 4:
        mask, mode = img[..., 3], "straight"
    h, w = img.shape[:2]
    rgb = img[..., :3]
    if downscale != 1.0:
        size = (round(h / downscale), round(w / downscale))
        check_size(size[0], size[1], str(image_path), downscale)
        if mode == "straight" and mask is not None:  # resample premultiplied colour, then un-premultiply
            pre = _area_resize(torch.cat([rgb * mask[..., None], mask[..., None]], -1), size)
            mask = pre[..., 3]
            rgb = torch.where(mask[..., None] > 0, pre[..., :3] / mask[..., None].clamp_min(1e-8), 0.0)
        else:
            rgb = _area_resize(rgb, size)
            mask = None if mask is None else _area_resize(mask[..., None], size)[..., 0]
    if mask is not None and mode != "none":
        m = mask[..., None]
        rgb = rgb + background * (1 - m) if mode == "premultiplied" else rgb * m + background * (1 - m)
    return rgb.clamp(0, 1).contiguous(), None if mask is None else mask.clamp(0, 1).contiguous(), (h, w)


def folder_frames(cam_dir: Path, need_masks: bool = True,
                  root: Path | None = None) -> tuple[list[Path], list[Path] | None]:
    """(images, masks) of a NeuS camera folder (``rgb/`` or ``image/``, ``mask/``), matched by position.

    Every file must lie (symlinks followed) inside ``root``, the dataset folder (default: ``cam_dir``).
    """
    img_dir = next((cam_dir / d for d in ("rgb", "image") if (cam_dir / d).is_dir()), None)
    if img_dir is None:
        raise DatasetError(f"{cam_dir}: no 'rgb/' or 'image/' folder")
    images = list_images(img_dir)
    if not images:
        raise DatasetError(f"{img_dir}: no images")
    masks = list_images(cam_dir / "mask")
    base = cam_dir if root is None else root
    for path in images:
        inside_root(base, path, str(img_dir), "image", path.name)
    for path in masks:
        inside_root(base, path, str(cam_dir / "mask"), "mask", path.name)
    if not masks:
        if need_masks:
            raise DatasetError(f"{cam_dir / 'mask'}: masks missing (one mask/*.png per image is needed)")
        return images, None
    if len(masks) != len(images):
        raise DatasetError(f"{cam_dir}: {len(images)} images in {img_dir.name}/ but {len(masks)} masks in mask/")
    return images, masks


def neus_view(K: np.ndarray, w2c: np.ndarray, image: Path, mask: Path | None, background: Tensor,
              downscale: float, composite: str, image_id: int, **cam_kw) -> View:
    """A View from a decomposed NeuS camera and its image / mask files."""
    rgb, m, (h, w) = load_rgb_mask(image, mask, background, downscale, composite)
    skew_warning(K, str(image))
    cam = Camera(world_to_cam=torch.from_numpy(w2c).float(), fx=float(K[0, 0]), fy=float(K[1, 1]),
                 cx=float(K[0, 2]), cy=float(K[1, 2]), width=w, height=h, **cam_kw)
    if (rgb.shape[0], rgb.shape[1]) != (h, w):
        cam = cam.scaled(rgb.shape[1] / w)
    return View(camera=cam, image=rgb, mask=m, image_id=image_id)


def _cam_index(name: str) -> int:
    m = re.search(r"(\d+)$", name)
    return int(m.group(1)) if m else 0


# -- the reader ----------------------------------------------------------------------------------
class OwliiDataset(DatasetReader):
    """Reader for OwlII-like multi-view video in the ResFields / NeuS layout.

    Args:
        root: scene folder holding ``cam_train_<k>/`` and ``cam_test*/`` folders.
        n_views: number of training cameras: None = all (or ``train_cameras``), 4 = the ResFields
            protocol (cam_train_1, 3, 6, 8), another count = K-means on the camera centres.
        train_cameras: explicit training camera folder names (overrides ``n_views``' choice).
        test_cameras: test camera folder names (None = every ``cam_test*`` folder).
        frames: keep the first ``frames`` frames (None = all).
        downscale: image downscale factor (2 = half resolution).
        background: ``white`` (default, as ResFields), ``black``, ``grey`` or [r, g, b].
        composite: ``premultiplied`` (RGB stored over black, this project's renders), ``straight``
            (ResFields' rgb * mask + bg * (1 - mask)) or ``none``.
        view_seed: seed of the K-means camera choice.
        n_test_frames: evenly spread test frames per test camera (None = all).
        n_test: then keep this many evenly strided test views (None = all).
        camera_ids: training camera numbers k of ``cam_train_<k>`` (the experiments' protocol key, e.g.
            [1, 3, 6, 8]); an alternative to ``train_cameras``.
    """

    def __init__(self, root: str, n_views: int | None = None, train_cameras: list[str] | None = None,
                 test_cameras: list[str] | None = None, frames: int | None = None, downscale: float = 1.0,
                 background: str | list[float] = "white", composite: str = "premultiplied", view_seed: int = 0,
                 n_test_frames: int | None = None, n_test: int | None = None,
                 camera_ids: list[int] | None = None) -> None:
        self.root = check_root(root)
        if camera_ids is not None:  # the experiments' camera numbers, e.g. [1, 3, 6, 8] -> cam_train_1, ...
            if train_cameras is not None:
                raise DatasetError("dataset.camera_ids and dataset.train_cameras both set: give one of them")
            if not all(isinstance(c, int) and c >= 0 for c in camera_ids):
                raise DatasetError(f"dataset.camera_ids={list(camera_ids)}: expected non-negative integers")
            train_cameras = [f"cam_train_{int(c)}" for c in camera_ids]
        if downscale <= 0:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0")
        if composite not in COMPOSITE_MODES:
            raise DatasetError(f"dataset.composite={composite!r}: expected one of {COMPOSITE_MODES}")
        if frames is not None and frames < 1:
            raise DatasetError(f"dataset.frames={frames} must be >= 1 (or null for all)")
        self.n_views = n_views
        self.train_cameras = None if train_cameras is None else [str(c) for c in train_cameras]
        self.test_cameras = None if test_cameras is None else [str(c) for c in test_cameras]
        self.frames = frames
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.composite = composite
        self.view_seed = view_seed
        self.n_test_frames = n_test_frames
        self.n_test = n_test

    def _folders(self, pattern: str) -> list[str]:
        return sorted((d.name for d in self.root.glob(pattern) if d.is_dir()), key=lambda n: (_cam_index(n), n))

    def _camera_folder(self, name: str) -> tuple[list, list[Path], list[Path]]:
        d = self.root / name
        inside_root(self.root, d, str(self.root), "camera folder", name)
        if not d.is_dir():
            raise DatasetError(f"camera folder not found: {d}")
        images, masks = folder_frames(d, root=self.root)
        return neus_cameras(d / "cameras_sphere.npz", len(images), d, self.root), images, masks

    def select_cameras(self, available: list[str]) -> list[str]:
        """Training camera folders (see ``n_views`` / ``train_cameras``)."""
        if self.train_cameras is not None:
            if self.n_views is not None and self.n_views != len(self.train_cameras):
                raise DatasetError(f"dataset.n_views={self.n_views} but dataset.train_cameras lists "
                                 f"{len(self.train_cameras)} cameras")
            return list(self.train_cameras)
        if self.n_views is None or self.n_views == len(available):
            return available
        if self.n_views == 4 and all(c in available for c in OWLII_4_VIEWS):
            return list(OWLII_4_VIEWS)
        centres = []
        for name in available:
            d = self.root / name
            _, w2c, _ = neus_cameras(d / "cameras_sphere.npz", len(folder_frames(d, root=self.root)[0]), d,
                                     self.root)[0]
            centres.append(-w2c[:3, :3].T @ w2c[:3, 3])
        return [available[i] for i in select_views(np.stack(centres), self.n_views, seed=self.view_seed)]

    def load(self) -> Scene:
        """Read the scene: every (kept) frame of the training cameras, test cameras, unit-sphere frame."""
        check_format(self.root, "owlii")
        available = self._folders("cam_train*")
        cams = self.select_cameras(available)
        loaded = {name: self._camera_folder(name) for name in cams}
        counts = {name: len(v[1]) for name, v in loaded.items()}
        if len(set(counts.values())) != 1:
            raise DatasetError(f"{self.root}: training cameras hold different numbers of frames: {counts}")
        n_total = next(iter(counts.values()))
        n_frames = min(self.frames or n_total, n_total)

        def time_of(fid: int) -> float:
            return fid / (n_frames - 1) if n_frames > 1 else 0.0

        train: list[View] = []
        view_ids: list[int] = []
        for name in cams:
            cam_list, images, masks = loaded[name]
            k = _cam_index(name)
            for fid in range(n_frames):
                K, w2c, _ = cam_list[fid]
                train.append(neus_view(K, w2c, images[fid], masks[fid], self.background, self.downscale,
                                       self.composite, fid, time=time_of(fid), frame_id=fid,
                                       name=f"{name}/{images[fid].stem}", camera_id=k))
                view_ids.append(available.index(name) * n_total + fid if name in available else -1)
        test_names = self.test_cameras if self.test_cameras is not None else self._folders("cam_test*")
        test: list[View] = []
        for name in test_names:
            cam_list, images, masks = self._camera_folder(name)
            if len(images) < n_frames:
                raise DatasetError(f"{self.root / name}: {len(images)} frames, fewer than the {n_frames} used")
            for fid in strided(n_frames, self.n_test_frames):
                K, w2c, _ = cam_list[fid]
                test.append(neus_view(K, w2c, images[fid], masks[fid], self.background, self.downscale,
                                      self.composite, fid, time=time_of(fid), frame_id=fid,
                                      name=f"{name}/{images[fid].stem}", camera_id=_cam_index(name)))
        test = [test[i] for i in strided(len(test), self.n_test)]
        S0 = loaded[cams[0]][0][0][2]
        if any(not np.allclose(c[2], S0) for v in loaded.values() for c in v[0][:n_frames]):
            log.warning("%s: scale_mat differs between images; each image uses its own, "
                        "Scene.normalisation records the first", self.root)
        norm = scale_mat_normalisation(S0, str(self.root / cams[0] / "cameras_sphere.npz"))
        return Scene(
            name=self.root.name, train=train, val=[], test=test, background=self.background,
            view_ids=view_ids, n_frames=n_frames, normalisation=norm,
            extent=cameras_extent([v.camera for v in train]),
            meta=scene_meta("owlii", self.root, train, train_cameras=cams, test_cameras=list(test_names),
                            n_frames=n_frames, frames_in_folder=n_total, composite=self.composite,
                            normalisation_source="scale_mat (unit sphere)"),
        )
