"""Differentiable Gaussian-splat rasterizers behind one interface.

All backends implement :class:`Rasterizer` with the semantics of the original 3DGS CUDA
rasterizer (Kerbl et al. 2023):

* EWA projection Sigma2D = J W Sigma W^T J^T + 0.3 I, where J is the perspective Jacobian evaluated at
  the camera-space centre whose x/z and y/z are clamped to 1.3x the image's half-extent.
* Splats with camera depth z <= 0.2 are culled; radius = ceil(3 sqrt(lambda_max(Sigma2D))).
* Pixels are processed in 16x16 tiles; a splat touches the tiles of its square of half-size
  ``radius`` around its centre (in 3DGS pixel coordinates u - 0.5, v - 0.5).
* alpha = min(0.99, o * exp(-0.5 d^T Sigma2D^-1 d)), skipped if the exponent is positive or
  alpha < 1/255; front-to-back compositing in a stable depth order, stopping before the splat that
  would take the transmittance T below 1e-4; the background adds T_final * bg.
* Conventions: OpenCV cameras, pixel (i, j) centred at (i + 0.5, j + 0.5), colours [H, W, C].

Every backend also takes ``antialiased=True``: Mip-Splatting's 2D Mip filter (Yu et al. 2024,
Sec. 5.2) in place of the 0.3 dilation, Sigma2D + ``filter_2d`` I (0.1) with the opacity multiplied by
sqrt(det(Sigma2D) / det(Sigma2D + filter_2d I)).

``surfels=True`` (every backend) renders the splats as 2D Gaussian surfels instead (2DGS, Huang et al.
2024): explicit ray-splat intersection with the object-space low-pass filter, the same alpha and
compositing rules, and a :class:`~src.core.splats.SurfelRenderOutput` with normal and depth-distortion
maps (:mod:`src.rasterizer.surfel_ref`: the rules and the torch reference; ``surfel_cpu``: the compiled
kernel; ``gsplat_surfel``: gsplat's 2DGS on CUDA).
"""

from src.rasterizer.base import Rasterizer

__all__ = ["Rasterizer"]
