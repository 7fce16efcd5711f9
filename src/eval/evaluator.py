"""Scores a trained model on the test (and training) views and writes the renders."""

from __future__ import annotations

import time
from pathlib import Path

import torch

from src.data.base import Scene, View
from src.data.images import write_png
from src.eval.metrics import mean_finite, psnr, quantise, ssim_eval
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer


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
    """

    def __init__(self, save_renders: bool = True, quantise: bool = True, train_views: bool = True,
                 moran: bool = True, moran_k: int = 5, moran_max_splats: int = 50_000,
                 fps_repeats: int = 3) -> None:
        self.save_renders = save_renders
        self.quantise = quantise
        self.train_views = train_views
        self.moran = moran
        self.moran_k = moran_k
        self.moran_max_splats = moran_max_splats
        self.fps_repeats = fps_repeats

    @torch.no_grad()
    def score_views(self, model: SplatModel, rasterizer: Rasterizer, views: list[View], background,
                    out_dir: Path | None) -> dict:
        """Per-view and mean PSNR / SSIM of ``views``; optionally writes renders."""
        per_view = []
        for v in views:
            splats = model.splats(v.camera)
            img = rasterizer.render(splats, v.camera, background).color
            if self.quantise:
                img = quantise(img)
            p, s = psnr(img, v.image), ssim_eval(img, v.image)
            per_view.append({"name": v.camera.name, "image_id": v.image_id, "time": v.camera.time,
                             "psnr": p, "ssim": s})
            if out_dir is not None:
                stem = f"{v.image_id:04d}_{v.camera.name}"
                write_png(out_dir / f"{stem}.png", img)
                write_png(out_dir / f"{stem}_gt.png", v.image)
        return {"psnr": mean_finite([x["psnr"] for x in per_view]),
                "ssim": mean_finite([x["ssim"] for x in per_view]), "per_view": per_view}

    @torch.no_grad()
    def evaluate(self, model: SplatModel, rasterizer: Rasterizer, scene: Scene, run_dir: Path) -> dict:
        """All evaluation metrics for the run record (``metrics`` block) plus per-view lists."""
        model.eval()
        bg = scene.background
        test = self.score_views(model, rasterizer, scene.test, bg,
                                run_dir / "renders" / "test" if self.save_renders else None)
        out: dict = {"psnr": test["psnr"], "ssim": test["ssim"], "per_view_test": test["per_view"]}
        if self.train_views:
            tr = self.score_views(model, rasterizer, scene.train, bg, None)
            out.update({"psnr_train": tr["psnr"], "ssim_train": tr["ssim"],
                        "delta_psnr": tr["psnr"] - test["psnr"]})
        try:
            baked = model.bake()
        except NotImplementedError:
            baked = None
        if baked is not None and self.fps_repeats > 0 and scene.test:
            cam = scene.test[0].camera
            rasterizer.render(baked, cam, bg)  # warm-up
            t0 = time.perf_counter()
            for _ in range(self.fps_repeats):
                rasterizer.render(baked, cam, bg)
            out["fps_baked"] = self.fps_repeats / (time.perf_counter() - t0)
            out["baked_psnr"] = mean_finite([
                psnr(quantise(rasterizer.render(baked, v.camera, bg).color) if self.quantise
                     else rasterizer.render(baked, v.camera, bg).color, v.image) for v in scene.test])
        if self.moran and baked is not None and baked.n > self.moran_k:
            out.update(self._moran(baked))
        model.train()
        return out

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
