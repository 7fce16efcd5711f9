"""Multi-view dynamic reader (``blender_mv``): NeRF-synthetic layout with time, frame and camera ids.

Layout (this project's generator, an OwlII-like rig rendered by Blender): ``transforms_{train,test}.json``
with ``camera_angle_x`` and frames ``{file_path, transform_matrix (camera-to-world, Blender/OpenGL),
time in [0, 1], frame_id (int), camera_id (int)}``; RGBA images. Cameras become OpenCV (x right,
y down, z forward) as in the NeRF-synthetic reader. Test cameras are physically different cameras
from the training ones; their ``camera_id`` numbering is the test file's own.

Sparse views are sparse CAMERAS: ``n_views = K`` keeps K training cameras and ALL their frames.
The cameras are ``camera_ids`` if given (the ResFields 4-view protocol is ``[1, 3, 6, 8]``), otherwise
K-means on the (per-camera mean) camera centres, as for static scenes. Test views are all frames of
the test cameras (``n_test_frames`` keeps evenly spread frames, ``n_test`` then thins the list).

``frames = F`` keeps the first F frames; frame ids are renumbered 0..F-1 in time order and times
rescaled linearly so the kept frames span [0, 1] (first -> 0, last -> 1), as the reference code does
with ``load_time_step``. Checks: times in [0, 1]; frame ids monotonic in time and consistent across
cameras; each (camera, frame) at most once.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from src.data.base import DatasetError, DatasetReader, Scene, View
from src.data.blender import load_transforms, parse_background, read_split
from src.data.detect import check_format, check_root
from src.data.dnerf import (
    apply_normalisation,
    check_monotonic_frame_ids,
    fit_dynamic_normalisation,
    frame_times,
    hull_groups,
    scene_meta,
    strided,
)
from src.data.normalise import cameras_extent
from src.data.validate import check_int
from src.data.views import select_views

log = logging.getLogger(__name__)

def read_rig(path: Path) -> tuple[dict, list[dict]]:
    """A multi-view transforms JSON and one record per frame: index, time, frame_id, camera_id, centre."""
    data = load_transforms(path)
    times = frame_times(data, path)
    recs = []
    seen: set[tuple[int, int]] = set()
    for i, (fr, t) in enumerate(zip(data["frames"], times, strict=True)):
        for key in ("frame_id", "camera_id"):
            if key not in fr:
                raise DatasetError(f"{path}: frames[{i}] is missing key '{key}' (multi-view dynamic layout)")
            check_int(fr[key], str(path), f"frames[{i}].{key}", minimum=0)
        key = (fr["camera_id"], fr["frame_id"])
        if key in seen:
            raise DatasetError(f"{path}: camera_id {key[0]} has frame_id {key[1]} twice")
        seen.add(key)
        centre = np.asarray(fr["transform_matrix"], dtype=np.float64)[:3, 3]
        recs.append({"index": i, "time": t, "frame_id": fr["frame_id"], "camera_id": fr["camera_id"],
                     "centre": centre})
    check_monotonic_frame_ids([r["frame_id"] for r in recs], times, path)
    return data, recs


class BlenderMVDataset(DatasetReader):
    """Reader for multi-view dynamic scenes in the NeRF-synthetic-like ``blender_mv`` layout.

    Args:
        root: scene folder holding ``transforms_{train,test}.json``.
        n_views: number of training CAMERAS (all their frames are used); None = every camera.
        camera_ids: explicit training cameras (e.g. [1, 3, 6, 8], the ResFields 4-view protocol);
            overrides the K-means choice (``n_views`` must then be None or ``len(camera_ids)``).
        downscale: image downscale factor (2 = half resolution).
        background: ``white`` (default), ``black``, ``grey`` or [r, g, b]; RGBA is composited on it.
        view_seed: seed of the K-means camera selection.
        frames: keep only the first ``frames`` frames (None = all).
        n_test_frames: test on this many evenly spread frames of each test camera (None = all).
        n_test: then keep this many evenly strided test views (None = all).
        normalise: fit the union of the per-frame visual hulls of the training masks into [-0.9, 0.9]^3.
        hull_min_views: views per hull group (frames are merged until a group has that many).
        protocol_cameras: {n_views: camera ids} used when ``camera_ids`` is None, so that every method
            trained with ``n_views`` = 4 sees the ResFields cameras (1, 3, 6, 8), not a K-means choice.
    """

    def __init__(self, root: str, n_views: int | None = None, camera_ids: list[int] | None = None,
                 downscale: float = 1.0, background: str | list[float] = "white", view_seed: int = 0,
                 frames: int | None = None, n_test_frames: int | None = None, n_test: int | None = None,
                 normalise: bool = True, hull_min_views: int = 2,
                 protocol_cameras: dict | None = None) -> None:
        self.root = check_root(root)
        if downscale <= 0:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0")
        if frames is not None and frames < 1:
            raise DatasetError(f"dataset.frames={frames} must be >= 1 (or null for all)")
        self.n_views = n_views
        self.camera_ids = None if camera_ids is None else [int(c) for c in camera_ids]
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.view_seed = view_seed
        self.frames = frames
        self.n_test_frames = n_test_frames
        self.n_test = n_test
        self.normalise = normalise
        self.hull_min_views = int(hull_min_views)
        self.protocol_cameras = {int(k): [int(c) for c in v] for k, v in (protocol_cameras or {}).items()}

    def select_cameras(self, recs: list[dict]) -> list[int]:
        """Training camera ids: ``camera_ids`` if given, else ``protocol_cameras[n_views]`` if listed,
        else K-means on the camera centres."""
        available = sorted({r["camera_id"] for r in recs})
        if self.camera_ids is None and self.n_views in self.protocol_cameras:
            chosen = self.protocol_cameras[self.n_views]
            if len(set(chosen)) != self.n_views:
                raise DatasetError(f"dataset.protocol_cameras[{self.n_views}]={chosen}: expected {self.n_views} "
                                 "distinct camera ids")
            if set(chosen) <= set(available):
                return sorted(chosen)
            log.warning("dataset.protocol_cameras[%d]=%s: not all among the training cameras %s of %s; "
                        "choosing %d cameras by K-means instead", self.n_views, chosen, available, self.root,
                        self.n_views)
        if self.camera_ids is not None:
            missing = sorted(set(self.camera_ids) - set(available))
            if missing:
                raise DatasetError(f"dataset.camera_ids={self.camera_ids}: cameras {missing} are not in the "
                                 f"training set (available: {available})")
            if self.n_views is not None and self.n_views != len(self.camera_ids):
                raise DatasetError(f"dataset.n_views={self.n_views} but dataset.camera_ids lists "
                                 f"{len(self.camera_ids)} cameras: set one of them (or make them agree)")
            return sorted(set(self.camera_ids))
        centres = np.stack([np.mean([r["centre"] for r in recs if r["camera_id"] == c], axis=0) for c in available])
        return [available[i] for i in select_views(centres, self.n_views, seed=self.view_seed)]

    def _views(self, split: str, recs: list[dict], cams: list[int], frame_map: dict[int, tuple[int, float]],
               n_keep: int | None = None) -> list[View]:
        chosen = sorted((r for r in recs if r["camera_id"] in cams and r["frame_id"] in frame_map),
                        key=lambda r: (r["camera_id"], r["frame_id"]))
        chosen = [chosen[i] for i in strided(len(chosen), n_keep)]
        views, _ = read_split(self.root, split, self.background, self.downscale, [r["index"] for r in chosen])
        for v, r in zip(views, chosen, strict=True):
            fid, t = frame_map[r["frame_id"]]
            v.camera = replace(v.camera, time=t, frame_id=fid, camera_id=r["camera_id"],
                               name=f"{split}/{v.camera.name}")
        return views

    def load(self) -> Scene:
        """Read the scene: all frames of the selected training cameras, test cameras, normalised cameras."""
        check_format(self.root, "blender_mv")
        train_path, test_path = self.root / "transforms_train.json", self.root / "transforms_test.json"
        _, train_recs = read_rig(train_path)
        _, test_recs = read_rig(test_path)
        times = {r["frame_id"]: r["time"] for r in train_recs}
        all_ids = sorted(times)
        kept = all_ids[: self.frames] if self.frames is not None else all_ids
        t0, t1 = times[kept[0]], times[kept[-1]]
        rescale = self.frames is not None and len(kept) < len(all_ids)

        def new_time(fid: int) -> float:
            if not rescale:
                return times[fid]
            return 0.0 if t1 <= t0 else (times[fid] - t0) / (t1 - t0)

        frame_map = {fid: (k, new_time(fid)) for k, fid in enumerate(kept)}
        for r in test_recs:
            if r["frame_id"] in times and abs(times[r["frame_id"]] - r["time"]) > 1e-6:
                raise DatasetError(f"{test_path}: frame_id {r['frame_id']} has time {r['time']} but "
                                   f"{train_path.name} gives it time {times[r['frame_id']]}")
        cams = self.select_cameras(train_recs)
        train = self._views("train", train_recs, cams, frame_map)
        test_ids = sorted({r["frame_id"] for r in test_recs} & set(kept))
        if not test_ids:
            raise DatasetError(f"{test_path}: no test frame among the training frames {kept[0]}..{kept[-1]}")
        test_map = {test_ids[i]: frame_map[test_ids[i]] for i in strided(len(test_ids), self.n_test_frames)}
        test_cams = sorted({r["camera_id"] for r in test_recs})
        test = self._views("test", test_recs, test_cams, test_map, self.n_test)
        norm = {"center": [0.0, 0.0, 0.0], "scale": 1.0}
        if self.normalise:
            center, scale = fit_dynamic_normalisation(hull_groups(train, self.hull_min_views), where=str(train_path))
            apply_normalisation([*train, *test], center, scale)
            norm = {"center": center.tolist(), "scale": scale}
        return Scene(
            name=self.root.name, train=train, val=[], test=test, background=self.background,
            view_ids=sorted(v.image_id for v in train), n_frames=len(kept), normalisation=norm,
            extent=cameras_extent([v.camera for v in train]),
            meta=scene_meta("blender_mv", self.root, train, train_cameras=cams, test_cameras=test_cams,
                            n_frames=len(kept), frames_in_file=len(all_ids), time_rescaled=rescale,
                            normalisation_source="per-frame visual hull" if self.normalise else "none"),
        )
