"""Loader check on the shipped data: the ground-truth render geometry seen through the loaded cameras must
reproduce the masks (``src.data.verify.mesh_iou``), and deliberately wrong cameras / times must not.

For every dataset under ``data/`` (static/, dynamic_mv/, dynamic_mono/, formats/*/) and the reader of
its format, on EVERY view the reader loads for its sparse-view protocol (training and test views;
28-144 per scene), with the scene's ``gt_mesh.npz`` (the exact triangle mesh the images were rendered
from, per frame for dynamic scenes; re-exported layouts use their source scene's):

* the check passes: every view's IoU > 0.98 and the mean IoU > 0.98 (measured: per-scene minimum
  0.988-0.997, means 0.996-0.999);
* a camera with its y row negated fails it (mean IoU < 0.9), and for dynamic scenes so does the mesh
  of the frame F/2 away (mean < 0.96 and some view < 0.92) and even that of the next frame (mean < 0.975
  and some view < 0.96; measured means 0.83-0.97).

IoU settings: exact mesh coverage at 16 x 16 samples per pixel; a pixel is in the silhouette when its
coverage passes the 8-bit mask's own threshold (an alpha rounded to 8 bits passes ``mask > 0.5`` from
127.5/255 on), compared with ``mask > 0.5``, both dilated by 1 px (``dilate=1``). The Nerfies export
has no masks (RGB over black): its mask is ``rgb > 0`` there, compared with any-coverage silhouettes
(``threshold=0``).

The shipped ``gt_points.npz`` (random surface samples, also scene-flow ground truth) must lie on that
mesh: all their projections fall on the mesh's silhouette (dilated by 1 px), frame by frame. Their own
point silhouettes (``silhouette_iou``) reached per-view minima of only 0.973-0.988 on these readers'
views (sub-pixel parts, edges of sparsely sampled floors), which is why the camera check renders the mesh.
"""

from __future__ import annotations

import importlib.util
import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy import ndimage

from src.core.cameras import Camera, look_at
from src.data.base import Scene, View
from src.data.blender import BlenderDataset
from src.data.detect import detect_format
from src.data.dnerf import DNerfDataset, strided
from src.data.dtu import DTUDataset
from src.data.multiview import BlenderMVDataset
from src.data.nerfies import NerfiesDataset
from src.data.owlii import OwliiDataset
from src.data.verify import (
    flip_camera_y,
    load_gt_mesh,
    mesh_coverage,
    mesh_iou,
    normalise_points,
    silhouette_iou,
)

DATA = Path(__file__).resolve().parents[1] / "data"
MEAN_BAR = VIEW_BAR = 0.98
SUPERSAMPLE = 16
# Where the ground truth of re-exported layouts lives (formats/<layout>/<scene> -> <kind>/<scene>).
GT_SOURCE = {"owlii_neus": "dynamic_mv", "nerfies": "dynamic_mono", "dtu_neus": "static"}
# The 4-view protocol cameras (ResFields: 1, 3, 6, 8), read from the config every run uses.
FOUR_VIEWS = list(OmegaConf.load(DATA.parent / "conf" / "dataset" / "blender_mv.yaml").protocol_cameras[4])


def _reader(fmt: str, root: Path):
    if fmt == "blender":
        return BlenderDataset(str(root), n_views=8)
    if fmt == "blender_mv":
        return BlenderMVDataset(str(root), camera_ids=FOUR_VIEWS)
    if fmt == "dnerf":
        return DNerfDataset(str(root))
    if fmt == "owlii":
        return OwliiDataset(str(root), n_views=4)
    if fmt == "dtu":
        return DTUDataset(str(root), n_views=3)
    if fmt == "nerfies":
        return NerfiesDataset(str(root))
    raise AssertionError(f"no reader for format {fmt!r}")


def shipped() -> list[str]:
    """Relative paths of every scene folder under data/ (two levels, three under formats/), but the captures:
    photos without masks or a ground-truth mesh, whose cameras tests/test_capture_scene.py checks instead."""
    if not DATA.is_dir():
        return []
    out = []
    for kind in sorted(p for p in DATA.iterdir() if p.is_dir() and p.name != "captures"):
        layouts = sorted(p for p in kind.iterdir() if p.is_dir()) if kind.name == "formats" else [kind]
        for layout in layouts:
            out += [str(s.relative_to(DATA)) for s in sorted(layout.iterdir()) if s.is_dir()]
    return out


def gt_path(rel: str, name: str = "gt_mesh.npz") -> Path:
    parts = Path(rel).parts
    if parts[0] == "formats" and not (DATA / rel / name).is_file():
        return DATA / GT_SOURCE.get(parts[1], parts[1]) / parts[-1] / name
    return DATA / rel / name


