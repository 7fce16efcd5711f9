"""DTU reader in the NeuS / IDR layout with the pixelNeRF sparse-view split.

Layout: ``image/*.png`` (or ``rgb/``), ``mask/*.png`` (matched by position; NeuS names masks
``000.png`` and images ``000000.png``), ``cameras_sphere.npz`` with ``world_mat_i`` = K [R | t]
(OpenCV world -> pixels) and ``scale_mat_i`` for the i-th image in sorted-name order. The cameras
come from the RQ decomposition of P = world_mat @ scale_mat (see :mod:`src.data.owlii`): OpenCV
(x right, y down, z forward), the FULL intrinsics are kept (fx, fy and the principal point; the
reference code kept only the field of view, i.e. assumed a centred principal point).

Split (pixelNeRF / RegNeRF protocol): training ids ``[25, 22, 28, 40, 44, 48, 0, 8, 13][:n_views]``
(3 views -> 25, 22, 28); ids ``[3-7, 16-21, 36-39]`` are excluded; the test views are all remaining
ids that are neither excluded nor in the full 9-id training list (25 views on the 49-image scans).

Normalisation: the data is already in the unit sphere through ``scale_mat`` (no visual-hull fit);
``Scene.normalisation`` records center = scale_mat[:3, 3], scale = 1 / scale_mat[0, 0].
"""

from __future__ import annotations

from src.data.base import DatasetError, DatasetReader, Scene, View
from src.data.blender import parse_background
from src.data.detect import check_format, check_root
from src.data.dnerf import scene_meta, strided
from src.data.normalise import cameras_extent
from src.data.owlii import COMPOSITE_MODES, folder_frames, neus_cameras, neus_view, scale_mat_normalisation

PIXELNERF_TRAIN = [25, 22, 28, 40, 44, 48, 0, 8, 13]
PIXELNERF_EXCLUDE = [3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39]


class DTUDataset(DatasetReader):
    """Reader for DTU scans in the NeuS/IDR layout (static scene, sparse training views).

    Args:
        root: scan folder holding ``image/``, ``mask/`` and ``cameras_sphere.npz``.
        n_views: number of training views, the first ``n_views`` of ``train_ids`` (None = all of them).
        train_ids: training-id order (default: pixelNeRF's [25, 22, 28, 40, 44, 48, 0, 8, 13]).
        exclude_ids: ids never used for testing (default: pixelNeRF's excluded ids).
        test_ids: explicit test ids (None = every id not excluded and not in ``train_ids``).
        downscale: image downscale factor (2 = half resolution).
        background: ``white`` (default), ``black``, ``grey`` or [r, g, b].
        composite: ``premultiplied`` (RGB stored over black, this project's renders), ``straight``
            (rgb * mask + bg * (1 - mask)) or ``none`` (keep real DTU photos as they are).
        n_test: keep this many evenly strided test views (None = all).
    """

    def __init__(self, root: str, n_views: int | None = 3, train_ids: list[int] | None = None,
                 exclude_ids: list[int] | None = None, test_ids: list[int] | None = None, downscale: float = 1.0,
                 background: str | list[float] = "white", composite: str = "premultiplied",
                 n_test: int | None = None) -> None:
        self.root = check_root(root)
        if downscale <= 0:
            raise DatasetError(f"dataset.downscale={downscale} must be > 0")
        if composite not in COMPOSITE_MODES:
            raise DatasetError(f"dataset.composite={composite!r}: expected one of {COMPOSITE_MODES}")
        self.train_ids = [int(i) for i in (PIXELNERF_TRAIN if train_ids is None else train_ids)]
        if n_views is not None and not 1 <= n_views <= len(self.train_ids):
            raise DatasetError(f"dataset.n_views={n_views} must be between 1 and {len(self.train_ids)} "
                             f"(the training-id list {self.train_ids})")
        self.n_views = n_views
        self.exclude_ids = [int(i) for i in (PIXELNERF_EXCLUDE if exclude_ids is None else exclude_ids)]
        self.test_ids = None if test_ids is None else [int(i) for i in test_ids]
        self.downscale = float(downscale)
        self.background = parse_background(background)
        self.composite = composite
        self.n_test = n_test

    def load(self) -> Scene:
        """Read the scan: the selected training views, the test views, cameras in the unit-sphere frame."""
        check_format(self.root, "dtu")
        images, masks = folder_frames(self.root, root=self.root)
        npz = self.root / "cameras_sphere.npz"
        cams = neus_cameras(npz, len(images), self.root, self.root)
        chosen = self.train_ids[: self.n_views] if self.n_views is not None else list(self.train_ids)
        test_ids = self.test_ids if self.test_ids is not None else [
            i for i in range(len(images)) if i not in self.exclude_ids and i not in self.train_ids]
        for i in (*chosen, *test_ids):
            if not 0 <= i < len(images):
                raise DatasetError(f"{self.root}: view id {i} requested but the scan has {len(images)} images")
        if not test_ids:
            raise DatasetError(f"{self.root}: no test views left after removing training and excluded ids")
        test_ids = [test_ids[k] for k in strided(len(test_ids), self.n_test)]

        def view(i: int) -> View:
            K, w2c, _ = cams[i]
            return neus_view(K, w2c, images[i], masks[i], self.background, self.downscale, self.composite, i,
                             name=images[i].stem)

        train = [view(i) for i in chosen]
        test = [view(i) for i in test_ids]
        norm = scale_mat_normalisation(cams[chosen[0]][2], str(npz))
        return Scene(
            name=self.root.name, train=train, val=[], test=test, background=self.background, view_ids=chosen,
            n_frames=1, normalisation=norm, extent=cameras_extent([v.camera for v in train]),
            meta=scene_meta("dtu", self.root, train, n_images=len(images), test_ids=test_ids,
                            composite=self.composite, normalisation_source="scale_mat (unit sphere)"),
        )
