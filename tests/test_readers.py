"""Dataset readers (D-NeRF, multi-view dynamic, OwlII/NeuS, DTU, Nerfies) and format detection.

Every format is written from known cameras by ``tests/format_writers.py`` (tiny random-splat renders)
and read back: cameras must equal the written ones up to the scene normalisation, rendering the known
splats through a loaded camera must reproduce the loaded mask, and bad inputs must raise a
DatasetError naming the file.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from src.core.cameras import Camera
from src.core.splats import Splats
from src.data.base import DatasetError, Scene
from src.data.blender import BlenderDataset
from src.data.detect import check_format, detect_format
from src.data.dnerf import DNerfDataset
from src.data.dtu import DTUDataset
from src.data.multiview import BlenderMVDataset
from src.data.nerfies import NerfiesDataset
from src.data.normalise import normalise_camera
from src.data.owlii import OwliiDataset, decompose_projection
from src.utils.instantiate import build
from tests import format_writers as fw
from tests.scenes import write_blender_scene

READERS = {"dnerf": DNerfDataset, "blender_mv": BlenderMVDataset, "owlii": OwliiDataset, "dtu": DTUDataset,
           "nerfies": NerfiesDataset}
CONF = Path(__file__).resolve().parents[1] / "conf" / "dataset"


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def written(one_thread, tmp_path_factory) -> dict[str, tuple[Path, fw.Truth]]:
    """One tiny dataset per format (written once per module); tests that break files copy them first."""
    base = tmp_path_factory.mktemp("formats")
    out = {
        "dnerf": (base / "dnerf", fw.write_dnerf(base / "dnerf", test_times=[0.05, 0.5, 0.97])),
        "blender_mv": (base / "blender_mv", fw.write_blender_mv(base / "blender_mv")),
        "owlii": (base / "owlii", fw.write_owlii(base / "owlii", n_cams=10, n_frames=2, size=(20, 16))),
        "dtu": (base / "dtu", fw.write_dtu(base / "dtu")),
        "nerfies": (base / "nerfies", fw.write_nerfies(base / "nerfies")),
    }
    write_blender_scene(base / "blender", n_train=4, n_test=1, size=16)
    out["blender"] = (base / "blender", None)
    return out


def copy_of(written, name: str, tmp_path: Path) -> Path:
    dst = tmp_path / name
    shutil.copytree(written[name][0], dst)
    return dst


def load(name: str, root: Path, **kw) -> Scene:
    return READERS[name](str(root), **kw).load()


def normalised_splats(s: Splats, norm: dict) -> Splats:
    """The splats in the scene frame ``scale * (world - center)`` (a similarity: scales scale too)."""
    c = torch.tensor(norm["center"], dtype=s.means.dtype)
    k = float(norm["scale"])
    return Splats(means=k * (s.means - c), scales=k * s.scales, quats=s.quats, opacities=s.opacities,
                  colors=s.colors)


def assert_same_camera(got: Camera, want: Camera, atol: float = 1e-4) -> None:
    assert torch.allclose(got.world_to_cam.double(), want.world_to_cam.double(), atol=atol), (got.name, got, want)
    for key in ("fx", "fy", "cx", "cy"):
        assert math.isclose(getattr(got, key), getattr(want, key), rel_tol=1e-5, abs_tol=1e-4), (key, got, want)
    assert (got.width, got.height) == (want.width, want.height)


# -- detection --------------------------------------------------------------------------------------
def assert_same_normalisation(got: dict, want: dict, rel: float = 1e-6) -> None:
    """``got`` and ``want`` ({"center": [3 floats], "scale": float}) have the same keys and close values."""
    assert set(got) == set(want), f"normalisation keys {sorted(got)} != {sorted(want)}"
    for key, value in want.items():
        np.testing.assert_allclose(np.asarray(got[key], dtype=float), np.asarray(value, dtype=float), rtol=rel,
                                   atol=1e-12, err_msg=f"normalisation[{key!r}]")


def test_detect_format_of_every_layout(written, tmp_path):
    for name, (root, _) in written.items():
        assert detect_format(root) == name
    assert detect_format(tmp_path) is None
    assert detect_format(tmp_path / "missing") is None


@pytest.mark.parametrize("reader", sorted(READERS))
@pytest.mark.parametrize("other", ["blender", "dnerf", "blender_mv", "owlii", "dtu", "nerfies"])
def test_reader_pointed_at_another_format(written, reader, other):
    if reader == other:
        return
    kw = {"n_views": None} if reader == "dtu" else {}
    with pytest.raises(DatasetError, match=rf"looks like a '{other}' dataset.*'{reader}' reader expects"):
        READERS[reader](str(written[other][0]), **kw).load()


def test_check_format_on_empty_folder(tmp_path):
    with pytest.raises(DatasetError, match="matches no known dataset format"):
        check_format(tmp_path, "owlii")
    with pytest.raises(DatasetError, match=r"dataset\.root is not set"):
        DNerfDataset("???")


# -- round trips: cameras and renders ---------------------------------------------------------------
ROUND_TRIP = {
    "dnerf": {"n_val": None},
    "blender_mv": {"n_views": 4},
    "owlii": {"n_views": 4},
    "dtu": {"n_views": 3},
    "nerfies": {},
}


@pytest.mark.parametrize("name", sorted(ROUND_TRIP))
def test_round_trip_cameras(written, name):
    """Loaded cameras = written OpenCV cameras moved into the scene frame; time / ids carried over."""
    root, truth = written[name]
    scene = load(name, root, **ROUND_TRIP[name])
    center = torch.tensor(scene.normalisation["center"])
    scale = scene.normalisation["scale"]
    views = [*scene.train, *scene.val, *scene.test]
    assert views and scene.train
    for v in views:
        want = truth.cameras[v.camera.name]
        assert_same_camera(v.camera, normalise_camera(want.to(dtype=torch.float64), center.double(), scale))
        assert v.camera.frame_id == want.frame_id and math.isclose(v.camera.time, want.time, abs_tol=1e-6)
        if name in ("blender_mv", "owlii"):
            assert v.camera.camera_id == want.camera_id
        assert v.image.shape == (v.camera.height, v.camera.width, 3)
    assert scene.meta["format"] == name
    assert scene.n_frames == (1 if name == "dtu" else max(c.frame_id for c in truth.cameras.values()) + 1)


@pytest.mark.parametrize("name", sorted(ROUND_TRIP))
def test_known_splats_rendered_through_loaded_cameras_match_masks(written, name):
    """Rendering the written splats (moved into the scene frame, at the view's time) reproduces the mask."""
    root, truth = written[name]
    kw = {**ROUND_TRIP[name], **({"composite": "premultiplied"} if name == "nerfies" else {})}
    scene = load(name, root, **kw)
    for v in [scene.train[0], scene.train[-1], scene.test[-1]]:
        want = fw.render_rgba(normalised_splats(truth.splats_at(v.camera.time), scene.normalisation), v.camera)
        got = v.mask if v.mask is not None else v.image.amax(-1)  # nerfies without masks: RGB over black
        ref = want[..., 3] if v.mask is not None else (want[..., :3] * want[..., 3:]).amax(-1)
        assert (got - ref).abs().max() < 0.02, (name, v.camera.name, float((got - ref).abs().max()))


@pytest.mark.parametrize("name", ["dnerf", "blender_mv", "nerfies"])
def test_normalised_object_inside_unit_cube(written, name):
    root, truth = written[name]
    scene = load(name, root, **ROUND_TRIP[name])
    for t in (0.0, 0.5, 1.0):
        m = normalised_splats(truth.splats_at(t), scene.normalisation).means
        assert m.abs().max() < 1.0, (name, t, float(m.abs().max()))


def test_rgba_compositing_uses_straight_alpha(written):
    root, truth = written["dnerf"]
    scene = load("dnerf", root, normalise=False)
    v = scene.train[0]
    rgba = fw.render_rgba(truth.splats_at(v.camera.time), v.camera)
    want = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])  # straight alpha on white
    assert (v.image - want).abs().max() < 0.02


