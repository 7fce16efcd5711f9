"""Read and write splat sets in the 3D Gaussian Splatting PLY layout, through :mod:`plyfile`.

One ``vertex`` element, binary little-endian ``float`` properties, in this order (the order that
common splat viewers expect)::

    x, y, z, nx, ny, nz, f_dc_0, f_dc_1, f_dc_2, f_rest_0 .. f_rest_{3(K-1)-1},
    opacity, scale_0, scale_1, scale_2, rot_0, rot_1, rot_2, rot_3

Conventions: ``opacity`` is a logit (opacity = sigmoid(value)); ``scale_*`` are natural logs of the
standard deviations along the splat's local axes; ``rot_*`` is a (w, x, y, z) quaternion; ``nx..nz``
are zeros; colour = 0.5 + C0 * f_dc (degree-0 spherical harmonics). ``f_rest`` holds the higher SH
bands ([N, K-1, 3] with K = (degree + 1)^2), stored channel-major ([3, K-1] per splat) as 3DGS does.

Dynamic (4D) runs may also hold one PLY per time step under ``<run_dir>/frames/``, indexed by
``frames/frames.json`` (see :func:`write_baked_frames` and :func:`read_baked_frames`).
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError
from torch import Tensor

from src.core.splats import Splats
from src.models.sh import C0, rgb_to_sh0
from src.utils.record import atomic_write_bytes, atomic_write_text

BAKED_PLY = "splats.ply"
FRAMES_DIR = "frames"
FRAMES_INDEX = "frames.json"

_HEAD = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
_TAIL = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
# What a reader needs (normals are optional: some exporters omit them).
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *_TAIL)


@dataclass
class PlySplats:
    """Activated splats read from a PLY plus optional higher-order SH coefficients [N, K-1, 3]."""

    splats: Splats
    sh_rest: Tensor | None

    @property
    def means(self) -> Tensor:
        """[N, 3] splat centres."""
        return self.splats.means


@dataclass(frozen=True)
class BakedFrame:
    """One per-time-step PLY of a dynamic run: the dataset's ``frame_id``, its ``time`` in [0, 1], the file."""

    frame_id: int
    time: float
    path: Path


def ply_property_names(n_rest: int = 0) -> list[str]:
    """Vertex property names, in file order, for ``n_rest`` ``f_rest_*`` values per splat (3 (K-1))."""
    return [*_HEAD, *(f"f_rest_{i}" for i in range(n_rest)), *_TAIL]


def _logit(p: Tensor) -> Tensor:
    p = p.clamp(1e-7, 1 - 1e-7)
    return torch.log(p) - torch.log1p(-p)


def ply_bytes(splats: Splats, sh_rest: Tensor | None = None) -> bytes:
    """The PLY file (binary little-endian) of activated ``splats`` and optional SH rest [N, K-1, 3].

    ``splats`` hold linear scales, opacities in (0, 1), (w, x, y, z) quaternions and RGB colours; the
    file gets log-scales, logit opacities, normalised quaternions and DC coefficients (module docstring).
    """
    if splats.colors.ndim != 2 or splats.colors.shape[1] != 3:
        raise ValueError(f"PLY export needs RGB colours (C = 3), got colours of shape {tuple(splats.colors.shape)}")
    splats.validate()
    s = splats.detach().to("cpu", torch.float32)
    n = s.n
    rest = np.zeros((n, 0), np.float32)
    if sh_rest is not None and sh_rest.shape[1] > 0:
        if sh_rest.ndim != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != 3:
            raise ValueError(f"sh_rest has shape {tuple(sh_rest.shape)}, expected ({n}, K-1, 3)")
        rest = sh_rest.detach().cpu().float().permute(0, 2, 1).reshape(n, -1).numpy()
    q = torch.nn.functional.normalize(s.quats, dim=-1)
    cols = [s.means.numpy(), np.zeros((n, 3), np.float32), rgb_to_sh0(s.colors).numpy(), rest,
            _logit(s.opacities)[:, None].numpy(), torch.log(s.scales.clamp_min(1e-12)).numpy(), q.numpy()]
    table = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    names = ply_property_names(rest.shape[1])
    vertex = np.empty(n, dtype=[(nm, "<f4") for nm in names])
    for i, nm in enumerate(names):
        vertex[nm] = table[:, i]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(buf)
    return buf.getvalue()


