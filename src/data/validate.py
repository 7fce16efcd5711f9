"""Checks of files, values, cameras and images, shared by every reader; errors name the file, entry and field.

Every file a reader opens (images, masks, camera and pose files) must resolve, symlinks followed,
inside the resolved ``dataset.root`` (:func:`inside_root`). Every value read from a file is
type-checked before use (:func:`check_number`, :func:`check_int`, :func:`check_list`,
:func:`check_matrix`, :func:`check_array`): a boolean, a string, ``null``, a list of the wrong length
or a non-finite value is refused, never converted. A pose must be finite and rigid (rotation block
orthonormal with determinant +1, last row 0 0 0 1); intrinsics finite with positive focal lengths and
the principal point inside the image; images at least :data:`MIN_SIDE` pixels and of the size their
camera says. Readers call these checks while parsing (so the message names the file and entry);
:func:`validate_scene` checks every view of a loaded :class:`Scene` whatever reader made it.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from src.data.base import DatasetError, Scene

MIN_SIDE = 8  # pixels: smaller images leave too little to fit or to score
RIGID_TOL = 1e-3  # max |R^T R - I| and |det R - 1| of a pose's rotation block
SHOWN_CHARS = 60  # longest rendering of a bad value in a message


def inside_root(root: Path | str, path: Path | str, where: str, what: str = "file",
                written: str | None = None) -> Path:
    """``path`` resolved (symlinks followed); DatasetError unless it lies inside the resolved ``root``.

    Args:
        root: the dataset folder (``dataset.root``); a symlinked root is fine, it is resolved too.
        path: the file as the reader would open it.
        where: the file and entry that named it, e.g. ``transforms_train.json: frames[3]``.
        what: what the file is, e.g. ``image``, ``mask``, ``camera file``.
        written: the path as the entry wrote it (default: ``path``).
    """
    base = Path(root).resolve()
    resolved = Path(path).resolve()
    if not resolved.is_relative_to(base):
        raise DatasetError(f"{where}: {what} '{path if written is None else written}' resolves to {resolved}, "
                           f"outside dataset.root {base}; images, masks and camera files must lie inside the "
                           "dataset folder")
    return resolved


def kind_of(value: object) -> str:
    """What ``value`` is, in the words of a JSON file (``a boolean``, ``null``, ``a list of 3``, ...)."""
    if value is None:
        return "null"
    if isinstance(value, bool | np.bool_):
        return "a boolean"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list | tuple):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, numbers.Integral):
        return "an integer"
    if isinstance(value, numbers.Real):
        return "a number"
    return f"a {type(value).__name__}"


def shown(value: object) -> str:
    """``repr(value)`` cut to :data:`SHOWN_CHARS` characters, on one line."""
    text = " ".join(repr(value).split())
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 3] + "..."


def check_number(value: object, where: str, field: str, expected: str = "a finite number",
                 valid: Callable[[float], bool] | None = None) -> float:
    """``value`` as a float; DatasetError unless it is a finite real number (not a boolean) that is ``valid``.

    Args:
        value: what the file holds.
        where: the file, e.g. ``transforms_train.json``.
        field: the field within it, e.g. ``frames[3].time``.
        expected: what a good value is, for the message (``a time in [0, 1]``).
        valid: an extra test of the float (a range), or None.
    """
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise DatasetError(f"{where}: {field}={shown(value)} is not a number: found {kind_of(value)}, "
                           f"expected {expected}")
    x = float(value)
    if not math.isfinite(x):
        raise DatasetError(f"{where}: {field}={shown(value)} is not finite: expected {expected}")
    if valid is not None and not valid(x):
        raise DatasetError(f"{where}: {field}={shown(value)} is outside the valid range: expected {expected}")
    return x


def check_int(value: object, where: str, field: str, minimum: int | None = 0) -> int:
    """``value`` as an int; DatasetError unless it is an integer (not a boolean or a float) >= ``minimum``."""
    expected = "an integer" if minimum is None else f"an integer >= {minimum}"
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        raise DatasetError(f"{where}: {field}={shown(value)} is not an integer: found {kind_of(value)}, "
                           f"expected {expected}")
    if minimum is not None and int(value) < minimum:
        raise DatasetError(f"{where}: {field}={int(value)} is outside the valid range: expected {expected}")
    return int(value)


def check_list(value: object, where: str, field: str, length: int | None = None) -> list:
    """``value`` as a list; DatasetError unless it is a list (of ``length`` items if given)."""
    if not isinstance(value, list | tuple) or (length is not None and len(value) != length):
        expected = "a list" if length is None else f"a list of {length}"
        raise DatasetError(f"{where}: {field}={shown(value)} is {kind_of(value)}, expected {expected}")
    return list(value)


def check_matrix(value: object, where: str, field: str, shape: tuple[int, ...]) -> Tensor:
    """Nested lists of numbers (as a JSON file holds them) as a float64 tensor of ``shape``.

    Raises:
        DatasetError naming the first entry that is not a list of the right length or not a number
        (booleans, strings and ``null`` are refused), or the field if it holds NaN or Inf.
    """
    text = "x".join(str(n) for n in shape)

    def walk(item: object, dims: tuple[int, ...], name: str) -> object:
        if not dims:
            if isinstance(item, bool | np.bool_) or not isinstance(item, numbers.Real):
                raise DatasetError(f"{where}: {name}={shown(item)} is not a number: found {kind_of(item)}, "
                                   f"expected a number ({field} must be {text} numbers)")
            return float(item)
        if not isinstance(item, list | tuple) or len(item) != dims[0]:
            raise DatasetError(f"{where}: {name}={shown(item)} is {kind_of(item)}, expected a list of {dims[0]} "
                               f"({field} must be {text} numbers)")
        return [walk(x, dims[1:], f"{name}[{k}]") for k, x in enumerate(item)]

    m = torch.tensor(walk(value, shape, field), dtype=torch.float64)
    if not torch.isfinite(m).all():
        raise DatasetError(f"{where}: {field} holds non-finite values (NaN or Inf)")
    return m


def check_array(array: np.ndarray, where: str, field: str, shapes: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """An array read from a binary file (npz) as float64; DatasetError unless numeric, of one of ``shapes``, finite."""
    text = " or ".join("x".join(str(n) for n in s) for s in shapes)
    if array.dtype.kind not in "iuf":
        raise DatasetError(f"{where}: '{field}' holds {array.dtype} values, expected numbers (a {text} matrix)")
    if array.shape not in shapes:
        raise DatasetError(f"{where}: '{field}' has shape {array.shape}, expected {text}")
    if not np.isfinite(array).all():
        raise DatasetError(f"{where}: '{field}' holds non-finite values (NaN or Inf)")
    return array.astype(np.float64)


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


def check_fov(fov: object, where: str, field: str = "camera_angle_x") -> float:
    """The field of view ``fov`` (radians) as a float; DatasetError unless a number with 0 < fov < pi."""
    x = check_number(fov, where, field, f"radians with 0 < {field} < pi")
    if not 0.0 < x < math.pi:
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
