"""The compressed splat file (LightGaussian's vector quantisation, Fan et al., NeurIPS 2024, Sec. 3.4).

Splat attributes are stored as the model holds them (raw): centres [N, 3], log-scales [N, 3], (w, x, y, z)
quaternions [N, 4] (normalised before storing), logit opacities [N] and SH coefficients [N, K, 3]
(K = (degree + 1)^2, index 0 the DC term; colour = max(0, SH + 0.5)). The SH coefficients of the
``vq_ratio`` least significant splats are replaced by the index of the nearest entry of a K-means codebook
(fitted with the splats' significance as weights); the most significant splats keep theirs. Everything but
the centres is stored in half precision, the codebook included (the reference code keeps the centres in
float32). The file is a ``numpy.savez_compressed`` archive of plain numeric arrays, read back with
``allow_pickle=False`` (no code runs when it is loaded):

=============  ==========================================================================
``format``     [1] int64, :data:`FORMAT_VERSION`
``n``          [1] int64, number of splats N
``sh_degree``  [1] int64, SH degree of the coefficients
``means``      [N, 3] float32 (float16 with ``half_means``)
``scales``     [N, 3] float16 log-scales
``quats``      [N, 4] float16 unit quaternions (w, x, y, z)
``opacities``  [N] float16 logits
``raw_mask``   bit-packed [N] bool: True where the SH coefficients are stored raw
``sh_raw``     [N_raw, K, 3] float16 coefficients of those splats (in splat order)
``codebook``   [C, K * 3] float16 codebook
``index_bits`` [1] int64, b = bits per codebook index (max(1, ceil(log2 C)))
``vq_index``   bit-packed [N - N_raw, b] bits of each remaining splat's codebook index (MSB first)
=============  ==========================================================================
"""

from __future__ import annotations

import io
import math
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from src.utils.record import atomic_write_bytes

FORMAT_VERSION = 1
COMPRESSED_FILE = "splats_compressed.npz"
#: Raw attribute names, with their shapes per splat (``sh`` is [K, 3]).
ATTRIBUTES = ("means", "scales", "quats", "opacities", "sh")


def nearest_code(x: Tensor, codebook: Tensor, chunk: int = 8192) -> Tensor:
    """[M] index of the codebook row [C, D] nearest (Euclidean) to each row of ``x`` [M, D] (ties: lowest)."""
    out = torch.empty(x.shape[0], dtype=torch.long)
    c2 = (codebook * codebook).sum(1)  # [C]
    for i in range(0, x.shape[0], chunk):
        xi = x[i:i + chunk]
        d = (xi * xi).sum(1, keepdim=True) - 2.0 * xi @ codebook.T + c2[None, :]  # [m, C]
        out[i:i + chunk] = d.argmin(1)
    return out


