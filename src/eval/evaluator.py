"""Scores a trained model on the test (and training) views and writes the renders."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import torch

from src.core.cameras import Camera
from src.core.splats import Splats
from src.data.base import Scene, View
from src.data.images import write_png
from src.eval.metrics import mean_finite, psnr, quantise, ssim_eval
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer


@torch.no_grad()
def views_psnr(splats_for: Callable[[Camera], Splats], rasterizer: Rasterizer, views: list[View],
               background: torch.Tensor, quantised: bool = True) -> float:
    """Mean PSNR (dB) over ``views`` of the splats ``splats_for(view.camera)`` rendered on ``background``
    (8-bit rounded if ``quantised``, the reference protocol) against the views' images."""
    scores = []
    for v in views:
        img = rasterizer.render(splats_for(v.camera), v.camera, background).color  # [H, W, 3]
        scores.append(psnr(quantise(img) if quantised else img, v.image))
    return mean_finite(scores)


class Evaluator:
    """Test-view evaluation.

    Args:
        save_renders: write test renders (and ground truth) as PNG under ``<run>/renders/test``.
        quantise: score 8-bit-rounded renders (reference protocol).
        train_views: also score the training views (for Tab. C.6's train/test gap).
        moran: compute Moran's I of colour, opacity and covariance of the final splats (B.3-B.5).
        moran_k: neighbourhood size N (5).
        moran_max_splats: subsample to this many splats for Moran's I (kNN cost).
        fps_repeats: renders of the baked model used to time rendering FPS (0 = skip).
        perceptual: score LPIPS (only with user-supplied backbone weights) and ST-LPIPS (if installed) on the
            test views; what cannot be computed is recorded as unavailable, never as a number.
        perceptual_net: LPIPS backbone (``alex`` or ``vgg``).
        curve_every: every this many iterations, score held-out views during training for the learning
            curve (``metrics.json`` ``curve``); 0 = no curve.
        curve_views: how many held-out views (evenly strided) the curve scores: the validation split
            where the reader has one, else the test views (a report, never used to choose settings).
    """

    def __init__(self, save_renders: bool = True, quantise: bool = True, train_views: bool = True,
                 moran: bool = True, moran_k: int = 5, moran_max_splats: int = 50_000,
                 fps_repeats: int = 3, perceptual: bool = True, perceptual_net: str = "alex",
                 curve_every: int = 0, curve_views: int = 4) -> None:
        self.save_renders = save_renders
        self.quantise = quantise
        self.train_views = train_views
        self.moran = moran
        self.moran_k = moran_k
        self.moran_max_splats = moran_max_splats
        self.fps_repeats = fps_repeats
        self.perceptual = perceptual
        self.perceptual_net = perceptual_net
        if curve_every < 0 or curve_views < 1:
            raise ValueError(f"eval.curve_every={curve_every} must be >= 0 and eval.curve_views={curve_views} >= 1")
        self.curve_every = curve_every
        self.curve_views = curve_views

    def curve_scorer(self, scene: Scene, rasterizer: Rasterizer) -> tuple[str, Callable[[SplatModel], float]] | None:
        """(split name, model -> mean held-out PSNR) for learning curves, or None when ``curve_every`` is 0.

        Scores up to ``curve_views`` evenly strided views of ``scene.val`` (``val``) or, where the reader
        has no validation split, of ``scene.test`` (``test``), with the evaluation protocol (8-bit renders).
        """
        if not self.curve_every:
            return None
        split, pool = ("val", scene.val) if scene.val else ("test", scene.test)
        if not pool:
            return None
        step = max(1, len(pool) // self.curve_views)
        views = pool[::step][: self.curve_views]

        @torch.no_grad()
        def score(model: SplatModel) -> float:
            was_training = model.training
            model.eval()
            value = views_psnr(model.splats, rasterizer, views, scene.background, self.quantise)
            model.train(was_training)
            return value

        return split, score

    @torch.no_grad()
    def score_views(self, model: SplatModel, rasterizer: Rasterizer, views: list[View], background,
                    out_dir: Path | None, perceptual: bool = False) -> dict:
        """Per-view and mean PSNR / SSIM (and perceptual metrics if asked) of ``views``; optionally writes renders."""
        per_view = []
        unavailable: dict = {}
        for v in views:
            splats = model.splats(v.camera)
            img = rasterizer.render(splats, v.camera, background).color
            if self.quantise:
                img = quantise(img)
            p, s = psnr(img, v.image), ssim_eval(img, v.image)
            row = {"name": v.camera.name, "image_id": v.image_id, "time": v.camera.time, "psnr": p, "ssim": s}
            if perceptual:
                from src.eval.perceptual import perceptual_metrics

                pm = perceptual_metrics(img, v.image, self.perceptual_net)
                row.update({k: pm[k] for k in ("lpips", "st_lpips") if pm[k] is not None})
                unavailable.update(pm["reasons"])
            per_view.append(row)
            if out_dir is not None:
                stem = f"{v.image_id:04d}_{v.camera.name}"
                write_png(out_dir / f"{stem}.png", img)
                write_png(out_dir / f"{stem}_gt.png", v.image)
        out = {"psnr": mean_finite([x["psnr"] for x in per_view]),
               "ssim": mean_finite([x["ssim"] for x in per_view]), "per_view": per_view}
        for k in ("lpips", "st_lpips"):
            vals = [x[k] for x in per_view if k in x]
            if vals and k not in unavailable:
                out[k] = mean_finite(vals)
        if unavailable:
            out["unavailable_metrics"] = unavailable
        return out

    @torch.no_grad()
    def evaluate(self, model: SplatModel, rasterizer: Rasterizer, scene: Scene, run_dir: Path) -> dict:
        """All evaluation metrics for the run record (``metrics`` block) plus per-view lists."""
        model.eval()
        bg = scene.background
        test = self.score_views(model, rasterizer, scene.test, bg,
                                run_dir / "renders" / "test" if self.save_renders else None, self.perceptual)
        out: dict = {"psnr": test["psnr"], "ssim": test["ssim"], "per_view_test": test["per_view"]}
        out.update({k: test[k] for k in ("lpips", "st_lpips", "unavailable_metrics") if k in test})
        if self.train_views:
            tr = self.score_views(model, rasterizer, scene.train, bg, None)
            out.update({"psnr_train": tr["psnr"], "ssim_train": tr["ssim"],
                        "delta_psnr": tr["psnr"] - test["psnr"]})
        if scene.is_dynamic:
            out["per_frame"] = self._per_frame(test["per_view"])
        baked = self._baked_metrics(model, rasterizer, scene, out)
        if self.moran and baked is not None and baked.n > self.moran_k:
            out.update(self._moran(baked))
        model.train()
        return out

    @torch.no_grad()
    def log_images(self, run_dir: Path, model: SplatModel, rasterizer: Rasterizer, scene: Scene, step: int,
                   n: int = 3) -> None:
        """Write render | ground truth of the first ``n`` test views to TensorBoard (``<run>/tb``, eval/)."""
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run_dir / "tb"))
        try:
            for i, v in enumerate(scene.test[:n]):
                img = rasterizer.render(model.splats(v.camera), v.camera, scene.background).color.clamp(0, 1)
                writer.add_image(f"eval/test_{i}", torch.cat([img, v.image], dim=1).cpu(), step, dataformats="HWC")
        finally:
            writer.close()

    @staticmethod
    def _per_frame(per_view: list[dict]) -> list[dict]:
        """Mean PSNR/SSIM of the test views of each time (dynamic scenes)."""
        frames: dict[float, list[dict]] = {}
        for v in per_view:
            frames.setdefault(v["time"], []).append(v)
        return [{"time": t, "psnr": mean_finite([x["psnr"] for x in vs]), "ssim": mean_finite([x["ssim"] for x in vs]),
                 "n_views": len(vs)} for t, vs in sorted(frames.items())]

    def _baked_metrics(self, model: SplatModel, rasterizer: Rasterizer, scene: Scene, out: dict):
        """Bake the model per test time, score the baked splats and time rendering with/without networks.

        Writes ``baked_psnr``, ``fps_baked`` (network-free splats) and ``fps_fields`` (fields evaluated
        per frame, then rendered) into ``out``; returns the splat set baked at the first test time.
        """
        if not scene.test:
            return None
        bg = scene.background
        cache: dict = {}

        def baked_for(cam):
            key = (cam.frame_id, cam.time)
            if key not in cache:
                cache[key] = model.bake(time=cam.time, frame_id=cam.frame_id)
            return cache[key]

        try:
            first = baked_for(scene.test[0].camera)
        except NotImplementedError:
            return None
        out["baked_psnr"] = views_psnr(baked_for, rasterizer, scene.test, bg, self.quantise)
        if self.fps_repeats > 0:
            cam = scene.test[0].camera
            rasterizer.render(first, cam, bg)  # warm-up
            t0 = time.perf_counter()
            for _ in range(self.fps_repeats):
                rasterizer.render(first, cam, bg)
            out["fps_baked"] = self.fps_repeats / (time.perf_counter() - t0)
            t0 = time.perf_counter()
            for _ in range(self.fps_repeats):
                rasterizer.render(model.splats(cam), cam, bg)
            out["fps_fields"] = self.fps_repeats / (time.perf_counter() - t0)
        return first

    def _moran(self, splats) -> dict:
        from src.losses.moran import covariance_features, knn_indices, morans_i

        s = splats
        if s.n > self.moran_max_splats:
            g = torch.Generator().manual_seed(0)
            s = s.index(torch.randperm(s.n, generator=g)[: self.moran_max_splats])
        nn_idx = knn_indices(s.means, self.moran_k)
        cov = covariance_features(s.scales, s.quats)
        return {f"moran_{k}": float(morans_i(s.means, a, k=self.moran_k, center=True, neighbours=nn_idx))
                for k, a in (("rgb", s.colors), ("opacity", s.opacities), ("cov", cov))}
