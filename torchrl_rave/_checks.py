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
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Reads ``key`` from ``tensordict``; raises ``ValueError`` naming the key when it is
    missing, when its last dimension is not ``size``, when it is a floating-point tensor
    of another ``dtype`` than the model's, or when it holds NaN/inf."""
    value = tensordict.get(key, None)
    if value is None:
        raise ValueError(f"the input tensordict has no entry {key!r}")
    if size is not None and value.shape[-1] != size:
        raise ValueError(
            f"entry {key!r} has shape {tuple(value.shape)}, expected last dimension {size}"
        )
    if dtype is not None and value.is_floating_point() and value.dtype != dtype:
        raise ValueError(
            f"entry {key!r} is {value.dtype} but the model's parameters are {dtype}: cast "
            f"the batch (e.g. td.to({dtype})) or the model"
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


def check_not_empty(tensordict: TensorDictBase, who: str) -> None:
    """Refuses a batch without transitions (its losses would be NaN or fail deep inside)."""
    if 0 in tensordict.batch_size:  # (TensorDict.numel() reports 1 for these)
        raise ValueError(
            f"{who} got an empty batch (batch size {tuple(tensordict.batch_size)}): there is "
            "nothing to compute a loss on"
        )


def first_param_dtype(module) -> torch.dtype | None:
    """The dtype of ``module``'s first floating-point parameter (``None`` if it has none,
    or is not an ``nn.Module``: the estimators accept any world model of the protocol)."""
    for param in getattr(module, "parameters", tuple)():
        if param.is_floating_point():
            return param.dtype
    return None