def weighted_kmeans(x: Tensor, weights: Tensor, k: int, iters: int,
                    generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Weighted K-means (Lloyd) of the rows of ``x`` [M, D]; returns (codebook [min(k, M), D], assignment [M]).

    Centres start at ``k`` distinct rows drawn with probability proportional to ``weights`` [M] (>= 0); each
    iteration assigns every row to its nearest centre and moves each centre to the weighted mean of its rows.
    A centre left without rows takes the row with the largest weighted error (as the reference code
    re-seeds its least used codes with the most significant vectors).
    """
    x = x.float()
    m = x.shape[0]
    k = min(int(k), m)
    if k <= 0:
        return x.new_zeros(0, x.shape[1]), torch.zeros(m, dtype=torch.long)
    w = weights.float().clamp_min(0)
    w = w / w.max() if float(w.max()) > 0 else torch.ones_like(w)
    w = w + 1e-6  # every row can be drawn and pulls its centre a little
    codebook = x[torch.multinomial(w, k, replacement=False, generator=generator)].clone()  # [k, D]
    assign = nearest_code(x, codebook)
    for _ in range(iters):
        sums = torch.zeros_like(codebook).index_add_(0, assign, x * w[:, None])
        mass = torch.zeros(k).index_add_(0, assign, w)
        filled = mass > 0
        codebook[filled] = sums[filled] / mass[filled, None]
        empty = torch.nonzero(~filled).squeeze(1)
        if empty.numel():
            err = w * ((x - codebook[assign]) ** 2).sum(1)
            codebook[empty] = x[torch.argsort(err, descending=True, stable=True)[: empty.numel()]]
        new = nearest_code(x, codebook)
        if torch.equal(new, assign) and not empty.numel():
            break
        assign = new
    return codebook, nearest_code(x, codebook)


def encode(attrs: dict[str, Tensor], significance: Tensor, vq_ratio: float = 0.6, codebook_size: int = 8192,
           kmeans_iters: int = 20, generator: torch.Generator | None = None,
           half_means: bool = False) -> dict[str, np.ndarray]:
    """The arrays of the compressed file (module docstring) of raw splat attributes.

    Args:
        attrs: ``means`` [N, 3], ``scales`` [N, 3] (log), ``quats`` [N, 4] (wxyz), ``opacities`` [N] (logit),
            ``sh`` [N, K, 3].
        significance: [N] global significance; the ``round(vq_ratio * N)`` lowest get codebook SH
            (the rest keep theirs), weighted by it in the K-means fit.
        vq_ratio: fraction of splats whose SH coefficients are vector-quantised (LightGaussian: 0.6).
        codebook_size: K-means codebook entries C (LightGaussian: 8192; fewer if fewer splats are quantised).
        kmeans_iters: Lloyd iterations.
        generator: RNG of the codebook initialisation.
        half_means: store the centres in float16 too (the reference keeps float32).
    """
    missing = [a for a in ATTRIBUTES if a not in attrs]
    if missing:
        raise ValueError(f"encode: missing attributes {missing}")
    if not 0.0 <= vq_ratio <= 1.0 or codebook_size < 1:
        raise ValueError(f"vq_ratio={vq_ratio} must be in [0, 1] and codebook_size={codebook_size} >= 1")
    a = {k: attrs[k].detach().to("cpu", torch.float32) for k in ATTRIBUTES}
    n, k_sh = a["means"].shape[0], a["sh"].shape[1]
    degree = math.isqrt(k_sh) - 1
    if (degree + 1) ** 2 != k_sh or a["sh"].shape != (n, k_sh, 3):
        raise ValueError(f"encode: sh has shape {tuple(a['sh'].shape)}, expected ({n}, (d + 1)^2, 3)")
    generator = generator if generator is not None else torch.Generator().manual_seed(0)
    sig = significance.detach().to("cpu", torch.float32).reshape(n)
    n_vq = round(vq_ratio * n)
    order = torch.argsort(sig, descending=True, stable=True)
    raw = torch.ones(n, dtype=torch.bool)
    raw[order[n - n_vq:]] = False  # the n_vq least significant are quantised
    flat = a["sh"].reshape(n, k_sh * 3)
    codebook, index = weighted_kmeans(flat[~raw], sig[~raw], codebook_size, kmeans_iters, generator)
    codebook = codebook.half().float()  # assign to the codebook as it is stored
    index = nearest_code(flat[~raw], codebook) if codebook.shape[0] else index
    bits = max(1, math.ceil(math.log2(max(codebook.shape[0], 1))))
    index_bits = ((index[:, None] >> torch.arange(bits - 1, -1, -1)) & 1).to(torch.uint8).numpy()  # [n_vq, b]
    quats = torch.nn.functional.normalize(a["quats"], dim=-1)
    return {
        "format": np.array([FORMAT_VERSION], np.int64), "n": np.array([n], np.int64),
        "sh_degree": np.array([degree], np.int64),
        "means": a["means"].numpy().astype(np.float16 if half_means else np.float32),
        "scales": a["scales"].numpy().astype(np.float16), "quats": quats.numpy().astype(np.float16),
        "opacities": a["opacities"].reshape(n).numpy().astype(np.float16),
        "raw_mask": np.packbits(raw.numpy()), "sh_raw": a["sh"][raw].numpy().astype(np.float16),
        "codebook": codebook.numpy().astype(np.float16), "index_bits": np.array([bits], np.int64),
        "vq_index": np.packbits(index_bits.reshape(-1)),
    }


def decode(arrays: dict[str, np.ndarray]) -> dict[str, Tensor]:
    """Raw float32 attributes (``means``, ``scales``, ``quats``, ``opacities``, ``sh``) of :func:`encode`'s arrays."""
    version = int(arrays["format"][0])
    if version != FORMAT_VERSION:
        raise ValueError(f"compressed splats of format {version}, this reader knows {FORMAT_VERSION}")
    n, degree, bits = int(arrays["n"][0]), int(arrays["sh_degree"][0]), int(arrays["index_bits"][0])
    k_sh = (degree + 1) ** 2
    raw = torch.from_numpy(np.unpackbits(arrays["raw_mask"], count=n).astype(bool))
    n_vq = n - int(raw.sum())
    codebook = torch.from_numpy(arrays["codebook"].astype(np.float32))  # [C, K * 3]
    idx_bits = np.unpackbits(arrays["vq_index"], count=n_vq * bits).reshape(n_vq, bits).astype(np.int64)
    index = torch.from_numpy(idx_bits @ (1 << np.arange(bits - 1, -1, -1, dtype=np.int64)))  # [n_vq]
    if n_vq and (codebook.shape[0] == 0 or int(index.max()) >= codebook.shape[0]):
        raise ValueError(f"compressed splats: codebook index out of range ({codebook.shape[0]} entries)")
    sh = torch.empty(n, k_sh, 3)
    sh[raw] = torch.from_numpy(arrays["sh_raw"].astype(np.float32)).reshape(-1, k_sh, 3)
    if n_vq:
        sh[~raw] = codebook[index].reshape(n_vq, k_sh, 3)
    out = {k: torch.from_numpy(arrays[k].astype(np.float32)) for k in ("means", "scales", "quats", "opacities")}
    out["sh"] = sh
    return out


def write_compressed(path: Path | str, arrays: dict[str, np.ndarray]) -> int:
    """Write :func:`encode`'s arrays as a compressed ``.npz`` at ``path`` (atomically); returns its size in bytes."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    data = buf.getvalue()
    atomic_write_bytes(path, data)
    return len(data)


def read_compressed(path: Path | str) -> dict[str, Tensor]:
    """Decode the compressed file at ``path`` into raw float32 attributes (:func:`decode`).

    Loaded with ``numpy.load(allow_pickle=False)``: only plain numeric arrays are read, no code runs. Raises
    FileNotFoundError for a missing file and ValueError naming the file for a malformed one.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such compressed splat file")
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        return decode(arrays)
    except (KeyError, ValueError, OSError, EOFError, IndexError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: unreadable compressed splats ({type(e).__name__}: {e})") from e
