"""D-NeRF (monocular dynamic) reader, plus the time / frame / normalisation helpers of dynamic readers.

Layout: NeRF-synthetic (``transforms_{train,val,test}.json``, ``camera_angle_x``, per-frame
``transform_matrix`` camera-to-world in Blender/OpenGL axes, RGBA images) where every frame also
carries ``time`` in [0, 1] (and optionally ``frame_id``). One camera moves around the object and
sees one time step per image, so every training image is a training view (``n_views`` does not
apply). Cameras become OpenCV (x right, y down, z forward) exactly as in the NeRF-synthetic reader.

Frames: ``n_frames`` = number of distinct training times; a view's ``frame_id`` is the index of its
time among the sorted distinct training times. A val/test time that is not a training time is mapped
to the NEAREST training time's frame id (its ``camera.time`` keeps the exact file value), and the
largest such gap is recorded in ``scene.meta["test_time_gap"]``.

Normalisation of a dynamic scene: the visual hull of ALL training masks together would be the
intersection of the object over time (too small for a moving object), so hull boxes are computed per
group of views that see (nearly) the same time (a frame of a multi-view rig; a window of consecutive
frames of a monocular sequence, at least ``hull_min_views`` views), and the union of the boxes is
mapped into [-0.9, 0.9]^3.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from src.data.base import DatasetError, DatasetReader, Scene, View
from src.data.blender import load_transforms, parse_background, read_split
from src.data.detect import check_format, check_root
from src.data.hull import hull_bounds
from src.data.normalise import cameras_extent, normalise_camera
from src.data.validate import check_int, check_number

log = logging.getLogger(__name__)


# -- helpers shared by the dynamic readers -------------------------------------------------------
def strided(n_total: int, n_keep: int | None) -> list[int]:
    """``n_keep`` indices spread evenly over range(n_total) (all of them if None or n_keep >= n_total)."""
    if n_keep is None or n_keep >= n_total:
        return list(range(n_total))
    if n_keep < 1:
        raise ValueError(f"cannot keep {n_keep} of {n_total} items: need at least 1")
    return sorted({round(i * n_total / n_keep) for i in range(n_keep)})


def frame_times(data: dict, path: Path) -> list[float]:
    """Per-frame ``time`` of a transforms JSON, validated to lie in [0, 1] (errors name file and frame)."""
    times = []
    for i, fr in enumerate(data["frames"]):
        if "time" not in fr:
            raise DatasetError(f"{path}: frames[{i}] is missing key 'time' (a dynamic scene needs one per frame)")
        t = check_number(fr["time"], str(path), f"frames[{i}].time", "a time in [0, 1]")
        if not 0.0 <= t <= 1.0:
            raise DatasetError(f"{path}: frames[{i}].time={t} is outside [0, 1]")
        times.append(t)
    return times


def distinct_times(times: Sequence[float], tol: float = 1e-6) -> list[float]:
    """Sorted distinct values of ``times`` (values closer than ``tol`` count as one)."""
    out: list[float] = []
    for t in sorted(times):
        if not out or t - out[-1] > tol:
            out.append(t)
    return out


def nearest_index(values: Sequence[float], t: float) -> int:
    """Index of the entry of the sorted ``values`` nearest to ``t``."""
    arr = np.asarray(values)
    return int(np.argmin(np.abs(arr - t)))


def check_monotonic_frame_ids(frame_ids: Sequence[int], times: Sequence[float], path: Path) -> None:
    """DatasetError unless ``frame_ids`` increase with ``times`` (same time <-> same id, later -> larger)."""
    by_id: dict[int, float] = {}
    for fid, t in zip(frame_ids, times, strict=True):
        if fid in by_id and abs(by_id[fid] - t) > 1e-6:
            raise DatasetError(f"{path}: frame_id {fid} appears with two different times ({by_id[fid]} and {t})")
        by_id[fid] = t
    ids = sorted(by_id)
    for a, b in itertools.pairwise(ids):
        if not by_id[a] < by_id[b]:
            raise DatasetError(
                f"{path}: frame ids are not monotonic in time: frame_id {a} has time {by_id[a]} but "
                f"frame_id {b} has time {by_id[b]}"
            )


def hull_groups(views: list[View], min_views: int) -> list[list[View]]:
    """Views grouped by frame, consecutive frames merged until each group has >= ``min_views`` views."""
    by_frame: dict[int, list[View]] = {}
    for v in views:
        by_frame.setdefault(v.camera.frame_id, []).append(v)
    groups: list[list[View]] = []
    cur: list[View] = []
    for fid in sorted(by_frame):
        cur = cur + by_frame[fid]
        if len(cur) >= min_views:
            groups.append(cur)
            cur = []
    if cur:
        if groups:
            groups[-1] = groups[-1] + cur
        else:
            groups.append(cur)
    return groups


def fit_dynamic_normalisation(groups: list[list[View]], target: float = 0.9, resolution: int = 64,
                              where: str = "") -> tuple[Tensor, float]:
    """(center [3], scale) mapping the union of the groups' visual-hull boxes into [-target, target]^3."""
    lo = hi = None
    for g in groups:
        masks = [v.mask for v in g]
        if any(m is None for m in masks):
            raise DatasetError(f"{where}: normalisation needs masks (alpha or mask images) for every training view")
        frames = sorted({v.camera.frame_id for v in g})
        glo, ghi = hull_bounds([v.camera for v in g], masks, resolution=resolution,
                               where=f"{where}: frames {frames[0]}..{frames[-1]}")
        lo = glo if lo is None else torch.minimum(lo, glo)
        hi = ghi if hi is None else torch.maximum(hi, ghi)
    if lo is None:
        raise DatasetError(f"{where}: no training views to normalise the scene with")
    center = 0.5 * (lo + hi)
    half = float((0.5 * (hi - lo)).max())
    return center.to(torch.float32), target / half


