"""torchrl-rave: Risk Averse Value Expansion (RAVE), MVE and STEVE as TorchRL components.

The public pieces:

- :class:`~torchrl_rave.modules.WorldModelEnsemble`: probabilistic transition, reward and
  termination ensembles, all members in one batched call.
- :class:`~torchrl_rave.objectives.WorldModelLoss`: Gaussian NLL / cross-entropy with
  independent bootstrap resamples per member.
- :class:`~torchrl_rave.objectives.RAVEValueEstimator`, :class:`~torchrl_rave.objectives.STEVEEstimator`,
  :class:`~torchrl_rave.objectives.MVEEstimator`: TorchRL value estimators for any
  DDPG/TD3-style loss.
- :class:`~torchrl_rave.transforms.AdaptiveAlpha`: the per-sample confidence factor of eq. 12.
- :class:`~torchrl_rave.objectives.EnsembleDDPGLoss` (DDPG on K critics, STEVE/RAVE's base
  learner) and :class:`~torchrl_rave.objectives.ForeachSoftUpdate` (one fused Polyak update).
"""

from torchrl_rave._compat import patch_value_estimator_setter

patch_value_estimator_setter()

from torchrl_rave.envs import ToyEnv, ground_truth_q  # noqa: E402  (registers RAVEToy-v0)
from torchrl_rave.modules import (  # noqa: E402
    EpsilonGaussianModule,
    TensorCall,
    WorldModelEnsemble,
)
from torchrl_rave.objectives import (  # noqa: E402
    EnsembleDDPGLoss,
    ForeachSoftUpdate,
    MVEEstimator,
    RAVEValueEstimator,
    STEVEEstimator,
    ValueExpansionEstimator,
    WorldModelLoss,
    make_value_expansion_estimator,
)
from torchrl_rave.transforms import AdaptiveAlpha  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "AdaptiveAlpha",
    "EnsembleDDPGLoss",
    "EpsilonGaussianModule",
    "ForeachSoftUpdate",
    "TensorCall",
    "WorldModelEnsemble",
    "WorldModelLoss",
    "ValueExpansionEstimator",
    "MVEEstimator",
    "STEVEEstimator",
    "RAVEValueEstimator",
    "ToyEnv",
    "ground_truth_q",
    "make_value_expansion_estimator",
]
