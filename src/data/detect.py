"""Dataset format detection from the files present in a scene folder.

Formats (name: what identifies it):

* ``blender``: ``transforms_train.json`` whose frames carry no ``time`` (NeRF-synthetic);
* ``dnerf``: ``transforms_train.json`` whose frames carry ``time`` but no ``camera_id`` (D-NeRF);
* ``blender_mv``: ``transforms_train.json`` whose frames carry ``time`` and ``camera_id``
  (multi-view dynamic, this project's generator);
* ``nerfies``: ``dataset.json`` + ``metadata.json`` (+ ``camera/``) (Nerfies / HyperNeRF / NeRF-DS);
* ``owlii``: ``cam_train*/cameras_sphere.npz`` sub-folders (ResFields' NeuS layout of OwlII);
* ``dtu``: ``cameras_sphere.npz`` + ``image/`` at the top level (NeuS/IDR layout of DTU);
* ``colmap``: ``images/`` + ``sparse/0/cameras.{bin,txt}`` or ``sparse/cameras.{bin,txt}`` (a COLMAP
  sparse model), when no ``transforms_train.json`` is present.

Every reader of this package (except the NeRF-synthetic one) calls :func:`check_format` first, so a
reader pointed at a folder of another format fails with a message naming both formats.
"""

from __future__ import annotations

import json
from pathlib import Path

from src.data.base import DatasetError

#: What each reader expects to find (used in error messages).
EXPECTED_FILES: dict[str, str] = {
    "blender": "transforms_{train,test}.json (frames without 'time') + RGBA images",
    "dnerf": "transforms_{train,val,test}.json whose frames carry 'time' in [0, 1] (no 'camera_id')",
    "blender_mv": "transforms_{train,test}.json whose frames carry 'time', 'frame_id' and 'camera_id'",
    "nerfies": "dataset.json, metadata.json, scene.json, camera/<id>.json and rgb/<n>x/<id>.png",
    "owlii": "cam_train_<k>/ folders, each with {rgb|image}/*.png, mask/*.png and cameras_sphere.npz",
    "dtu": "cameras_sphere.npz, image/*.png and mask/*.png at the top level",
    "colmap": "images/ and a COLMAP model sparse/0/{cameras,images,points3D}.bin (or .txt, or in sparse/)",
}


def _first_frame_keys(path: Path) -> set[str] | None:
    try:
        data = json.loads(path.read_text())
        frames = data.get("frames") if isinstance(data, dict) else None
        if isinstance(frames, list) and frames and isinstance(frames[0], dict):
            return set(frames[0])
    except (OSError, json.JSONDecodeError):
        return None
    return set()


def detect_format(root: str | Path) -> str | None:
    """Name of the dataset format of ``root`` (see the module docstring), or None if none matches."""
    root = Path(root)
    if not root.is_dir():
        return None
    if (root / "dataset.json").is_file() and (root / "metadata.json").is_file():
        return "nerfies"
    if any((d / "cameras_sphere.npz").is_file() for d in root.glob("cam_train*") if d.is_dir()):
        return "owlii"
    if (root / "cameras_sphere.npz").is_file() and ((root / "image").is_dir() or (root / "rgb").is_dir()):
        return "dtu"
    tr = root / "transforms_train.json"
    if tr.is_file():
        keys = _first_frame_keys(tr)
        if keys is None:  # unreadable JSON: the reader reports the details
            return "blender"
        if "time" not in keys:
            return "blender"
        return "blender_mv" if "camera_id" in keys else "dnerf"
    if (root / "images").is_dir() and any((root / sub / f"cameras{ext}").is_file()
                                          for sub in ("sparse/0", "sparse") for ext in (".bin", ".txt")):
        return "colmap"
    return None


def check_root(root: str | Path | None) -> Path:
    """``root`` as an existing directory, or DatasetError explaining how to set it."""
    if root is None or str(root) in ("", "???"):
        raise DatasetError("dataset.root is not set: pass dataset.root=/path/to/scene")
    path = Path(root).expanduser()
    if not path.is_dir():
        raise DatasetError(f"dataset.root={path} does not exist or is not a directory")
    return path


def check_format(root: str | Path, expected: str) -> Path:
    """Raise DatasetError unless ``root`` holds a dataset of format ``expected``; returns the path."""
    path = check_root(root)
    if expected not in EXPECTED_FILES:
        raise ValueError(f"unknown dataset format {expected!r}; known: {sorted(EXPECTED_FILES)}")
    found = detect_format(path)
    if found == expected:
        return path
    what = (f"looks like a '{found}' dataset ({EXPECTED_FILES[found]})" if found is not None
            else "matches no known dataset format")
    raise DatasetError(
        f"{path} {what}, but the '{expected}' reader expects {EXPECTED_FILES[expected]}"
        + (f"; use dataset={found}" if found is not None else "")
    )
