"""TorchRL transforms."""

from torchrl_rave.transforms.adaptive_alpha import AdaptiveAlpha

__all__ = ["AdaptiveAlpha"]
