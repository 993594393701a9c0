"""A curriculum: an env setting that steps through stages as an evaluation metric passes
thresholds (the supplement's target-speed curriculum for Learn to Move: a fast gait
first, then lower target speeds while keeping it)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["Curriculum"]


class Curriculum:
    """Stages of one env setting (e.g. ``LearnToMove-v0``'s ``constant_speed``), first to
    last. :meth:`update` moves to the next stage when ``metrics[metric]`` reaches the
    current stage's threshold; the last stage stays. ``stage`` is all its state
    (``state_dict``).

    Args:
        values (Sequence): the setting's value at each stage.
        thresholds (float or Sequence[float]): the metric value that ends each stage but the
            last: one number for all, or ``len(values) - 1`` of them.
        metric (str): the metric read (an evaluation metric, e.g. ``"eval/return"``).

    Examples:
        >>> c = Curriculum([3.0, 2.0, 1.4], thresholds=[500.0, 800.0])
        >>> c.value, c.update({"eval/return": 450.0}), c.update({"eval/return": 510.0})
        (3.0, False, True)
        >>> c.stage, c.value, c.update({"eval/return": 700.0}), c.update({"eval/return": 900.0})
        (1, 2.0, False, True)
        >>> c.value, c.update({"eval/return": 10**6}), c.state_dict()
        (1.4, False, {'stage': 2})
    """

    def __init__(
        self,
        values: Sequence[Any],
        thresholds: float | Sequence[float],
        metric: str = "eval/return",
    ) -> None:
        self.values = list(values)
        if not self.values:
            raise ValueError("a curriculum needs at least one stage")
        if isinstance(thresholds, (int, float)):
            thresholds = [float(thresholds)] * (len(self.values) - 1)
        self.thresholds = [float(t) for t in thresholds]
        if len(self.thresholds) != len(self.values) - 1:
            raise ValueError(
                f"a curriculum of {len(self.values)} stages needs {len(self.values) - 1} "
                f"thresholds, got {len(self.thresholds)}"
            )
        if not all(math.isfinite(t) for t in self.thresholds):
            raise ValueError(f"thresholds must be finite, got {self.thresholds}")
        self.metric = metric
        self.stage = 0

    @property
    def value(self) -> Any:
        """The setting at the current stage."""
        return self.values[self.stage]

    def update(self, metrics: Mapping[str, float]) -> bool:
        """Moves on one stage if the metric reached the current threshold; ``True`` if it did."""
        value = metrics.get(self.metric)
        if (
            self.stage == len(self.values) - 1
            or value is None
            or not value >= self.thresholds[self.stage]
        ):
            return False
        self.stage += 1
        return True

    def state_dict(self) -> dict:
        return {"stage": self.stage}

    def load_state_dict(self, state: Mapping) -> None:
        stage = int(state["stage"])
        if not 0 <= stage < len(self.values):
            raise ValueError(f"stage {stage} is not one of this curriculum's {len(self.values)}")
        self.stage = stage