def test_neus_decomposition_recovers_k_r_t():
    g = torch.Generator().manual_seed(0)
    for sign in (1.0, -1.0):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        R = (q * torch.sign(torch.det(q))).numpy()
        K = np.array([[300.0, 0.0, 160.5], [0.0, 310.0, 118.25], [0.0, 0.0, 1.0]])
        t = np.array([0.3, -0.2, 4.0])
        P = sign * 2.5 * K @ np.concatenate([R, t[:, None]], 1)
        K2, w2c = decompose_projection(P)
        assert np.allclose(K2, K, atol=1e-8) and np.allclose(w2c[:3, :3], R, atol=1e-10)
        assert np.allclose(w2c[:3, 3], t, atol=1e-10)


# -- D-NeRF ---------------------------------------------------------------------------------------------
def test_dnerf_frames_times_and_nearest_test_time(written):
    root, _ = written["dnerf"]
    scene = load("dnerf", root, n_val=None)
    assert scene.n_frames == 8 and scene.view_ids == list(range(8))
    assert [v.camera.frame_id for v in sorted(scene.train, key=lambda v: v.camera.time)] == list(range(8))
    # test times 0.05, 0.5, 0.97 are not training times (k / 7): nearest frames 0, 3 or 4, 7
    fids = [v.camera.frame_id for v in scene.test]
    assert fids[0] == 0 and fids[2] == 7 and fids[1] in (3, 4)
    assert scene.test[0].camera.time == pytest.approx(0.05)
    assert scene.meta["test_time_gap"] == pytest.approx(0.5 - 3 / 7, abs=1e-6)  # largest of 0.05, 0.071, 0.03
    assert all(v.camera.camera_id == -1 for v in scene.train)


