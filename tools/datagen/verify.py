"""Check the rendered datasets: splat the ground-truth surface points through every saved
camera and compare the silhouette with the alpha mask. Needs only numpy + Pillow
(works in the project's environment or in .venv-datagen).

    python tools/datagen/verify.py [data]

Per view it computes, with ``splat`` = pixels hit by at least one projected point
(pixel centres at i + 0.5, so pixel index = floor(u)):
  * iou_raw      IoU(splat, alpha > 0)
  * iou_closed   IoU(close(splat, 3x3), alpha > 0)  (morphological closing fills sampling holes)
  * iou_dil      IoU(dilate(splat, 3x3), dilate(alpha > 0, 3x3))
and prints the per-scene minimum/mean of each. Exit code 1 if any scene's mean iou_dil < 0.97.
The files under data/formats/ are checked the same way through their own camera files.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from PIL import Image

MIN_MEAN_IOU_DIL = 0.97


def _dilate(m: np.ndarray) -> np.ndarray:
    p = np.pad(m, 1)
    out = np.zeros_like(m)
    for dy in range(3):
        for dx in range(3):
            out |= p[dy : dy + m.shape[0], dx : dx + m.shape[1]]
    return out


def _erode(m: np.ndarray) -> np.ndarray:
    return ~_dilate(~m)


def _iou(a, b):
    u = (a | b).sum()
    return 1.0 if u == 0 else float((a & b).sum() / u)


def project(points: np.ndarray, c2w: np.ndarray, camera_angle_x: float, w: int, h: int):
    """Blender/OpenGL camera-to-world -> integer pixel indices (row, col) of visible points."""
    f = 0.5 * w / math.tan(0.5 * camera_angle_x)
    R = c2w[:3, :3]
    t = c2w[:3, 3]
    pc = (points - t) @ R  # world -> camera (R orthonormal)
    z = -pc[:, 2]
    ok = z > 1e-6
    u = 0.5 * w + f * pc[ok, 0] / z[ok]
    v = 0.5 * h - f * pc[ok, 1] / z[ok]
    col = np.floor(u).astype(np.int64)
    row = np.floor(v).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return row[inside], col[inside]


def view_metrics(points, c2w, angle_x, rgba_path):
    a = np.asarray(Image.open(rgba_path))[..., 3]
    h, w = a.shape
    mask = a > 0
    splat = np.zeros((h, w), dtype=bool)
    r, c = project(points, np.asarray(c2w, dtype=np.float64), angle_x, w, h)
    splat[r, c] = True
    closed = _erode(_dilate(splat))
    return {
        "iou_raw": _iou(splat, mask),
        "iou_closed": _iou(closed | splat, mask),
        "iou_dil": _iou(_dilate(splat), _dilate(mask)),
    }


def check_scene(scene_dir: Path):
    gt = np.load(scene_dir / "gt_points.npz")
    pts = gt["points"].astype(np.float64)
    times = gt["times"] if "times" in gt.files else None
    rows = []
    for js in sorted(scene_dir.glob("transforms_*.json")):
        meta = json.loads(js.read_text())
        angle_x = float(meta["camera_angle_x"])
        for fr in meta["frames"]:
            if times is None:
                p = pts
            else:
                k = int(np.argmin(np.abs(times - float(fr["time"]))))
                assert abs(times[k] - float(fr["time"])) < 1e-6, "no gt points at this time"
                p = pts[k]
            png = scene_dir / (fr["file_path"] + ".png")
            rows.append(view_metrics(p, fr["transform_matrix"], angle_x, png))
    keys = rows[0].keys()
    return {k: (min(r[k] for r in rows), float(np.mean([r[k] for r in rows]))) for k in keys}, len(rows)


def _metrics(splat_rc, mask):
    splat = np.zeros_like(mask)
    splat[splat_rc] = True
    closed = _erode(_dilate(splat))
    return {
        "iou_raw": _iou(splat, mask),
        "iou_closed": _iou(closed | splat, mask),
        "iou_dil": _iou(_dilate(splat), _dilate(mask)),
    }


def project_P(points, P, w, h):
    """OpenCV 3x4 (or padded 4x4) world->pixel projection; pixel index = floor(u)."""
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    x = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ P.T
    ok = x[:, 2] > 1e-6
    col = np.floor(x[ok, 0] / x[ok, 2]).astype(np.int64)
    row = np.floor(x[ok, 1] / x[ok, 2]).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return row[inside], col[inside]


def rq_decompose(P):
    """NeuS/IDR-style decomposition of P = world_mat @ scale_mat into K (upper-triangular,
    positive diagonal, K[2,2] = 1) and the camera-to-world pose (OpenCV axes)."""
    M = np.asarray(P, dtype=np.float64)[:3, :3]
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ M).T)
    K = flip @ r.T @ flip
    R = flip @ q.T
    sgn = np.diag(np.sign(np.diag(K)))
    K, R = K @ sgn, sgn @ R
    if np.linalg.det(R) < 0:
        R = -R
        K = -K
    t = np.linalg.solve(K, np.asarray(P, dtype=np.float64)[:3, 3])
    pose = np.eye(4)
    pose[:3, :3] = R.T
    pose[:3, 3] = -R.T @ t
    return K / K[2, 2], pose


def check_neus_dir(cam_dir: Path, points_by_frame):
    """cameras_sphere.npz + mask/<id>.png: project with world_mat, and check that
    world_mat @ scale_mat maps the unit sphere around the subject (|x_unit| <= 1)."""
    cams = np.load(cam_dir / "cameras_sphere.npz")
    rows = []
    for mpath in sorted((cam_dir / "mask").glob("*.png")):
        i = int(mpath.stem)
        mask = np.asarray(Image.open(mpath)) > 0
        pts = points_by_frame(i)
        S = cams[f"scale_mat_{i}"]
        unit = (pts - S[:3, 3]) / S[0, 0]
        assert np.linalg.norm(unit, axis=1).max() <= 1.0 + 1e-5, "scale_mat does not enclose the object"
        K, pose = rq_decompose(cams[f"world_mat_{i}"] @ S)
        assert abs(K[0, 1]) < 1e-6 * K[0, 0] and K[0, 0] > 0 and K[1, 1] > 0, K
        assert abs(K[0, 2] - mask.shape[1] / 2) < 1e-4 and abs(K[1, 2] - mask.shape[0] / 2) < 1e-4, K
        assert np.linalg.norm(pose[:3, 3]) > 1.0, "camera inside the unit sphere"
        rows.append(_metrics(project_P(pts, cams[f"world_mat_{i}"], mask.shape[1], mask.shape[0]), mask))
    return rows


def check_nerfies(scene_dir: Path, gt_npz: Path):
    gt = np.load(gt_npz)
    meta = json.loads((scene_dir / "metadata.json").read_text())
    ds = json.loads((scene_dir / "dataset.json").read_text())
    rows = []
    for iid in ds["ids"]:
        cam = json.loads((scene_dir / "camera" / f"{iid}.json").read_text())
        Rw2c = np.asarray(cam["orientation"])
        c = np.asarray(cam["position"])
        f = cam["focal_length"]
        cx, cy = cam["principal_point"]
        K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
        P = K @ np.concatenate([Rw2c, (-Rw2c @ c)[:, None]], axis=1)
        a = np.asarray(Image.open(scene_dir / "rgb" / "1x" / f"{iid}.png").convert("RGB")).astype(int).sum(-1)
        pts = gt["points"][meta[iid]["time_id"]].astype(np.float64)
        # RGB over black: background is exactly 0 (a few dark object pixels may be 0 too)
        rows.append(_metrics(project_P(pts, P, a.shape[1], a.shape[0]), a > 0))
    return rows


def _summary(rows):
    keys = rows[0].keys()
    return {k: (min(r[k] for r in rows), float(np.mean([r[k] for r in rows]))) for k in keys}


def check_formats(root: Path):
    out = {}
    for d in sorted((root / "formats" / "owlii_neus").glob("*")):
        gt = np.load(root / "dynamic_mv" / d.name / "gt_points.npz")
        rows = []
        for cam_dir in sorted(d.glob("cam_*")):
            rows += check_neus_dir(cam_dir, lambda i, gt=gt: gt["points"][i].astype(np.float64))
        out[f"formats/owlii_neus/{d.name}"] = (_summary(rows), len(rows))
    for d in sorted((root / "formats" / "dtu_neus").glob("*")):
        pts = np.load(d / "gt_points.npz")["points"].astype(np.float64)
        rows = check_neus_dir(d, lambda i, pts=pts: pts)
        out[f"formats/dtu_neus/{d.name}"] = (_summary(rows), len(rows))
    for d in sorted((root / "formats" / "nerfies").glob("*")):
        rows = check_nerfies(d, root / "dynamic_mono" / d.name / "gt_points.npz")
        out[f"formats/nerfies/{d.name}"] = (_summary(rows), len(rows))
    return out


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    root = Path(argv[0]) if argv else Path(__file__).resolve().parents[2] / "data"
    ok = True
    results = {}
    for gt in sorted(root.glob("*/*/gt_points.npz")):
        if gt.parent.parent.name == "formats":
            continue
        results[str(gt.parent.relative_to(root))] = check_scene(gt.parent)
    if (root / "formats").is_dir():
        results.update(check_formats(root))
    for name, (stats, n) in results.items():
        line = "  ".join(f"{k} min {mn:.3f} mean {me:.3f}" for k, (mn, me) in stats.items())
        print(f"{name} ({n} views): {line}")
        ok &= stats["iou_dil"][1] >= MIN_MEAN_IOU_DIL
    print("[verify] " + ("ok" if ok else f"FAILED: some scene has mean iou_dil < {MIN_MEAN_IOU_DIL}"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
