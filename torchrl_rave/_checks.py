"""Input validation shared by the losses and estimators: clear errors before any work."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey


def get_checked(
    tensordict: TensorDictBase,
    key: NestedKey,
    size: int | None = None,
    *,
    check_finite: bool = True,
) -> torch.Tensor:
    """Reads ``key`` from ``tensordict``; raises ``ValueError`` naming the key when it is
    missing, when its last dimension is not ``size`` or when it holds NaN/inf."""
    value = tensordict.get(key, None)
    if value is None:
        raise ValueError(f"the input tensordict has no entry {key!r}")
    if size is not None and value.shape[-1] != size:
        raise ValueError(
            f"entry {key!r} has shape {tuple(value.shape)}, expected last dimension {size}"
        )
    if check_finite and value.is_floating_point():
        message = f"entry {key!r} holds NaN or infinite values"
        if torch.compiler.is_compiling():
            # reading the flag back on the host would break the graph; assert on device
            torch._assert_async(torch.isfinite(value).all(), message)
        elif not bool(torch.isfinite(value).all()):
            raise ValueError(message)
    return value


def check_positive_int(name: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return value


def check_non_negative(name: str, value) -> float:
    value = float(value)
    if not value >= 0:  # also catches NaN
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return value