def test_dnerf_without_frame_ids_and_strided_test(tmp_path):
    fw.write_dnerf(tmp_path / "s", n_train=5, n_test=4, frame_ids=False)
    scene = DNerfDataset(str(tmp_path / "s"), n_test=2, downscale=2).load()
    assert scene.n_frames == 5 and len(scene.test) == 2 and scene.test[0].image.shape == (12, 12, 3)


def test_dnerf_rejects_n_views(written):
    with pytest.raises(ValueError, match=r"monocular.*dataset\.n_views=null"):
        DNerfDataset(str(written["dnerf"][0]), n_views=8).load()


def _edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("bad", [1.5, -0.1])
def test_dnerf_time_outside_unit_interval(written, tmp_path, bad):
    root = copy_of(written, "dnerf", tmp_path)
    _edit_json(root / "transforms_train.json", lambda d: d["frames"][3].update(time=bad))
    with pytest.raises(DatasetError, match=rf"transforms_train\.json: frames\[3\]\.time={bad} is outside \[0, 1\]"):
        load("dnerf", root)


def test_dnerf_missing_time(written, tmp_path):
    root = copy_of(written, "dnerf", tmp_path)
    _edit_json(root / "transforms_test.json", lambda d: d["frames"][1].pop("time"))
    with pytest.raises(DatasetError, match=r"transforms_test\.json: frames\[1\] is missing key 'time'"):
        load("dnerf", root)


def test_dnerf_non_monotonic_frame_ids(written, tmp_path):
    root = copy_of(written, "dnerf", tmp_path)

    def swap(d):
        d["frames"][2]["frame_id"], d["frames"][5]["frame_id"] = 5, 2

    _edit_json(root / "transforms_train.json", swap)
    with pytest.raises(DatasetError, match=r"transforms_train\.json: frame ids are not monotonic"):
        load("dnerf", root)


