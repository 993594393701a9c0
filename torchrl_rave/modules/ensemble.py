"""Ensemble layers: N independent networks evaluated in one batched matmul.

Every layer keeps its members' parameters stacked along a leading ensemble
dimension, so one call evaluates all members at once (``torch.baddbmm``), with
no Python loop over members. Inputs come in two layouts:

- *shared*: ``[M, F]``, the same rows for every member; the output is ``[N, M, F']``.
- *per member*: ``[N, M, F]``, member ``i`` reads row block ``i``; the output is
  ``[N, M, F']``.

Callers flatten any batch dimensions into ``M`` first.

Stacked seeds. A :class:`~torchrl_rave.trainers.SeedGroup` stacks the parameters of
``S`` ensembles along a new leading dimension (weights ``[S, N, in, out]``); the same
modules then evaluate every seed at once, with inputs ``[S, M, F]`` (shared by a seed's
members) or ``[S, N, M, F]`` (per member) and outputs ``[S, N, M, F']``. Each layer is one
batched matmul over the ``S x N`` maps (:class:`_Linear`), so seed ``s``'s rows only meet
seed ``s``'s weights.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

from torchrl_rave._checks import check_positive_int

Tensor = torch.Tensor


def inplace_activation(activation: nn.Module):
    """The in-place form of a parameter-free activation (``torch.relu_`` for ``nn.ReLU``,
    likewise Tanh and Sigmoid), or ``None``. Applied to the fresh output of a linear
    layer, it skips one allocation per layer; autograd allows it there, as a linear
    layer's backward does not read its own output."""
    return _INPLACE.get(type(activation))


_INPLACE = {nn.ReLU: torch.relu_, nn.Tanh: torch.tanh_, nn.Sigmoid: torch.sigmoid_}


def ensemble_affine(
    x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None
) -> torch.Tensor:
    """``x @ weight + bias`` for ``E`` stacked affine maps in one kernel: the executor that
    every ensemble in this package evaluates its layers with (:class:`EnsembleLinear`,
    :class:`~torchrl_rave.modules.TensorCall`'s stacked critics, a
    :class:`~torchrl_rave.trainers.SeedGroup`'s ``S x E`` maps).

    Args:
        x (Tensor): ``[M, in]``, the same rows for every map (*shared*), or ``[E, M, in]``,
            map ``e`` reading block ``e``.
        weight (Tensor): ``[E, in, out]`` (any strides: a transposed view of ``nn.Linear``'s
            ``[E, out, in]`` is read as it is).
        bias (Tensor, optional): ``[E, 1, out]``.

    Returns:
        ``[E, M, out]``.

    Examples:
        >>> x, w, b = torch.ones(2, 3), torch.ones(4, 3, 5), torch.zeros(4, 1, 5)
        >>> ensemble_affine(x, w, b).shape
        torch.Size([4, 2, 5])
    """
    if x.dim() == 2:  # [M, in] @ [E, in, out] broadcasts to [E, M, out] in one kernel
        out = torch.matmul(x, weight)
        return out if bias is None else out + bias
    return torch.bmm(x, weight) if bias is None else torch.baddbmm(bias, x, weight)


# outputs of more floats than this (2 MiB) are computed as bmm + add_ (see _Linear)
_LARGE = 1 << 19


