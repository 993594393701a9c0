"""Studies: grids of recipe runs (tasks x algorithms x seeds at one frame budget) described
by a YAML file (``recipes/study/<name>.yaml``), whose finished cells are kept under
``results/<name>/<task>/<algorithm>/seed<k>/``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from torchrl_rave._checks import NON_NEGATIVE_INT, POSITIVE_INT
from torchrl_rave.recipe.config import ALGORITHMS, ConfigError

__all__ = ["STUDY_KEYS", "TASK_KEYS", "Task", "cells_elsewhere", "load_study", "report_frames",
           "result_dir", "tasks"]  # fmt: skip


@dataclass(frozen=True)
class Task:
    """One task of a study: ``label`` names its results directory, ``env`` is the
    recipe's ``env.name``, ``overrides`` go to its cells only (e.g. ``env.action_noise``),
    ``reference`` says whether published numbers for ``env`` apply to it, and
    ``cells_from`` names another study whose cells of the same label this one reads (up
    to its own budget) instead of running its own: a twin shared by two studies."""

    label: str
    env: str
    overrides: tuple[str, ...] = ()
    reference: bool = True
    cells_from: str | None = None


def tasks(study: DictConfig) -> list[Task]:
    """A study's tasks: an entry is an env id, or a mapping with ``label``, ``env`` and
    optional ``overrides``, ``reference`` (which defaults to no overrides) and
    ``cells_from``."""
    out = []
    for entry in study.tasks:
        if isinstance(entry, str):
            out.append(Task(entry, entry))
            continue
        extra = tuple(entry.get("overrides") or ())
        reference = bool(entry.get("reference", not extra))
        out.append(Task(entry.label, entry.env, extra, reference, entry.get("cells_from")))
    return out


STUDY_KEYS = ("name", "tasks", "algorithms", "seeds", "frames", "overrides", "contrasts",
              "report_at", "reference_runs", "algorithm_cells_from")  # fmt: skip
TASK_KEYS = ("label", "env", "overrides", "reference", "cells_from")


def load_study(path: Path) -> DictConfig:
    """A study file, checked: its keys, its task entries and their distinct labels, its
    algorithms, seeds and budget, its ``contrasts`` (optional pairs of task labels the
    report compares), its ``report_at`` (optional frames at which the report's tables
    read the metrics; half and all of the budget by default) and its ``reference_runs``
    (optional: the directory under the results, laid out as the study's cells, of a
    reference implementation's runs of the same tasks, algorithms and seeds, which the
    report's calibration table sets beside the study's own) and its
    ``algorithm_cells_from`` (optional: algorithm -> the study whose cells of that
    algorithm, same task labels and seeds, this study reads instead of running them; or
    -> ``{study: <name>, tasks: {<label>: <that study's label>}}`` where the labels
    differ).
    Every problem is raised at once, as one
    :class:`~torchrl_rave.recipe.config.ConfigError`."""
    study = OmegaConf.load(path)
    problems = [f"the study has no {key!r}" for key in STUDY_KEYS[:5] if key not in study]
    problems += [
        f"unknown key {key!r}: a study has {list(STUDY_KEYS)}"
        for key in study if key not in STUDY_KEYS
    ]  # fmt: skip
    if problems:
        raise ConfigError([f"{path}: {p}" for p in problems])
    if not study.tasks:
        problems.append("tasks is empty")
    for entry in study.tasks:
        if isinstance(entry, str):
            continue
        if not isinstance(entry, DictConfig) or not {"label", "env"} <= set(entry):
            problems.append(f"a task must be an env id or have a label and an env, got {entry}")
        else:
            problems += [
                f"task {entry.label!r} has an unknown key {key!r} (a task has {list(TASK_KEYS)})"
                for key in entry if key not in TASK_KEYS
            ]  # fmt: skip
    algorithms = list(study.algorithms)
    unknown = [a for a in algorithms if a not in ALGORITHMS]
    if not algorithms or unknown or len(set(algorithms)) != len(algorithms):
        problems.append(
            f"algorithms must be distinct, not empty and among {list(ALGORITHMS)}, got {algorithms}"
        )
    seeds = list(study.seeds)
    if not seeds or len(set(seeds)) != len(seeds) or not all(map(NON_NEGATIVE_INT.test, seeds)):
        problems.append(f"seeds must be distinct integers >= 0, got {seeds}")
    frames_ok = POSITIVE_INT.test(study.frames)
    if not frames_ok:
        problems.append(f"frames must be an integer >= 1, got {study.frames!r}")
    if problems:  # the checks below read the task labels and the budget
        raise ConfigError([f"{path}: {p}" for p in problems])
    labels = [t.label for t in tasks(study)]
    if len(set(labels)) != len(labels):
        problems.append(f"task labels repeat: {labels}")
    for pair in study.get("contrasts", None) or []:
        if len(pair) != 2 or not set(pair) <= set(labels):
            problems.append(f"a contrast is two of the task labels {labels}, got {list(pair)}")
    borrowed = study.get("algorithm_cells_from", None) or {}
    for algorithm, entry in borrowed.items():
        source, renamed = _borrowed_entry(entry)
        shown = OmegaConf.to_container(entry) if isinstance(entry, DictConfig) else entry
        extra = set(entry) - {"study", "tasks"} if isinstance(entry, DictConfig) else set()
        if (
            algorithm not in algorithms
            or not isinstance(source, str)
            or source == study.name
            or extra
        ):
            problems.append(
                f"algorithm_cells_from maps one of the algorithms {algorithms} to another "
                f"study's name, or to {{study: <name>, tasks: {{<label>: <its label>}}}}, "
                f"got {algorithm}: {shown!r}"
            )
        elif (
            not isinstance(renamed, DictConfig | dict)
            or not set(renamed) <= set(labels)
            or not all(isinstance(v, str) for v in renamed.values())
        ):
            problems.append(
                f"algorithm_cells_from's tasks for {algorithm} map some of the task labels "
                f"{labels} to {source}'s labels, got {shown['tasks']!r}"
            )
    at = list(study.get("report_at", None) or [])
    if not all(isinstance(f, int) and 0 < f <= study.frames for f in at) or at != sorted(set(at)):
        problems.append(
            f"report_at must be increasing frame counts in (0, {study.frames}], got {at}"
        )
    if problems:
        raise ConfigError([f"{path}: {p}" for p in problems])
    return study


def report_frames(study: DictConfig) -> list[int]:
    """The frames at which a study's tables read the metrics: its ``report_at``, or half
    and all of its budget."""
    return list(study.get("report_at", None) or [study.frames // 2, study.frames])


def _borrowed_entry(entry) -> tuple[object, object]:
    """An ``algorithm_cells_from`` entry as (the study, {this study's label: that study's
    label}): a study's name reads the same labels; ``{study: <name>, tasks: {...}}`` reads
    the labels ``tasks`` maps (the others unchanged)."""
    if isinstance(entry, DictConfig | dict):
        return entry.get("study"), entry.get("tasks") or {}
    return entry, {}


def _cells_source(study: DictConfig, task: str, algorithm: str) -> tuple[str | None, str]:
    """(the study that keeps the cells of (task label, algorithm), or ``None`` for this
    one; the label they are kept under there)."""
    borrowed = (study.get("algorithm_cells_from", None) or {}).get(algorithm)
    if borrowed is not None:
        source, labels = _borrowed_entry(borrowed)
        return source, labels.get(task, task)
    return next((t.cells_from for t in tasks(study) if t.label == task), None), task


def cells_elsewhere(study: DictConfig, task: str, algorithm: str) -> str | None:
    """The study that runs and keeps the cells of (task label, algorithm): the one the
    algorithm's ``algorithm_cells_from`` entry names, or the task's ``cells_from``;
    ``None`` when this study runs them."""
    return _cells_source(study, task, algorithm)[0]


def result_dir(results: Path, study: DictConfig, task: str, algorithm: str, seed: int) -> Path:
    """Where the finished cell of (task label, algorithm, seed) is kept: under the study's
    name, or under the one :func:`~torchrl_rave.recipe.studies.cells_elsewhere` names (and
    there under the label its ``algorithm_cells_from`` entry maps ``task`` to)."""
    source, label = _cells_source(study, task, algorithm)
    return results / (source or study.name) / label / algorithm / f"seed{seed}"
