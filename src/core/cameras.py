"""Pinhole cameras in the OpenCV convention."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor


@dataclass
class Camera:
    """A calibrated pinhole camera (OpenCV convention: x right, y down, z forward).

    Attributes:
        world_to_cam: [4, 4] rigid transform from world to camera coordinates.
        fx, fy, cx, cy: intrinsics in pixels; a camera point (x, y, z) projects to
            (fx * x / z + cx, fy * y / z + cy), pixel (i, j) has its centre at (i + 0.5, j + 0.5).
        width, height: image size in pixels.
        time: normalised time in [0, 1] (0 for static scenes).
        frame_id: integer frame index of ``time`` in its sequence (0 for static scenes).
        name: an identifier (image file stem or camera id) for logs and file names.
        camera_id: index of the physical camera (multi-view rigs), -1 if unknown.
    """

    world_to_cam: Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    time: float = 0.0
    frame_id: int = 0
    name: str = ""
    camera_id: int = -1
    extras: dict = field(default_factory=dict)

    @property
    def center(self) -> Tensor:
        """[3] camera centre in world coordinates."""
        R = self.world_to_cam[:3, :3]
        t = self.world_to_cam[:3, 3]
        return -R.T @ t

    @property
    def K(self) -> Tensor:
        """[3, 3] intrinsic matrix."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=self.world_to_cam.dtype,
        )

    @property
    def fov_x(self) -> float:
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Camera:
        """A copy with ``world_to_cam`` moved/cast."""
        return replace(self, world_to_cam=self.world_to_cam.to(device=device, dtype=dtype))

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (e.g. 0.5 halves width and height).

        The image plane is scaled about the origin, so pixel-centre conventions are preserved:
        a point at u maps to u * factor.
        """
        w = round(self.width * factor)
        h = round(self.height * factor)
        sx, sy = w / self.width, h / self.height
        return replace(
            self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h
        )

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points [N, 3] to pixel coordinates [N, 2] (u, v) and depths [N]."""
        R = self.world_to_cam[:3, :3].to(points)
        t = self.world_to_cam[:3, 3].to(points)
        pc = points @ R.T + t
        z = pc[:, 2]
        u = self.fx * pc[:, 0] / z + self.cx
        v = self.fy * pc[:, 1] / z + self.cy
        return torch.stack([u, v], dim=-1), z


def opengl_to_opencv(c2w_gl: Tensor) -> Tensor:
    """Convert a camera-to-world matrix from Blender/OpenGL (camera looks along -z, +y up) to OpenCV.

    Right-multiplies by diag(1, -1, -1, 1): flips the camera's y and z axes.
    """
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=c2w_gl.dtype))
    return c2w_gl @ flip


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """World-to-camera [4, 4] (OpenCV) for a camera at ``eye`` looking at ``target``.

    ``up`` (default +z, Blender's world up) maps to the camera's -y (image up).
    """
    if up is None:
        up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-8:  # looking along up: pick any perpendicular
        x = torch.linalg.cross(z, torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], dim=0)  # rows: camera axes in world
    w2c = torch.eye(4, dtype=eye.dtype)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c
