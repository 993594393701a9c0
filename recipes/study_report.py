"""``study.py report``: a study's tables and figures, rebuilt from ``results/`` alone.

Per task and algorithm, over the seeds that finished: the evaluation return at half and
all of the budget and over the last quarter, the falling rate, RAVE's mean minus each
other algorithm's; where the cells logged it, the critics' value error (``eval/q_bias``,
``eval/q_rmse``, ``eval/q_corr``); the diagnostics of the value-expansion targets; the
change between the tasks a study pairs in ``contrasts``; what the cells cost; and per task
the curves of return, falling rate, value bias and RAVE's diagnostics.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from compare import REFERENCE
from plot_curves import band_plot, seeds, study_figures

from torchrl_rave.recipe.runs import read_scalar, train_seconds
from torchrl_rave.recipe.stats import (
    difference95,
    improvement_interval,
    interval95,
    iqm,
    mean,
    stratified_interval,
    wilson_interval,
)
from torchrl_rave.recipe.studies import load_study, report_frames, result_dir, tasks

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


# TianShou's MuJoCo benchmark at 100k frames (gym v3, 10 seeds, 256 x 256, batch 256): mean
# and std over seeds of the evaluation return. Theirs, not ours.
PUBLISHED_100K = {
    "Hopper": {"sac": (2613, 991), "td3": (597, 288), "ddpg": (904, 396)},
    "Walker2d": {"sac": (1305, 795), "td3": (483, 174), "ddpg": (113, 78)},
    "HalfCheetah": {"sac": (6515, 514), "td3": (5336, 376), "ddpg": (6308, 1011)},
}
# the bar a baseline must meet (the published mean minus one published std) and the
# learners held to it
CALIBRATED = ("sac", "td3")


def calibration(study, results: Path, out: Path) -> list[str]:
    """The calibration table and curves: per task and algorithm, the study's return at
    its budget beside the reference implementation's runs (``reference_runs``) and the
    published one, and whether the learner meets the bar (at least the published mean
    minus one published std, and not below the reference run here by more than its own
    seed spread); with the training-episode returns of both, per 10,000 frames."""
    name = study.get("reference_runs", None)
    if name is None:
        return []
    rows, training = [], []
    bins = np.arange(0, study.frames, 10_000) + 10_000
    for entry in tasks(study):
        curves = {}
        for algorithm in study.algorithms:
            ours = group(study, results, entry.label, algorithm)
            refs = [d for s in study.seeds
                    if ((d := results / name / entry.label / algorithm / f"seed{s}") / "reference.json").exists()]  # fmt: skip
            published = PUBLISHED_100K.get(entry.env.split("-")[0], {}).get(algorithm)
            if not ours and not refs:
                continue
            ends = [at_frame(runs, "eval/return", study.frames) if runs else None
                    for runs in (ours, refs)]  # fmt: skip
            cells = [f"{v.mean():.0f} ± {v.std(ddof=1):.0f} ({len(v)})" if v is not None and
                     len(v) > 1 else "n/a" for v in ends]  # fmt: skip
            pub = f"{published[0]} ± {published[1]}" if published else "n/a"
            verdict = "n/a"
            if algorithm in CALIBRATED and published and ends[0] is not None:
                bar = published[0] - published[1]
                checks = [f"{'meets' if ends[0].mean() >= bar else 'misses'} the bar {bar}"]
                if ends[1] is not None and len(ends[1]) > 1:
                    floor = ends[1].mean() - ends[1].std(ddof=1)
                    checks.append(f"{'within' if ends[0].mean() >= floor else 'below'} the "
                                  f"reference's spread (>= {floor:.0f})")  # fmt: skip
                verdict = "; ".join(checks)
            rows.append(f"| {entry.label} | {algorithm} | {cells[0]} | {cells[1]} | {pub} | "
                        f"{verdict} |")  # fmt: skip
            per_bin = []
            for runs in (ours, refs):
                if not runs:
                    per_bin.append(["n/a"] * len(bins))
                    continue
                means = []
                for r in runs:
                    steps, values = read_metric(r, "train/episode_reward")
                    idx = np.digitize(steps, bins, right=True)
                    means.append([values[idx == i].mean() if (idx == i).any() else np.nan
                                  for i in range(len(bins))])  # fmt: skip
                columns = np.array(means).T  # per bin: each seed's mean (NaN: no episode)
                per_bin.append([f"{c[~np.isnan(c)].mean():.0f}" if (~np.isnan(c)).any()
                                else "n/a" for c in columns])  # fmt: skip
            for who, cols in zip(("ours", "reference"), per_bin, strict=True):
                training.append(
                    f"| {entry.label} | {algorithm} | {who} | " + " | ".join(cols) + " |"
                )
            for who, runs in (("ours", ours), ("reference", refs)):
                if runs:
                    steps, values = series(runs, "eval/return", study.frames)
                    curves[f"{algorithm}, {who} ({seeds(len(runs))})"] = (
                        steps, values.mean(0), values.min(0), values.max(0))  # fmt: skip
        if curves:
            band_plot(curves, out / f"{study.name}_{entry.label}_calibration.png",
                      xlabel="environment frames",
                      ylabel="eval/return (mean, band: min-max over seeds)",
                      title=f"{entry.label}: ours and the reference implementation run here")  # fmt: skip
    lines = section(
        f"Calibration at {study.frames:,} frames: the evaluation return, mean ± std over seeds "
        "(seeds in brackets), of this study's cells, of the reference implementation run here "
        f"on the same task and seeds (`results/{name}`), and as published (TianShou's "
        "benchmark, gym v3, 10 seeds; theirs, not ours). The bar: at least the published "
        "mean minus one published std, and not below the reference run here by more than its "
        "own seed spread (its mean minus its std).",
        ["task", "algorithm", "ours", "reference, run here", "published", "verdict"],
        rows,
    )
    return lines + section(
        "Training-episode returns of ours and the reference, mean over seeds of each seed's "
        "mean per 10,000 frames (the batches' means of the episodes ending in them).",
        ["task", "algorithm", "run", *(f"to {b // 1000}k" for b in bins)],
        training,
    )


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


def report(args) -> str:
    study = load_study(args.config)
    out = args.figures
    # an empty report would overwrite the committed tables and figures with n/a
    if not any(
        group(study, args.results, t.label, a) for t in tasks(study) for a in study.algorithms
    ):
        raise SystemExit(
            f"{study.name}: no finished cell under --results {args.results}; nothing to "
            f"report, and nothing in {out} was changed"
        )
    out.mkdir(parents=True, exist_ok=True)
    at = report_frames(study)
    # the published reference is at 100k frames: beside a shorter study it would mislead
    with_ref = study.frames >= 100_000
    # one evaluation is 10 episodes of one policy snapshot; the evaluations of the last
    # quarter of the budget, averaged per seed, say more about where a run has got to
    tail_from = study.frames * 3 // 4
    until = study.frames  # cells read from a longer study count up to this budget only
    lines = [
        f"Evaluation return ({study.name}): mean ± 95 % t-interval half-width over the seeds "
        "that finished; the last-quarter column first averages each seed's evaluations after "
        f"{tail_from:,} frames; falling rate pooled over seeds at the last evaluation, "
        "with its 95 % Wilson interval.",
        "",
        "| task | algorithm | seeds | "
        + " | ".join(f"return at {f:,}" for f in at)
        + f" | mean return after {tail_from:,} | falling rate |"
        + (" reference at 100k (tianshou, gym v3; not ours) |" if with_ref else ""),
        "| --- " * (5 + len(at) + with_ref) + "|",
    ]
    cost, versus, value_rows, versus_more, diagnostics = [], [], [], [], []
    robust, finals = [], {}  # the bootstrap tables; (when, task, algorithm) -> per-seed
    # (task, algorithm) -> metric -> per-seed values at each of ``at``
    measured: dict[tuple[str, str], dict[str, list]] = {}
    for entry in tasks(study):
        task = entry.label
        curves, diag, falling, q_bias = {}, {}, {}, {}
        for algorithm in study.algorithms:
            runs = group(study, args.results, task, algorithm)
            # a task read from another study's cells cost that study, not this one
            minutes = [] if entry.cells_from else [m / 60 for m in map(train_seconds, runs) if m]
            if minutes:
                cost.append(
                    f"| {task} | {algorithm} | {len(minutes)} | {min(minutes):.0f} | "
                    f"{max(minutes):.0f} | {sum(minutes) / 60:.1f} |"
                )
            ref = REFERENCE.get(entry.env.split("-")[0], {}).get(algorithm, "")
            ref = ref if entry.reference else ""
            ref = (f" {ref.split(' / ')[0]} |" if ref else "  |") if with_ref else ""
            m = measured[task, algorithm] = {
                k: [at_frame(runs, f"eval/{k}", f) for f in at]
                for k in ("return", "falling_rate", "q_bias", "q_rmse", "q_corr")
            }
            if not runs:
                lines.append(f"| {task} | {algorithm} | 0 |" + " n/a |" * (len(at) + 2) + ref)
                continue
            steps, values = series(runs, "eval/return", until)
            if missing := [f for f in at if f not in steps]:
                raise ValueError(
                    f"{study.name}: the {task} {algorithm} cells have no evaluation at "
                    f"{missing} frames (they evaluated at {steps[:3].tolist()}, ...); set "
                    "report_at in the study file to frames they evaluated at"
                )
            last = tail_means(runs, "eval/return", tail_from, until)
            fall_steps, falls = series(runs, "eval/falling_rate", until)
            falling[algorithm] = (fall_steps, falls.mean(0), falls.min(0), falls.max(0))
            episodes = [eval_episodes(r) for r in runs]
            fell = round(float(falls[:, -1] @ np.array(episodes)))
            lo, hi = wilson_interval(fell, sum(episodes))
            lines.append(
                f"| {task} | {algorithm} | {len(runs)} | "
                + " | ".join(cells_of([*m["return"], last]))
                + f" | {fell / sum(episodes):.2f} [{lo:.2f}, {hi:.2f}] |{ref}"
            )
            label = f"{algorithm} ({seeds(len(runs))})"
            curves[label] = (steps, values.mean(0), values.min(0), values.max(0))
            if m["q_bias"][-1] is not None:
                value_rows.append(
                    f"| {task} | {algorithm} | {len(runs)} | "
                    + " | ".join(cells_of(m["q_bias"] + m["q_rmse"]) + cells_of(m["q_corr"], 2))
                    + " |"
                )
                s, v = series(runs, "eval/q_bias", until)
                q_bias[label] = (s, v.mean(0), v.min(0), v.max(0))
            if algorithm == "rave":
                diag = {k: series(runs, f"train/{k}", until) for k in RAVE_DIAGNOSTICS}
            weights = [
                tail_means(runs, f"train/horizon_weight_h{h}", tail_from, until) for h in range(4)
            ]
            if weights[0] is not None:
                alpha = tail_means(runs, "train/rave_alpha", tail_from, until)
                v0, v3 = (
                    tail_means(runs, f"train/candidate_variance_h{h}", tail_from, until)
                    for h in (0, 3)
                )
                error = tail_means(runs, "train/wm_transition_mse", tail_from, until)
                ratio = None if v0 is None or v3 is None else v3 / v0
                diagnostics.append(
                    f"| {task} | {algorithm} | {len(runs)} | "
                    + " | ".join(cells_of([*weights, alpha], 2) + cells_of([ratio], 1))
                    + " | "
                    + " | ".join(cells_of([error], 3))
                    + " |"
                )
        for f, when in ((at[-1], f"at {at[-1]:,}"), (None, f"after {tail_from:,}")):
            for algorithm in study.algorithms:
                runs = group(study, args.results, task, algorithm)
                scores = (
                    measured[task, algorithm]["return"][-1]
                    if f is not None
                    else tail_means(runs, "eval/return", tail_from, until)
                    if runs
                    else None
                )
                if scores is not None:
                    robust.append(
                        f"| {task} | {when} | {algorithm} | {len(scores)} | "
                        + " | ".join(fmt_bootstrap(stratified_interval([scores], stat))
                                     for stat in (mean, iqm))
                        + " |"
                    )  # fmt: skip
                    finals[when, task, algorithm] = scores
        rave = measured[task, "rave"] if "rave" in study.algorithms else None
        for other in (a for a in study.algorithms if rave is not None and a != "rave"):
            theirs = measured[task, other]
            row = differences(rave["return"], theirs["return"])
            if row is not None:
                versus.append(f"| {task} | rave - {other} | " + " | ".join(row) + " |")
            falls_row = differences(rave["falling_rate"], theirs["falling_rate"], 2)
            bias_row = differences(rave["q_bias"], theirs["q_bias"])
            if falls_row is not None and bias_row is not None:
                versus_more.append(
                    f"| {task} | rave - {other} | " + " | ".join(falls_row + bias_row) + " |"
                )
        study_figures(
            out / f"{study.name}_{task}", f"{task}, {study.name}", curves, diag, falling, q_bias
        )

    def by_frame(*names: str) -> list[str]:
        return [f"{k} at {f:,}" for k in names for f in at]

    lines += section(
        f"RAVE's mean minus each other algorithm's, with {WELCH}.",
        ["task", "difference", *(f"at {f:,}" for f in at)],
        versus,
    )
    lines += calibration(study, args.results, out)
    lines += section(
        "Mean and interquartile mean (IQM) of the evaluation return over seeds, with 95 % "
        f"percentile intervals from {BOOTSTRAP}; per task, at the budget and over the "
        f"last quarter (each seed's evaluations after {tail_from:,} frames averaged first).",
        ["task", "when", "algorithm", "seeds", "mean [95 % CI]", "IQM [95 % CI]"],
        robust,
    )
    improves = []
    for when in dict.fromkeys(w for w, _, _ in finals) if "rave" in study.algorithms else []:
        for other in (a for a in study.algorithms if a != "rave"):
            per_task = {
                t.label: (finals[when, t.label, "rave"], finals[when, t.label, other])
                for t in tasks(study)
                if (when, t.label, "rave") in finals and (when, t.label, other) in finals
            }
            chosen = [(label, [pair]) for label, pair in per_task.items()]
            if len(per_task) > 1:
                chosen.append(("all tasks", list(per_task.values())))
            for label, pairs in chosen:
                xs, ys = zip(*pairs, strict=True)
                improves.append(
                    f"| {label} | {when} | rave > {other} | "
                    + fmt_bootstrap(improvement_interval(list(xs), list(ys)), 2)
                    + " |"
                )
    lines += section(
        "The probability that a RAVE run's evaluation return beats another algorithm's "
        "(ties count half; over all tasks: the mean over tasks), with a 95 % percentile "
        f"interval from {BOOTSTRAP}; 0.5 is no difference.",
        ["task", "when", "comparison", "P(rave > other) [95 % CI]"],
        improves,
    )
    lines += section(
        "Value error: the critics' estimate of Q(s_t, pi(s_t)) minus the discounted "
        "Monte-Carlo return of the evaluation episodes (`eval/q_bias`; which states count, "
        "and how each algorithm's critics are read, is in recipes/README.md), its root mean "
        "square and the correlation of the two; mean ± 95 % t-interval over seeds.",
        ["task", "algorithm", "seeds", *by_frame("q_bias", "q_rmse", "q_corr")],
        value_rows,
    )
    lines += section(
        f"RAVE minus each other algorithm: falling rate and value bias, with {WELCH}.",
        ["task", "difference", *by_frame("falling rate", "q_bias")],
        versus_more,
    )
    rows = {}
    for a, b in study.get("contrasts", []):
        for algorithm in study.algorithms:
            for k, d in (("return", 0), ("falling_rate", 2), ("q_bias", 0)):
                cells = differences(measured[b, algorithm][k], measured[a, algorithm][k], d)
                rows.setdefault((a, b, algorithm), []).extend(cells or ["n/a"] * len(at))
    lines += section(
        f"The change from one task to its pair, per algorithm: the second's mean minus the "
        f"first's, with {WELCH}.",
        ["from", "to", "algorithm", *by_frame("return", "falling rate", "q_bias")],
        [f"| {a} | {b} | {alg} | " + " | ".join(c) + " |" for (a, b, alg), c in rows.items()],
    )
    lines += section(
        f"The value-expansion targets after {tail_from:,} frames (each seed's mean over its "
        "updates there, then mean ± 95 % t-interval over seeds): the normalised weight w_H of "
        "each horizon H, alpha (eq. 12), the horizon-3 candidates' variance over the "
        "horizon-0 ones', and the world model's transition MSE (normalised units).",
        ["task", "algorithm", "seeds", "w_0", "w_1", "w_2", "w_3", "alpha", "V_3 / V_0",
         "model MSE"],
        diagnostics,
    )  # fmt: skip
    lines += section(
        "What the finished cells cost: their own collection, update and evaluation time "
        "(`time/*_s`, summed), in minutes per cell, and hours in all.",
        ["task", "algorithm", "cells", "min", "max", "hours"],
        cost,
    )
    text = "\n".join(lines)
    (out / f"{study.name}.md").write_text(text + "\n")
    print(text)
    return text
