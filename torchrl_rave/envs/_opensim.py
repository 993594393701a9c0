"""What the OpenSim tasks share: a checked action of muscle excitations, set as the
prescribed controls of the next step."""

from __future__ import annotations

import numpy as np


def set_excitations(who: str, action, excitations, shape: tuple[int, ...]) -> None:
    """Sets ``excitations`` (the controller's ``opensim.Constant`` functions, in the
    action's order) to ``action`` clipped to ``[0, 1]``; an action of another ``shape`` or
    with NaN/inf is refused, naming ``who``."""
    action = np.asarray(action, dtype=np.float64)
    if action.shape != shape:
        raise ValueError(
            f"{who} takes {shape[0]} muscle excitations, got an action of shape {action.shape}"
        )
    if not np.isfinite(action).all():
        raise ValueError(f"{who} got a non-finite action: {action}")
    for excitation, value in zip(excitations, np.clip(action, 0.0, 1.0), strict=True):
        excitation.setValue(float(value))
