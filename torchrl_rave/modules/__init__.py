"""TensorDict modules: the probabilistic world-model ensemble and its building blocks."""

from torchrl_rave.modules.ensemble import (
    EnsembleLinear,
    EnsembleMLP,
    GaussianEnsembleMLP,
    ensemble_affine,
)
from torchrl_rave.modules.exploration import EpsilonGaussianModule
from torchrl_rave.modules.normalizer import RunningNormalizer
from torchrl_rave.modules.tensor_call import TensorCall
from torchrl_rave.modules.world_model import WorldModelEnsemble

__all__ = [
    "EnsembleLinear",
    "EnsembleMLP",
    "EpsilonGaussianModule",
    "GaussianEnsembleMLP",
    "RunningNormalizer",
    "TensorCall",
    "WorldModelEnsemble",
    "ensemble_affine",
]
