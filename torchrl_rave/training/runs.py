"""Run directories: the one reader of their metrics, and the one launcher of grids of runs."""

from __future__ import annotations

import csv
import glob
import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "Cell",
    "curves",
    "launch_grid",
    "parse_groups",
    "read_scalar",
    "train_seconds",
    "value_logged_at",
]


def read_scalar(run_dir: str | Path, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (frames) and values of ``metric`` (e.g. ``"eval/return"``) in one run
    directory, as the recipe's CSV logger writes them (``<run>/<exp>/scalars/<metric>.csv``).

    A resumed run logs again the steps between its last checkpoint and where it stopped:
    the later value of a step wins, so a resumed run reads like an uninterrupted one.
    """
    files = sorted(Path(run_dir).glob(f"*/scalars/{metric}.csv"))
    if len(files) != 1:
        raise FileNotFoundError(
            f"{run_dir}: expected one <exp>/scalars/{metric}.csv, found {len(files)}"
        )
    with open(files[0]) as f:
        rows = [(int(step), float(value)) for step, value in csv.reader(f)]
    latest = dict(rows)
    steps = np.array(sorted(latest), dtype=np.int64)
    return steps, np.array([latest[s] for s in steps], dtype=np.float64)


def train_seconds(run_dir: str | Path) -> int | None:
    """A run's own collection, update and evaluation seconds, summed over its batches
    (``time/collect_s``, ``time/update_s``, ``time/eval_s``; a resumed run's repeated
    batches count once, as if it had run uninterrupted), or ``None`` when it logged none.
    Process starts and checkpoint writes are not in it."""
    try:
        parts = [
            read_scalar(run_dir, f"time/{m}_s")[1].sum() for m in ("collect", "update", "eval")
        ]
    except FileNotFoundError:
        return None
    return round(float(sum(parts)))


def value_logged_at(run_dir: str | Path, metric: str, frames: int) -> float | None:
    """The value of ``metric`` logged at exactly ``frames``, or ``None`` (not there yet)."""
    try:
        steps, values = read_scalar(run_dir, metric)
    except FileNotFoundError:
        return None
    hit = np.flatnonzero(steps == frames)
    return float(values[hit[-1]]) if hit.size else None


def parse_groups(specs: Sequence[str]) -> dict[str, list[Path]]:
    """``LABEL=PATTERN`` arguments (a glob of run directories per label)."""
    groups = {}
    for spec in specs:
        if "=" not in spec:
            raise ValueError(f"{spec!r}: expected LABEL=PATTERN")
        label, pattern = spec.split("=", 1)
        runs = sorted(Path(p) for p in glob.glob(pattern))
        if not runs:
            raise FileNotFoundError(f"{label}: no run directory matches {pattern!r}")
        groups[label] = runs
    return groups


def curves(groups: dict[str, list[Path]], metric: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per group: the steps all its runs logged and the values ``[runs, steps]``."""
    out = {}
    for label, runs in groups.items():
        data = [read_scalar(r, metric) for r in runs]
        common = sorted(set.intersection(*(set(s.tolist()) for s, _ in data)))
        values = np.stack([v[np.searchsorted(s, common)] for s, v in data])
        out[label] = (np.array(common), values)
    return out


@dataclass(frozen=True)
class Cell:
    """One run of a grid: its directory, its frame budget and its recipe overrides."""

    run_dir: Path
    frames: int
    overrides: tuple[str, ...] = field(default_factory=tuple)

    def finished(self) -> bool:
        """The run evaluated at its last frame (it always does, then checkpoints)."""
        return value_logged_at(self.run_dir, "eval/return", self.frames) is not None


def _run_cell(script: Path, cell: Cell) -> int:
    args = [
        *cell.overrides,
        f"collector.total_frames={cell.frames}",
        "logger.progress_bar=false",
        f"hydra.run.dir={cell.run_dir}",
    ]
    if any((cell.run_dir / "checkpoints").glob("checkpoint-*")):
        args.append(f"resume={cell.run_dir}")  # an interrupted cell continues
    cell.run_dir.mkdir(parents=True, exist_ok=True)
    # one thread per run: a grid runs `jobs` trainings side by side
    environ = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with open(cell.run_dir / "stdout.log", "a") as log:
        return subprocess.call(
            [sys.executable, str(script), *args], stdout=log, stderr=subprocess.STDOUT, env=environ
        )


def launch_grid(
    script: str | Path,
    cells: Sequence[Cell],
    jobs: int = 1,
    on_done: Callable[[Cell, int], None] | None = None,
) -> dict[Cell, int]:
    """Runs the cells not yet finished, ``jobs`` at a time, each as its own
    ``python <script> <overrides>`` process at one thread; returns their exit codes.

    Finished cells are skipped and interrupted ones resumed from their last checkpoint,
    so the same call can be repeated until the grid is complete. Each cell's output goes
    to ``<run_dir>/stdout.log``; ``on_done(cell, code)`` is called as each one ends.
    """
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    todo = [cell for cell in cells if not cell.finished()]

    def run(cell: Cell) -> int:
        code = _run_cell(Path(script), cell)
        if on_done is not None:
            on_done(cell, code)
        return code

    with ThreadPoolExecutor(jobs) as pool:
        return dict(zip(todo, pool.map(run, todo), strict=True))