# -- multi-view dynamic ---------------------------------------------------------------------------------
def test_blender_mv_camera_selection(written):
    root, _ = written["blender_mv"]
    scene = load("blender_mv", root, camera_ids=[1, 3, 4])
    assert scene.meta["train_cameras"] == [1, 3, 4] and scene.n_frames == 4
    assert sorted({(v.camera.camera_id, v.camera.frame_id) for v in scene.train}) == [
        (c, f) for c in (1, 3, 4) for f in range(4)]
    assert len(scene.test) == 2 * 4 and scene.view_ids == sorted(v.image_id for v in scene.train)
    a = load("blender_mv", root, n_views=3, normalise=False)
    b = load("blender_mv", root, n_views=3, normalise=False)
    assert a.meta["train_cameras"] == b.meta["train_cameras"] and len(a.meta["train_cameras"]) == 3
    assert len(a.train) == 12
    assert len(load("blender_mv", root, normalise=False).meta["train_cameras"]) == 6
    # a protocol list for this view count wins over K-means (every method sees the same cameras) ...
    p = load("blender_mv", root, n_views=3, normalise=False, protocol_cameras={3: [0, 2, 5]})
    assert p.meta["train_cameras"] == [0, 2, 5]
    # ... an inconsistent one is refused, naming the key, and one naming absent cameras falls back to K-means
    with pytest.raises(ValueError, match=r"protocol_cameras\[3\]"):
        load("blender_mv", root, n_views=3, normalise=False, protocol_cameras={3: [0, 2]})
    q = load("blender_mv", root, n_views=3, normalise=False, protocol_cameras={3: [0, 2, 9]})
    assert q.meta["train_cameras"] == a.meta["train_cameras"]


def test_blender_mv_frames_and_test_subsets(written):
    root, _ = written["blender_mv"]
    scene = load("blender_mv", root, n_views=2, frames=2, n_test_frames=1, normalise=False)
    assert scene.n_frames == 2 and {v.camera.frame_id for v in scene.train} == {0, 1}
    assert {v.camera.time for v in scene.train} == {0.0, 1.0}  # first 2 of 4 frames, rescaled
    assert len(scene.test) == 2 and {v.camera.frame_id for v in scene.test} == {0}
    assert len(load("blender_mv", root, n_test=3, normalise=False).test) == 3


@pytest.mark.parametrize("kw, match", [({"n_views": 2, "camera_ids": [1, 3, 4]}, "n_views=2"),
                                       ({"camera_ids": [1, 9]}, r"cameras \[9\]"),
                                       ({"n_views": 7}, "n_views=7")])
def test_blender_mv_bad_selection(written, kw, match):
    with pytest.raises(ValueError, match=match):
        load("blender_mv", written["blender_mv"][0], **kw)


def test_blender_mv_bad_files(written, tmp_path):
    root = copy_of(written, "blender_mv", tmp_path)
    tr = root / "transforms_train.json"
    orig = tr.read_text()
    _edit_json(tr, lambda d: d["frames"][0].update(time=2.0))
    with pytest.raises(DatasetError, match=r"transforms_train\.json: frames\[0\]\.time=2\.0 is outside"):
        load("blender_mv", root)

    def reorder(d):  # frame 1 and 2 swap ids in camera 0 only: id 1 gets two times
        d["frames"][1]["frame_id"], d["frames"][2]["frame_id"] = 2, 1

    tr.write_text(orig)
    _edit_json(tr, reorder)
    with pytest.raises(DatasetError, match=r"frame_id \d appears with two different times"):
        load("blender_mv", root)

    def reverse(d):  # consistently reversed ids: later time, smaller id
        for fr in d["frames"]:
            fr["frame_id"] = 3 - fr["frame_id"]

    tr.write_text(orig)
    _edit_json(tr, reverse)
    with pytest.raises(DatasetError, match="not monotonic in time"):
        load("blender_mv", root)
    tr.write_text(orig)
    _edit_json(tr, lambda d: d["frames"][1].update(frame_id=0, time=0.0))
    with pytest.raises(DatasetError, match="camera_id 0 has frame_id 0 twice"):
        load("blender_mv", root)


