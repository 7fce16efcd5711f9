"""LightGaussian's vector quantisation of a trained 3DGS model (Fan et al., NeurIPS 2024, Sec. 3.4).

``compress=lightgaussian`` (``+experiment=lightgaussian``): after training, the model's raw splat attributes
are written to ``<run>/splats_compressed.npz`` (:mod:`src.io.compressed`: a K-means codebook for the SH
coefficients of the least significant splats, half precision elsewhere), the file is read back, and the
model's parameters are replaced by the decoded ones, so that the evaluation, ``splats.ply`` and every
metric describe the DECOMPRESSED splats. Significance: :func:`src.strategy.significance.global_significance`
over the training views. The block returned goes into ``metrics.json`` (``size_mb``, ``psnr_before_vq``, ...).
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import Tensor, nn

from src.data.base import Scene
from src.eval.evaluator import views_psnr
from src.io.compressed import COMPRESSED_FILE, encode, read_compressed, write_compressed
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer
from src.strategy.significance import SCORES, global_significance
from src.utils.instantiate import ConfigError

log = logging.getLogger(__name__)
MIB = 2**20
#: The free-splat parameters the compressed file stores (a GaussianSplatModel's ``params``).
PARAMS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def model_attributes(model: SplatModel) -> dict[str, Tensor]:
    """Raw attributes of a free-splat (3DGS) model: means, log-scales, wxyz quats, logit opacities and the SH
    coefficients [N, K, 3] up to its active degree (what its renders use)."""
    params = getattr(model, "params", None)
    if not isinstance(params, nn.ParameterDict) or any(k not in params for k in PARAMS):
        raise ConfigError(f"compress: {type(model).__name__} has no free per-splat parameters {PARAMS} "
                          "(the compressed file holds 3DGS-type splats; use model=gs3d or lightgaussian)")
    k = (int(getattr(model, "active_sh_degree", 0)) + 1) ** 2
    sh = torch.cat([params["sh0"], params["shN"]], dim=1)[:, :k]
    return {"means": params["means"], "scales": params["scales"], "quats": params["quats"],
            "opacities": params["opacities"], "sh": sh}


@torch.no_grad()
def load_attributes(model: SplatModel, attrs: dict[str, Tensor]) -> None:
    """Overwrite a free-splat model's parameters with decoded ``attrs`` (same splat count and order).

    SH bands the file does not hold (above its degree) are set to zero; the model's degrees are unchanged.
    """
    params = model.params
    n = params["means"].shape[0]
    if attrs["means"].shape[0] != n:
        raise ValueError(f"decoded {attrs['means'].shape[0]} splats for a model of {n}")
    for k in ("means", "scales", "quats", "opacities"):
        params[k].data.copy_(attrs[k].reshape(params[k].shape).to(params[k]))
    sh = attrs["sh"].to(params["sh0"])  # [N, K, 3]
    params["sh0"].data.copy_(sh[:, :1])
    rest = torch.zeros_like(params["shN"].data)
    m = min(rest.shape[1], sh.shape[1] - 1)
    rest[:, :m] = sh[:, 1:1 + m]
    params["shN"].data.copy_(rest)


class LightGaussianCompression:
    """Write the VQ-compressed splat file, then evaluate from what it decodes to.

    Args:
        vq_ratio: fraction of splats (least significant first) whose SH coefficients get a codebook index
            (LightGaussian: 0.6).
        codebook_size: K-means codebook entries (LightGaussian: 8192).
        kmeans_iters: Lloyd iterations of the codebook fit.
        volume_power: beta of the significance's volume term (LightGaussian: 0.1).
        score: significance per pixel, ``hits`` (the paper's) or ``blend``.
        half_means: store the centres in float16 too (reference: float32).
        quantise: score ``psnr_before_vq`` on 8-bit renders, as the evaluation does.
        seed: seed of the codebook initialisation.
    """

    enabled = True

    def __init__(self, vq_ratio: float = 0.6, codebook_size: int = 8192, kmeans_iters: int = 20,
                 volume_power: float = 0.1, score: str = "hits", half_means: bool = False, quantise: bool = True,
                 seed: int = 0) -> None:
        if not 0.0 <= vq_ratio <= 1.0 or codebook_size < 1 or kmeans_iters < 0 or score not in SCORES:
            raise ValueError(f"compress: vq_ratio={vq_ratio} in [0, 1], codebook_size={codebook_size} >= 1, "
                             f"kmeans_iters={kmeans_iters} >= 0 and score in {SCORES} expected")
        self.vq_ratio, self.codebook_size, self.kmeans_iters = vq_ratio, codebook_size, kmeans_iters
        self.volume_power, self.score, self.half_means = volume_power, score, half_means
        self.quantise, self.seed = quantise, seed

    def apply(self, model: SplatModel, rasterizer: Rasterizer, scene: Scene, run_dir: Path) -> dict:
        """Compress ``model`` to ``run_dir / COMPRESSED_FILE``, load the decoded splats into it; returns the metrics."""
        if scene.is_dynamic:
            raise ConfigError("compress: the compressed splat file holds one static splat set (a static scene)")
        attrs = model_attributes(model)
        was_training = model.training
        model.eval()
        before = views_psnr(model.splats, rasterizer, scene.test, scene.background, self.quantise) if scene.test \
            else float("nan")
        sig = global_significance(model, rasterizer, scene.train, self.volume_power, self.score)
        arrays = encode(attrs, sig, self.vq_ratio, self.codebook_size, self.kmeans_iters,
                        torch.Generator().manual_seed(int(self.seed)), self.half_means)
        path = Path(run_dir) / COMPRESSED_FILE
        size = write_compressed(path, arrays)
        load_attributes(model, read_compressed(path))
        model.train(was_training)
        n = model.n_splats
        n_vq = n - int(arrays["sh_raw"].shape[0])
        log.info("compressed %d splats to %s (%.3f MiB; %d with codebook SH)", n, path.name, size / MIB, n_vq)
        return {"size_mb": size / MIB, "psnr_before_vq": before, "n_vq": n_vq,
                "codebook_size": int(arrays["codebook"].shape[0]), "sh_degree": int(arrays["sh_degree"][0])}