def apply_normalisation(views: list[View], center: Tensor, scale: float) -> None:
    """Move every view's camera into the frame ``scale * (world - center)`` (in place)."""
    for v in views:
        v.camera = normalise_camera(v.camera, center, scale)


def scene_meta(fmt: str, root: Path, train: list[View], **extra) -> dict:
    """The ``Scene.meta`` fields every reader records."""
    return {"format": fmt, "root": str(root), "height": int(train[0].image.shape[0]),
            "width": int(train[0].image.shape[1]), **extra}


# -- the reader --------------------------------------------------------------------------------------
class DNerfDataset(DatasetReader):
    """Reader for D-NeRF monocular dynamic scenes (every training image is a training view).

    Args:
        root: scene folder holding ``transforms_{train,val,test}.json`` with per-frame ``time``.
        n_views: must be None: a monocular sequence has one view per time step.
        downscale: image downscale factor (2 = half resolution).
        background: ``white`` (default), ``black``, ``grey`` or [r, g, b]; RGBA is composited on it.
        n_test: keep only ``n_test`` evenly strided test views (None = all).
        n_val: same for the validation split (0 = skip it, None = all).
        normalise: fit the union of the training masks' windowed visual hulls into [-0.9, 0.9]^3.
        hull_min_views: views per hull window (consecutive frames) used by the normalisation.
        time_tol: times closer than this are the same time step.
    """

    def __init__(self, root: str, n_views: int | None = None, downscale: float = 1.0,
                 background: str | list[float] = "white", n_test: int | None = None, n_val: int | None = 0,
                 normalise: bool = True, hull_min_views: int = 4, time_tol: float = 1e-6) -> None:
        self.root = check_root(root)
        self.n_views = n_views  # checked in load() (config composition may set it before the reader is chosen)
        if downscale <= 0:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0")
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.n_test, self.n_val = n_test, n_val
        self.normalise = normalise
        self.hull_min_views = int(hull_min_views)
        self.time_tol = float(time_tol)

    def _split(self, split: str, train_times: list[float], n_keep: int | None) -> tuple[list[View], float]:
        """Views of one split with time / frame_id set; returns (views, largest gap to a train time)."""
        path = self.root / f"transforms_{split}.json"
        data = load_transforms(path)
        times = frame_times(data, path)
        if all("frame_id" in fr for fr in data["frames"]):
            ids = [check_int(fr["frame_id"], str(path), f"frames[{i}].frame_id") for i, fr in enumerate(data["frames"])]
            check_monotonic_frame_ids(ids, times, path)
        keep = strided(len(times), n_keep)
        views, _ = read_split(self.root, split, self.background, self.downscale, keep)
        gap = 0.0
        for v in views:
            t = times[v.image_id]
            fid = nearest_index(train_times, t)
            gap = max(gap, abs(train_times[fid] - t))
            v.camera = replace(v.camera, time=t, frame_id=fid, camera_id=-1, name=f"{split}/{v.camera.name}")
        return views, gap

    def load(self) -> Scene:
        """Read the scene: all training frames, (strided) test/val views, normalised OpenCV cameras."""
        if self.n_views is not None:
            raise DatasetError(
                f"dataset.n_views={self.n_views}: a D-NeRF scene is monocular (one view per time step), so every "
                "training frame is used; set dataset.n_views=null"
            )
        check_format(self.root, "dnerf")
        train_path = self.root / "transforms_train.json"
        train_data = load_transforms(train_path)
        train_times = distinct_times(frame_times(train_data, train_path), self.time_tol)
        train, _ = self._split("train", train_times, None)
        test, test_gap = self._split("test", train_times, self.n_test)
        val: list[View] = []
        if self.n_val != 0 and (self.root / "transforms_val.json").is_file():
            val, _ = self._split("val", train_times, self.n_val)
        if test_gap > self.time_tol:
            log.warning("%s: some test times are not training times (largest gap %.4g): they use the nearest "
                        "training frame's frame_id", self.root, test_gap)
        norm = {"center": [0.0, 0.0, 0.0], "scale": 1.0}
        if self.normalise:
            groups = hull_groups(sorted(train, key=lambda v: v.camera.time), self.hull_min_views)
            center, scale = fit_dynamic_normalisation(groups, where=str(train_path))
            apply_normalisation([*train, *val, *test], center, scale)
            norm = {"center": center.tolist(), "scale": scale}
        return Scene(
            name=self.root.name, train=train, val=val, test=test, background=self.background,
            view_ids=list(range(len(train))), n_frames=len(train_times), normalisation=norm,
            extent=cameras_extent([v.camera for v in train]),
            meta=scene_meta("dnerf", self.root, train, n_frames=len(train_times), n_train_images=len(train),
                            test_time_gap=test_gap, normalisation_source="windowed visual hull"
                            if self.normalise else "none"),
        )
