"""Readers refuse input that would silently give wrong results, with one line naming file, entry and field.

Three kinds of input are covered, for every reader: files outside the dataset folder (a ``../`` or
absolute path, a symlink pointing out; a symlinked dataset root itself is fine), values of the wrong
type in camera files (a boolean read as a number, strings or ``null`` in a matrix, wrong nesting,
NaN), and visual hulls that cannot bound the object (identical poses, duplicate frames, all-zero
masks), which must name the training views used and the likely causes. Two cases go through the CLI:
exit status 2, one ``error:`` line on stderr, ``invalid input`` recorded in metrics.json.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from src.data.base import DatasetError
from src.data.blender import BlenderDataset
from src.data.dnerf import DNerfDataset
from src.data.dtu import DTUDataset
from src.data.images import write_png
from src.data.multiview import BlenderMVDataset
from src.data.nerfies import NerfiesDataset
from src.data.owlii import OwliiDataset
from src.data.validate import check_matrix, check_number, inside_root
from src.init import HullInit
from tests import format_writers as fw
from tests.scenes import write_blender_scene

REPO = Path(__file__).resolve().parents[1]
PLANT = REPO / "data" / "static" / "plant"
READERS = {"blender": BlenderDataset, "dnerf": DNerfDataset, "blender_mv": BlenderMVDataset,
           "owlii": OwliiDataset, "dtu": DTUDataset, "nerfies": NerfiesDataset}

pytestmark = pytest.mark.usefixtures("one_thread")


# -- helpers ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def written(one_thread, tmp_path_factory) -> dict[str, Path]:
    """One tiny dataset per layout, written once; tests that break files work on copies."""
    base = tmp_path_factory.mktemp("safety")
    fw.write_dnerf(base / "dnerf", n_train=6, n_val=1, n_test=2, size=16)
    fw.write_blender_mv(base / "blender_mv", n_cams=4, n_test_cams=1, n_frames=2, size=16)
    fw.write_owlii(base / "owlii", n_cams=3, n_frames=2, size=(16, 12))
    fw.write_dtu(base / "dtu", n_images=30, size=(16, 12))
    fw.write_nerfies(base / "nerfies", n_train=5, n_val=2, size=(16, 12), scales=(1,))
    write_blender_scene(base / "blender", n_train=6, n_test=2, size=16)
    return {name: base / name for name in READERS}


def copy_of(written: dict[str, Path], name: str, dst: Path) -> Path:
    shutil.copytree(written[name], dst)
    return dst


def load(name: str, root: Path, **kw):
    return READERS[name](str(root), **kw).load()


def edit_json(path: Path, fn: Callable[[dict], object]) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def refused(fn: Callable[[], object], *parts: str) -> str:
    """The one-line DatasetError message ``fn`` raises, checked to hold every one of ``parts``."""
    with pytest.raises(DatasetError) as info:
        fn()
    msg = str(info.value)
    assert "\n" not in msg, msg
    for part in parts:
        assert part in msg, f"{part!r} not in: {msg}"
    return msg


def outside_image(tmp_path: Path, src: Path) -> Path:
    """A real image (a copy of ``src``) in a folder next to, not inside, the dataset under test."""
    dst = tmp_path / "outside" / src.name
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(src, dst)
    return dst


def set_frame(split: str, index: int, **values) -> Callable[[dict], None]:
    def fn(d: dict) -> None:
        d["frames"][index].update(values)
    return fn


# -- files outside the dataset ------------------------------------------------------------------------------
def test_dotdot_file_path_to_another_scenes_image_is_refused(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    other = copy_of(written, "blender", tmp_path / "other")
    assert (other / "train" / "r_0.png").is_file()  # followed, it would load without complaint
    edit_json(root / "transforms_train.json", set_frame("train", 2, file_path="../other/train/r_0"))
    for n_views in (None, 2):  # refused whether or not the frame is among the selected views
        refused(lambda n=n_views: load("blender", root, n_views=n),
                "transforms_train.json: frames[2]: image '../other/train/r_0' resolves to",
                str((other / "train" / "r_0").resolve()), f"outside dataset.root {root.resolve()}")


def test_absolute_path_to_an_existing_image_is_refused(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    target = outside_image(tmp_path, root / "test" / "r_1.png")
    edit_json(root / "transforms_test.json", set_frame("test", 1, file_path=str(target)))
    refused(lambda: load("blender", root), f"transforms_test.json: frames[1]: image '{target}'",
            f"outside dataset.root {root.resolve()}")


def test_absolute_path_to_a_system_file_is_refused(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    edit_json(root / "transforms_train.json", set_frame("train", 0, file_path="/etc/passwd"))
    refused(lambda: load("blender", root), "frames[0]: image '/etc/passwd'", "outside dataset.root")


def test_symlink_inside_the_dataset_pointing_outside_is_refused(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    link = root / "train" / "r_1.png"
    target = outside_image(tmp_path, link)
    link.unlink()
    link.symlink_to(target)
    refused(lambda: load("blender", root, n_views=None), "transforms_train.json: frames[1]: image './train/r_1'",
            f"resolves to {target.resolve()}", "outside dataset.root")


def test_symlinked_folder_inside_the_dataset_pointing_outside_is_refused(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    shutil.move(root / "test", tmp_path / "elsewhere")
    (root / "test").symlink_to(tmp_path / "elsewhere")
    refused(lambda: load("blender", root), "transforms_test.json: frames[0]: image './test/r_0'",
            "outside dataset.root")


def test_symlinked_dataset_root_is_fine(written, tmp_path):
    link = tmp_path / "link"
    link.symlink_to(written["blender"])
    scene = load("blender", link, n_views=3)
    assert len(scene.train) == 3
    inside = tmp_path / "scene"
    copy_of(written, "blender", inside)
    edit_json(inside / "transforms_train.json", set_frame("train", 0, file_path="../scene/train/r_0"))
    assert len(load("blender", inside, n_views=None).train) == 6  # leaves and re-enters: still inside


def test_inside_root_names_the_path_as_written_the_entry_and_the_root(tmp_path):
    (tmp_path / "root").mkdir()
    assert inside_root(tmp_path / "root", tmp_path / "root" / "a.png", "x.json: frames[0]") == \
        (tmp_path / "root" / "a.png").resolve()
    refused(lambda: inside_root(tmp_path / "root", tmp_path / "root" / ".." / "b.png", "x.json: frames[4]",
                                "mask", "../b.png"),
            "x.json: frames[4]: mask '../b.png' resolves to", f"outside dataset.root {(tmp_path / 'root').resolve()}")


LAYOUT_FILES = [  # (reader, a file the reader opens, relative to the dataset root)
    ("dnerf", "train/r_000.png"),
    ("dnerf", "transforms_test.json"),
    ("blender_mv", "train/c01_f000.png"),
    ("owlii", "cam_train_0/rgb/000001.png"),
    ("owlii", "cam_train_1/mask/000000.png"),
    ("owlii", "cam_train_2/cameras_sphere.npz"),
    ("dtu", "image/000025.png"),
    ("dtu", "mask/003.png"),
    ("dtu", "cameras_sphere.npz"),
    ("nerfies", "rgb/1x/train_002.png"),
    ("nerfies", "camera/val_001.json"),
    ("nerfies", "scene.json"),
]


@pytest.mark.parametrize("name, rel", LAYOUT_FILES)
def test_every_reader_refuses_a_symlink_out_of_the_dataset(written, tmp_path, name, rel):
    root = copy_of(written, name, tmp_path / name)
    link = root / rel
    target = outside_image(tmp_path, link)
    link.unlink()
    link.symlink_to(target)
    refused(lambda: load(name, root), link.stem, f"' resolves to {target.resolve()}",
            f"outside dataset.root {root.resolve()}")


@pytest.mark.parametrize("name", ["dnerf", "blender_mv"])
def test_dynamic_readers_refuse_a_dotdot_file_path(written, tmp_path, name):
    root = copy_of(written, name, tmp_path / name)
    copy_of(written, name, tmp_path / "other")
    first = json.loads((root / "transforms_train.json").read_text())["frames"][0]["file_path"]
    bad = "../other/" + first.removeprefix("./")
    edit_json(root / "transforms_train.json", set_frame("train", 0, file_path=bad))
    refused(lambda: load(name, root), f"transforms_train.json: frames[0]: image '{bad}'", "outside dataset.root")


def test_nerfies_refuses_an_id_leaving_the_dataset(written, tmp_path):
    root = copy_of(written, "nerfies", tmp_path / "nerfies")
    other = copy_of(written, "nerfies", tmp_path / "other")
    iid = "../../../other/rgb/1x/train_000"  # rgb/1x/<id>.png is the other scene's real image
    edit_json(root / "dataset.json", lambda d: d["train_ids"].__setitem__(0, iid))
    edit_json(root / "metadata.json", lambda d: d.__setitem__(iid, d["train_000"]))
    shutil.copy(other / "camera" / "train_000.json", root / "camera" / "x.json")  # the camera file is inside
    refused(lambda: load("nerfies", root), f"image '{iid}' resolves to", "outside dataset.root")


def test_owlii_refuses_a_camera_folder_outside(written, tmp_path):
    root = copy_of(written, "owlii", tmp_path / "owlii")
    copy_of(written, "owlii", tmp_path / "other")
    refused(lambda: load("owlii", root, train_cameras=["../other/cam_train_0"]),
            "camera folder '../other/cam_train_0' resolves to", "outside dataset.root")


# -- values of the wrong type -----------------------------------------------------------------------------
def _matrix_entry(value):
    def fn(d: dict) -> None:
        d["frames"][1]["transform_matrix"][2][3] = value
    return fn


def _matrix(value):
    def fn(d: dict) -> None:
        d["frames"][1]["transform_matrix"] = value
    return fn


def _top(key, value):
    def fn(d: dict) -> None:
        d[key] = value
    return fn


BLENDER_VALUES = [
    (_top("camera_angle_x", True), "transforms_train.json: camera_angle_x=True is not a number: found a boolean"),
    (_top("camera_angle_x", "0.69"), "camera_angle_x='0.69' is not a number: found a string"),
    (_top("camera_angle_x", None), "camera_angle_x=None is not a number: found null"),
    (_top("camera_angle_x", [0.69]), "camera_angle_x=[0.69] is not a number: found a list of 1"),
    (_top("camera_angle_x", math.nan), "camera_angle_x=nan is not finite"),
    (_matrix_entry("4.0"), "frames[1].transform_matrix[2][3]='4.0' is not a number: found a string"),
    (_matrix_entry(True), "frames[1].transform_matrix[2][3]=True is not a number: found a boolean"),
    (_matrix_entry(None), "frames[1].transform_matrix[2][3]=None is not a number: found null"),
    (_matrix_entry([4.0]), "frames[1].transform_matrix[2][3]=[4.0] is not a number: found a list of 1"),
    (_matrix_entry(math.inf), "frames[1].transform_matrix holds non-finite values"),
    (_matrix(None), "frames[1].transform_matrix=None is null, expected a list of 4"),
    (_matrix([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4]]),
     "frames[1].transform_matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4]] is a list of 3, expected a list of 4"),
    (_matrix([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1], [0, 0, 0, 1]]),
     "frames[1].transform_matrix[2]=[0, 0, 1] is a list of 3, expected a list of 4 (frames[1].transform_matrix "
     "must be 4x4 numbers)"),
    (_matrix("eye(4)"), "frames[1].transform_matrix='eye(4)' is a string, expected a list of 4"),
    (set_frame("train", 1, file_path=7), "frames[1].file_path=7: expected a non-empty relative path"),
    (set_frame("train", 1, time=True), "frames[1].time=True is not a number: found a boolean"),
    (set_frame("train", 1, frame_id=1.5), "frames[1].frame_id=1.5 is not an integer: found a number"),
    (_top("frames", [None]), "frames[0]=None is null, expected an object"),
]


@pytest.mark.parametrize("edit, needle", BLENDER_VALUES)
def test_blender_values_of_the_wrong_type(written, tmp_path, edit, needle):
    root = copy_of(written, "blender", tmp_path / "scene")
    edit_json(root / "transforms_train.json", edit)
    refused(lambda: load("blender", root), needle, str(root / "transforms_train.json"))


@pytest.mark.parametrize("name, split, edit, needle", [
    ("dnerf", "train", set_frame("train", 3, time=True), "frames[3].time=True is not a number: found a boolean"),
    ("dnerf", "test", set_frame("test", 1, time="0.5"), "frames[1].time='0.5' is not a number: found a string"),
    ("dnerf", "train", set_frame("train", 2, frame_id="2"), "frames[2].frame_id='2' is not an integer: found a string"),
    ("blender_mv", "train", set_frame("train", 0, camera_id=True),
     "frames[0].camera_id=True is not an integer: found a boolean"),
    ("blender_mv", "train", set_frame("train", 1, frame_id=-1), "frames[1].frame_id=-1 is outside the valid range"),
    ("blender_mv", "test", _matrix_entry("x"), "frames[1].transform_matrix[2][3]='x' is not a number"),
])
def test_dynamic_values_of_the_wrong_type(written, tmp_path, name, split, edit, needle):
    root = copy_of(written, name, tmp_path / name)
    edit_json(root / f"transforms_{split}.json", edit)
    refused(lambda: load(name, root), f"transforms_{split}.json: {needle}")


def _set(key, value):
    def fn(d: dict) -> None:
        d[key] = value
    return fn


@pytest.mark.parametrize("rel, edit, needle", [
    ("camera/train_001.json", _set("focal_length", True), "train_001.json: focal_length=True is not a number"),
    ("camera/train_001.json", _set("focal_length", -20.0), "focal_length=-20.0 is outside the valid range"),
    ("camera/train_001.json", _set("image_size", ["16", 12]), "image_size[0]='16' is not an integer: found a string"),
    ("camera/train_001.json", _set("image_size", [16]), "image_size=[16] is a list of 1, expected a list of 2"),
    ("camera/train_001.json", lambda d: d["orientation"][1].__setitem__(0, None),
     "orientation[1][0]=None is not a number: found null"),
    ("camera/train_001.json", _set("position", [0.0, 1.0]), "position=[0.0, 1.0] is a list of 2, expected a list of 3"),
    ("camera/train_001.json", _set("principal_point", [8.0, math.nan]), "principal_point holds non-finite values"),
    ("camera/train_001.json", _set("pixel_aspect_ratio", False), "pixel_aspect_ratio=False is not a number"),
    ("camera/train_001.json", _set("radial_distortion", [0.0, "0"]), "radial_distortion[1]='0' is not a number"),
    ("scene.json", _set("scale", True), "scene.json: scale=True is not a number: found a boolean"),
    ("scene.json", _set("scale", 0.0), "scene.json: scale=0.0 is outside the valid range: expected a scale > 0"),
    ("scene.json", _set("center", [0.0, "1", 0.0]), "scene.json: center[1]='1' is not a number"),
    ("scene.json", _set("far", 0.1), "scene.json: far=0.1 is outside the valid range: expected a distance > near"),
    ("scene.json", _set("near", "0.5"), "scene.json: near='0.5' is not a number"),
    ("metadata.json", lambda d: d["train_002"].update(time_id=True), "'train_002' needs a non-negative integer"),
    ("metadata.json", lambda d: d["val_000"].update(camera_id="1"), "val_000.camera_id='1' is not an integer"),
    ("dataset.json", lambda d: d["val_ids"].__setitem__(1, 5), "dataset.json: val_ids[1]=5 is an integer, expected"),
])
def test_nerfies_values_of_the_wrong_type(written, tmp_path, rel, edit, needle):
    root = copy_of(written, "nerfies", tmp_path / "nerfies")
    edit_json(root / rel, edit)
    refused(lambda: load("nerfies", root), needle)


def _npz_edit(npz: Path, key: str, value: np.ndarray) -> None:
    with np.load(npz) as z:
        arrays = {k: z[k].copy() for k in z.files}
    arrays[key] = value
    np.savez(npz, **arrays)


@pytest.mark.parametrize("name, rel", [("dtu", "cameras_sphere.npz"), ("owlii", "cam_train_1/cameras_sphere.npz")])
@pytest.mark.parametrize("key, value, needle", [
    ("world_mat_1", np.array([["1"] * 4] * 4), "'world_mat_1' holds <U1 values, expected numbers"),
    ("world_mat_1", np.eye(4, dtype=bool), "'world_mat_1' holds bool values, expected numbers"),
    ("world_mat_1", np.zeros((4, 4)), "'world_mat_1' @ 'scale_mat_1' has a singular 3x3 block"),
    ("scale_mat_1", np.diag([0.0, 0.0, 0.0, 1.0]), "'scale_mat_1' has a 3x3 block with determinant 0"),
    ("scale_mat_1", np.eye(3), "'scale_mat_1' has shape (3, 3), expected 4x4 or 3x4"),
])
def test_neus_camera_arrays_of_the_wrong_type(written, tmp_path, name, rel, key, value, needle):
    root = copy_of(written, name, tmp_path / name)
    _npz_edit(root / rel, key, value)
    kw = {"n_views": None, "test_ids": [1]} if name == "dtu" else {}
    refused(lambda: load(name, root, **kw), f"{rel}: {needle}")


def test_check_number_and_check_matrix_accept_numbers_only():
    assert check_number(3, "f.json", "x") == 3.0 and check_number(np.float32(0.5), "f.json", "x") == 0.5
    assert check_matrix([[1, 2.5]], "f.json", "m", (1, 2)).tolist() == [[1.0, 2.5]]
    refused(lambda: check_number(False, "f.json", "x"), "f.json: x=False is not a number: found a boolean")
    refused(lambda: check_number(-1, "f.json", "x", "a value > 0", lambda v: v > 0),
            "f.json: x=-1 is outside the valid range: expected a value > 0")


# -- visual hulls that cannot bound the object ----------------------------------------------------------------
def _same_pose(d: dict) -> None:
    for fr in d["frames"]:
        fr["transform_matrix"] = d["frames"][0]["transform_matrix"]


def _duplicate_frames(d: dict) -> None:
    d["frames"] = [d["frames"][0]] * len(d["frames"])


def zero_alpha(folder: Path, pattern: str = "*.png") -> None:
    """Set the alpha (or a mask image) of every matching file to zero, keeping the colours."""
    from src.data.images import read_image

    for path in sorted(folder.glob(pattern)):
        img = read_image(path)
        if img.shape[-1] == 4:
            img[..., 3] = 0.0
        else:
            img = torch.zeros_like(img)
        write_png(path, img)


CAUSES = "likely causes: identical or duplicate camera poses, all-zero or inverted masks, or cameras not looking"


@pytest.mark.parametrize("edit", [_same_pose, _duplicate_frames])
def test_identical_poses_are_refused_naming_the_views(written, tmp_path, edit):
    root = copy_of(written, "blender", tmp_path / "scene")
    edit_json(root / "transforms_train.json", edit)
    refused(lambda: load("blender", root, n_views=3), "transforms_train.json: visual hull cannot bound the object",
            "the 3 training views used: r_", "share one camera position", CAUSES)


def test_all_zero_masks_are_refused_naming_the_views(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    zero_alpha(root / "train")
    msg = refused(lambda: load("blender", root, n_views=None), "transforms_train.json: visual hull is empty",
                  "the 6 training views used: r_0, r_1, r_2, r_3, r_4, r_5", "all-zero masks in views r_0", CAUSES)
    assert msg.count("r_5") == 2  # once among the views used, once among the all-zero masks


def test_a_camera_turned_away_is_named(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")

    def turn_away(d: dict) -> None:  # half a turn about the camera's own y axis: still a rigid pose
        m = torch.tensor(d["frames"][2]["transform_matrix"], dtype=torch.float64)
        d["frames"][2]["transform_matrix"] = (m @ torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0],
                                                                          dtype=torch.float64))).tolist()

    edit_json(root / "transforms_train.json", turn_away)
    refused(lambda: load("blender", root, n_views=None), "visual hull is empty",
            "views r_2 do not see the point the cameras' optical axes meet", CAUSES)


def test_hull_init_names_the_views_when_the_hull_is_empty(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    zero_alpha(root / "train")
    scene = BlenderDataset(str(root), n_views=4, normalise=False).load()
    refused(lambda: HullInit(n_points=50)(scene, torch.Generator().manual_seed(0)),
            f"{root}: init=hull: visual hull is empty", "the 4 training views used: r_", "all-zero masks", CAUSES)


def test_hull_init_refuses_views_from_one_position(written, tmp_path):
    root = copy_of(written, "blender", tmp_path / "scene")
    edit_json(root / "transforms_train.json", _duplicate_frames)
    scene = BlenderDataset(str(root), n_views=2, normalise=False).load()
    refused(lambda: HullInit(n_points=50)(scene, torch.Generator().manual_seed(0)),
            "init=hull: visual hull cannot bound the object", "views r_0 = r_0 share one camera position", CAUSES)


def test_dynamic_hull_with_empty_masks_names_frames_and_views(written, tmp_path):
    root = copy_of(written, "blender_mv", tmp_path / "mv")
    zero_alpha(root / "train", "c0[0-3]_f000.png")
    refused(lambda: load("blender_mv", root), "transforms_train.json: frames 0..0: visual hull is empty",
            "train/c00_f000", "all-zero masks in views train/c00_f000", CAUSES)


# -- through the command line ----------------------------------------------------------------------------------
def _dotdot_plant(root: Path) -> None:
    outside = root.parent / "other_scene"
    shutil.copytree(PLANT / "train", outside / "train")
    edit_json(root / "transforms_train.json", set_frame("train", 0, file_path="../other_scene/train/r_0"))


def _identical_plant(root: Path) -> None:
    edit_json(root / "transforms_train.json", _same_pose)


@pytest.mark.parametrize("breaks, needle", [(_dotdot_plant, "image '../other_scene/train/r_0' resolves to"),
                                            (_identical_plant, "visual hull cannot bound the object")])
def test_cli_exits_2_with_one_error_line(tmp_path, breaks, needle):
    root = tmp_path / "plant"
    shutil.copytree(PLANT, root, ignore=shutil.ignore_patterns("gt_*.npz"))
    breaks(root)
    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "src.run", "+experiment=gs3d", f"dataset.root={root}",
                           f"hydra.run.dir={run_dir}", "threads=1", "+ci=smoke"],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1 and needle in errors[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    rec = json.loads((run_dir / "metrics.json").read_text())
    assert rec["status"] == "failed" and rec["reason"].startswith("invalid input") and needle in rec["reason"]
