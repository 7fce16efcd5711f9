"""Initial splat centres: visual hull of the training masks, a box, a finished 3DGS run, or SfM points."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from pathlib import Path

import torch
from torch import Tensor

from src.data.base import DatasetError, Scene
from src.data.hull import sample_hull
from src.utils.validate import QUERY_SELECT, ConfigValueError

log = logging.getLogger(__name__)


class Initialiser(ABC):
    """Initial canonical splat centres for a scene (normalised coordinates, [N, 3])."""

    @abstractmethod
    def __call__(self, scene: Scene, generator: torch.Generator) -> Tensor:
        """[N, 3] initial centres, drawn with ``generator``."""


class HullInit(Initialiser):
    """Points uniform inside the visual hull of the training masks (the paper's protocol).

    Args:
        n_points: number of points (reference: 100k; CPU scale: fewer).
        threshold: a point is inside a mask where mask > threshold (reference: 0).
        box: half-size of the cube the points are drawn from (the normalised scene is in [-1, 1]^3).
        first_frame_only: dynamic scenes: True = the hull of frame 0 (reference; right when the subject
            stays in place, as in OwlII); False = the union of the per-frame hulls, ``n_points`` split
            evenly over the frames (for subjects that travel further than their own width, where
            splats of frame 0 never overlap later frames and their gradients only fade them out).
        without_masks: what to do when training views have no mask: ``"sfm"`` = the structure-from-motion
            points when the reader has them (``dataset=colmap``, as ``init=sfm``), else the box; ``"box"`` =
            sample the cube as ``init=box`` does (Nerfies / NeRF-DS layouts); ``"error"`` = refuse. A warning
            names the replacement.

    Raises:
        ConfigValueError: ``without_masks`` not one of the three, naming ``init.without_masks``.
        DatasetError: (when called) training views without masks and ``without_masks="error"``.
    """

    def __init__(self, n_points: int = 100_000, threshold: float = 0.0, box: float = 1.0,
                 first_frame_only: bool = True, without_masks: str = "sfm") -> None:
        if without_masks not in ("sfm", "box", "error"):
            raise ConfigValueError(f"init.without_masks={without_masks!r}: expected 'sfm', 'box' or 'error'")
        self.n_points = n_points
        self.threshold = threshold
        self.box = box
        self.first_frame_only = first_frame_only
        self.without_masks = without_masks

    def __call__(self, scene: Scene, generator: torch.Generator) -> Tensor:
        views = scene.train
        if any(v.mask is None for v in views):
            msg = f"init=hull needs masks, but scene {scene.name} has training views without one"
            if self.without_masks == "error":
                raise DatasetError(f"{msg} (init.without_masks=error): use init=box, init=sfm or "
                                   "init.without_masks=sfm (e.g. for Nerfies/NeRF-DS data or photos without masks)")
            points = scene.meta.get("points")
            if self.without_masks == "sfm" and points is not None and points.shape[0] > 0:
                log.warning("%s: starting from its %d structure-from-motion points instead, as init=sfm does",
                            msg, points.shape[0])
                return SfmInit(self.n_points)(scene, generator)
            log.warning("%s: sampling the box [-%g, %g]^3 instead, as init=box does", msg, self.box, self.box)
            return BoxInit(self.n_points, self.box)(scene, generator)
        frames = sorted({v.camera.frame_id for v in views})
        if scene.is_dynamic and self.first_frame_only:
            frames = frames[:1]
        counts = [self.n_points // len(frames) + (i < self.n_points % len(frames)) for i in range(len(frames))]
        where = f"{scene.meta.get('root', scene.name)}: init=hull"
        return torch.cat([self._sample(n, [v for v in views if v.camera.frame_id == f], generator,
                                       f"{where}, frame {f}" if scene.is_dynamic else where)
                          for f, n in zip(frames, counts, strict=True) if n > 0])

    def _sample(self, n: int, views: list, generator: torch.Generator, where: str) -> Tensor:
        """[n, 3] points inside the visual hull of ``views`` (one frame's training views).

        Raises DatasetError (prefixed by ``where``) naming the views if their hull is empty or unbounded.
        """
        lo = torch.full((3,), -self.box, dtype=torch.float64)
        hi = torch.full((3,), self.box, dtype=torch.float64)
        cams = [v.camera.to("cpu") for v in views]
        masks = [v.mask.cpu() for v in views]
        return sample_hull(n, cams, masks, lo, hi, generator, self.threshold, where=where)


class BoxInit(Initialiser):
    """Points uniform in the cube [-box, box]^3 (3DGS random init for synthetic scenes)."""

    def __init__(self, n_points: int = 100_000, box: float = 1.0) -> None:
        self.n_points = n_points
        self.box = box

    def __call__(self, scene: Scene, generator: torch.Generator) -> Tensor:
        return (torch.rand(self.n_points, 3, generator=generator) * 2 - 1) * self.box


class FromRunInit(Initialiser):
    """Splat centres of a finished 3DGS run (the paper's two-stage Blender protocol).

    Reads ``<run_dir>/splats.ply`` (written by every run at the end of training), keeps points inside
    the training masks' visual hull (reference) and subsamples to ``n_points``.

    Args:
        run_dir: directory of the finished 3DGS run.
        n_points: maximum number of points kept.
        hull_filter: drop points outside the visual hull of the training masks.
        select: how ``n_points`` are chosen from more: ``random`` (uniform, the reference) or
            ``opacity`` (the most opaque splats of the first stage, sigmoid opacity, ties by index).
    """

    def __init__(self, run_dir: str | None = None, n_points: int = 100_000, hull_filter: bool = True,
                 select: str = "random") -> None:
        if select not in QUERY_SELECT:
            raise ValueError(f"init.select={select!r}: expected one of {', '.join(QUERY_SELECT)}")
        self.run_dir = run_dir
        self.n_points = n_points
        self.hull_filter = hull_filter
        self.select = select

    def __call__(self, scene: Scene, generator: torch.Generator) -> Tensor:
        from src.data.hull import inside_hull
        from src.io.ply import read_ply

        if self.run_dir is None:
            raise DatasetError("init=from_run needs init.run_dir=<directory of a finished gs3d run>")
        path = Path(self.run_dir) / "splats.ply"
        if not path.is_file():
            raise DatasetError(
                f"{path} not found: produce it with `python -m src.run +experiment=gs3d "
                f"dataset.root={scene.meta.get('root', '<scene>')} dataset.n_views={len(scene.train)} "
                f"hydra.run.dir={self.run_dir}` (or +experiment=gs3d_stage1 with the same dataset and seed; "
                "+experiment=splatfields3d_2stage trains it itself unless stage1.auto=false)"
            )
        try:
            splats = read_ply(path).splats
        except (OSError, ValueError) as e:
            raise DatasetError(f"init=from_run: {e}; expected the splats.ply a finished run writes") from None
        pts = splats.means.float()                              # [N, 3]
        opacity = splats.opacities.reshape(-1).float()          # [N], in (0, 1)
        bad = ~(torch.isfinite(pts).all(dim=1) & torch.isfinite(opacity))
        if pts.shape[0] == 0 or bool(bad.all()):
            raise DatasetError(f"{path}: init=from_run found no splat with finite centre and opacity "
                               f"({int(bad.sum())} of {pts.shape[0]} non-finite); expected a finished run's splats")
        if bool(bad.any()):
            raise DatasetError(f"{path}: {int(bad.sum())} of {pts.shape[0]} splats have a non-finite centre or "
                               "opacity (a diverged run?); re-train that run or choose another init.run_dir")
        if self.hull_filter and any(v.mask is None for v in scene.train):
            log.warning("init.hull_filter: the training views of %s have no masks; the first stage's centres "
                        "are kept unfiltered", scene.name)
        elif self.hull_filter:
            keep = inside_hull(pts.double(), [v.camera.to("cpu") for v in scene.train],
                               [v.mask.cpu() for v in scene.train])
            pts, opacity = pts[keep], opacity[keep]
        if pts.shape[0] > self.n_points:
            if self.select == "opacity":
                order = torch.sort(opacity, descending=True, stable=True).indices
                pts = pts[order[: self.n_points]]
            else:
                pts = pts[torch.randperm(pts.shape[0], generator=generator)[: self.n_points]]
        return pts


class SfmInit(Initialiser):
    """The structure-from-motion model's 3D points as centres (3DGS's initialisation of real captures).

    Reads ``scene.meta["points"]`` ([P, 3], normalised like the cameras), which ``dataset=colmap`` fills
    from the model's ``points3D``; their colours (``scene.meta["point_colors"]``) stay unused, the
    interface returning centres only. The points come from every image the model was built from, test
    views included, as in the few-view papers' LLFF protocol.

    Args:
        n_points: keep at most this many, a uniform subsample drawn with the generator; fewer are all kept.
    """

    def __init__(self, n_points: int = 100_000) -> None:
        self.n_points = n_points

    def __call__(self, scene: Scene, generator: torch.Generator) -> Tensor:
        points = scene.meta.get("points")
        if points is None:
            raise DatasetError(f"init=sfm needs the 3D points of a structure-from-motion model (dataset=colmap); "
                               f"scene {scene.name} was read by dataset={scene.meta.get('format', '?')}, which has "
                               "none: use init=hull or init=box")
        if points.shape[0] == 0:
            raise DatasetError(f"{scene.meta.get('points_file', scene.name)}: the COLMAP model has no 3D points, which "
                               "init=sfm needs: rebuild it with `python -m src.data.sfm PHOTOS_DIR OUT_DIR` or use "
                               "init=box")
        points = points.float()                                   # [P, 3]
        if points.shape[0] > self.n_points:
            points = points[torch.randperm(points.shape[0], generator=generator)[: self.n_points]]
        return points.clone()
