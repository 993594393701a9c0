"""TorchRL transforms: RAVE's adaptive confidence factor, and an env's reward as
separately weighted terms."""

from torchrl_rave.transforms.adaptive_alpha import AdaptiveAlpha
from torchrl_rave.transforms.reward_terms import (
    DelayedWeight,
    RewardTermsReader,
    ReweightRewardTerms,
)

__all__ = ["AdaptiveAlpha", "DelayedWeight", "RewardTermsReader", "ReweightRewardTerms"]
