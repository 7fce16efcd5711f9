"""Camera-format helpers shared by the renderer and the format writers (numpy + Pillow only,
no bpy, so they also run in the project's environment)."""

from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def write_json(path: Path, obj) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")


def write_npz(path: Path, **arrays) -> None:
    """Like np.savez_compressed, but with deterministic bytes (fixed zip timestamps, sorted keys).

    A Fortran-ordered array is stored as such (np.load gives back the same values and shape);
    for [F, N, 3] point tracks this puts each point's coordinate over time next to each other,
    so static or slowly moving parts compress well."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for key in sorted(arrays):
            buf = io.BytesIO()
            arr = np.asarray(arrays[key])
            if not arr.flags.f_contiguous:  # keep Fortran order when the caller asked for it
                arr = np.ascontiguousarray(arr)
            np.lib.format.write_array(buf, arr, allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue(), compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)


def save_png(img: Image.Image, dst: Path) -> None:
    """Deterministic, maximally compressed PNG without text chunks."""
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True, compress_level=9)
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(buf.getvalue())


def opencv_K(w, h, angle_x):
    f = 0.5 * w / math.tan(0.5 * angle_x)
    return np.array([[f, 0.0, 0.5 * w], [0.0, f, 0.5 * h], [0.0, 0.0, 1.0]])


def world_mat_from_c2w(c2w_gl, K):
    """NeuS/IDR world_mat = K [R|t] (OpenCV world->image), padded to 4x4."""
    c2w_cv = np.asarray(c2w_gl, dtype=np.float64) @ GL_TO_CV
    w2c = np.linalg.inv(c2w_cv)
    P = np.eye(4)
    P[:3, :4] = K @ w2c[:3, :4]
    return P


def scale_mat_from_points(points, margin=1.05):
    """Maps the unit sphere onto a sphere enclosing the object: x_world = S @ x_unit."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = 0.5 * (pts.min(0) + pts.max(0))
    radius = float(np.linalg.norm(pts - centre, axis=1).max()) * margin
    S = np.diag([radius, radius, radius, 1.0])
    S[:3, 3] = centre
    return S


def rgb_and_mask(src_png: Path, rgb_dst: Path, mask_dst: Path, bg=(0, 0, 0)):
    """RGBA -> RGB composited over ``bg`` and an 8-bit grey alpha mask (both max-compressed)."""
    arr = np.asarray(Image.open(src_png).convert("RGBA")).astype(np.float64)
    a = arr[..., 3:4] / 255.0
    rgb = np.clip(np.round(arr[..., :3] * a + np.asarray(bg, dtype=np.float64) * (1.0 - a)), 0, 255)
    save_png(Image.fromarray(rgb.astype(np.uint8), "RGB"), rgb_dst)
    if mask_dst is not None:
        save_png(Image.fromarray(arr[..., 3].astype(np.uint8), "L"), mask_dst)
