"""SplatFields: an experiment framework for sparse-view 3D/4D reconstruction with neural Gaussian splats.

Conventions used throughout the package (each sub-package repeats the ones it relies on):

* Cameras follow OpenCV: x right, y down, z forward; ``world_to_cam`` is a 4x4 rigid transform.
  A pixel with integer index (i, j) covers [i, i+1) x [j, j+1); its centre is (i + 0.5, j + 0.5).
  A camera-space point (x, y, z) projects to u = fx * x / z + cx, v = fy * y / z + cy.
* Images are float tensors in [0, 1], sRGB-encoded as stored in the PNGs, layout [H, W, C].
* Splats handed to a rasterizer are *activated*: positive linear scales, unit quaternions in
  (w, x, y, z) order, opacities in (0, 1), colours/features as rendered. Models keep their raw
  parameters (log-scales, logit-opacities) and activate them.
* Time is a float in [0, 1]; ``frame_id`` is the integer index of a frame in its sequence.

Importing the package has no side effect: the entry points (``src.run``, ``src.bench``, ``src.view``,
``src.prune``) set the OpenMP threading environment themselves (:mod:`src.kernels.threads`).
"""
