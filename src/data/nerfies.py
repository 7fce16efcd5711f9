"""Nerfies / HyperNeRF / NeRF-DS reader.

Layout:
* ``dataset.json``: ``{train_ids, val_ids}`` (the val ids are this reader's test views);
* ``metadata.json``: ``{id: {time_id | warp_id, camera_id, ...}}``;
* ``scene.json``: ``{scale, center, near, far}``: the Nerfies scene frame is ``scale * (world - center)``;
* ``camera/<id>.json``: ``orientation`` (3x3, rows = camera axes in world, i.e. world-to-camera
  rotation), ``position`` (camera centre, world), ``focal_length``, ``principal_point``,
  ``pixel_aspect_ratio`` (fy = focal * ratio), ``image_size`` [w, h] (of the 1x images), ``skew``,
  ``radial_distortion`` / ``tangential_distortion`` (ignored: a warning if non-zero);
* ``rgb/<s>x/<id>.png`` (``image_scale`` = s; the camera is scaled to the image size);
* optional masks: alpha of RGBA images, or ``mask/<s>x/<id>.png``.

Cameras: Nerfies projects ``local = orientation @ (p - position)``, ``pixel = focal * local.xy /
local.z + principal_point`` with pixel centres at +0.5, i.e. exactly OpenCV (x right, y down,
z forward): world_to_cam = [orientation | -orientation @ position].

Normalisation: scene.json's ``scale``/``center`` is always applied. With masks for every training
view (and ``normalise``), a windowed visual-hull fit into [-0.9, 0.9]^3 is composed on top (as for
D-NeRF); without masks, scene.json alone defines the frame (masks are None; NeRF-DS has none).

Time: ``frame_id`` = ``time_id`` (``warp_id`` if absent); ``n_frames`` = 1 + the largest training
time id; ``time`` = frame_id / (n_frames - 1). Test time ids beyond the training range are clamped
to the last training frame (warning).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from src.core.cameras import Camera
from src.data.base import DatasetError, DatasetReader, Scene, View, read_json
from src.data.blender import parse_background
from src.data.detect import check_format, check_root
from src.data.dnerf import apply_normalisation, fit_dynamic_normalisation, hull_groups, scene_meta, strided
from src.data.normalise import cameras_extent
from src.data.owlii import COMPOSITE_MODES, IMAGE_SUFFIXES, load_rgb_mask
from src.data.validate import check_int, check_list, check_matrix, check_number, inside_root, kind_of, shown

log = logging.getLogger(__name__)


def optional_numbers(cam: dict, key: str, where: str) -> list[float]:
    """The numbers of the optional list ``cam[key]`` (empty if absent); DatasetError naming any bad entry."""
    values = check_list(cam.get(key, []), where, key)
    return [check_number(x, where, f"{key}[{k}]") for k, x in enumerate(values)]


def nerfies_intrinsics(cam: dict, where: str) -> dict:
    """fx, fy, cx, cy, width, height of a Nerfies camera JSON, every value type-checked."""
    size = check_list(cam["image_size"], where, "image_size", 2)
    w, h = (check_int(x, where, f"image_size[{k}]", minimum=1) for k, x in enumerate(size))
    f = check_number(cam["focal_length"], where, "focal_length", "a focal length in pixels > 0", lambda x: x > 0)
    cx, cy = w / 2.0, h / 2.0
    if "principal_point" in cam:
        cx, cy = check_matrix(cam["principal_point"], where, "principal_point", (2,)).tolist()
    aspect = 1.0
    if "pixel_aspect_ratio" in cam:
        aspect = check_number(cam["pixel_aspect_ratio"], where, "pixel_aspect_ratio", "a ratio > 0", lambda x: x > 0)
    return {"fx": f, "fy": f * aspect, "cx": cx, "cy": cy, "width": w, "height": h}


def nerfies_camera(path: Path, root: Path | None = None) -> tuple[torch.Tensor, dict]:
    """(world_to_cam [4, 4] float64, intrinsics dict) of a Nerfies camera JSON (OpenCV axes).

    ``root``: the dataset folder the file must lie in (default: the file's ``camera/`` folder's parent).
    """
    inside_root(path.parent.parent if root is None else root, path, str(path.parent), "camera file", path.name)
    cam = read_json(path, "camera file")
    where = str(path)
    for key in ("orientation", "position", "focal_length", "image_size"):
        if key not in cam:
            raise DatasetError(f"{path}: missing key '{key}'")
    R = check_matrix(cam["orientation"], where, "orientation", (3, 3)).numpy()
    c = check_matrix(cam["position"], where, "position", (3,)).numpy()
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
        raise DatasetError(f"{path}: 'orientation' is not a rotation matrix")
    intr = nerfies_intrinsics(cam, where)
    skew = check_number(cam.get("skew", 0.0), where, "skew")
    if abs(skew) > 1e-6:
        log.warning("%s: skew %s ignored (pinhole camera without skew)", path, skew)
    dist = [*optional_numbers(cam, "radial_distortion", where), *optional_numbers(cam, "tangential_distortion", where)]
    if any(abs(d) > 1e-9 for d in dist):
        log.warning("%s: lens distortion %s ignored (images are not undistorted)", path, dist)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.from_numpy(R)
    w2c[:3, 3] = torch.from_numpy(-R @ c)
    return w2c, intr


def read_scene_json(path: Path) -> dict:
    """``scale`` (> 0), ``center`` [3] and the optional ``near`` / ``far`` (0 <= near < far) of scene.json."""
    sc = read_json(path, "scene file")
    where = str(path)
    for key in ("scale", "center"):
        if key not in sc:
            raise DatasetError(f"{path}: missing key '{key}'")
    out = {"scale": check_number(sc["scale"], where, "scale", "a scale > 0", lambda x: x > 0),
           "center": check_matrix(sc["center"], where, "center", (3,)).tolist(),
           "near": None, "far": None}
    if sc.get("near") is not None:
        out["near"] = check_number(sc["near"], where, "near", "a distance >= 0", lambda x: x >= 0)
    if sc.get("far") is not None:
        near = out["near"] or 0.0
        out["far"] = check_number(sc["far"], where, "far", f"a distance > near ({near:g})", lambda x: x > near)
    return out


def read_ids(path: Path) -> dict[str, list[str]]:
    """``train_ids`` (non-empty) and ``val_ids`` of dataset.json: lists of non-empty strings."""
    ds = read_json(path, "dataset file")
    out: dict[str, list[str]] = {}
    for key in ("train_ids", "val_ids"):
        if key not in ds or not isinstance(ds[key], list):
            raise DatasetError(f"{path}: missing list '{key}'")
        for k, iid in enumerate(ds[key]):
            if not isinstance(iid, str) or not iid:
                raise DatasetError(f"{path}: {key}[{k}]={shown(iid)} is {kind_of(iid)}, expected a non-empty id "
                                   "string (the name of camera/<id>.json and rgb/<s>x/<id>.png)")
        out[key] = list(ds[key])
    if not out["train_ids"]:
        raise DatasetError(f"{path}: 'train_ids' is empty")
    return out


def frame_record(md: dict, iid: str, md_path: Path) -> dict:
    """``{frame_id, camera_id}`` of image ``iid`` from metadata.json (time_id, else warp_id; camera_id 0 if absent)."""
    if iid not in md:
        raise DatasetError(f"{md_path}: no entry for id '{iid}'")
    m = md[iid]
    if not isinstance(m, dict):
        raise DatasetError(f"{md_path}: '{iid}'={shown(m)} is {kind_of(m)}, expected an object with 'time_id'")
    tid = m.get("time_id", m.get("warp_id"))
    if isinstance(tid, bool) or not isinstance(tid, int) or tid < 0:
        raise DatasetError(f"{md_path}: '{iid}' needs a non-negative integer 'time_id' (or 'warp_id'), "
                           f"got {shown(tid)} ({kind_of(tid)})")
    return {"frame_id": tid, "camera_id": check_int(m.get("camera_id", 0), str(md_path), f"{iid}.camera_id")}


class NerfiesDataset(DatasetReader):
    """Reader for Nerfies-layout dynamic scenes (Nerfies, HyperNeRF, NeRF-DS).

    Args:
        root: scene folder holding ``dataset.json``, ``metadata.json``, ``scene.json``, ``camera/``, ``rgb/``.
        n_views: must be None (the training views are ``train_ids``).
        image_scale: which ``rgb/<s>x`` folder to read (1 = full resolution, 2 = half as NeRF-DS' 2x).
        downscale: extra downscale factor on top of ``image_scale``.
        background: colour the masked images are composited on (also recorded when there are no masks:
            ``black`` matches renders stored over black).
        composite: with a ``mask/`` folder: ``straight`` (rgb * m + bg * (1 - m)), ``premultiplied``
            (RGB over black) or ``none``.
        n_test: keep this many evenly strided test (``val_ids``) views (None = all).
        normalise: with masks, compose a windowed visual-hull fit into [-0.9, 0.9]^3 on top of scene.json.
        hull_min_views: views per hull window (consecutive time ids) for that fit.
    """

    def __init__(self, root: str, n_views: int | None = None, image_scale: int = 1, downscale: float = 1.0,
                 background: str | list[float] = "black", composite: str = "straight", n_test: int | None = None,
                 normalise: bool = True, hull_min_views: int = 4) -> None:
        self.root = check_root(root)
        self.n_views = n_views  # checked in load()
        if downscale <= 0 or image_scale < 1:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0 and image_scale={image_scale} >= 1")
        if composite not in COMPOSITE_MODES:
            raise DatasetError(f"dataset.composite={composite!r}: expected one of {COMPOSITE_MODES}")
        self.image_scale = int(image_scale)
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.composite = composite
        self.n_test = n_test
        self.normalise = normalise
        self.hull_min_views = int(hull_min_views)

    def _file(self, kind: str, iid: str) -> Path | None:
        """The ``<kind>/<s>x/<iid>.<ext>`` file (checked to lie inside the dataset), or None if there is none."""
        folder = self.root / kind / f"{self.image_scale}x"
        what = "image" if kind == "rgb" else "mask"
        inside_root(self.root, folder / iid, str(folder), what, iid)
        path = next((folder / f"{iid}{s}" for s in IMAGE_SUFFIXES if (folder / f"{iid}{s}").is_file()), None)
        if path is not None:
            inside_root(self.root, path, str(folder), what, path.name)
        return path

    def _image(self, iid: str) -> tuple[Path, Path | None]:
        img = self._file("rgb", iid)
        if img is None:
            raise DatasetError(f"image of id '{iid}' not found: {self.root / 'rgb' / f'{self.image_scale}x' / iid}.png")
        return img, self._file("mask", iid)

    def _json(self, name: str, what: str) -> Path:
        """``root / name`` once checked to lie inside the dataset folder."""
        inside_root(self.root, self.root / name, str(self.root), what, name)
        return self.root / name

    def _view(self, iid: str, k: int, meta: dict, n_frames: int, mask_files: bool) -> View:
        w2c, intr = nerfies_camera(self.root / "camera" / f"{iid}.json", self.root)
        img_path, mask_path = self._image(iid)
        rgb, mask, (h, w) = load_rgb_mask(img_path, mask_path if mask_files else None, self.background,
                                          self.downscale, self.composite)
        expected = (round(intr["height"] / self.image_scale), round(intr["width"] / self.image_scale))
        if abs(h - expected[0]) > 1 or abs(w - expected[1]) > 1:
            raise DatasetError(f"{img_path}: image size {(h, w)} does not match camera/{iid}.json image_size "
                               f"{[intr['width'], intr['height']]} at scale {self.image_scale}x")
        fid = min(meta["frame_id"], n_frames - 1)
        cam = Camera(world_to_cam=w2c.float(), **intr, time=fid / (n_frames - 1) if n_frames > 1 else 0.0,
                     frame_id=fid, name=iid, camera_id=meta["camera_id"])
        cam = cam.scaled(rgb.shape[1] / cam.width)
        return View(camera=cam, image=rgb, mask=mask, image_id=k)

    def load(self) -> Scene:
        """Read the scene: train_ids as training views, val_ids as test views, OpenCV cameras."""
        if self.n_views is not None:
            raise DatasetError(f"dataset.n_views={self.n_views}: the Nerfies layout defines its training views "
                             "(dataset.json train_ids); set dataset.n_views=null")
        check_format(self.root, "nerfies")
        ds = read_ids(self._json("dataset.json", "dataset file"))
        md_path = self._json("metadata.json", "metadata file")
        md = read_json(md_path, "metadata file")
        sc = read_scene_json(self._json("scene.json", "scene file"))
        meta = {iid: frame_record(md, iid, md_path) for iid in (*ds["train_ids"], *ds["val_ids"])}
        n_frames = 1 + max(meta[i]["frame_id"] for i in ds["train_ids"])
        beyond = [i for i in ds["val_ids"] if meta[i]["frame_id"] >= n_frames]
        if beyond:
            log.warning("%s: %d test ids have time ids beyond the training range: clamped to frame %d",
                        md_path, len(beyond), n_frames - 1)
        test_ids = [ds["val_ids"][k] for k in strided(len(ds["val_ids"]), self.n_test)] if ds["val_ids"] else []
        mask_files = all(self._image(i)[1] is not None for i in ds["train_ids"])
        train = [self._view(i, k, meta[i], n_frames, mask_files) for k, i in enumerate(ds["train_ids"])]
        test = [self._view(i, ds["val_ids"].index(i), meta[i], n_frames, mask_files) for i in test_ids]
        has_masks = all(v.mask is not None for v in train)
        center = torch.tensor(sc["center"], dtype=torch.float64)
        scale = sc["scale"]
        source = "scene.json"
        if has_masks and self.normalise:
            tmp = [View(camera=v.camera, image=v.image, mask=v.mask, image_id=v.image_id) for v in train]
            apply_normalisation(tmp, center.float(), scale)
            c2, s2 = fit_dynamic_normalisation(hull_groups(tmp, self.hull_min_views), where=str(self.root))
            center, scale = center + c2.double() / scale, scale * s2
            source = "scene.json + windowed visual hull"
        apply_normalisation([*train, *test], center.float(), scale)
        return Scene(
            name=self.root.name, train=train, val=[], test=test, background=self.background,
            view_ids=list(range(len(train))), n_frames=n_frames,
            normalisation={"center": center.tolist(), "scale": scale},
            extent=cameras_extent([v.camera for v in train]),
            meta=scene_meta("nerfies", self.root, train, n_frames=n_frames, image_scale=self.image_scale,
                            near=sc.get("near"), far=sc.get("far"), has_masks=has_masks,
                            normalisation_source=source),
        )

