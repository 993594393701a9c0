"""One random stream per seed, for many seeds trained in one process."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch

__all__ = ["SeedStreams"]

Tensor = torch.Tensor


class SeedStreams:
    """One random stream per seed of a group trained in one process.

    Torch draws from process-global generators (the CPU one and each accelerator's), so a
    seed's stream is kept as a saved generator state and swapped in around everything
    done for that seed: :meth:`use` for a phase (collection, sampling, evaluation, a
    checkpoint), :meth:`stack` for one draw per seed inside a batched update. Work done
    under ``use(i)`` sees exactly the generator a single run of seed ``i`` would see, so a
    seed's draws do not depend on the other seeds of its group. Python's ``random`` and
    NumPy's global generator are left shared (the recipe draws from neither: its envs have
    their own generators).

    Args:
        num_seeds (int): the group's size.
        device (torch.device, optional): the device the group's tensors live on; a CUDA
            device's generator is swapped along with the CPU's.

    Each seed's state is taken with :meth:`capture` once the seed has been set up (after
    ``torch.manual_seed`` and its networks' initialisation, as a single run does them).

    Examples:
        >>> streams = SeedStreams(2)
        >>> for i, seed in enumerate([0, 1]):
        ...     _ = torch.manual_seed(seed)
        ...     streams.capture(i)
        >>> with streams.use(1):
        ...     a = torch.rand(3)
        >>> _ = torch.manual_seed(1)
        >>> torch.equal(a, torch.rand(3))
        True
    """

    def __init__(self, num_seeds: int, device: torch.device | str | None = None) -> None:
        self.num_seeds = num_seeds
        self._generators = [torch.default_generator]
        device = torch.device(device) if device is not None else None
        if device is not None and device.type == "cuda":
            index = device.index if device.index is not None else torch.cuda.current_device()
            self._generators.append(torch.cuda.default_generators[index])
        self._states: list[list[Tensor] | None] = [None] * num_seeds

    def capture(self, i: int) -> None:
        """Takes the generators' current state as seed ``i``'s stream."""
        self._states[i] = [g.get_state() for g in self._generators]

    @contextlib.contextmanager
    def use(self, i: int):
        """A context in which the process's generators are seed ``i``'s; on leaving it the
        advanced state is kept as seed ``i``'s stream."""
        self._enter(i)
        try:
            yield
        finally:
            self.capture(i)

    def _enter(self, i: int) -> None:
        state = self._states[i]
        if state is None:
            raise RuntimeError(f"seed {i}'s random stream was never captured (capture({i}))")
        for g, one in zip(self._generators, state, strict=True):
            g.set_state(one)

    def stack(self, draw: Callable[[int], Tensor], dim: int = 0) -> Tensor:
        """``draw(i)`` for each seed under its own stream, stacked along ``dim``."""
        out = []
        for i in range(self.num_seeds):
            self._enter(i)
            out.append(draw(i))
            self.capture(i)
        return torch.stack(out, dim)


def _randn_like(x: Tensor, streams: SeedStreams | None) -> Tensor:
    """Standard normal noise shaped as ``x`` (the seed leading): seed by seed from
    ``streams``, or one draw for the group."""
    if streams is None:
        return torch.randn_like(x)
    return streams.stack(lambda i: torch.randn_like(x[i]))