class _Linear:
    """One grouped affine layer and the activation after it (``None``: none).

    The weight is ``[S, *E, out, in]`` (``output_major``, ``nn.Linear``'s layout) or
    ``[S, *E, in, out]`` (:class:`~torchrl_rave.modules.EnsembleLinear`'s), with ``E`` the
    ensemble dimensions (none for the actor, ``K`` critics, ``N`` world-model members).
    Inputs are ``[S, R, in]``, shared by a seed's members, or ``[S, *E, R, in]``, one block
    per member; the output is ``[S, *E, R, out]``. Each layer is one ``baddbmm`` over the
    ``S x E`` matrices; a layer of one matrix (a group of one's actor, or DDPG's one
    critic) is the ``F.linear`` call its single learner makes, so that a group of one
    rounds as its single run does.

    Outputs larger than the caches (over 2 MiB) cost a pass over memory for each
    element-wise step, so the layer avoids them where it can. Without autograd, a ReLU
    layer's output is returned with its bias still *owed*: ``max(x w, -b)``, which is
    ``relu(x w + b) - b``, with ``b`` handed on (:meth:`apply`) and folded into the next
    layer's bias as ``b + owed w``. That is one pass (the clamp) where ``bias add`` and
    ``relu`` take two. At S = 8 it spares five of the value target's passes over
    13.6 MB tensors (``benchmarks/README.md``, the seed-group section). The product is the
    same up to rounding. At the default sizes a group of one's outputs stay under 2 MiB,
    so it still rounds as its single run does (with a larger batch or network, this path
    and the in-place bias add below round otherwise than its learner's ``baddbmm``)."""

    __slots__ = ("weight", "bias", "activation", "output_major")

    def __init__(self, weight, bias, activation, output_major: bool) -> None:
        self.weight, self.bias, self.activation = weight, bias, activation
        self.output_major = output_major

    def __call__(self, x: Tensor, detach: bool = False, owed: Tensor | None = None) -> Tensor:
        return _settle(*self.apply(x, detach, owed))

    def apply(
        self, x: Tensor, detach: bool = False, owed: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """The layer on ``x + owed`` (``owed``: a bias ``[S * E, 1, in]`` that ``x`` does
        not hold yet, or ``None``); returns ``(y, owed)`` in the same sense."""
        w, b = self.weight, self.bias
        if detach:
            w, b = w.detach(), None if b is None else b.detach()
        if self.output_major:
            w = w.mT  # a transposed view: BLAS reads it as it is
        elif w.shape[-1] < w.shape[-2]:  # as EnsembleLinear._matmul_weight
            w = w.mT.clone(memory_format=torch.contiguous_format).mT
        lead, (fan_in, fan_out) = w.shape[:-2], w.shape[-2:]
        rows = x.shape[-2]
        flat = len(lead) == 1 and x.dim() == 3  # one matrix per seed: x, w, y are [S, ., .]
        if not flat:
            if x.dim() == 3 and len(lead) > 1:  # shared by the members: one copy per member
                x = x.unsqueeze(1).expand(*lead, rows, fan_in)
            x = x.reshape(-1, rows, fan_in)
            w = w.reshape(-1, fan_in, fan_out)
        if b is not None:
            b = b.reshape(-1, 1, fan_out)
        if owed is not None:  # (x + owed) w + b = x w + (owed w + b)
            b = ensemble_affine(owed, w, b)
        large = x.shape[0] * rows * fan_out > _LARGE
        if (
            large
            and b is not None
            and type(self.activation) is torch.nn.ReLU
            and not (torch.is_grad_enabled() and (x.requires_grad or w.requires_grad))
        ):
            y = torch.bmm(x, w).clamp_(min=b.neg())  # relu(x w + b) - b
            return y.view(*lead, rows, fan_out), b
        if x.shape[0] == 1 and self.output_major:
            # one matrix (a group of one's actor, or its one critic): the 2-D call its
            # learner makes (nn.Linear's, as TensorCall makes for one member); BLAS need
            # not round a batch of one as it rounds that call, and on some CPUs does not
            y = F.linear(x[0], w[0].mT, None if b is None else b.reshape(fan_out))
        elif large and b is not None:
            # an output larger than the caches: baddbmm first writes the bias over all of
            # it and BLAS then reads it back; the product, then the bias added in place,
            # spares one pass (a RAVE target layer at S = 8: 6.6 -> 5.5 ms at 1 thread)
            y = torch.bmm(x, w).add_(b)
        else:
            y = ensemble_affine(x, w, b)  # the S x E maps of [S * E, rows, in] in one kernel
        if self.activation is not None:
            # on the product itself, before the view: an in-place op on a view makes
            # autograd rebase it (CopySlices), whose backward clones and zero-fills the
            # whole output (128 of the ATen calls of a RAVE group update)
            inplace = inplace_activation(self.activation)
            y = self.activation(y) if inplace is None else inplace(y)
        return (y if y.dim() == len(lead) + 2 else y.view(*lead, rows, fan_out)), None


def _settle(y: Tensor, owed: Tensor | None) -> Tensor:
    """``y`` with the bias it owes (see :class:`_Linear`) added."""
    if owed is None:
        return y
    return y.add_(owed.view(*y.shape[:-2], 1, y.shape[-1]))


def _run(
    layers: list[_Linear], x: Tensor, detach: bool = False, settle: bool = True
) -> Tensor | tuple[Tensor, Tensor | None]:
    """The layers in turn; with ``settle=False``, ``(y, owed)`` as :meth:`_Linear.apply`."""
    owed = None
    for layer in layers:
        x, owed = layer.apply(x, detach, owed)
    return _settle(x, owed) if settle else (x, owed)


def _check_layout(
    x: Tensor, num_members: int, in_features: int, per_member: bool, seeds: tuple = ()
) -> None:
    """Shared input ``[*S, M, in]`` or per-member input ``[*S, N, M, in]``, with ``S`` the
    stacked seeds' leading sizes (none for one ensemble)."""
    if x.shape[-1] != in_features:
        raise ValueError(
            f"ensemble layer expects {in_features} input features, got a tensor of shape "
            f"{tuple(x.shape)}"
        )
    lead = (*seeds, num_members) if per_member else tuple(seeds)
    if x.dim() != len(lead) + 2 or tuple(x.shape[: len(lead)]) != lead:
        shape = ", ".join(map(str, (*lead, "M", in_features)))
        kind = "per-member" if per_member else "shared"
        raise ValueError(f"{kind} input must have shape [{shape}], got {tuple(x.shape)}")


class EnsembleLinear(nn.Module):
    """``N`` independent affine maps with stacked parameters.

    Args:
        num_members (int): ensemble size ``N``.
        in_features (int): input size.
        out_features (int): output size.

    Shapes:
        ``weight``: ``[N, in_features, out_features]``; ``bias``: ``[N, 1, out_features]``.
        Input ``[M, in]`` (shared) or ``[N, M, in]`` (per member); output ``[N, M, out]``.

    Examples:
        >>> layer = EnsembleLinear(3, 4, 2)
        >>> layer(torch.randn(5, 4)).shape
        torch.Size([3, 5, 2])
        >>> layer(torch.randn(3, 5, 4), per_member=True).shape
        torch.Size([3, 5, 2])
    """

    def __init__(self, num_members: int, in_features: int, out_features: int) -> None:
        super().__init__()
        check_positive_int("num_members", num_members)
        check_positive_int("in_features", in_features)
        check_positive_int("out_features", out_features)
        self.num_members = num_members
        self.in_features = in_features
        self.out_features = out_features
        self.weight = nn.Parameter(torch.empty(num_members, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(num_members, 1, out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Same distribution as nn.Linear's default, drawn independently per member
        # so that members start apart.
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def _matmul_weight(self) -> torch.Tensor:
        """The ``[N, in, out]`` weight as the matmul gets it.

        A layer narrower on its output than on its input (a model's output head, a
        reward's single unit) is multiplied by an output-major copy, ``[N, out, in]`` in
        memory as ``nn.Linear`` stores it: CPU BLAS runs a batched product whose operand
        has a leading dimension of 1 to 11 several times slower than the same product
        with the operand transposed (``benchmarks/README.md``, item 11). The copy is
        ``N x in x out`` numbers, tracked by autograd; the parameter keeps its layout,
        so checkpoints and optimiser states are unchanged.
        """
        w = self.weight
        if self.out_features < self.in_features:
            w = w.mT.clone(memory_format=torch.contiguous_format).mT
        return w

    def forward(self, x: torch.Tensor, per_member: bool = False) -> torch.Tensor:
        if self.weight.dim() == 4:  # stacked seeds
            seeds = self.weight.shape[:1]
            _check_layout(x, self.num_members, self.in_features, per_member, seeds)
            return _Linear(self.weight, self.bias, None, output_major=False)(x)
        if x.shape[-1] != self.in_features or (
            per_member and (x.dim() != 3 or x.shape[0] != self.num_members)
        ):
            _check_layout(x, self.num_members, self.in_features, per_member)
        return self._affine(x)

    def _affine(self, x: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` without its input check: the ensemble MLPs check their input
        once and call their layers through this, so the update step pays no check per
        layer."""
        return ensemble_affine(x, self._matmul_weight(), self.bias)

    def extra_repr(self) -> str:
        return f"num_members={self.num_members}, in_features={self.in_features}, out_features={self.out_features}"


class EnsembleMLP(nn.Module):
    """A stack of :class:`EnsembleLinear` layers with an activation between them.

    Args:
        num_members (int): ensemble size ``N``.
        in_features (int): input size.
        out_features (int): output size of the last layer.
        num_cells (Sequence[int]): hidden widths; ``len(num_cells) + 1`` FC layers in all.
        activation (type[nn.Module]): activation class placed after every hidden layer.

    Examples:
        >>> mlp = EnsembleMLP(4, 3, 2, num_cells=[16, 16])
        >>> mlp(torch.randn(10, 3)).shape
        torch.Size([4, 10, 2])
    """

    def __init__(
        self,
        num_members: int,
        in_features: int,
        out_features: int,
        num_cells: Sequence[int],
        activation: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        if isinstance(num_cells, (int, str)) or not all(
            isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in num_cells
        ):
            raise ValueError(f"num_cells must be a sequence of integers >= 1, got {num_cells!r}")
        self.num_members = num_members
        self.in_features = in_features
        sizes = [in_features, *num_cells, out_features]
        self.layers = nn.ModuleList(
            EnsembleLinear(num_members, fan_in, fan_out)
            for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True)
        )
        self.activation = activation()

    def activate(self, x: torch.Tensor) -> torch.Tensor:
        """The activation on a linear layer's fresh output (in place where it can be)."""
        inplace = inplace_activation(self.activation)
        return self.activation(x) if inplace is None else inplace(x)

    def grouped_layers(self, last_activation: bool = False) -> list:
        """The layers of stacked seeds' parameters (``[S, N, in, out]``) as the grouped
        executor's, the activation after every hidden layer (and, with
        ``last_activation``, after the last one)."""
        depth = len(self.layers)
        return [
            _Linear(layer.weight, layer.bias,
                    self.activation if n < depth - 1 or last_activation else None, False)
            for n, layer in enumerate(self.layers)
        ]  # fmt: skip

    def forward(self, x: torch.Tensor, per_member: bool = False) -> torch.Tensor:
        if self.layers[0].weight.dim() == 4:  # stacked seeds
            seeds = self.layers[0].weight.shape[:1]
            _check_layout(x, self.num_members, self.in_features, per_member, seeds)
            return _run(self.grouped_layers(), x)
        _check_layout(x, self.num_members, self.in_features, per_member)
        for n, layer in enumerate(self.layers):
            # after the first layer every member has its own rows
            x = layer._affine(x)
            if n < len(self.layers) - 1:
                x = self.activate(x)
        return x


class GaussianEnsembleMLP(nn.Module):
    """Ensemble MLP with a mean head and a soft-bounded log-variance head.

    The trunk has ``len(num_cells)`` hidden layers; the mean and log-variance are two
    output layers on top of it (paper appendix A: "two output layers corresponding to
    the mean and the variances"). The log-variance is squashed between learned per-member
    bounds with softplus, so it cannot run to +-inf off-distribution:

    ``logvar = max - softplus(max - raw)``, then ``logvar = min + softplus(logvar - min)``.

    The bounds are parameters; :meth:`bound_penalty` is the small regulariser that keeps
    them tight (add it to the loss).

    Args:
        num_members (int): ensemble size ``N``.
        in_features (int): input size.
        out_features (int): size of the predicted Gaussian.
        num_cells (Sequence[int]): hidden widths of the trunk.
        activation (type[nn.Module]): hidden activation.
        init_max_logvar (float): initial upper bound of the log-variance.
        init_min_logvar (float): initial lower bound of the log-variance.

    Examples:
        >>> head = GaussianEnsembleMLP(4, 3, 2, num_cells=[16])
        >>> mean, logvar = head(torch.randn(10, 3))
        >>> mean.shape, logvar.shape
        (torch.Size([4, 10, 2]), torch.Size([4, 10, 2]))
        >>> bool((logvar <= head.max_logvar).all() and (logvar >= head.min_logvar).all())
        True
    """

    def __init__(
        self,
        num_members: int,
        in_features: int,
        out_features: int,
        num_cells: Sequence[int],
        activation: type[nn.Module] = nn.ReLU,
        init_max_logvar: float = 0.5,
        init_min_logvar: float = -10.0,
    ) -> None:
        super().__init__()
        if isinstance(num_cells, (int, str)) or len(num_cells) == 0:
            raise ValueError(
                f"a Gaussian ensemble needs at least one hidden layer: num_cells must be a "
                f"non-empty sequence of integers, got {num_cells!r}"
            )
        low, high = float(init_min_logvar), float(init_max_logvar)
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(
                "init_min_logvar must be below init_max_logvar, both finite, got "
                f"{init_min_logvar!r} and {init_max_logvar!r}"
            )
        self.trunk = EnsembleMLP(
            num_members, in_features, num_cells[-1], num_cells[:-1], activation
        )
        self.mean_head = EnsembleLinear(num_members, num_cells[-1], out_features)
        self.logvar_head = EnsembleLinear(num_members, num_cells[-1], out_features)
        self.max_logvar = nn.Parameter(torch.full((num_members, 1, out_features), init_max_logvar))
        self.min_logvar = nn.Parameter(torch.full((num_members, 1, out_features), init_min_logvar))

    def forward(
        self, x: torch.Tensor, per_member: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if self.max_logvar.dim() == 4:  # stacked seeds
            seeds = self.max_logvar.shape[:1]
            _check_layout(x, self.trunk.num_members, self.trunk.in_features, per_member, seeds)
            return self._grouped_forward(x)
        h = self.trunk.activate(self.trunk(x, per_member=per_member))
        mean = self.mean_head._affine(h)  # h is the trunk's own output
        raw = self.logvar_head._affine(h)
        return mean, self.bounded_logvar(raw, self.max_logvar, self.min_logvar)

    def _grouped_forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` over stacked seeds. The trunk's last layer may hand its bias on
        to the heads (see :class:`_Linear`). Without autograd, in a group of more than one,
        both heads run as one layer of twice the width: BLAS runs an 11-wide product far
        below its speed, and the 22-wide one takes about the time of one 11-wide (a
        rollout step's heads at S = 8: 0.40 -> 0.21 ms). A group of one keeps its single
        run's calls."""
        h, owed = _run(self.trunk.grouped_layers(last_activation=True), x, settle=False)
        means, logvars = self.mean_head, self.logvar_head
        if torch.is_grad_enabled() or means.weight.shape[0] == 1:
            mean = _Linear(means.weight, means.bias, None, False)(h, owed=owed)
            raw = _Linear(logvars.weight, logvars.bias, None, False)(h, owed=owed)
        else:
            width = means.weight.shape[-1]
            both = _Linear(torch.cat([means.weight, logvars.weight], -1),
                           torch.cat([means.bias, logvars.bias], -1), None, False)  # fmt: skip
            y = both(h, owed=owed)
            mean, raw = y[..., :width], y[..., width:]
        return mean, self.bounded_logvar(raw, self.max_logvar, self.min_logvar)

    @staticmethod
    def bounded_logvar(
        raw: torch.Tensor, max_logvar: torch.Tensor, min_logvar: torch.Tensor
    ) -> torch.Tensor:
        """The raw log-variance squashed between the bounds (any leading dimensions that
        broadcast): ``max - softplus(max - raw)``, then ``min + softplus(logvar - min)``.

        Examples:
            >>> GaussianEnsembleMLP.bounded_logvar(
            ...     torch.tensor([-50.0, 0.0, 50.0]), torch.tensor(1.0), torch.tensor(-10.0))
            tensor([-10.0000,  -0.3132,   1.0000])
        """
        logvar = max_logvar - F.softplus(max_logvar - raw)
        return min_logvar + F.softplus(logvar - min_logvar)

    def bound_penalty(self) -> torch.Tensor:
        """``sum(max_logvar) - sum(min_logvar)``: pulls the learned bounds together
        (``[S]``, one per seed, over stacked seeds)."""
        if self.max_logvar.dim() == 4:
            return self.max_logvar.sum((1, 2, 3)) - self.min_logvar.sum((1, 2, 3))
        return self.max_logvar.sum() - self.min_logvar.sum()
