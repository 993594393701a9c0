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


def check_transition_layout(
    tensordict: TensorDictBase, reward_key: NestedKey, flag_keys: list[NestedKey]
) -> None:
    """TorchRL's layout of a batch of transitions ``[*B]``: one floating-point reward per
    transition, ``[*B, 1]``, and boolean ``done`` / ``terminated`` flags ``[*B, 1]`` (a
    flag that is absent is not asked for). Raises ``ValueError`` naming the entry, the
    shape or dtype it has and the one expected; TorchRL's own estimators fail on these
    further in, with messages that name neither."""
    expected = (*tensordict.batch_size, 1)
    reward = tensordict.get(reward_key, None)
    if reward is not None and tuple(reward.shape) != expected:
        raise ValueError(
            f"entry {reward_key!r} has shape {tuple(reward.shape)}, expected {expected}: one "
            f"reward per transition of the batch {tuple(tensordict.batch_size)}, with the "
            "trailing dimension of 1 that TorchRL's envs write"
        )
    for key in flag_keys:
        flag = tensordict.get(key, None)
        if flag is None:
            continue
        if flag.dtype != torch.bool:
            raise ValueError(
                f"entry {key!r} is {flag.dtype}, expected torch.bool, as TorchRL's envs write "
                "done and terminated flags: cast it (flag.bool())"
            )
        if tuple(flag.shape) != expected:
            raise ValueError(f"entry {key!r} has shape {tuple(flag.shape)}, expected {expected}")


def check_finite_losses(who: str, losses: dict, tensordict: TensorDictBase, keys) -> None:
    """After a loss whose inputs were checked finite: a loss that is not finite means
    values too large for the arithmetic (e.g. rewards of 1e20 overflow float32 in the
    squared error, and one optimiser step later every parameter is NaN). Raises
    ``ValueError`` naming the losses and the input of largest magnitude among ``keys``."""
    if torch.compiler.is_compiling():
        return
    bad = {k: float(v.detach()) for k, v in losses.items() if not bool(torch.isfinite(v).all())}
    if not bad:
        return
    largest = max(
        ((k, float(tensordict.get(k).detach().abs().max())) for k in keys
         if k in tensordict.keys(True) and tensordict.get(k).is_floating_point()
         and tensordict.get(k).numel()),
        key=lambda kv: kv[1], default=(None, float("nan")),
    )  # fmt: skip
    raise ValueError(
        f"{who}: the losses {bad} are not finite although the batch holds no NaN or inf: "
        f"its values are too large for {next(iter(losses.values())).dtype} arithmetic "
        f"(entry {largest[0]!r} reaches {largest[1]:.3g}); scale the rewards or "
        "observations (e.g. with torchrl's RewardScaling or ObservationNorm)"
    )


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
