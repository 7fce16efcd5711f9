"""Datasets: readers that turn a scene folder into calibrated, normalised views.

Conventions: cameras are OpenCV (x right, y down, z forward) after loading, whatever the file format;
the scene is normalised so the object lies inside [-1, 1]^3 (derived from the training cameras and
masks, never from a per-scene table); images are [H, W, 3] float in [0, 1] composited on the
configured background; masks are [H, W] in [0, 1].
"""

from src.data.base import DatasetError, DatasetReader, Scene, View

__all__ = ["DatasetError", "DatasetReader", "Scene", "View"]
