"""Read and write splat sets in the 3DGS PLY layout (binary little-endian).

Vertex properties, in order: x, y, z, nx, ny, nz, f_dc_0..2, f_rest_0..(3(K-1)-1), opacity,
scale_0..2, rot_0..3. ``opacity`` is a logit, ``scale_*`` are log standard deviations, ``rot_*`` a
(w, x, y, z) quaternion, colour = 0.5 + C0 * f_dc (degree-0 SH). ``f_rest`` is stored channel-major
([3, K-1] per splat) as 3DGS does.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from src.core.splats import Splats
from src.models.sh import C0, rgb_to_sh0
from src.utils.record import atomic_write_bytes


@dataclass
class PlySplats:
    """Activated splats read from a PLY plus optional higher-order SH [N, K-1, 3]."""

    splats: Splats
    sh_rest: Tensor | None

    @property
    def means(self) -> Tensor:
        return self.splats.means


def _logit(p: Tensor) -> Tensor:
    p = p.clamp(1e-7, 1 - 1e-7)
    return torch.log(p) - torch.log1p(-p)


def write_ply(path: Path | str, splats: Splats, sh_rest: Tensor | None = None) -> None:
    """Write activated ``splats`` (RGB colours, C = 3) to ``path`` atomically."""
    if splats.colors.shape[1] != 3:
        raise ValueError(f"PLY export needs RGB colours (C = 3), got C = {splats.colors.shape[1]}")
    s = splats.detach().to("cpu", torch.float32)
    n = s.n
    rest = np.zeros((n, 0), np.float32)
    if sh_rest is not None and sh_rest.shape[1] > 0:
        rest = sh_rest.detach().cpu().float().permute(0, 2, 1).reshape(n, -1).numpy()
    q = torch.nn.functional.normalize(s.quats, dim=-1)
    cols = [s.means.numpy(), np.zeros((n, 3), np.float32), rgb_to_sh0(s.colors).numpy(), rest,
            _logit(s.opacities)[:, None].numpy(), torch.log(s.scales.clamp_min(1e-12)).numpy(), q.numpy()]
    data = np.concatenate(cols, axis=1).astype("<f4")
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(rest.shape[1])]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {nm}\n" for nm in names) + "end_header\n"
    atomic_write_bytes(path, header.encode("ascii") + data.tobytes())


def read_ply(path: Path | str) -> PlySplats:
    """Read a 3DGS-layout PLY written by this project or by 3DGS/gsplat (binary little-endian floats)."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    header = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary_little_endian PLY is supported")
    n = 0
    names: list[str] = []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n = int(parts[2])
        elif parts[:1] == ["property"]:
            if parts[1] != "float":
                raise ValueError(f"{path}: property {parts[-1]} has type {parts[1]}, expected float")
            names.append(parts[2])
    body = np.frombuffer(raw[end + len(b"end_header\n"):], dtype="<f4", count=n * len(names))
    table = body.reshape(n, len(names))
    col = {nm: i for i, nm in enumerate(names)}
    for req in ("x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"):
        if req not in col:
            raise ValueError(f"{path}: missing vertex property '{req}'")

    def get(keys: list[str]) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(table[:, [col[k] for k in keys]]))

    rest_keys = sorted((k for k in names if k.startswith("f_rest_")), key=lambda k: int(k.split("_")[-1]))
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


def write_baked_ply(model, run_dir: Path) -> None:
    """The model's baked splat set as ``<run_dir>/splats.ply`` (read by ``init=from_run`` and viewers).

    Skipped for models that cannot bake and for non-RGB colour channels.
    """
    try:
        baked = model.bake()
    except NotImplementedError:
        return
    if baked.colors.shape[1] == 3:
        write_ply(Path(run_dir) / "splats.ply", baked.to("cpu"))
