"""Running mean/variance normaliser kept as buffers."""

from __future__ import annotations

import torch
from torch import nn


class RunningNormalizer(nn.Module):
    """Per-feature running mean and variance, merged batch by batch (Chan et al.).

    The statistics are buffers, so they travel with ``state_dict`` and ``.to(device)``.
    Before any update the normaliser is the identity (mean 0, std 1).

    Args:
        size (int): number of features (last dimension).
        min_std (float): floor on the standard deviation, so constant features
            do not blow up.

    Examples:
        >>> norm = RunningNormalizer(2)
        >>> norm.update(torch.tensor([[0.0, 10.0], [2.0, 10.0]]))
        >>> norm.mean
        tensor([ 1., 10.])
        >>> norm.normalize(torch.tensor([[3.0, 10.0]]))
        tensor([[2., 0.]])
        >>> norm.denormalize(norm.normalize(torch.tensor([[3.0, 12.0]])))
        tensor([[ 3., 12.]])
    """

    def __init__(self, size: int, min_std: float = 1e-4) -> None:
        super().__init__()
        self.size = size
        self.min_std = min_std
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("var", torch.ones(size))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merges the rows of ``x`` (shape ``[*B, size]``) into the statistics; raises
        ``ValueError``, leaving them unchanged, when they would not fit the buffers' dtype
        (float32 variances end near 3.4e38, so at inputs near 1.8e19)."""
        if self.mean.dim() != 1:
            raise RuntimeError(
                "stacked seeds' statistics are updated through each learner's own normaliser"
            )
        if x.shape[-1] != self.size:
            raise ValueError(
                f"normaliser of size {self.size} got a tensor of shape {tuple(x.shape)}"
            )
        x = x.reshape(-1, self.size).to(torch.float64)
        n = x.shape[0]
        if n == 0:
            return
        batch_mean = x.mean(0)
        batch_var = x.var(0, unbiased=False)
        if self.count == 0:
            new_mean, new_var = batch_mean, batch_var
        else:
            total = self.count + n
            delta = batch_mean - self.mean.to(torch.float64)
            new_mean = self.mean + delta * n / total
            m2 = self.var * self.count + batch_var * n + delta.pow(2) * self.count * n / total
            new_var = m2 / total
        fits = torch.isfinite(new_mean.to(self.mean.dtype)).all()
        fits &= torch.isfinite(new_var.to(self.var.dtype)).all()
        if not bool(fits):  # the statistics are left as they were
            if not bool(torch.isfinite(x).all()):
                raise ValueError("RunningNormalizer: the inputs hold NaN or infinite values")
            raise ValueError(
                f"RunningNormalizer: inputs up to {x.abs().max().item():.3g} in magnitude "
                f"give statistics beyond {self.var.dtype}'s range; scale them down "
                "(e.g. a reward scale or an observation transform) before they reach the model"
            )
        self.mean.copy_(new_mean)
        self.var.copy_(new_var)
        self.count += n

    @property
    def std(self) -> torch.Tensor:
        return self.floored_std(self.var, self.min_std)

    @staticmethod
    def floored_std(var: torch.Tensor, min_std: float) -> torch.Tensor:
        """The standard deviation of variances ``var`` (any shape), at least ``min_std``."""
        return var.sqrt().clamp_min(min_std)

    def _stats(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The mean and std as they broadcast against ``x``: as they are, or, stacked
        seeds' ``[S, size]`` statistics, viewed ``[S, 1, ..., size]`` against
        ``[S, ..., size]``."""
        if self.mean.dim() == 1:
            return self.mean, self.std
        shape = (x.shape[0],) + (1,) * (x.dim() - 2) + (x.shape[-1],)
        return self.mean.view(shape), self.std.view(shape)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self._stats(x)
        return (x - mean) / std

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        mean, std = self._stats(x)
        return x * std + mean

    def extra_repr(self) -> str:
        return f"size={self.size}, count={int(self.count)}"
