"""The study report's building blocks: reading a study's finished cells and writing
markdown tables of them (``study_report.py`` and ``study_calibration.py`` use them)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchrl_rave.recipe.runs import read_scalar
from torchrl_rave.recipe.stats import difference95, interval95
from torchrl_rave.recipe.studies import result_dir

RAVE_DIAGNOSTICS = ["rave_alpha", "wm_transition_mse", *(f"horizon_weight_h{h}" for h in range(4))]
# metrics under an earlier name in cells that ran before the rename
EARLIER_NAMES = {"train/rave_alpha": "train/alpha", "train/sac_temperature": "train/sac_alpha"}
WELCH = (
    "the 95 % interval of the difference (Welch's standard error, min(seeds) - 1 degrees "
    "of freedom); an interval that contains 0 does not separate the two"
)


def fmt_interval(mean: float, half: float, sign: str = "", digits: int = 0) -> str:
    """``mean ± half``, or ``mean (1 seed)`` where one seed leaves no interval (NaN)."""
    value = f"{mean:{sign}.{digits}f}"
    return value + (" (1 seed)" if np.isnan(half) else f" ± {half:.{digits}f}")


BOOTSTRAP = (
    "a stratified bootstrap (each task's seeds resampled within the task, 10,000 times, "
    "seeded; `torchrl_rave.recipe.stats`, the rliable method)"
)


def fmt_bootstrap(estimate: tuple[float, float, float], digits: int = 0) -> str:
    """``value [lo, hi]``, or ``value (no interval)`` where the bootstrap gives none."""
    value, lo, hi = estimate
    if np.isnan(lo):
        return f"{value:.{digits}f} (no interval)"
    return f"{value:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def group(study, results: Path, task: str, algorithm: str) -> list[Path]:
    dirs = [result_dir(results, study, task, algorithm, s) for s in study.seeds]
    return [d for d in dirs if (d / "cell.json").exists()]


def eval_episodes(run: Path) -> int:
    """Episodes per evaluation of a finished cell, from the config in its cell.json."""
    return int(json.loads((run / "cell.json").read_text())["config"]["eval"]["episodes"])


def read_metric(run: Path, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_scalar`, or the metric's earlier name in a cell that logged that one."""
    try:
        return read_scalar(run, metric)
    except FileNotFoundError:
        if metric not in EARLIER_NAMES:
            raise
        return read_scalar(run, EARLIER_NAMES[metric])


def series(
    runs: list[Path], metric: str, until: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per run, ``metric`` at the steps every run logged (up to ``until`` frames)."""
    data = [read_metric(r, metric) for r in runs]
    if until is not None:
        data = [(s[s <= until], v[s <= until]) for s, v in data]
    common = sorted(set.intersection(*(set(s.tolist()) for s, _ in data)))
    return np.array(common), np.stack([v[np.searchsorted(s, common)] for s, v in data])


def at_frame(runs: list[Path], metric: str, frame: int) -> np.ndarray | None:
    """Per run: ``metric`` logged at exactly ``frame``; ``None`` when no run is given or
    one of them lacks it (cells from before the metric existed)."""
    if not runs:
        return None
    try:
        steps, values = series(runs, metric)
    except FileNotFoundError:
        return None
    hit = np.flatnonzero(steps == frame)
    return values[:, hit[0]] if hit.size else None


def tail_means(
    runs: list[Path], metric: str, after: int, until: int | None = None
) -> np.ndarray | None:
    """Per run: the mean of ``metric``'s values logged after ``after`` frames (up to
    ``until``)."""
    try:
        steps, values = series(runs, metric, until)
    except FileNotFoundError:
        return None
    last = steps > after
    return values[:, last].mean(1) if last.any() else None


def cells_of(values: list[np.ndarray | None], digits: int = 0) -> list[str]:
    return ["n/a" if v is None else fmt_interval(*interval95(v), digits=digits) for v in values]


def differences(a: list, b: list, digits: int = 0) -> list[str] | None:
    """``a - b`` with its Welch interval per column, or ``None`` when a column lacks data."""
    if any(v is None for v in a + b):
        return None
    return [fmt_interval(*difference95(x, y), "+", digits) for x, y in zip(a, b, strict=True)]


def section(caption: str, columns: list[str], rows: list[str]) -> list[str]:
    """A markdown table of ``rows`` under its caption and ``columns``; nothing without rows."""
    if not rows:
        return []
    return [
        "",
        caption,
        "",
        "| " + " | ".join(columns) + " |",
        "| --- " * len(columns) + "|",
        *rows,
    ]
