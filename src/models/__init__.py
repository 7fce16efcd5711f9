"""Scene models: what produces the splats that get rendered.

* ``GaussianSplatModel`` (3DGS baseline): free per-splat parameters.
* ``SplatFieldsModel``: splat attributes predicted by neural fields at canonical points.
* ``ScaffoldGSModel`` (Scaffold-GS baseline): splats decoded per view from anchors by small MLPs.
* ``Gaussian4DModel`` (4D-GS baseline): free 4D Gaussians, sliced at the render time.

Conventions: raw parameters are log-scales, logit-opacities and unnormalised (w, x, y, z)
quaternions; ``splats(camera)`` returns activated attributes in OpenCV world coordinates.
"""

from src.models.base import SplatModel

__all__ = ["SplatModel"]