pytestmark = pytest.mark.usefixtures("one_thread")


@cache
def loaded(rel: str) -> tuple[Scene, torch.Tensor, torch.Tensor, bool]:
    """(scene, gt mesh vertices [V, 3] or [F, V, 3] in the original world frame, faces [T, 3], masks-from-image)."""
    root = DATA / rel
    fmt = detect_format(root)
    assert fmt is not None, f"{root}: unknown layout"
    scene = _reader(fmt, root).load()
    gt = gt_path(rel)
    assert gt.is_file(), f"{rel}: ground-truth mesh not found at {gt}"
    verts, faces, _ = load_gt_mesh(gt)
    from_image = any(v.mask is None for v in scene.train)
    return scene, verts, faces, from_image


def views_of(scene: Scene, n: int | None = None) -> list[View]:
    """All training and test views, or ``n`` evenly spread ones of each split."""
    return ([scene.train[i] for i in strided(len(scene.train), n)]
            + [scene.test[i] for i in strided(len(scene.test), n)])


def frame_of(verts: torch.Tensor, view: View, shift: int = 0) -> torch.Tensor:
    return verts[(view.camera.frame_id + shift) % verts.shape[0]] if verts.ndim == 3 else verts


def ious(rel: str, views: list[View], frame_shift: int = 0, flip: bool = False) -> list[float]:
    scene, verts, faces, from_image = loaded(rel)
    out = []
    for v in views:
        p = frame_of(verts, v, frame_shift)
        if flip:
            v = View(flip_camera_y(v.camera), v.image, v.mask, v.image_id)
        if from_image:  # RGB over black, no mask: any-coverage silhouettes against rgb > 0
            out.append(mesh_iou(p, faces, v, scene.normalisation, dilate=1, supersample=SUPERSAMPLE,
                                mask=v.image.amax(-1), threshold=0.0))
        else:
            out.append(mesh_iou(p, faces, v, scene.normalisation, dilate=1, supersample=SUPERSAMPLE))
    return out


def passes(values: list[float]) -> bool:
    return float(np.mean(values)) > MEAN_BAR and min(values) > VIEW_BAR


SCENES = shipped()


def test_shipped_data_exists():
    """The silhouette tests must not pass vacuously: the static scenes at least must be there."""
    static = [s for s in SCENES if s.startswith("static/")]
    assert static, f"no static scenes under {DATA / 'static'}: the datasets are missing"
    assert all(gt_path(s).is_file() for s in static)


@pytest.mark.parametrize("rel", SCENES)
def test_gt_mesh_reproduces_masks(rel):
    scene, _, _, _ = loaded(rel)
    values = ious(rel, views_of(scene))
    msg = f"{rel}: IoU min {min(values):.4f} mean {np.mean(values):.4f} over {len(values)} views"
    print(msg)
    assert passes(values), msg


@pytest.mark.parametrize("rel", SCENES)
def test_flipped_camera_fails(rel):
    scene, _, _, _ = loaded(rel)
    values = ious(rel, views_of(scene, 4), flip=True)
    assert not passes(values) and np.mean(values) < 0.9, (rel, values)


@pytest.mark.parametrize("rel", SCENES)
def test_wrong_frame_fails(rel):
    scene, verts, _, _ = loaded(rel)
    if verts.ndim != 3:
        pytest.skip("static scene")
    values = ious(rel, views_of(scene, 6), frame_shift=verts.shape[0] // 2)
    assert not passes(values) and np.mean(values) < 0.96 and min(values) < 0.92, (rel, values)


@pytest.mark.parametrize("rel", SCENES)
def test_off_by_one_frame_fails(rel):
    """The next frame's geometry (1/23 or 1/49 of the sequence later) fails the check too."""
    scene, verts, _, _ = loaded(rel)
    if verts.ndim != 3:
        pytest.skip("static scene")
    values = ious(rel, views_of(scene, 6), frame_shift=1)
    assert not passes(values) and np.mean(values) < 0.975 and min(values) < 0.96, (rel, values)


@pytest.mark.parametrize("rel", [s for s in SCENES if not s.startswith("formats/")] + ["formats/dtu_neus/trinkets"])
def test_gt_points_lie_on_the_mesh(rel):
    """The shipped points (same frame, same time index) all project onto the mesh's silhouette (+1 px)."""
    scene, verts, faces, _ = loaded(rel)
    points = torch.from_numpy(np.load(gt_path(rel, "gt_points.npz"))["points"]).double()
    for v in views_of(scene, 2):
        cam = v.camera.to("cpu", torch.float64)
        cover = mesh_coverage(normalise_points(frame_of(verts, v), scene.normalisation), faces, cam, 4) > 0
        cover = ndimage.binary_dilation(cover, np.ones((3, 3), dtype=bool))  # sub-pixel parts hit no sample
        uv, _ = cam.project(normalise_points(frame_of(points, v), scene.normalisation))
        j, i = np.floor(uv.numpy()).astype(int).T
        inside = (i >= 0) & (i < cam.height) & (j >= 0) & (j < cam.width)
        on = cover[i[inside], j[inside]]
        assert inside.mean() > 0.9 and on.all(), (rel, v.camera.name, inside.mean(), on.mean())


# -- the check itself on an analytic object (no data needed) ----------------------------------------------
def _sphere_mask(cam: Camera, centre: torch.Tensor, radius: float, ss: int = 8) -> torch.Tensor:
    """[H, W] fraction of each pixel's ss x ss sub-pixel rays that hit the sphere."""
    ys, xs = torch.meshgrid(torch.arange(cam.height * ss), torch.arange(cam.width * ss), indexing="ij")
    u, v = (xs.double() + 0.5) / ss, (ys.double() + 0.5) / ss
    d_cam = torch.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, torch.ones_like(u)], -1)
    R = cam.world_to_cam[:3, :3].double()
    d = d_cam @ R  # camera -> world directions (R^T d)
    d = d / d.norm(dim=-1, keepdim=True)
    o = cam.center.double()
    oc = o - centre
    b = (d * oc).sum(-1)
    hit = (b * b - (oc @ oc - radius**2)) > 0
    return hit.double().reshape(cam.height, ss, cam.width, ss).mean((1, 3))


