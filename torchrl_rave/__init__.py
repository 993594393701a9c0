"""torchrl-rave: Risk Averse Value Expansion (RAVE), MVE and STEVE as TorchRL components.

The public pieces:

- :class:`~torchrl_rave.modules.WorldModelEnsemble`: probabilistic transition, reward and
  termination ensembles, all members in one batched call.
- :class:`~torchrl_rave.objectives.WorldModelEnsembleLoss`: Gaussian NLL / cross-entropy
  with independent bootstrap resamples per member.
- :class:`~torchrl_rave.trainers.WorldModelTrainer`: the world model's loss, optimiser,
  normaliser updates and pretraining schedule, for any collector loop or TorchRL trainer.
- :class:`~torchrl_rave.objectives.RAVEValueEstimator`, :class:`~torchrl_rave.objectives.STEVEEstimator`,
  :class:`~torchrl_rave.objectives.MVEEstimator`: TorchRL value estimators for any
  DDPG/TD3-style loss.
- :class:`~torchrl_rave.transforms.AdaptiveAlpha`: the per-sample confidence factor of eq. 12.
- :class:`~torchrl_rave.objectives.EnsembleDDPGLoss` (DDPG on K critics with DDPGLoss's
  arguments and outputs, STEVE/RAVE's base learner) and
  :class:`~torchrl_rave.objectives.ForeachSoftUpdate` (one fused Polyak update).

Importing the package changes nothing in TorchRL. :func:`patch_value_estimator_setter` is
an explicit opt-in fix for ``loss.value_estimator = estimator`` in torchrl 0.14.
"""

from torchrl_rave._compat import patch_value_estimator_setter
from torchrl_rave.envs import ToyEnv, ground_truth_q  # registers RAVEToy-v0
from torchrl_rave.modules import (
    EpsilonGaussianModule,
    TensorCall,
    WorldModelEnsemble,
)
from torchrl_rave.objectives import (
    EnsembleDDPGLoss,
    ForeachSoftUpdate,
    MVEEstimator,
    RAVEValueEstimator,
    STEVEEstimator,
    ValueExpansionEstimator,
    WorldModelEnsembleLoss,
    make_value_expansion_estimator,
)
from torchrl_rave.trainers import WorldModelTrainer
from torchrl_rave.transforms import AdaptiveAlpha

__version__ = "0.2.0"

__all__ = [
    "AdaptiveAlpha",
    "EnsembleDDPGLoss",
    "EpsilonGaussianModule",
    "ForeachSoftUpdate",
    "TensorCall",
    "WorldModelEnsemble",
    "WorldModelEnsembleLoss",
    "WorldModelTrainer",
    "patch_value_estimator_setter",
    "ValueExpansionEstimator",
    "MVEEstimator",
    "STEVEEstimator",
    "RAVEValueEstimator",
    "ToyEnv",
    "ground_truth_q",
    "make_value_expansion_estimator",
]
