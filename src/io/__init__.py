"""File formats: the standard 3DGS PLY layout for splat sets.

Conventions: positions in the (normalised) scene frame, scales stored as logs, opacities as logits,
rotations as (w, x, y, z) quaternions (rot_0 = w), colours as SH DC coefficients (f_dc_*).
"""
