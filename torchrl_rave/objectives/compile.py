"""``torch.compile`` of a loss's forward, shared by the world-model trainer and the
recipe's agent update."""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["compile_loss"]


def compile_loss(fn: Callable, mode: str | None = None) -> Callable:
    """``torch.compile`` of a loss's forward, as the update steps use it.

    Only the forward is compiled (AOTAutograd compiles its backward alongside); the
    backward call, the fused Adam steps and the soft target update stay eager. Compiling
    those too costs graph breaks (fused Adam and ``zero_grad`` are not traced) and was
    slower on CPU (benchmarks/README.md). ``fallback_random`` makes the compiled code draw
    its random numbers (RAVE's rollout noise) from torch's generator, as eager code does,
    so a compiled run follows the eager run's random stream.
    """
    from torch._inductor import list_mode_options

    # torch.compile takes a mode or options, not both: the mode's own options, plus ours
    options = list_mode_options(mode) if mode not in (None, "default") else {}
    return torch.compile(fn, options={**options, "fallback_random": True})
