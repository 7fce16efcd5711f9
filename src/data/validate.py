"""Checks of loaded cameras and images, shared by every reader; errors name the file or view and the field.

A pose must be finite and rigid (rotation block orthonormal with determinant +1, last row 0 0 0 1);
intrinsics finite with positive focal lengths and the principal point inside the image; images at
least :data:`MIN_SIDE` pixels and of the size their camera says. Readers call :func:`check_pose`,
:func:`check_fov` and :func:`check_size` while parsing (so the message names the file and entry);
:func:`validate_scene` checks every view of a loaded :class:`Scene` whatever reader made it.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from src.data.base import DatasetError, Scene

MIN_SIDE = 8  # pixels: smaller images leave too little to fit or to score
RIGID_TOL = 1e-3  # max |R^T R - I| and |det R - 1| of a pose's rotation block


def check_pose(matrix: Tensor, where: str, field: str = "pose") -> None:
    """Raise DatasetError unless ``matrix`` [4, 4] (or [3, 4]) is a finite rigid transform.

    Args:
        matrix: camera-to-world or world-to-camera matrix (either convention: rigidity is the same).
        where: the file and entry, e.g. ``transforms_test.json: frames[3]``.
        field: the field's name in that file, e.g. ``transform_matrix``.
    """
    m = torch.as_tensor(matrix, dtype=torch.float64)
    if m.shape not in ((4, 4), (3, 4)):
        raise DatasetError(f"{where}.{field}: expected a 4x4 matrix, got shape {tuple(m.shape)}")
    if not torch.isfinite(m).all():
        raise DatasetError(f"{where}.{field} holds non-finite values (NaN or Inf)")
    R = m[:3, :3]
    ortho = float((R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max())
    det = float(torch.linalg.det(R))
    if ortho > RIGID_TOL or abs(det - 1.0) > RIGID_TOL:
        raise DatasetError(f"{where}.{field} is not a rigid transform (rotation block: max |R^T R - I| = "
                           f"{ortho:.3g}, det = {det:.4g}; expected an orthonormal rotation with det +1)")
    if m.shape == (4, 4) and float((m[3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)).abs().max()) > 1e-6:
        raise DatasetError(f"{where}.{field}: last row is {m[3].tolist()}, expected [0, 0, 0, 1]")


def check_fov(fov: float, where: str, field: str = "camera_angle_x") -> float:
    """The field of view ``fov`` (radians) as a float; DatasetError unless 0 < fov < pi."""
    try:
        x = float(fov)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {field}={fov!r} is not a number (radians expected)") from None
    if not math.isfinite(x) or not 0.0 < x < math.pi:
        raise DatasetError(f"{where}: {field}={fov!r} must be a field of view in radians with 0 < {field} < pi")
    return x


def check_size(height: int, width: int, where: str, downscale: float = 1.0) -> None:
    """DatasetError if an image (after ``downscale``) is smaller than MIN_SIDE pixels on a side."""
    if min(height, width) < MIN_SIDE:
        how = f" after dataset.downscale={downscale:g}" if downscale != 1.0 else ""
        raise DatasetError(f"{where}: image is {width}x{height} px{how}; at least {MIN_SIDE} px per side are needed"
                           + (" (use a smaller dataset.downscale)" if downscale != 1.0 else ""))


def validate_scene(scene: Scene, source: str) -> None:
    """Check every view of ``scene`` (read from ``source``): rigid finite poses, sane intrinsics, image sizes.

    Raises:
        DatasetError naming ``source``, the split and the view.
    """
    if not scene.train:
        raise DatasetError(f"{source}: no training views")
    for split, views in (("train", scene.train), ("val", scene.val), ("test", scene.test)):
        for i, v in enumerate(views):
            cam = v.camera
            where = f"{source}: {split} view {i} ({cam.name or v.image_id})"
            check_pose(cam.world_to_cam.detach().cpu(), where, "camera pose")
            intr = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}
            bad = {k: x for k, x in intr.items() if not math.isfinite(float(x))}
            if bad or cam.fx <= 0 or cam.fy <= 0:
                raise DatasetError(f"{where}: intrinsics {intr} must be finite with fx, fy > 0")
            check_size(cam.height, cam.width, where)
            if not (0.0 < cam.cx < cam.width and 0.0 < cam.cy < cam.height):
                raise DatasetError(f"{where}: principal point ({cam.cx:.1f}, {cam.cy:.1f}) lies outside the "
                                   f"{cam.width}x{cam.height} image: the image does not match its intrinsics")
            if tuple(v.image.shape) != (cam.height, cam.width, 3):
                raise DatasetError(f"{where}: image of shape {tuple(v.image.shape)} does not match its intrinsics "
                                   f"({cam.height}x{cam.width} px, 3 channels expected)")
            if v.mask is not None and tuple(v.mask.shape) != (cam.height, cam.width):
                raise DatasetError(f"{where}: mask of shape {tuple(v.mask.shape)} does not match the image "
                                   f"({cam.height}x{cam.width})")
            if not bool(torch.isfinite(v.image).all()):
                raise DatasetError(f"{where}: image holds non-finite values")
