"""Re-export shipped renders in other datasets' layouts (numpy + Pillow only, no bpy):

* OwlII / ResFields NeuS layout for a multi-view dynamic scene:
    data/formats/owlii_neus/<scene>/cam_train_<k>/{rgb,mask}/<frame:06d>.png + cameras_sphere.npz
    data/formats/owlii_neus/<scene>/cam_test_<k>/...   (the held-out cameras)
  ``world_mat_<frame>`` = K [R|t] (OpenCV, world -> pixels, 3x4 padded to 4x4; the cameras are
  fixed, so it repeats per frame), ``scale_mat_<frame>`` maps the unit sphere onto a sphere that
  encloses the subject over the whole sequence. RGB is composited over black; mask = alpha.
* Nerfies layout for the monocular sequence:
    data/formats/nerfies/<scene>/{dataset,metadata,scene}.json, camera/<id>.json, rgb/1x/<id>.png
  camera JSON: ``orientation`` = world->camera rotation (OpenCV rows), ``position`` = camera centre,
  ``focal_length``, ``principal_point``, ``image_size`` [w, h], zero distortion.

The DTU-like NeuS layout needs new views and is rendered by render_all.py
(job ``formats/dtu_neus/trinkets``).

    python tools/datagen/formats.py [--data data] [--owlii SCENE ...]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from layouts import (
    GL_TO_CV,
    opencv_K,
    rgb_and_mask,
    scale_mat_from_points,
    world_mat_from_c2w,
    write_json,
    write_npz,
)

OWLII_SCENES = ["mocap_figure"]
NERFIES_SCENES = ["bouncing"]


def export_owlii(data: Path, scene: str) -> int:
    src = data / "dynamic_mv" / scene
    dst = data / "formats" / "owlii_neus" / scene
    if dst.exists():
        shutil.rmtree(dst)
    S = scale_mat_from_points(np.load(src / "gt_points.npz")["points"])
    n = 0
    for split in ("train", "test"):
        meta = json.loads((src / f"transforms_{split}.json").read_text())
        mats: dict[int, dict] = {}
        for fr in meta["frames"]:
            cdir = dst / f"cam_{split}_{fr['camera_id']}"
            png = src / (fr["file_path"] + ".png")
            w, h = Image.open(png).size
            K = opencv_K(w, h, meta["camera_angle_x"])
            name = f"{fr['frame_id']:06d}.png"
            rgb_and_mask(png, cdir / "rgb" / name, cdir / "mask" / name)
            m = mats.setdefault(fr["camera_id"], {})
            m[f"world_mat_{fr['frame_id']}"] = world_mat_from_c2w(fr["transform_matrix"], K)
            m[f"scale_mat_{fr['frame_id']}"] = S
            n += 1
        for cid, m in mats.items():
            write_npz(dst / f"cam_{split}_{cid}" / "cameras_sphere.npz", **m)
    return n


def export_nerfies(data: Path, scene: str) -> int:
    src = data / "dynamic_mono" / scene
    dst = data / "formats" / "nerfies" / scene
    if dst.exists():
        shutil.rmtree(dst)
    ids, train_ids, val_ids, metadata = [], [], [], {}
    n_frames = int(np.load(src / "gt_points.npz")["times"].shape[0])
    for split in ("train", "val", "test"):
        meta = json.loads((src / f"transforms_{split}.json").read_text())
        for k, fr in enumerate(meta["frames"]):
            iid = f"{split}_{k:03d}"
            png = src / (fr["file_path"] + ".png")
            img = Image.open(png).convert("RGBA")
            w, h = img.size
            K = opencv_K(w, h, meta["camera_angle_x"])
            c2w_cv = np.asarray(fr["transform_matrix"], dtype=np.float64) @ GL_TO_CV
            cam = {
                "orientation": c2w_cv[:3, :3].T.tolist(),
                "position": c2w_cv[:3, 3].tolist(),
                "focal_length": float(K[0, 0]),
                "principal_point": [float(K[0, 2]), float(K[1, 2])],
                "skew": 0.0,
                "pixel_aspect_ratio": 1.0,
                "radial_distortion": [0.0, 0.0, 0.0],
                "tangential_distortion": [0.0, 0.0],
                "image_size": [w, h],
            }
            write_json(dst / "camera" / f"{iid}.json", cam)
            rgb_and_mask(png, dst / "rgb" / "1x" / f"{iid}.png", None)
            fid = int(fr["frame_id"])
            metadata[iid] = {
                "time_id": fid,
                "warp_id": fid,
                "appearance_id": fid,
                "camera_id": 0 if split == "train" else 1,
            }
            ids.append(iid)
            (train_ids if split == "train" else val_ids).append(iid)
    write_json(
        dst / "dataset.json",
        {"count": len(ids), "num_exemplars": len(train_ids), "ids": ids, "train_ids": train_ids, "val_ids": val_ids},
    )
    write_json(dst / "metadata.json", metadata)
    write_json(
        dst / "scene.json",
        {
            "scale": 1.0,
            "scene_to_metric": 1.0,
            "center": [0.0, 0.0, 0.0],
            "near": 2.0,
            "far": 6.0,
            "num_time_ids": n_frames,
        },
    )
    return len(ids)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "data")
    ap.add_argument("--owlii", nargs="+", default=None, metavar="SCENE",
                    help="multi-view scenes under DATA/dynamic_mv to export in the OwlII layout, and nothing else "
                         f"(default: the shipped {OWLII_SCENES} and the Nerfies {NERFIES_SCENES})")
    args = ap.parse_args(argv)
    needed = ("transforms_train.json", "transforms_test.json", "gt_points.npz")
    for s in args.owlii or ():  # checked before any export: an export first removes its destination
        missing = [f for f in needed if not (args.data / "dynamic_mv" / s / f).is_file()]
        if missing:
            ap.error(f"--owlii {s}: {args.data / 'dynamic_mv' / s} is not a rendered multi-view scene "
                     f"(expected {', '.join(needed)}; missing {', '.join(missing)})")
    for s in OWLII_SCENES if args.owlii is None else args.owlii:
        print(f"[datagen] formats/owlii_neus/{s}: {export_owlii(args.data, s)} images")
    for s in NERFIES_SCENES if args.owlii is None else ():
        print(f"[datagen] formats/nerfies/{s}: {export_nerfies(args.data, s)} images")


if __name__ == "__main__":
    main()
