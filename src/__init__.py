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
"""

import os

# OpenMP threads that wait passively: on shared CPUs, spinning barriers of the compiled rasterizer
# and torch stall when a partner thread is descheduled (measured 20x slowdowns under load). Must be
# set before torch loads the OpenMP runtime; an explicit user setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# ... after a short spin: a passive wait alone costs a futex sleep and wake-up per parallel region
# or barrier (~30-60 us on these VMs, ~28 per render: ~15 % of a 10 k-splat render), while ~1 000
# spins (a few us) catch most of them and waste little when the partner is descheduled (two renders
# sharing 2 cores: within 10 % of the pure passive policy; 20 000 spins: 2.5x slower). libgomp only;
# not applied when the user chose another wait policy.
if os.environ["OMP_WAIT_POLICY"].upper() == "PASSIVE":
    os.environ.setdefault("GOMP_SPINCOUNT", "1000")
