"""The calibration section of a study report: the study's learners beside a reference
implementation run on this machine and beside the published returns."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plot_curves import band_plot, seeds
from study_tables import at_frame, group, read_metric, section, series

from torchrl_rave.recipe.studies import tasks

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
            cells = ["n/a" if v is None or not len(v) else f"{v[0]:.0f} (1)" if len(v) == 1
                     else f"{v.mean():.0f} ± {v.std(ddof=1):.0f} ({len(v)})" for v in ends]  # fmt: skip
            pub = f"{published[0]} ± {published[1]}" if published else "n/a"
            verdict = "n/a"
            if algorithm in CALIBRATED and published and ends[0] is not None:
                bar = published[0] - published[1]
                checks = [f"{'meets' if ends[0].mean() >= bar else 'misses'} the bar {bar}"]
                if ends[1] is not None and len(ends[1]) > 1:
                    floor = ends[1].mean() - ends[1].std(ddof=1)
                    checks.append(f"{'within' if ends[0].mean() >= floor else 'below'} the "
                                  f"reference's spread (>= {floor:.0f})")  # fmt: skip
                else:  # half the bar: no verdict until the reference has a spread
                    done = 0 if ends[1] is None else len(ends[1])
                    checks.append("reference not run yet" if not done else
                                  "reference: 1 seed so far, no spread yet")  # fmt: skip
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