def test_silhouette_iou_on_a_sphere():
    g = torch.Generator().manual_seed(0)
    world_c, r = torch.tensor([0.5, -0.3, 0.2], dtype=torch.float64), 0.6
    dirs = torch.randn(20000, 3, generator=g, dtype=torch.float64)
    pts = world_c + r * dirs / dirs.norm(dim=1, keepdim=True)  # original world frame
    norm = {"center": [0.4, -0.2, 0.1], "scale": 1.4}
    c_n = 1.4 * (world_c - torch.tensor(norm["center"], dtype=torch.float64))
    eye = c_n + torch.tensor([2.5, 1.0, 1.2], dtype=torch.float64)
    cam = Camera(look_at(eye, c_n + torch.tensor([0.0, 0.0, 0.35], dtype=torch.float64)), 60.0, 60.0, 24.0, 20.0,
                 48, 40)
    view = View(cam, torch.zeros(40, 48, 3), _sphere_mask(cam, c_n, 1.4 * r).float(), 0)
    assert silhouette_iou(pts, view, norm, dilate=0) > 0.97
    assert silhouette_iou(pts, view, norm, dilate=1) > 0.98
    flipped = View(flip_camera_y(cam), view.image, view.mask, 0)  # sphere sits off the image centre
    assert silhouette_iou(pts, flipped, norm, dilate=1) < 0.8
    wrong_norm = {"center": norm["center"], "scale": 1.2}
    assert silhouette_iou(pts, view, wrong_norm, dilate=1) < 0.9
    assert math.isclose(silhouette_iou(pts[:0], View(cam, view.image, torch.zeros(40, 48), 0), norm,
                                       close=1.0), 1.0)


def test_gt_mesh_file_round_trip(tmp_path):
    """tools/datagen/layouts.write_gt_mesh (numpy only) -> load_gt_mesh: within half a quantisation step."""
    spec = importlib.util.spec_from_file_location("layouts", DATA.parent / "tools" / "datagen" / "layouts.py")
    layouts = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layouts)
    g = np.random.default_rng(1)
    faces = g.integers(0, 40000, (3000, 3))
    for verts, times in ((g.normal(0, 1, (40000, 3)), None),  # > 32768 vertices: index differences wrap
                         (g.normal(0, 1, (1, 40000, 3)) + np.linspace(0, 0.3, 3)[:, None, None], np.arange(3) / 2)):
        err = layouts.write_gt_mesh(tmp_path / "m.npz", verts, faces, times)
        v, f, t = load_gt_mesh(tmp_path / "m.npz")
        step = (verts.reshape(-1, 3).max(0) - verts.reshape(-1, 3).min(0)) / 65535
        assert v.shape == verts.shape and err <= step.max() / 2 + 1e-12
        assert np.abs(v.numpy() - verts).max() <= step.max() / 2 + 1e-12
        np.testing.assert_array_equal(f.numpy(), faces)
        assert (t is None) == (times is None) and (t is None or np.allclose(t, times))


