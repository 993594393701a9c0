"""Polyak target updates in one fused call."""

from __future__ import annotations

import torch
from torchrl.objectives import SoftUpdate

from torchrl_rave._checks import UNIT_INTERVAL

__all__ = ["ForeachSoftUpdate"]


class ForeachSoftUpdate(SoftUpdate):
    """:class:`~torchrl.objectives.SoftUpdate` with the same update, done by one
    ``torch._foreach_lerp_`` over flat lists of tensors.

    TorchRL's ``SoftUpdate.step`` walks the parameter TensorDicts and lerps every network
    as a TensorDict (unlocking and relocking it each time); on small networks that costs
    more than a whole critic update. Here the ``(target, source)`` leaves are listed once
    and re-listed only when the storage behind them changes (a ``.to(device)`` of the loss).
    ``state_dict``/``load_state_dict`` are TorchRL's.

    Examples:
        >>> from torchrl.modules import MLP, ValueOperator, Actor
        >>> from torchrl.objectives import DDPGLoss
        >>> actor = Actor(MLP(in_features=3, out_features=1, num_cells=[4]))
        >>> critic = ValueOperator(MLP(in_features=4, out_features=1, num_cells=[4]),
        ...                        in_keys=["observation", "action"])
        >>> loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
        >>> updater = ForeachSoftUpdate(loss, tau=0.25)
        >>> with torch.no_grad():
        ...     _ = loss.value_network_params.apply(lambda p: p.fill_(1.0))
        ...     _ = loss.target_value_network_params.apply(lambda p: p.fill_(0.0))
        >>> updater.step()
        >>> loss.target_value_network_params["module", "0", "bias"]
        tensor([0.2500, 0.2500, 0.2500, 0.2500])
    """

    _pairs: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None

    def __init__(self, loss_module, *, eps: float | None = None, tau: float | None = None):
        # TorchRL reports a bad tau as "eps = 1 - tau"; name the argument given
        for name, value in (("tau", tau), ("eps", eps)):
            if value is not None:
                UNIT_INTERVAL.check(name, value.item() if torch.is_tensor(value) else value)
        super().__init__(loss_module, eps=eps, tau=tau)

    def _list_pairs(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        for name in self._target_names:  # as TorchRL does: lets the loss refresh its targets
            getattr(self.loss_module, name)
        targets, sources = [], []
        key = next(iter(self._sources.keys()))
        leaf = next(iter(self._sources.get(key).keys(True, True)))
        self._probe = (key, leaf if isinstance(leaf, tuple) else (leaf,))
        for key, source in self._sources.items():
            target = self._targets.get(f"target_{key}")
            if target.requires_grad:
                raise RuntimeError("the target parameter is part of a graph.")
            for leaf in source.keys(True, True):
                targets.append(target.get(leaf).data)
                sources.append(source.get(leaf).data)
        return targets, sources

    def _stale(self) -> bool:
        if self._pairs is None:
            return True
        key, leaf = self._probe
        return (
            self._targets.get((f"target_{key}", *leaf)).data_ptr() != self._pairs[0][0].data_ptr()
            or self._sources.get((key, *leaf)).data_ptr() != self._pairs[1][0].data_ptr()
        )

    def step(self) -> None:
        if not self.initialized:
            raise RuntimeError(
                f"{type(self).__name__} must be initialized (`init_()`) before calling step()"
            )
        if self._stale():
            self._pairs = self._list_pairs()
        targets, sources = self._pairs
        with torch.no_grad():
            torch._foreach_lerp_(targets, sources, 1.0 - self.eps)