def write_ply(path: Path | str, splats: Splats, sh_rest: Tensor | None = None) -> None:
    """Write activated ``splats`` (RGB colours, C = 3) and optional SH rest [N, K-1, 3] to ``path`` atomically.

    The file stores log-scales, logit opacities and (w, x, y, z) quaternions (layout: module docstring).
    """
    atomic_write_bytes(path, ply_bytes(splats, sh_rest))


def read_ply(path: Path | str) -> PlySplats:
    """Read a 3DGS-layout PLY (this project's, 3DGS's or gsplat's; any PLY format and numeric type).

    Returns activated splats: linear scales = exp(scale_*), opacities = sigmoid(opacity), (w, x, y, z)
    quaternions as stored, RGB = 0.5 + C0 * f_dc; ``sh_rest`` [N, K-1, 3] if the file has ``f_rest_*``.
    Parsing is data-only (no code runs). Raises FileNotFoundError for a missing file and ValueError
    naming the file and the property for a malformed one.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such PLY file")
    try:
        ply = PlyData.read(str(path))
    except PlyParseError as e:
        raise ValueError(f"{path}: malformed PLY ({e})") from e
    except (ValueError, EOFError, UnicodeDecodeError, IndexError, TypeError) as e:
        raise ValueError(f"{path}: unreadable PLY ({type(e).__name__}: {e})") from e
    try:
        vertex = ply["vertex"]
    except KeyError:
        found = ", ".join(el.name for el in ply.elements) or "none"
        raise ValueError(f"{path}: no 'vertex' element (found: {found})") from None
    data = vertex.data
    names = [p.name for p in vertex.properties]
    for req in _REQUIRED:
        if req not in names:
            raise ValueError(f"{path}: missing vertex property '{req}' (3DGS layout needs {', '.join(_REQUIRED)})")
    n = len(data)
    rest_keys = [k for k in names if k.startswith("f_rest_")]
    for k in rest_keys:
        if not k[len("f_rest_"):].isdigit():
            raise ValueError(f"{path}: malformed vertex property name '{k}' (expected f_rest_<index>)")
    rest_keys.sort(key=lambda k: int(k[len("f_rest_"):]))
    if [int(k[len("f_rest_"):]) for k in rest_keys] != list(range(len(rest_keys))) or len(rest_keys) % 3:
        raise ValueError(f"{path}: malformed f_rest_* properties ({len(rest_keys)} found; expected "
                         "f_rest_0 .. f_rest_{3m-1} without gaps)")

    def column(key: str) -> np.ndarray:
        col = data[key]
        if col.dtype.kind not in "fiu":
            raise ValueError(f"{path}: vertex property '{key}' is not a numeric scalar (type {col.dtype})")
        col = col.astype(np.float32)
        if not np.isfinite(col).all():
            bad = int(np.flatnonzero(~np.isfinite(col))[0])
            raise ValueError(f"{path}: vertex property '{key}' is not finite at vertex {bad}")
        return col

    def get(keys: Sequence[str]) -> Tensor:
        return torch.from_numpy(np.stack([column(k) for k in keys], axis=1).reshape(n, len(keys)))

    sh_rest = None
    if rest_keys:
        sh_rest = get(rest_keys).reshape(n, 3, -1).permute(0, 2, 1).contiguous()
    splats = Splats(
        means=get(["x", "y", "z"]),
        scales=torch.exp(get(["scale_0", "scale_1", "scale_2"])),
        quats=get(["rot_0", "rot_1", "rot_2", "rot_3"]),
        opacities=torch.sigmoid(get(["opacity"])[:, 0]),
        colors=(0.5 + C0 * get(["f_dc_0", "f_dc_1", "f_dc_2"])),
    )
    return PlySplats(splats=splats, sh_rest=sh_rest)


def _trained_sh_rest(model) -> Tensor | None:
    """The higher SH bands a model trained (``shN`` up to its active degree), or None."""
    params = getattr(model, "params", None)
    degree = int(getattr(model, "active_sh_degree", 0) or 0)
    if params is None or "shN" not in params or degree <= 0:
        return None
    k = (degree + 1) ** 2 - 1
    return params["shN"].detach()[:, :k].to("cpu", torch.float32)


def _bake(model, time: float = 0.0, frame_id: int = 0) -> Splats | None:
    try:
        baked = model.bake(time=time, frame_id=frame_id)
    except NotImplementedError:
        return None
    return baked.to("cpu") if baked.colors.shape[1] == 3 else None


def write_baked_ply(model, run_dir: Path | str, frames: Sequence[tuple[int, float]] | None = None,
                    max_frames: int | None = 30) -> None:
    """The model's baked splat set as ``<run_dir>/splats.ply`` (read by ``init=from_run`` and viewers).

    The file holds activated splats as log-scales, logit opacities and (w, x, y, z) quaternions with
    DC colours; a model with trained higher SH bands (3DGS, ``active_sh_degree`` > 0) also writes them
    as ``f_rest_*`` so splat viewers show its view-dependent colour (this project's readers use DC).
    For a dynamic scene, pass ``frames`` as its (frame_id, time) pairs (:func:`scene_frames`) to also
    write per-time-step PLYs (:func:`write_baked_frames`, at most ``max_frames``, None = all).
    Skipped for models that cannot bake and for non-RGB colour channels.
    """
    baked = _bake(model)
    if baked is None:
        return
    write_ply(Path(run_dir) / BAKED_PLY, baked, _trained_sh_rest(model))
    if frames is not None and len({fid for fid, _ in frames}) > 1:
        write_baked_frames(model, run_dir, frames, max_frames)


def scene_frames(scene) -> list[tuple[int, float]]:
    """Distinct (frame_id, time) pairs of a scene's training views, sorted by time ([] if static)."""
    if getattr(scene, "n_frames", 1) <= 1:
        return []
    by_id: dict[int, float] = {}
    for v in scene.train:
        by_id.setdefault(int(v.camera.frame_id), float(v.camera.time))
    return sorted(by_id.items(), key=lambda ft: (ft[1], ft[0]))


def _evenly(items: list, k: int | None) -> list:
    if k is None or len(items) <= k:
        return items
    if k <= 1:
        return items[:1]
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))
    return [items[i] for i in idx]


