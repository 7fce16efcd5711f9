"""Scene and view containers shared by every dataset reader."""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from src.core.cameras import Camera


class DatasetError(ValueError):
    """A dataset could not be read: the message names the file, the field and what was expected."""


def read_json(path: Path, what: str) -> dict:
    """A JSON object from ``path`` (DatasetError naming the file if missing or malformed)."""
    if not path.is_file():
        raise DatasetError(f"{what} not found: {path}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: malformed JSON ({e})") from e
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


@dataclass
class View:
    """One calibrated image.

    Attributes:
        camera: OpenCV camera (normalised scene coordinates).
        image: [H, W, 3] float in [0, 1], composited on the scene background.
        mask: [H, W] float in [0, 1] (foreground alpha), or None if the dataset has no masks.
        image_id: index of the image within its split (as listed in the file).
    """

    camera: Camera
    image: Tensor
    mask: Tensor | None
    image_id: int

    def on_background(self, background: Tensor, stored: Tensor) -> View:
        """This view composited on ``background`` [3] instead of the ``stored`` [3] colour it was read on.

        Exact for images composited as ``rgb * alpha + stored * (1 - alpha)`` with ``alpha`` = ``mask``
        (every masked reader here): ``image + (1 - mask) * (background - stored)``. Needs a mask.
        """
        if self.mask is None:
            raise ValueError(f"view {self.image_id} ({self.camera.name}) has no mask: "
                             "it cannot be put on another background")
        shift = (background - stored).to(self.image).reshape(1, 1, 3)
        image = self.image + (1 - self.mask)[..., None] * shift       # [H, W, 3]
        return View(camera=self.camera, image=image, mask=self.mask, image_id=self.image_id)


@dataclass
class Scene:
    """A loaded scene: training / validation / test views and what describes the scene.

    Attributes:
        name: scene name (folder name).
        train, val, test: views; ``train`` holds only the selected sparse views.
        background: [3] background colour the images were composited on.
        view_ids: indices (into the full training list) of the selected training views.
        n_frames: number of time steps (1 for static scenes).
        normalisation: dict(center=[3], scale=float): world_normalised = scale * (world - center).
        extent: 1.1 x the largest distance of a training camera from their centroid (3DGS's
            "cameras extent", used to scale position learning rates and densification thresholds).
        meta: free-form reader information (format, root, resolution, ...).
    """

    name: str
    train: list[View]
    val: list[View]
    test: list[View]
    background: Tensor
    view_ids: list[int]
    n_frames: int = 1
    normalisation: dict = field(default_factory=dict)
    extent: float = 1.0
    meta: dict = field(default_factory=dict)

    @property
    def is_dynamic(self) -> bool:
        return self.n_frames > 1

    @property
    def image_size(self) -> list[int]:
        """[W, H] in pixels of the first training view (every run records it as ``image_size``)."""
        cam = self.train[0].camera
        return [int(cam.width), int(cam.height)]

    def to(self, device: torch.device | str) -> Scene:
        """Move every image, mask and camera to ``device`` (in place) and return self."""
        for views in (self.train, self.val, self.test):
            for v in views:
                v.camera = v.camera.to(device)
                v.image = v.image.to(device)
                if v.mask is not None:
                    v.mask = v.mask.to(device)
        self.background = self.background.to(device)
        return self


class DatasetReader(ABC):
    """A scene reader (one per file format): constructor arguments are the ``dataset/`` config keys."""

    @abstractmethod
    def load(self) -> Scene:
        """Read the scene: selected training views, test (and val) views, normalised OpenCV cameras."""
