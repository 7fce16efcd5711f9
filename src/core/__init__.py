"""Core data types shared by every component: cameras, splat sets, render outputs.

Conventions: OpenCV cameras (x right, y down, z forward), pixel centres at (i + 0.5, j + 0.5),
images [H, W, C] in [0, 1], quaternions (w, x, y, z), activated splat attributes.
"""

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats

__all__ = ["Camera", "RenderOutput", "Splats"]
