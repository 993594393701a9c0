"""``study.py compare``: are two studies' cells of the same configuration the same run?

    python recipes/study.py compare --config recipes/study/stochastic100k.yaml \\
        --task Hopper-v5-noise0 --against recipes/study/mujoco100k.yaml --against-task Hopper-v5

For every algorithm and seed that both tasks have a finished cell of, it reads one metric
(``eval/return`` by default) from both cells and finds the first evaluation at which the
two differ, beside what each ``cell.json`` records of where the cell ran: its machine (CPU
and vector unit) and the frames it started from (a resumed cell started more than once).
Steps a cell's losses log twice show a second start where its ``cell.json`` predates the
record of starts (a start after a kill or a crash; a run stopped by Ctrl-C or SIGTERM
checkpoints where it stops and logs nothing twice). Values are compared as the CSVs hold
them, so "the same" is to the last digit. Two runs of one configuration part for one of
three reasons, and the table shows which applies: a code change that reorders
floating-point operations, another machine (BLAS picks its kernels by the CPU), or a
resume (before resumes continued the episode they stopped in).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchrl_rave.recipe.runs import read_scalar, relogged
from torchrl_rave.recipe.studies import load_study, result_dir, tasks


def _provenance(cell: Path) -> tuple[str, str, str, str]:
    """(commit, machine, starts, steps logged twice) of a finished cell: the first three as
    its ``cell.json`` records them ("not recorded" where the cell predates the record),
    the last read from its CSVs (:func:`~torchrl_rave.recipe.runs.relogged`), which
    shows a second start even where ``cell.json`` does not."""
    meta = json.loads((cell / "cell.json").read_text())
    m = meta.get("machine")
    machine = f"{m.get('cpu', '?')} ({m.get('vector', '?')})" if m else "not recorded"
    starts = meta.get("starts")
    started = "not recorded"
    if starts:
        frames = [s.get("from_frame") for s in starts]
        started = ", then ".join(f"{f:,}" if isinstance(f, int) else "?" for f in frames)
    step, changed = relogged(cell)
    twice = "none"
    if step is not None:
        twice = f"from {step:,} ({'other values' if changed else 'the same values'})"
    return str(meta.get("commit", "?"))[:7], machine, started, twice


def first_difference(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]):
    """Over the steps both series logged: (how many, the last step where every value so
    far was equal or None, the first step that differs or None)."""
    (sa, va), (sb, vb) = a, b
    common = sorted(set(sa.tolist()) & set(sb.tolist()))
    da = dict(zip(sa.tolist(), va.tolist(), strict=True))
    db = dict(zip(sb.tolist(), vb.tolist(), strict=True))
    last_same = None
    for step in common:
        x, y = da[step], db[step]
        if x != y and not (np.isnan(x) and np.isnan(y)):
            return len(common), last_same, (step, x, y)
        last_same = step
    return len(common), last_same, None


def compare(args) -> str:
    mine, other = load_study(args.config), load_study(args.against)
    labels = {t.label for t in tasks(mine)}, {t.label for t in tasks(other)}
    if args.task not in labels[0]:
        raise SystemExit(
            f"--task {args.task!r} is not a task of {args.config} ({sorted(labels[0])})"
        )
    if args.against_task not in labels[1]:
        raise SystemExit(
            f"--against-task {args.against_task!r} is not a task of {args.against} "
            f"({sorted(labels[1])})"
        )
    lines = [
        f"`{args.metric}` of `{mine.name}`'s {args.task} cells against `{other.name}`'s "
        f"{args.against_task} cells of the same algorithm and seed:",
        "",
        "| algorithm | seed | evaluations | the same up to | first difference | "
        f"{mine.name}: commit; machine; started at; logged twice | "
        f"{other.name}: commit; machine; started at; logged twice |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    missing = []
    for algorithm in [a for a in mine.algorithms if a in other.algorithms]:
        for seed in [s for s in mine.seeds if s in other.seeds]:
            a = result_dir(args.results, mine, args.task, algorithm, seed)
            b = result_dir(args.results, other, args.against_task, algorithm, seed)
            if not (a / "cell.json").is_file() or not (b / "cell.json").is_file():
                missing.append(f"{algorithm} seed {seed}")
                continue
            n, same, diff = first_difference(
                read_scalar(a, args.metric), read_scalar(b, args.metric)
            )
            upto = "every evaluation" if diff is None else (
                "none" if same is None else f"{same:,} frames"
            )  # fmt: skip
            first = "" if diff is None else f"{diff[0]:,} frames: {diff[1]:.2f} vs {diff[2]:.2f}"
            pa, pb = _provenance(a), _provenance(b)
            lines.append(
                f"| {algorithm} | {seed} | {n} | {upto} | {first} | "
                f"{'; '.join(pa)} | {'; '.join(pb)} |"
            )
    if missing:
        lines += ["", f"Not compared (a cell not finished in one of them): {'; '.join(missing)}."]
    text = "\n".join(lines)
    print(text)
    return text
