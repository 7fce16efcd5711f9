"""Writers of tiny synthetic datasets in every format the readers support (for tests).

Each writer renders a few random splats (moving along +x over time for dynamic formats) with the
torch reference rasterizer from known OpenCV cameras and writes the files of one layout. It returns a
:class:`Truth` with the world-frame cameras (keyed by the name the reader gives the view) and the
splats, so tests can check that a reader recovers the cameras (up to the scene normalisation) and
that rendering the known splats through a loaded camera reproduces the loaded image.

The object sits off the origin (``CENTER``) so that normalisations are not trivial.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from src.core.cameras import Camera, look_at
from src.core.splats import Splats
from src.data.images import write_png
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_scene

CENTER = torch.tensor([0.4, -0.2, 0.3], dtype=torch.float64)  # world position of the object
VELOCITY = torch.tensor([0.35, 0.0, 0.1])  # displacement of every splat over t in [0, 1]
GL_FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass
class Truth:
    """What a writer wrote: world-frame OpenCV cameras by view name, and the splats."""

    cameras: dict[str, Camera] = field(default_factory=dict)
    base: Splats | None = None
    dynamic: bool = False
    extra: dict = field(default_factory=dict)

    def splats_at(self, t: float) -> Splats:
        """World-frame splats at time ``t`` (static scenes ignore ``t``)."""
        s = self.base
        if not self.dynamic:
            return s
        return Splats(means=s.means + float(t) * VELOCITY, scales=s.scales, quats=s.quats,
                      opacities=s.opacities, colors=s.colors)


def make_splats(seed: int = 0, n: int = 150) -> Splats:
    """Opaque-ish random splats around ``CENTER`` (radius ~0.3)."""
    s = random_scene(n, seed=seed, spread=0.22, scale_range=(0.03, 0.08))
    s.opacities = s.opacities.clamp_min(0.7)
    s.means = s.means + CENTER.float()
    return s


def orbit_cameras(n: int, size: tuple[int, int], seed: int = 0, radius: float = 3.0, fx: float | None = None,
                  fy: float | None = None, cx: float | None = None, cy: float | None = None,
                  elevation: tuple[float, float] = (0.2, 1.1)) -> list[Camera]:
    """``n`` OpenCV cameras around ``CENTER`` (random azimuth / elevation, +z world up), image ``size`` (w, h)."""
    w, h = size
    g = torch.Generator().manual_seed(seed)
    cams = []
    for i in range(n):
        az = 2 * math.pi * (i + 0.5 * float(torch.rand(1, generator=g))) / n
        el = elevation[0] + float(torch.rand(1, generator=g)) * (elevation[1] - elevation[0])
        eye = CENTER + radius * torch.tensor([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el),
                                              math.sin(el)], dtype=torch.float64)
        f = 1.2 * w
        cams.append(Camera(look_at(eye, CENTER), fx=fx or f, fy=fy or f, cx=w / 2 if cx is None else cx,
                           cy=h / 2 if cy is None else cy, width=w, height=h))
    return cams


_RAST = TorchRefRasterizer()


def render_rgba(splats: Splats, cam: Camera) -> torch.Tensor:
    """[H, W, 4] straight-alpha RGBA of ``splats`` seen by ``cam``."""
    with torch.no_grad():
        out = _RAST.render(splats, cam.to(dtype=torch.float32), torch.zeros(3))
    a = out.alpha.clamp(0, 1)
    rgb = torch.where(a[..., None] > 0, out.color / a[..., None].clamp_min(1e-6), out.color).clamp(0, 1)
    return torch.cat([rgb, a[..., None]], dim=-1)


def _premultiplied(rgba: torch.Tensor) -> torch.Tensor:
    return rgba[..., :3] * rgba[..., 3:]


def c2w_gl(cam: Camera) -> list[list[float]]:
    """Blender/OpenGL camera-to-world of an OpenCV camera (as NeRF-synthetic JSON stores it)."""
    return (torch.linalg.inv(cam.world_to_cam.double()) @ GL_FLIP).tolist()


def _angle_x(cam: Camera) -> float:
    return 2 * math.atan(cam.width / (2 * cam.fx))


# -- NeRF-synthetic-like dynamic layouts --------------------------------------------------------------
def write_dnerf(root: Path, n_train: int = 8, n_val: int = 2, n_test: int = 3, size: int = 24, seed: int = 0,
                test_times: list[float] | None = None, frame_ids: bool = True) -> Truth:
    """D-NeRF layout: one moving camera, train time i / (n_train - 1); val/test at training times."""
    root.mkdir(parents=True, exist_ok=True)
    truth = Truth(base=make_splats(seed), dynamic=True)
    train_times = [i / (n_train - 1) for i in range(n_train)]
    plans = {
        "train": (orbit_cameras(n_train, (size, size), seed=seed), train_times),
        "val": (orbit_cameras(n_val, (size, size), seed=seed + 1), [train_times[(2 * i + 1) % n_train]
                                                                   for i in range(n_val)]),
        "test": (orbit_cameras(n_test, (size, size), seed=seed + 2), test_times or [
            train_times[(3 * i + 2) % n_train] for i in range(n_test)]),
    }
    for split, (cams, times) in plans.items():
        frames = []
        for i, (cam, t) in enumerate(zip(cams, times, strict=True)):
            fid = min(range(n_train), key=lambda k, t=t: abs(train_times[k] - t))
            cam = replace(cam, time=t, frame_id=fid)
            write_png(root / split / f"r_{i:03d}.png", render_rgba(truth.splats_at(t), cam))
            fr = {"file_path": f"./{split}/r_{i:03d}", "rotation": 0.0, "time": t, "transform_matrix": c2w_gl(cam)}
            if frame_ids:
                fr["frame_id"] = fid
            frames.append(fr)
            truth.cameras[f"{split}/r_{i:03d}"] = cam
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": _angle_x(cams[0]),
                                                                   "frames": frames}))
    return truth


def write_blender_mv(root: Path, n_cams: int = 6, n_test_cams: int = 2, n_frames: int = 4, size: int = 24,
                     seed: int = 0) -> Truth:
    """Multi-view dynamic layout (this project's generator): fixed cameras x frames, time = f / (F - 1)."""
    root.mkdir(parents=True, exist_ok=True)
    truth = Truth(base=make_splats(seed), dynamic=True)
    for split, cams in (("train", orbit_cameras(n_cams, (size, size), seed=seed)),
                        ("test", orbit_cameras(n_test_cams, (size, size), seed=seed + 7))):
        frames = []
        for cid, cam0 in enumerate(cams):
            for fid in range(n_frames):
                t = fid / (n_frames - 1)
                cam = replace(cam0, time=t, frame_id=fid, camera_id=cid)
                name = f"c{cid:02d}_f{fid:03d}"
                write_png(root / split / f"{name}.png", render_rgba(truth.splats_at(t), cam))
                frames.append({"file_path": f"./{split}/{name}", "transform_matrix": c2w_gl(cam), "time": t,
                               "frame_id": fid, "camera_id": cid})
                truth.cameras[f"{split}/{name}"] = cam
        (root / f"transforms_{split}.json").write_text(json.dumps({
            "camera_angle_x": _angle_x(cams[0]), "num_frames": n_frames, "num_cameras": len(cams),
            "frames": frames}))
    return truth


# -- NeuS / IDR layouts ------------------------------------------------------------------------------
SPHERE_RADIUS = 0.8  # scale_mat radius written by the NeuS writers


def scale_mat() -> np.ndarray:
    """x_world = S @ x_unit: the unit sphere around ``CENTER`` with radius ``SPHERE_RADIUS``."""
    S = np.diag([SPHERE_RADIUS] * 3 + [1.0])
    S[:3, 3] = CENTER.numpy()
    return S


def world_mat(cam: Camera) -> np.ndarray:
    """NeuS ``world_mat`` = K [R | t] padded to 4x4."""
    P = np.eye(4)
    P[:3, :4] = cam.K.double().numpy() @ cam.world_to_cam.double().numpy()[:3, :4]
    return P


def _write_neus_folder(folder: Path, cams: list[Camera], truth: Truth, image_dir: str = "rgb",
                       mask_name: str = "{:06d}.png", name_prefix: str = "") -> None:
    mats = {}
    for i, cam in enumerate(cams):
        rgba = render_rgba(truth.splats_at(cam.time), cam)
        write_png(folder / image_dir / f"{i:06d}.png", _premultiplied(rgba))
        write_png(folder / "mask" / mask_name.format(i), rgba[..., 3:].expand(-1, -1, 3))
        mats[f"world_mat_{i}"] = world_mat(cam)
        mats[f"scale_mat_{i}"] = scale_mat()
        truth.cameras[f"{name_prefix}{i:06d}"] = cam
    np.savez(folder / "cameras_sphere.npz", **mats)


def write_owlii(root: Path, n_cams: int = 6, test_cams: tuple[str, ...] = ("cam_test",), n_frames: int = 3,
                size: tuple[int, int] = (24, 20), seed: int = 0, image_dir: str = "rgb") -> Truth:
    """ResFields OwlII layout: cam_train_<k>/{rgb,mask}/<frame>.png + cameras_sphere.npz; RGB over black."""
    truth = Truth(base=make_splats(seed), dynamic=True)
    w, h = size
    cams = orbit_cameras(n_cams + len(test_cams), size, seed=seed, fx=1.2 * w, fy=1.25 * w, cx=w / 2 + 1.5,
                         cy=h / 2 - 1.0)
    folders = [f"cam_train_{k}" for k in range(n_cams)] + list(test_cams)
    for k, (name, cam0) in enumerate(zip(folders, cams, strict=True)):
        per_frame = [replace(cam0, time=f / (n_frames - 1) if n_frames > 1 else 0.0, frame_id=f,
                             camera_id=k if k < n_cams else 0) for f in range(n_frames)]
        _write_neus_folder(root / name, per_frame, truth, image_dir, name_prefix=f"{name}/")
    return truth


def write_dtu(root: Path, n_images: int = 49, size: tuple[int, int] = (20, 16), seed: int = 0) -> Truth:
    """NeuS DTU layout: image/<i:06d>.png (RGB over black), mask/<i:03d>.png, cameras_sphere.npz.

    The principal point is off-centre and fx != fy (DTU keeps its full intrinsics).
    """
    truth = Truth(base=make_splats(seed))
    w, h = size
    cams = orbit_cameras(n_images, size, seed=seed, fx=1.3 * w, fy=1.32 * w, cx=w / 2 + 0.7, cy=h / 2 - 0.4)
    _write_neus_folder(root, cams, truth, image_dir="image", mask_name="{:03d}.png")
    return truth


# -- Nerfies -----------------------------------------------------------------------------------------------
def write_nerfies(root: Path, n_train: int = 8, n_val: int = 3, size: tuple[int, int] = (24, 20), seed: int = 0,
                  scene_scale: float = 0.7, scene_center: tuple[float, float, float] = (0.3, -0.1, 0.2),
                  masks: bool = False, scales: tuple[int, ...] = (1, 2)) -> Truth:
    """Nerfies layout: dataset/metadata/scene.json, camera/<id>.json, rgb/<s>x/<id>.png (RGB over black).

    Train ids ``train_XXX`` at time ids 0..n_train-1 (camera_id 0), val ids ``val_XXX`` at training
    time ids (camera_id 1). With ``masks``, ``mask/<s>x/<id>.png`` holds the alpha.
    """
    truth = Truth(base=make_splats(seed), dynamic=True)
    w, h = size
    train = orbit_cameras(n_train, size, seed=seed, fx=1.2 * w, fy=1.2 * w * 1.05, cx=w / 2 + 0.8, cy=h / 2 - 0.6)
    val = orbit_cameras(n_val, size, seed=seed + 3, fx=1.2 * w, fy=1.2 * w * 1.05, cx=w / 2 + 0.8, cy=h / 2 - 0.6)
    ids, train_ids, val_ids, metadata = [], [], [], {}
    entries = [(f"train_{i:03d}", c, i, 0) for i, c in enumerate(train)]
    entries += [(f"val_{i:03d}", c, (2 * i + 1) % n_train, 1) for i, c in enumerate(val)]
    for iid, cam0, tid, cam_id in entries:
        t = tid / (n_train - 1)
        cam = replace(cam0, time=t, frame_id=tid, camera_id=cam_id, name=iid)
        w2c = cam.world_to_cam.double()
        R = w2c[:3, :3]
        pos = -R.T @ w2c[:3, 3]
        (root / "camera").mkdir(parents=True, exist_ok=True)
        (root / "camera" / f"{iid}.json").write_text(json.dumps({
            "orientation": R.tolist(), "position": pos.tolist(), "focal_length": cam.fx,
            "principal_point": [cam.cx, cam.cy], "skew": 0.0, "pixel_aspect_ratio": cam.fy / cam.fx,
            "radial_distortion": [0.0, 0.0, 0.0], "tangential_distortion": [0.0, 0.0], "image_size": [w, h]}))
        for s in scales:
            c = cam.scaled(1.0 / s)
            rgba = render_rgba(truth.splats_at(t), c)
            write_png(root / "rgb" / f"{s}x" / f"{iid}.png", _premultiplied(rgba))
            if masks:
                write_png(root / "mask" / f"{s}x" / f"{iid}.png", rgba[..., 3:])
        metadata[iid] = {"time_id": tid, "warp_id": tid, "appearance_id": tid, "camera_id": cam_id}
        ids.append(iid)
        (train_ids if iid.startswith("train") else val_ids).append(iid)
        truth.cameras[iid] = cam
    (root / "dataset.json").write_text(json.dumps({"count": len(ids), "num_exemplars": len(train_ids), "ids": ids,
                                                   "train_ids": train_ids, "val_ids": val_ids}))
    (root / "metadata.json").write_text(json.dumps(metadata))
    (root / "scene.json").write_text(json.dumps({"scale": scene_scale, "center": list(scene_center),
                                                 "near": 0.5, "far": 5.0}))
    truth.extra = {"scale": scene_scale, "center": list(scene_center)}
    return truth


WRITERS = {
    "dnerf": write_dnerf,
    "blender_mv": write_blender_mv,
    "owlii": write_owlii,
    "dtu": write_dtu,
    "nerfies": write_nerfies,
}
