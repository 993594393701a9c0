"""``study.py report``: a study's tables and figures, rebuilt from ``results/`` alone.

Per task and algorithm, over the seeds that finished: the evaluation return at half and
all of the budget and over the last quarter, the falling rate, RAVE's mean minus each
other algorithm's; where the cells logged it, the critics' value error (``eval/q_bias``,
``eval/q_rmse``, ``eval/q_corr``); the diagnostics of the value-expansion targets; the
change between the tasks a study pairs in ``contrasts``; what the cells cost; and per task
the curves of return, falling rate, value bias and RAVE's diagnostics.
"""

from __future__ import annotations

import numpy as np
from compare import REFERENCE
from plot_curves import seeds, study_figures
from study_calibration import calibration
from study_tables import (
    BOOTSTRAP,
    RAVE_DIAGNOSTICS,
    WELCH,
    at_frame,
    cells_of,
    differences,
    eval_episodes,
    fmt_bootstrap,
    group,
    section,
    series,
    tail_means,
)

from torchrl_rave.recipe.runs import train_seconds
from torchrl_rave.recipe.stats import (
    improvement_interval,
    iqm,
    mean,
    stratified_interval,
    wilson_interval,
)
from torchrl_rave.recipe.studies import cells_elsewhere, load_study, report_frames, tasks


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
    # the algorithm the others are measured against: RAVE on its paper's base, else on SAC's
    subject = next((a for a in ("rave", "rave_sac") if a in study.algorithms), None)
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
            # cells read from another study cost that study, not this one
            elsewhere = cells_elsewhere(study, task, algorithm)
            minutes = [] if elsewhere else [m / 60 for m in map(train_seconds, runs) if m]
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
            if algorithm == subject:
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
        rave = measured[task, subject] if subject else None
        for other in (a for a in study.algorithms if rave is not None and a != subject):
            theirs = measured[task, other]
            row = differences(rave["return"], theirs["return"])
            if row is not None:
                versus.append(f"| {task} | {subject} - {other} | " + " | ".join(row) + " |")
            falls_row = differences(rave["falling_rate"], theirs["falling_rate"], 2)
            bias_row = differences(rave["q_bias"], theirs["q_bias"])
            if falls_row is not None and bias_row is not None:
                versus_more.append(
                    f"| {task} | {subject} - {other} | " + " | ".join(falls_row + bias_row) + " |"
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
    for when in dict.fromkeys(w for w, _, _ in finals) if subject else []:
        for other in (a for a in study.algorithms if a != subject):
            per_task = {
                t.label: (finals[when, t.label, subject], finals[when, t.label, other])
                for t in tasks(study)
                if (when, t.label, subject) in finals and (when, t.label, other) in finals
            }
            chosen = [(label, [pair]) for label, pair in per_task.items()]
            if len(per_task) > 1:
                chosen.append(("all tasks", list(per_task.values())))
            for label, pairs in chosen:
                xs, ys = zip(*pairs, strict=True)
                improves.append(
                    f"| {label} | {when} | {subject} > {other} | "
                    + fmt_bootstrap(improvement_interval(list(xs), list(ys)), 2)
                    + " |"
                )
    lines += section(
        "The probability that a RAVE run's evaluation return beats another algorithm's "
        "(ties count half; over all tasks: the mean over tasks), with a 95 % percentile "
        f"interval from {BOOTSTRAP}; 0.5 is no difference.",
        ["task", "when", "comparison", f"P({subject or 'rave'} > other) [95 % CI]"],
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
        "(`time/*_s`, summed), in minutes per cell, and hours in all. These are wall-clock "
        "times: they include any time a run was paused or shared its core with another.",
        ["task", "algorithm", "cells", "min", "max", "hours"],
        cost,
    )
    text = "\n".join(lines)
    (out / f"{study.name}.md").write_text(text + "\n")
    print(text)
    return text
