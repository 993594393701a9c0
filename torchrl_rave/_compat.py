"""Compatibility fixes for the pinned TorchRL release.

``loss.value_estimator = estimator`` is documented TorchRL API, but ``nn.Module.__setattr__``
registers any module value as a submodule before Python looks at the ``value_estimator``
property setter. In torchrl 0.14.x the estimator therefore lands in ``loss._modules``
under ``"value_estimator"``, the getter still finds ``_value_estimator is None`` and
silently builds the default TD(0) estimator. We route that one assignment through the
property setter; everything else is left to the original ``__setattr__``.
"""

from __future__ import annotations

import torch
from torchrl.objectives import LossModule
from torchrl.objectives.value import ValueEstimatorBase


def _setter_is_bypassed() -> bool:
    class _Probe(LossModule):
        pass

    class _Estimator(ValueEstimatorBase):
        def forward(self, tensordict, **kwargs):
            return tensordict

    loss = _Probe()
    estimator = _Estimator(value_network=None)
    with torch.no_grad():
        loss.value_estimator = estimator
    return loss.__dict__.get("_value_estimator", None) is not estimator and (
        loss._modules.get("_value_estimator", None) is not estimator
    )


def patch_value_estimator_setter() -> bool:
    """Makes ``loss.value_estimator = est`` install ``est`` on every TorchRL loss; returns
    whether a patch was needed (``False`` when the installed TorchRL already does it, or
    the patch is in place).

    An explicit opt-in, never applied on import: it replaces ``LossModule.__setattr__``
    for the whole process, routing that one assignment to TorchRL's own property setter
    (see the module docstring for why torchrl 0.14 needs it). ``make_value_estimator(est)``
    installs an estimator without it.

    Examples:
        >>> from torchrl_rave import patch_value_estimator_setter
        >>> patch_value_estimator_setter() in (True, False)
        True
    """
    if getattr(LossModule, "_rave_setter_patched", False) or not _setter_is_bypassed():
        return False
    original = LossModule.__setattr__

    def __setattr__(self, name, value):
        if name == "value_estimator" and isinstance(value, ValueEstimatorBase):
            LossModule.value_estimator.fset(self, value)
            return
        original(self, name, value)

    LossModule.__setattr__ = __setattr__
    LossModule._rave_setter_patched = True
    return True
