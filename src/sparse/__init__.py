"""Training-free sparse-view ingredients, chosen by the ``sparse`` config group (conf/sparse/).

Each ingredient acts on training only, through the hooks of :class:`SparseIngredient`, and so composes
with every scene model (3DGS, Mip-Splatting, SplatFields): DropGaussian (random splat dropping),
Binocular3DGS's opacity decay and binocular self-consistency loss, and CoR-GS's co-training of two
models with co-pruning and pseudo-view co-regularisation. ``sparse=none`` (the default) trains as before.
"""

from src.sparse.base import SparseIngredient, SparseRecipe, members_of, optimizer_for, split_by_member
from src.sparse.binocular import BinocularConsistency
from src.sparse.corgs import CoRGS
from src.sparse.dropgaussian import DropGaussian
from src.sparse.opacity_decay import OpacityDecay
from src.sparse.pair import CoTrainedPair, CoTrainingStrategy, MemberOptimizers

__all__ = ["BinocularConsistency", "CoRGS", "CoTrainedPair", "CoTrainingStrategy", "DropGaussian", "MemberOptimizers",
           "OpacityDecay", "SparseIngredient", "SparseRecipe", "members_of", "optimizer_for", "split_by_member"]
