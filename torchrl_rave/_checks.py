"""Input validation shared by the losses and estimators: clear errors before any work."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

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
    floating: bool = False,
) -> torch.Tensor:
    """Reads ``key`` from ``tensordict``; raises ``ValueError`` naming the key when it is
    missing, when its last dimension is not ``size``, when ``floating`` and it is not a
    floating-point tensor (an integer reward or action would be silently cast), when it is
    a floating-point tensor of another ``dtype`` than the model's, or when it holds NaN/inf."""
    value = tensordict.get(key, None)
    if value is None:
        raise ValueError(f"the input tensordict has no entry {key!r}")
    if floating and not value.is_floating_point():
        raise ValueError(
            f"entry {key!r} is {value.dtype}, expected a floating-point tensor"
            + (f" ({dtype}, as the model's parameters)" if dtype is not None else "")
            + ": cast it (e.g. with torchrl's DoubleToFloat or a dtype cast) first"
        )
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


@dataclass(frozen=True)
class Rule:
    """A range rule, written once for every place that checks it: the library's
    constructors (:meth:`check`) and the recipe's config schema (its ``expected`` text)."""

    test: Callable[[Any], bool]
    expected: str

    def holds(self, value) -> bool:
        try:
            return bool(self.test(value))
        except (TypeError, ValueError):
            return False

    def check(self, name: str, value):
        """``value`` itself, or a ``ValueError`` naming ``name``."""
        if not self.holds(value):
            raise ValueError(f"{name} must be {self.expected}, got {value!r}")
        return value


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


FINITE = Rule(_is_number, "a finite number")
POSITIVE = Rule(lambda v: _is_number(v) and v > 0, "a finite number > 0")
NON_NEGATIVE = Rule(lambda v: _is_number(v) and v >= 0, "a finite number >= 0")
UNIT_INTERVAL = Rule(lambda v: _is_number(v) and 0 <= v <= 1, "in [0, 1]")
POSITIVE_INT = Rule(lambda v: _is_int(v) and v >= 1, "an integer >= 1")
NON_NEGATIVE_INT = Rule(lambda v: _is_int(v) and v >= 0, "an integer >= 0")


def one_of(choices: list) -> Rule:
    return Rule(lambda v: v in choices, f"one of {choices}")


def optional(rule: Rule) -> Rule:
    """``rule``, or ``None``."""
    return Rule(lambda v: v is None or rule.test(v), f"null or {rule.expected}")


def check_positive_int(name: str, value, minimum: int = 1) -> int:
    rule = POSITIVE_INT if minimum == 1 else NON_NEGATIVE_INT if minimum == 0 else None
    rule = rule or Rule(lambda v: _is_int(v) and v >= minimum, f"an integer >= {minimum}")
    return rule.check(name, value)


def check_non_negative(name: str, value) -> float:
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.item()
    return float(NON_NEGATIVE.check(name, value))


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