def _brute_coverage(verts: torch.Tensor, faces: torch.Tensor, cam: Camera, s: int) -> np.ndarray:
    """Reference for mesh_coverage: every sample point against every triangle (both windings)."""
    uv, _ = cam.project(verts)
    tri = uv.numpy()[faces.numpy()] * s - 0.5
    ys, xs = np.mgrid[0:cam.height * s, 0:cam.width * s].astype(np.float64)
    fine = np.zeros(ys.shape, dtype=bool)
    for a, b, c in tri:
        e = [(q[0] - p[0]) * (ys - p[1]) - (q[1] - p[1]) * (xs - p[0]) for p, q in ((a, b), (b, c), (c, a))]
        fine |= ((e[0] >= 0) & (e[1] >= 0) & (e[2] >= 0)) | ((e[0] <= 0) & (e[1] <= 0) & (e[2] <= 0))
    return fine.reshape(cam.height, s, cam.width, s).mean((1, 3))


def test_mesh_coverage_exact():
    cam = Camera(torch.eye(4, dtype=torch.float64), 50.0, 50.0, 20.0, 20.0, 40, 40)

    def unproject(u, v, z=2.0):
        return [(u - 20) / 50 * z, (v - 20) / 50 * z, z]

    # a rectangle over pixels [10.25, 20.75) x [5.5, 30.875): coverage 0.75 / 0.5 / 0.875 on its border
    square = torch.tensor([unproject(10.25, 5.5), unproject(20.75, 5.5), unproject(20.75, 30.875),
                           unproject(10.25, 30.875)], dtype=torch.float64)
    cov = mesh_coverage(square, torch.tensor([[0, 1, 2], [0, 3, 2]]), cam, 8)
    expect = np.zeros((40, 40))
    expect[5:31, 10:21] = 1.0
    expect[5:31, [10, 20]] = 0.75
    expect[5, 10:21] *= 0.5
    expect[30, 10:21] *= 0.875
    np.testing.assert_allclose(cov, expect)
    # random triangles of both windings, partly outside the image: same as testing every sample
    g = np.random.default_rng(0)
    verts = torch.from_numpy(np.c_[g.uniform(-0.7, 0.7, (300, 2)), g.uniform(1.5, 3.0, 300)])
    faces = torch.from_numpy(g.integers(0, 300, (60, 3)))
    cam = Camera(torch.eye(4, dtype=torch.float64), 30.0, 30.0, 12.0, 10.0, 24, 20)
    for s in (1, 4):
        np.testing.assert_array_equal(mesh_coverage(verts, faces, cam, s), _brute_coverage(verts, faces, cam, s))


def _sphere_mesh(centre: torch.Tensor, radius: float, n: int = 96) -> tuple[torch.Tensor, torch.Tensor]:
    """Latitude-longitude triangle mesh (n longitudes, n/2 latitudes) circumscribing the sphere closely."""
    th = torch.linspace(0, math.pi, n // 2 + 1, dtype=torch.float64)
    ph = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    t, p = torch.meshgrid(th, ph, indexing="ij")
    r = radius / math.cos(math.pi / n) ** 2  # the facets' mid-points sit on the sphere, not inside it
    verts = centre + r * torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()], -1).reshape(-1, 3)
    idx = torch.arange(len(th) * n).reshape(len(th), n)
    a, b = idx[:-1], idx[:-1].roll(-1, 1)
    c, d = idx[1:], idx[1:].roll(-1, 1)
    faces = torch.cat([torch.stack([a, b, d], -1).reshape(-1, 3), torch.stack([a, d, c], -1).reshape(-1, 3)])
    return verts, faces


def test_mesh_iou_on_a_sphere():
    world_c, r = torch.tensor([0.5, -0.3, 0.2], dtype=torch.float64), 0.6
    verts, faces = _sphere_mesh(world_c, r)
    norm = {"center": [0.4, -0.2, 0.1], "scale": 1.4}
    c_n = 1.4 * (world_c - torch.tensor(norm["center"], dtype=torch.float64))
    eye = c_n + torch.tensor([2.5, 1.0, 1.2], dtype=torch.float64)
    cam = Camera(look_at(eye, c_n + torch.tensor([0.0, 0.0, 0.35], dtype=torch.float64)), 60.0, 60.0, 24.0, 20.0,
                 48, 40)
    view = View(cam, torch.zeros(40, 48, 3), _sphere_mask(cam, c_n, 1.4 * r, ss=16).float(), 0)
    assert mesh_iou(verts, faces, view, norm, dilate=0) > 0.99
    assert mesh_iou(verts, faces, view, norm, dilate=1) > 0.99
    flipped = View(flip_camera_y(cam), view.image, view.mask, 0)  # sphere sits off the image centre
    assert mesh_iou(verts, faces, flipped, norm, dilate=1) < 0.8
    wrong_norm = {"center": norm["center"], "scale": 1.2}
    assert mesh_iou(verts, faces, view, wrong_norm, dilate=1) < 0.9