# -- OwlII ----------------------------------------------------------------------------------------------
def test_owlii_protocols_and_frames(written):
    root, _ = written["owlii"]
    four = load("owlii", root, n_views=4)
    assert four.meta["train_cameras"] == ["cam_train_1", "cam_train_3", "cam_train_6", "cam_train_8"]
    assert sorted({v.camera.camera_id for v in four.train}) == [1, 3, 6, 8] and len(four.train) == 8
    assert_same_normalisation(four.normalisation, {"center": fw.CENTER.tolist(), "scale": 1 / fw.SPHERE_RADIUS})
    assert [v.camera.time for v in four.train[:2]] == [0.0, 1.0]
    assert {v.camera.camera_id for v in four.test} == {0} and len(four.test) == 2
    three = load("owlii", root, n_views=3)
    assert len(three.meta["train_cameras"]) == 3
    explicit = load("owlii", root, train_cameras=["cam_train_2", "cam_train_5"], frames=1)
    assert explicit.n_frames == 1 and len(explicit.train) == 2 and explicit.train[0].camera.time == 0.0
    half = load("owlii", root, n_views=4, downscale=2)
    assert half.train[0].image.shape == (8, 10, 3) and half.train[0].mask.shape == (8, 10)
    assert half.train[0].camera.fx == pytest.approx(four.train[0].camera.fx / 2)
    assert half.train[0].camera.cx == pytest.approx(four.train[0].camera.cx / 2)


def test_owlii_image_folder_variant(tmp_path):
    fw.write_owlii(tmp_path / "s", n_cams=3, n_frames=2, size=(12, 10), image_dir="image",
                   test_cams=("cam_test_0", "cam_test_1"))
    scene = OwliiDataset(str(tmp_path / "s"), n_test_frames=1).load()
    assert len(scene.train) == 6 and len(scene.test) == 2
    assert sorted(v.camera.camera_id for v in scene.test) == [0, 1]


def test_owlii_bad_files(written, tmp_path):
    root = copy_of(written, "owlii", tmp_path)
    shutil.rmtree(root / "cam_train_3" / "mask")
    with pytest.raises(DatasetError, match=r"cam_train_3/mask: masks missing"):
        load("owlii", root, n_views=4)
    root = copy_of(written, "owlii", tmp_path / "b")
    (root / "cam_train_6" / "rgb" / "000001.png").unlink()
    with pytest.raises(DatasetError, match=r"cam_train_6: 1 images in rgb/ but 2 masks"):
        load("owlii", root, n_views=4)
    (root / "cam_train_6" / "mask" / "000001.png").unlink()
    with pytest.raises(DatasetError, match=r"cam_train_6/cameras_sphere\.npz: 2 world_mat_\* entries but 1 images"):
        load("owlii", root, n_views=4)
    root = copy_of(written, "owlii", tmp_path / "c")
    npz = root / "cam_train_1" / "cameras_sphere.npz"
    cams = dict(np.load(npz))
    del cams["world_mat_1"]
    np.savez(npz, **cams)
    with pytest.raises(DatasetError, match=r"cam_train_1/cameras_sphere\.npz: missing 'world_mat_1'"):
        load("owlii", root, n_views=4)


# -- DTU --------------------------------------------------------------------------------------------------
def test_dtu_pixelnerf_split_and_full_intrinsics(written):
    root, truth = written["dtu"]
    scene = load("dtu", root)
    assert scene.view_ids == [25, 22, 28] and [v.camera.name for v in scene.train] == ["000025", "000022", "000028"]
    excluded = {3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39}
    test_ids = [v.image_id for v in scene.test]
    assert len(test_ids) == 25 and not set(test_ids) & (excluded | {25, 22, 28, 40, 44, 48, 0, 8, 13})
    cam = scene.train[0].camera
    assert cam.cx == pytest.approx(truth.cameras["000025"].cx) and cam.fx != pytest.approx(cam.fy)
    assert load("dtu", root, n_views=None).view_ids == [25, 22, 28, 40, 44, 48, 0, 8, 13]
    assert len(load("dtu", root, n_test=5).test) == 5
    with pytest.raises(ValueError, match="n_views=10"):
        DTUDataset(str(root), n_views=10)


