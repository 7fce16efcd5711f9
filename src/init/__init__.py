"""Splat initialisers: callables ``(scene, generator) -> [N, 3]`` canonical centres.

Conventions: normalised scene coordinates (the object inside [-1, 1]^3).
"""

from src.init.initialisers import BoxInit, FromRunInit, HullInit, Initialiser, SfmInit

__all__ = ["BoxInit", "FromRunInit", "HullInit", "Initialiser", "SfmInit"]
