"""``python -m src.data.texture ROOT [ROOT ...] [--split train]``

How much fine texture a scene's object carries, from its images alone: the mean Sobel gradient
magnitude of the luminance over the object's pixels (``texture_energy``). It reads no result, so it can
be computed for a scene before anything is trained on it. Across the project's fifteen scenes the
most textured ones have the smallest leads of SplatFields3D over 3DGS at 4 views and 100 px on average,
but the measure does not decide the sign: of the two highest values, ``heldout/robot`` (3DGS ahead by
1.1 dB) and ``heldout/chess`` (SplatFields3D ahead by 0.9 dB) (docs/results.md, "Where the field loses").

Conventions: Blender-layout scenes (``transforms_<split>.json`` and RGBA images, straight alpha);
luminance Y = 0.299 R + 0.587 G + 0.114 B of the image composited on white; the object's pixels are
those with alpha >= 0.99, shrunk by ``erode`` pixels so that the silhouette's edge against the
background is not counted; the gradient is per pixel of the image as stored, so a scene rendered at
twice the size scores lower (0.77-0.84x on the project's scenes at 200 against 100 px).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import binary_erosion
from skimage.filters import sobel

from src.data.base import DatasetError
from src.data.blender import load_transforms, resolve_image
from src.data.images import composite, read_image

LUMA = np.array([0.299, 0.587, 0.114])


def image_texture_energy(rgba: np.ndarray, erode: int = 2) -> tuple[float, float]:
    """(mean Sobel gradient of the luminance over the object's pixels, object fraction) of one image.

    ``rgba``: [H, W, 4] float in [0, 1], straight alpha. Returns (nan, 0) when no pixel is the object's.
    """
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"expected an [H, W, 4] RGBA image, got shape {tuple(rgba.shape)}")
    image = torch.from_numpy(rgba)
    rgb, alpha = (t.numpy() for t in composite(image, torch.ones(3, dtype=image.dtype)))
    luma = rgb @ LUMA  # [H, W], on white
    mask = alpha >= 0.99
    if erode > 0:
        mask = binary_erosion(mask, iterations=erode)
    if not mask.any():
        return float("nan"), 0.0
    return float(sobel(luma)[mask].mean()), float(mask.mean())


def texture_energy(root: Path | str, split: str = "train", erode: int = 2) -> dict[str, float]:
    """Mean over a split's images of ``image_texture_energy``: {"texture_energy", "object_fraction", "images"}."""
    root = Path(root)
    json_path = root / f"transforms_{split}.json"
    energies, fractions = [], []
    for i, frame in enumerate(load_transforms(json_path)["frames"]):  # errors name the file, frame and field
        path = resolve_image(root, frame["file_path"], json_path, i)
        image = read_image(path).numpy()
        if image.shape[2] != 4:
            raise DatasetError(
                f"{path}: expected an RGBA image (the object's mask is its alpha), got {image.shape[2]} channels"
            )
        energy, fraction = image_texture_energy(image, erode)
        if fraction > 0:
            energies.append(energy)
            fractions.append(fraction)
    if not energies:
        raise DatasetError(f"{root}: no image of split {split!r} shows the object (alpha >= 0.99)")
    return {
        "texture_energy": float(np.mean(energies)),
        "object_fraction": float(np.mean(fractions)),
        "images": len(energies),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m src.data.texture", description=__doc__.split("\n\n")[1])
    parser.add_argument("roots", nargs="+", help="scene directories in the Blender layout")
    parser.add_argument("--split", default="train", help="transforms_<split>.json to read (default: train)")
    parser.add_argument("--erode", type=int, default=2, help="pixels shrunk off the object's mask (default: 2)")
    args = parser.parse_args(argv)
    print(f"{'scene':40s} {'texture_energy':>14s} {'object_fraction':>15s} {'images':>6s}")
    for root in args.roots:
        try:
            stats = texture_energy(root, args.split, args.erode)
        except (DatasetError, OSError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        print(f"{root!s:40s} {stats['texture_energy']:14.4f} {stats['object_fraction']:15.3f} {stats['images']:6d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