def test_dtu_bad_files(written, tmp_path):
    root = copy_of(written, "dtu", tmp_path)
    shutil.rmtree(root / "mask")
    with pytest.raises(DatasetError, match=r"mask: masks missing"):
        load("dtu", root)
    small = tmp_path / "small"
    fw.write_dtu(small, n_images=30, size=(8, 6))
    with pytest.raises(DatasetError, match="view id 40 requested but the scan has 30 images"):
        DTUDataset(str(small), n_views=None).load()
    scene = DTUDataset(str(small), n_views=3).load()  # 25, 22, 28 exist; test = the rest below 30
    assert scene.view_ids == [25, 22, 28] and all(v.image_id < 30 for v in scene.test)


# -- Nerfies ----------------------------------------------------------------------------------------------
def test_nerfies_scene_json_masks_and_scales(written, tmp_path):
    root, truth = written["nerfies"]
    scene = load("nerfies", root)
    assert_same_normalisation(scene.normalisation, truth.extra)  # no masks: scene.json alone
    assert all(v.mask is None for v in scene.train) and scene.meta["has_masks"] is False
    assert scene.n_frames == 8 and [v.camera.camera_id for v in scene.test] == [1, 1, 1]
    half = load("nerfies", root, image_scale=2)
    assert half.train[0].image.shape == (10, 12, 3)
    want = normalise_camera(truth.cameras["train_000"].scaled(0.5), torch.tensor(truth.extra["center"]),
                            truth.extra["scale"])
    assert_same_camera(half.train[0].camera, want)
    fw.write_nerfies(tmp_path / "m", masks=True, scales=(1,))
    masked = NerfiesDataset(str(tmp_path / "m")).load()
    assert all(v.mask is not None for v in masked.train) and "visual hull" in masked.meta["normalisation_source"]
    assert masked.normalisation["scale"] != pytest.approx(truth.extra["scale"])
    with pytest.raises(ValueError, match="n_views=3"):
        NerfiesDataset(str(root), n_views=3).load()


def test_nerfies_bad_files(written, tmp_path, caplog):
    root = copy_of(written, "nerfies", tmp_path)
    _edit_json(root / "camera" / "train_001.json", lambda d: d.update(radial_distortion=[0.1, 0.0, 0.0]))
    with caplog.at_level(logging.WARNING):
        load("nerfies", root)
    assert "train_001.json: lens distortion" in caplog.text
    (root / "camera" / "val_002.json").unlink()
    with pytest.raises(DatasetError, match=r"camera file not found: .*camera/val_002\.json"):
        load("nerfies", root)
    root = copy_of(written, "nerfies", tmp_path / "b")
    _edit_json(root / "metadata.json", lambda d: [d["train_003"].pop(k) for k in ("time_id", "warp_id")])
    with pytest.raises(DatasetError, match=r"metadata\.json: 'train_003' needs a non-negative integer 'time_id'"):
        load("nerfies", root)


# -- configs ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(READERS))
def test_dataset_config_instantiates_and_loads(written, name):
    cfg = OmegaConf.load(CONF / f"{name}.yaml")
    assert OmegaConf.to_container(cfg, resolve=False)["root"].startswith("${paths.data_dir}/")
    cfg.root = str(written[name][0])
    cfg.downscale, cfg.n_test = 2.0, 2  # what +ci=smoke sets (downscale 4 on the 100 px shipped data)
    if name in ("blender_mv", "owlii"):
        cfg.n_views = 4
    scene = build(cfg).load()
    assert scene.train and len(scene.test) == 2 and scene.meta["format"] == name


def test_blender_reader_still_reads_its_layout(written):
    scene = BlenderDataset(str(written["blender"][0]), n_test=1).load()
    assert scene.n_frames == 1 and detect_format(written["blender"][0]) == "blender"
