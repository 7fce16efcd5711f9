"""Neural fields of SplatFields: encodings, ResField layers, MLP heads, tri-plane backbone, 4D flows.

Conventions used in this package:

* Points are world coordinates [N, 3] and are assumed to lie in [-1, 1]^3 (the tri-plane samples
  them with ``grid_sample(align_corners=False)`` and zero padding, without normalisation).
* Quaternions are (w, x, y, z); ``SplatFieldNetwork`` returns ACTIVATED attributes (positive linear
  scales, unit quaternions, opacities and colours in (0, 1)), ready for ``src.core.Splats``.
* Time is a float in [0, 1]; ``frame_id`` is the integer frame index (frame k sits at time
  k / (n_frames - 1)). Static models ignore both.
* MLP sizes: ``n_layers`` counts every linear layer (input and output included, the paper's
  "8-layer MLP"); ``skips`` are linear indices before which the original input is re-concatenated.
* Defaults follow the supplementary material (B.2); reference-code behaviours that differ are
  opt-in flags whose names end in ``_quirk`` (or ``ref_*``).
* Backbones split work into ``prepare()`` (once per step, e.g. the tri-plane CNN) and
  ``sample(state, points)``, so several views of one step share the CNN evaluation.
"""

from src.fields.backbones import CNNTriplaneBackbone, FieldBackbone, MLPBackbone, NoBackbone
from src.fields.encoding import PositionalEncoding
from src.fields.flows import (
    FLOWS,
    DCTFlow,
    Flow,
    OffsetFlow,
    ScaledSE3Flow,
    SE3Flow,
    StaticFlow,
    quat_multiply_wxyz,
    quat_to_rotmat_wxyz,
    rotmat_to_quat_wxyz,
    se3_exp,
)
from src.fields.mlp import FieldMLP
from src.fields.network import HeadSpec, SplatFieldNetwork
from src.fields.resfield import ResFieldLinear
from src.fields.triplane import TriplaneGenerator

__all__ = [
    "FLOWS",
    "CNNTriplaneBackbone",
    "DCTFlow",
    "FieldBackbone",
    "FieldMLP",
    "Flow",
    "HeadSpec",
    "MLPBackbone",
    "NoBackbone",
    "OffsetFlow",
    "PositionalEncoding",
    "ResFieldLinear",
    "SE3Flow",
    "ScaledSE3Flow",
    "SplatFieldNetwork",
    "StaticFlow",
    "TriplaneGenerator",
    "quat_multiply_wxyz",
    "quat_to_rotmat_wxyz",
    "rotmat_to_quat_wxyz",
    "se3_exp",
]