def write_baked_frames(model, run_dir: Path | str, frames: Sequence[tuple[int, float]],
                       max_frames: int | None = 30) -> list[BakedFrame]:
    """Bake ``model`` at each (frame_id, time) of ``frames`` into ``<run_dir>/frames/frame_<id>.ply``.

    Needs only the model in memory (no checkpoint); ``max_frames`` (None = all) keeps that many frames
    evenly spread in time. Writes the index ``frames/frames.json`` ({"frames": [{frame_id, time, file}]})
    last, so a reader never sees an index naming a missing file. Files hold DC colours, log-scales,
    logit opacities and (w, x, y, z) quaternions. Returns the frames written ([] if the model cannot bake).
    """
    out_dir = Path(run_dir) / FRAMES_DIR
    chosen = _evenly(sorted({int(f): float(t) for f, t in frames}.items(), key=lambda ft: (ft[1], ft[0])),
                     max_frames)
    written: list[BakedFrame] = []
    for fid, t in chosen:
        baked = _bake(model, time=t, frame_id=fid)
        if baked is None:
            return []
        path = out_dir / f"frame_{fid:04d}.ply"
        out_dir.mkdir(parents=True, exist_ok=True)
        write_ply(path, baked)
        written.append(BakedFrame(fid, t, path))
    if written:
        index = {"frames": [{"frame_id": f.frame_id, "time": f.time, "file": f.path.name} for f in written]}
        atomic_write_text(out_dir / FRAMES_INDEX, json.dumps(index, indent=2) + "\n")
    return written


def read_baked_frames(run_dir: Path | str) -> list[BakedFrame]:
    """The per-time-step PLYs of a run (from ``frames/frames.json``), sorted by time; [] if there is no index.

    Raises ValueError naming the index for a malformed one or one that names a missing file.
    """
    index_path = Path(run_dir) / FRAMES_DIR / FRAMES_INDEX
    if not index_path.is_file():
        return []
    try:
        entries = json.loads(index_path.read_text())["frames"]
        frames = [BakedFrame(int(e["frame_id"]), float(e["time"]), index_path.parent / str(e["file"]))
                  for e in entries]
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{index_path}: malformed frame index ({type(e).__name__}: {e})") from e
    for f in frames:
        if f.path.parent != index_path.parent:
            raise ValueError(f"{index_path}: frame {f.frame_id} names a file outside {index_path.parent}")
        if not f.path.is_file():
            raise ValueError(f"{index_path}: frame {f.frame_id} names {f.path}, which does not exist")
    return sorted(frames, key=lambda f: (f.time, f.frame_id))
