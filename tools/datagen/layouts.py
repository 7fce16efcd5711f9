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


MESH_QUANT = 65535  # gt_mesh.npz vertex coordinates: uint16 steps across the bounding box


def delta_planes(x: np.ndarray) -> np.ndarray:
    """uint16 array [..., N] -> uint8 [2, ..., N]: differences along the last axis (the first entry kept),
    modulo 2^16, as a low-byte and a high-byte plane. Neighbouring entries that change little (a vertex
    over time, consecutive indices) turn into runs of small numbers, which deflate compresses well."""
    x = np.asarray(x, dtype=np.uint16)
    d = np.diff(x, axis=-1, prepend=np.zeros_like(x[..., :1]))  # uint16 arithmetic wraps modulo 2^16
    return np.stack([d & 0xFF, d >> 8]).astype(np.uint8)


def undelta_planes(planes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`delta_planes`."""
    d = planes[0].astype(np.uint16) | (planes[1].astype(np.uint16) << 8)
    return np.cumsum(d, axis=-1, dtype=np.uint16)


def write_gt_mesh(path: Path, vertices, faces, times=None) -> float:
    """Write a ground-truth triangle mesh (one topology, vertices per frame) compactly to ``path``.

    ``vertices`` [V, 3] (static) or [F, V, 3] (one set per frame), ``faces`` [T, 3] vertex indices
    (V <= 65536). The coordinates are quantised to uint16 ``q`` in the bounding box over all frames,
    ``world = offset + q * step`` (65535 steps per axis), and, like the face indices, stored through
    :func:`delta_planes`:

    * ``vertices``: uint8 [2, 3, V] of ``q`` as [3, V] (static; differences along the vertex list) or
      [2, 3, V, F] of ``q`` as [3, V, F] (dynamic; differences over time);
    * ``faces``: uint8 [2, 3 T] of the flattened index list;
    * ``offset``, ``step``: [3] float64; ``times``: [F] float32 (dynamic only).

    Returns the largest coordinate error of the quantisation (<= step / 2)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    assert v.shape[-1] == 3 and f.ndim == 2 and f.shape[1] == 3 and f.min() >= 0 and f.max() < v.shape[-2]
    assert v.shape[-2] <= 65536, "more than 65536 vertices"
    lo = v.reshape(-1, 3).min(0)
    hi = v.reshape(-1, 3).max(0)
    step = np.maximum(hi - lo, 1e-12) / MESH_QUANT
    q = np.clip(np.round((v - lo) / step), 0, MESH_QUANT).astype(np.uint16)
    err = float(np.abs(lo + q * step - v).max())
    arrays = {
        "vertices": delta_planes(q.transpose(2, 1, 0) if q.ndim == 3 else q.T),  # [3, V(, F)]
        "offset": lo,
        "step": step,
        "faces": delta_planes(f.reshape(-1).astype(np.uint16)),
    }
    if times is not None:
        arrays["times"] = np.asarray(times, dtype=np.float32)
    write_npz(path, **arrays)
    return err


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
