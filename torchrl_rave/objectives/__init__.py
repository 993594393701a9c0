"""Losses and value estimators: world-model NLL, MVE / STEVE / RAVE targets."""

from torchrl_rave.objectives import functional
from torchrl_rave.objectives.ensemble_ddpg import EnsembleDDPGLoss
from torchrl_rave.objectives.target_networks import TargetNetworks
from torchrl_rave.objectives.target_update import ForeachSoftUpdate
from torchrl_rave.objectives.value_expansion import (
    MVEEstimator,
    RAVEValueEstimator,
    STEVEEstimator,
    ValueExpansionEstimator,
    make_value_expansion_estimator,
)
from torchrl_rave.objectives.world_model_loss import (
    WorldModelEnsembleLoss,
    gaussian_nll,
    world_model_loss_terms,
)

__all__ = [
    "functional",
    "EnsembleDDPGLoss",
    "ForeachSoftUpdate",
    "MVEEstimator",
    "RAVEValueEstimator",
    "STEVEEstimator",
    "TargetNetworks",
    "ValueExpansionEstimator",
    "WorldModelEnsembleLoss",
    "gaussian_nll",
    "make_value_expansion_estimator",
    "world_model_loss_terms",
]
