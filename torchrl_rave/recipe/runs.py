"""Run directories: the one reader of their metrics, and the one launcher of grids of runs."""

from __future__ import annotations

import contextlib
import csv
import difflib
import glob
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchrl_rave.recipe.agent import check_env
from torchrl_rave.recipe.checkpoint import (
    DamagedCheckpoint,
    RunCheckpoint,
    check_run_directory,
    config_for_resume,
    newest_frame,
)
from torchrl_rave.recipe.config import ConfigError, check_config, override_keys, preset_of
from torchrl_rave.recipe.schema import with_algorithm_preset

__all__ = [
    "Cell",
    "GridStopped",
    "cell_arguments",
    "check_cells",
    "curves",
    "launch_grid",
    "parse_groups",
    "read_scalar",
    "relogged",
    "train_seconds",
    "value_logged_at",
]


def read_scalar(run_dir: str | Path, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """Steps (frames) and values of ``metric`` (e.g. ``"eval/return"``) in one run
    directory, as the recipe's logger wrote them: CSV (``<run>/<exp>/scalars/<metric>.csv``)
    TensorBoard (``<run>/<exp>/events.out.tfevents.*``, read with the ``tensorboard``
    package) or MLflow (``<run>/mlflow.db``, read with ``mlflow``). A run logged to W&B (or
    not at all) is refused with a message that says so.

    A resumed run logs again the steps between its last checkpoint and where it stopped:
    the later value of a step wins, so a resumed run reads like an uninterrupted one.

    A symbolic link under ``run_dir`` that leads out of it is refused
    (:class:`~torchrl_rave.recipe.checkpoint.UnsafeRunDirectory`) before any file is
    opened: a reader never reads, nor lets MLflow write, through one.
    """
    run_dir = Path(run_dir)
    check_run_directory(run_dir)
    files = sorted(run_dir.glob(f"*/scalars/{metric}.csv"))
    if len(files) > 1:
        raise FileNotFoundError(
            f"{run_dir}: expected one <exp>/scalars/{metric}.csv, found {len(files)}"
        )
    if files:
        rows = _csv_rows(files[0])
    elif any(run_dir.glob("*/events.out.tfevents.*")):
        rows = _tensorboard_rows(run_dir, metric)
    elif (run_dir / "mlflow.db").is_file():
        rows = _mlflow_rows(run_dir, metric)
    else:
        logged = sorted(
            str(
                p.relative_to(run_dir / p.relative_to(run_dir).parts[0] / "scalars").with_suffix("")
            )
            for p in run_dir.glob("*/scalars/**/*.csv")
        )
        if logged:  # a misspelt metric: name the close ones, or what there is
            close = difflib.get_close_matches(metric, logged, n=3)
            hint = f"did you mean {close}?" if close else f"it logged {logged}"
            raise FileNotFoundError(f"{run_dir}: no {metric!r} logged; {hint}")
        raise FileNotFoundError(f"{run_dir}: no {metric!r} logged{_backend_note(run_dir)}")
    latest = dict(rows)
    steps = np.array(sorted(latest), dtype=np.int64)
    return steps, np.array([latest[s] for s in steps], dtype=np.float64)


def relogged(run_dir: str | Path, metrics: str = "train/loss_*") -> tuple[int | None, bool]:
    """Whether a run directory's losses log some step twice, as a run that was stopped
    and started again does: it logs again the steps between the checkpoint it started
    from and where it stopped. ``metrics`` globs the CSV metrics read: by default the
    losses, which a run logs once per batch (an episode's return may log several rows
    at one step, and timings differ between any two starts). Returns the first step
    logged twice (``None`` if none) and whether any value logged again differs from the
    first: the same values mean the second start repeated the first exactly (a restart
    from frame 0, or a resume that continued its episode), other values that the run
    parted from there on. Only a stop that lost frames shows (a kill, a crash, the end of
    a machine): a run stopped by Ctrl-C or SIGTERM checkpoints where it stops, and its
    resume logs nothing twice."""
    first_twice, changed = None, False
    check_run_directory(run_dir)
    for path in Path(run_dir).glob(f"*/scalars/{metrics}.csv"):
        seen: dict[int, float] = {}
        for step, value in _csv_rows(path):
            if step in seen:
                first_twice = step if first_twice is None else min(first_twice, step)
                changed |= value != seen[step] and not (np.isnan(value) and np.isnan(seen[step]))
            else:
                seen[step] = value
    return first_twice, changed


def _csv_rows(path: Path) -> list[tuple[int, float]]:
    """``(step, value)`` rows of one metric's CSV; a line that is not ``step,value`` (a
    file damaged or edited by hand) is named with its file and line number."""
    rows = []
    with open(path, newline="") as f:
        for number, row in enumerate(csv.reader(f), 1):
            try:
                step, value = row
                rows.append((int(step), float(value)))
            except ValueError:
                raise ValueError(
                    f"{path}:{number}: expected a line 'step,value', got {','.join(row)!r}"
                ) from None
    return rows


def _tensorboard_rows(run_dir: Path, metric: str) -> list[tuple[int, float]]:
    """``(step, value)`` of a scalar in a run's TensorBoard event files, in write order."""
    try:
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    except ImportError as err:
        raise ImportError(
            f"{run_dir} was logged with logger.backend=tensorboard: reading it needs the "
            "'tensorboard' package (pip install 'torchrl-rave[logging]')"
        ) from err
    (exp_dir,) = {p.parent for p in run_dir.glob("*/events.out.tfevents.*")}
    events = EventAccumulator(str(exp_dir), size_guidance={"scalars": 0})
    events.Reload()  # every event file of the directory, oldest first
    if metric not in events.Tags()["scalars"]:
        raise FileNotFoundError(f"{run_dir}: no {metric!r} in its TensorBoard events")
    return [(int(e.step), float(e.value)) for e in events.Scalars(metric)]


def _mlflow_rows(run_dir: Path, metric: str) -> list[tuple[int, float]]:
    """``(step, value)`` of a metric in a run's MLflow store (``mlflow.db``): every MLflow
    run in it (one per start of the training run), oldest first."""
    try:
        from mlflow.tracking import MlflowClient
    except ImportError as err:
        raise ImportError(
            f"{run_dir} was logged with logger.backend=mlflow: reading it needs the 'mlflow' "
            "package (pip install 'torchrl-rave[logging]')"
        ) from err
    store = run_dir / "mlflow.db"
    with open(store, "rb") as f:  # MLflow would try to upgrade any other file in place
        if f.read(16) != b"SQLite format 3\x00":
            raise ValueError(f"{store} is not an SQLite database, as an MLflow store is")
    try:
        client = MlflowClient(tracking_uri=f"sqlite:///{store.resolve()}")
        ids = [e.experiment_id for e in client.search_experiments()]
        rows = []
        for run in client.search_runs(ids, order_by=["attributes.start_time ASC"]):
            history = client.get_metric_history(run.info.run_id, metric)
            rows += [(int(m.step), float(m.value))
                     for m in sorted(history, key=lambda m: m.timestamp)]  # fmt: skip
    except Exception as err:  # noqa: BLE001 (SQLAlchemy's and MLflow's errors name no file)
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise ValueError(
            f"{store} is not a readable MLflow store ({type(err).__name__}: {first})"
        ) from None
    if not rows:
        raise FileNotFoundError(f"{run_dir}: no {metric!r} in its MLflow store")
    return rows


def _backend_note(run_dir: Path) -> str:
    """Why a run directory has no metric files, from its saved config (plain JSON)."""
    try:
        backend = RunCheckpoint(run_dir).config()["logger"]["backend"]
    except (OSError, KeyError, TypeError, ValueError, DamagedCheckpoint):
        return " (no CSV or TensorBoard metrics here)"
    if backend in ("csv", "tensorboard", "mlflow"):
        return f" (it logged with logger.backend={backend})"
    where = f"to {backend}" if backend else "nowhere (logger.backend='')"
    return (
        f": this run logged its metrics {where}; the analyses read runs logged with "
        "logger.backend=csv, tensorboard or mlflow"
    )


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
    #: a seed group (``seeds=[...]`` among the overrides): its seeds, each run under
    #: ``run_dir/seed<s>``; empty for an ordinary run
    seeds: tuple[int, ...] = ()

    def members(self) -> list[Cell]:
        """A group's runs, one per seed (an ordinary cell is its own only member)."""
        if not self.seeds:
            return [self]
        return [Cell(self.run_dir / f"seed{s}", self.frames, self.overrides) for s in self.seeds]

    def finished(self) -> bool:
        """The run (every run of a group) evaluated at its last frame (it always does,
        then checkpoints)."""
        if self.seeds:
            return all(m.finished() for m in self.members())
        return value_logged_at(self.run_dir, "eval/return", self.frames) is not None

    def checkpoint_frame(self) -> int | None:
        """The frame of the newest checkpoint (for a group, the oldest of its seeds'
        newest ones), or ``None`` when some run has none."""
        frames = [newest_frame(m.run_dir) for m in self.members()]
        return None if None in frames else min(frames)

    def starts(self) -> list[dict]:
        """What :func:`launch_grid` wrote down at each start of this run, oldest first:
        ``from_frame`` (0, or its newest checkpoint's frame, which it resumes from unless
        that checkpoint is damaged), ``at`` (local time) and the caller's ``record``
        entries."""
        path = self.run_dir / STARTS
        return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


STARTS = "starts.jsonl"  # in a run directory, one line per start of its run


def check_cells(cells: Sequence[Cell], config_dir: str | Path, config_name: str = "config") -> None:
    """Checks the config every unfinished cell's run will start with, before any starts.

    Each cell's command line, as :func:`launch_grid` passes it (:func:`cell_arguments`), is
    composed with the recipe's ``config_dir/config_name`` (an interrupted cell's saved config
    is read as ``resume=`` reads it) and checked by
    :func:`~torchrl_rave.recipe.config.check_config`. A mistake in a grid (an env id, an
    algorithm, an extra key) would otherwise fail each of its runs in turn, each with its
    own log; here every problem is raised at once, as one
    :class:`~torchrl_rave.recipe.config.ConfigError` naming the cells. Each distinct env
    is built once (:func:`~torchrl_rave.recipe.agent.check_env`): a keyword it does not
    take, a space the learners cannot use or an extra not installed is found here too."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    where: dict[str, list[Path]] = {}  # each problem, and the cells that have it
    counts = Counter(Path(cell.run_dir) for cell in cells)
    shared = [  # two runs at once in one directory would corrupt both
        f"{n} cells would write one run directory, {run_dir} (a seed, env or algorithm given "
        "twice?)"
        for run_dir, n in counts.items() if n > 1
    ]  # fmt: skip
    envs: dict[str, list[str]] = {}  # each distinct env's problems, found building it once
    with initialize_config_dir(config_dir=str(Path(config_dir).resolve()), version_base="1.3"):
        for cell in cells:
            if cell.finished():
                continue
            # as the run will start: hydra's own keys are not the config's
            overrides = [a for a in cell_arguments(cell) if not a.startswith("hydra.")]
            try:
                if cell.checkpoint_frame() is not None:  # the saved config, as resume= reads it
                    cfg = config_for_resume(cell.run_dir, overrides, compose(config_name))
                else:
                    cfg = compose(config_name, overrides=overrides)
                    cfg = with_algorithm_preset(cfg, preset_of(overrides), override_keys(overrides))
                check_config(cfg)
                kwargs = cfg.env.kwargs
                kwargs = None if kwargs is None else OmegaConf.to_container(kwargs)
                env = json.dumps([cfg.env.name, kwargs], sort_keys=True)
                if env not in envs:
                    envs[env] = _env_problems(cfg)
                problems = envs[env]
            except ConfigError as e:
                problems = e.problems
            except Exception as e:  # hydra's own: a key the config does not have, bad syntax
                problems = [f"{type(e).__name__}: {e}".replace("\n", " ")]
            for problem in problems:
                where.setdefault(problem, []).append(cell.run_dir)
    if where or shared:
        raise ConfigError(shared + [
            f"{problem} (in {len(dirs)} cell{'s' if len(dirs) > 1 else ''}: {dirs[0]}"
            f"{', ...' if len(dirs) > 1 else ''})"
            for problem, dirs in where.items()
        ])  # fmt: skip


def _env_problems(cfg) -> list[str]:
    """The problems of building ``cfg``'s env (:func:`~torchrl_rave.recipe.agent.check_env`):
    a keyword or a space the learners cannot use, a family whose extra is not installed."""
    try:
        check_env(cfg)
    except ConfigError as e:
        return e.problems
    except Exception as e:  # e.g. gymnasium's DependencyNotInstalled
        return [f"env.name={cfg.env.name!r}: {type(e).__name__}: {str(e).splitlines()[0]}"]
    return []


def cell_arguments(cell: Cell) -> list[str]:
    """The recipe's command line for ``cell``: its overrides and frame budget, or, for an
    interrupted cell (one with a checkpoint), ``resume=`` its run directory and the budget.
    A resumed run keeps the config it was saved with, and refuses a ``preset=`` or the
    other keys it would ignore (:func:`~torchrl_rave.recipe.checkpoint.config_for_resume`);
    the cell's overrides are in that config already."""
    common = [
        f"collector.total_frames={cell.frames}",
        "logger.progress_bar=false",
        f"hydra.run.dir={cell.run_dir}",
    ]
    if cell.checkpoint_frame() is not None:
        return [f"resume={cell.run_dir}", *common]
    return [*cell.overrides, *common]


def _start_cell(script: Path, cell: Cell, record: dict) -> subprocess.Popen:
    args = cell_arguments(cell)
    frame = cell.checkpoint_frame() or 0
    cell.run_dir.mkdir(parents=True, exist_ok=True)
    when = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    with open(cell.run_dir / STARTS, "a") as f:
        f.write(json.dumps({**record, "from_frame": frame, "at": when}) + "\n")
    # one thread per run: a grid runs `jobs` trainings side by side
    environ = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with open(cell.run_dir / "stdout.log", "a") as log:
        # its own session: a terminal's Ctrl-C reaches the launcher only, which passes
        # it on once (a second one would stop the run before it checkpoints)
        return subprocess.Popen(
            [sys.executable, str(script), *args],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=environ,
            start_new_session=True,
        )


class GridStopped(KeyboardInterrupt):
    """:func:`launch_grid` was asked to stop (SIGINT or SIGTERM): the runs it had started
    checkpointed and stopped, the rest never started; the same call resumes them all."""


class _Launcher:
    """Starts cells and passes each stop signal the launcher gets to every running cell
    exactly once; a worker thread owns each child and forwards to it."""

    def __init__(self, script: Path, record: dict) -> None:
        self.script, self.record = script, record
        self.signals: list[int] = []  # the stop signals received, in order
        self.started: list[Cell] = []
        self.lock = threading.Lock()

    def handle(self, signum, frame) -> None:  # runs in the main thread
        self.signals.append(signum)

    def run(self, cell: Cell) -> int | None:
        """The cell's exit code, or ``None`` when a stop came before it could start."""
        with self.lock:
            if self.signals:
                return None
            child = _start_cell(self.script, cell, self.record)
            self.started.append(cell)
        forwarded = 0
        while True:
            try:
                return child.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                for signum in self.signals[forwarded:]:
                    child.send_signal(signum)
                forwarded = len(self.signals)

    @contextlib.contextmanager
    def forwarding(self):
        """Routes SIGINT and SIGTERM to :meth:`handle` for the block (main thread only;
        from another thread the signals keep their handlers and nothing is forwarded)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {sig: signal.signal(sig, self.handle) for sig in _STOP_SIGNALS}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def launch_grid(
    script: str | Path,
    cells: Sequence[Cell],
    jobs: int = 1,
    on_done: Callable[[Cell, int], None] | None = None,
    record: dict | None = None,
) -> dict[Cell, int]:
    """Runs the cells not yet finished, ``jobs`` at a time, each as its own
    ``python <script> <overrides>`` process at one thread; returns their exit codes.

    Finished cells are skipped and interrupted ones resumed from their last checkpoint,
    so the same call can be repeated until the grid is complete. Each cell's output goes
    to ``<run_dir>/stdout.log``; ``on_done(cell, code)`` is called as each one ends. Each
    start is written down (:meth:`Cell.starts`) with the JSON entries of ``record``, such
    as the commit of the code that runs it.

    SIGINT or SIGTERM to the launcher (called from the main thread) stops the grid as
    they stop one run: each running cell gets the signal once, checkpoints at the end of
    its batch and exits, no further cell starts, and :class:`GridStopped` is raised once
    they have all exited (``on_done`` is not called for a cell stopped that way). A
    second signal is passed on too, and stops the cells at once.
    """
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    todo = [cell for cell in cells if not cell.finished()]
    launcher = _Launcher(Path(script), dict(record or {}))

    def run(cell: Cell) -> int | None:
        code = launcher.run(cell)
        stopped = bool(launcher.signals) and code == 0 and not cell.finished()
        if code is not None and on_done is not None and not stopped:
            on_done(cell, code)
        return code

    with launcher.forwarding(), ThreadPoolExecutor(jobs) as pool:
        futures = [pool.submit(run, cell) for cell in todo]
        # short waits: a signal that lands on a worker thread runs its handler only once
        # the main thread runs Python again
        while wait(futures, timeout=0.2).not_done:
            pass
        codes = {cell: future.result() for cell, future in zip(todo, futures, strict=True)}
    if launcher.signals:
        stopped = [c for c in launcher.started if not c.finished()]
        waiting = sum(code is None for code in codes.values())
        raise GridStopped(
            f"stopped by {signal.Signals(launcher.signals[0]).name}: "
            f"{len(stopped)} run(s) checkpointed and stopped"
            + "".join(f"\n  {c.run_dir}" for c in stopped)
            + f"\n{waiting} run(s) had not started; run the same command again to resume"
        )
    return codes
