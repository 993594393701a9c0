"""Learning curves (mean and spread over seeds) for groups of recipe runs, and a table.

python recipes/plot_curves.py \
    rave='outputs/compare/Hopper-v5/rave/seed*' steve='outputs/compare/Hopper-v5/steve/seed*' \
    --metric eval/return --at 10000 30000 --out hopper.png

Each positional argument is ``LABEL=PATTERN``: the run directories matching the glob
``PATTERN`` (quote it) are the seeds of one curve. A run directory is what
``rave_mujoco.py`` writes (``<run>/<exp_name>/scalars/<metric>.csv``). Curves are drawn on
the steps every seed of a group has logged; the shaded band is ± one standard deviation
over seeds. The table gives, at each ``--at`` frame count, the mean ± std over seeds of the
last value logged at or before it; a group whose seeds have not all logged a step at or
beyond that frame count (a run stopped early, a shorter budget) reads ``n/a`` there, with
the step its curve ends at. ``--max-frames`` cuts every curve at that frame count, to
put longer runs beside shorter ones at the shorter budget.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from torchrl_rave.recipe.runs import curves, parse_groups


def value_at(steps: np.ndarray, values: np.ndarray, frame: int) -> np.ndarray:
    """Per seed: the last value logged at or before ``frame`` (NaN if none)."""
    idx = np.searchsorted(steps, frame, side="right") - 1
    return values[:, idx] if idx >= 0 else np.full(values.shape[0], np.nan)


def cut(steps: np.ndarray, values: np.ndarray, max_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The steps at or below ``max_frames``, and the values there."""
    keep = steps <= max_frames
    if not keep.any():
        raise ValueError(f"--max-frames {max_frames}: no step is logged at or before it")
    return steps[keep], values[:, keep]


def table(data: dict, at: list[int], metric: str) -> str:
    head = "| run | seeds | " + " | ".join(f"{metric} at {f:,}" for f in at) + " |"
    lines = [head, "|" + " --- |" * (2 + len(at))]
    for label, (steps, values) in data.items():
        cells = []
        for frame in at:
            if frame > steps[-1]:  # not reached by every seed: no value to report there
                cells.append(f"n/a (ends at {int(steps[-1]):,})")
                continue
            v = value_at(steps, values, frame)
            cells.append("n/a" if np.isnan(v).any() else f"{v.mean():.1f} ± {v.std():.1f}")
        lines.append(f"| {label} | {values.shape[0]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def seeds(n: int) -> str:
    """A curve's legend note: '1 seed', '3 seeds'."""
    return f"{n} seed" + ("s" if n != 1 else "")


def band_plot(
    series: dict[str, tuple],
    out: Path,
    *,
    xlabel: str,
    ylabel: str,
    title: str | None = None,
    ylim: tuple[float, float] | None = None,
    marker: str | None = None,
) -> None:
    """One line with a shaded band per label: ``series[label] = (x, centre, low, high)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, (x, centre, low, high) in series.items():
        (line,) = ax.plot(x, centre, label=label, marker=marker, markersize=3)
        ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if ylim is not None:
        ax.set_ylim(*ylim)
    if title:
        ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def study_figures(
    prefix: Path, title: str, curves: dict, diag: dict, falling: dict, q_bias: dict | None = None
) -> None:
    """One study task's figures, each series ``(x, centre, low, high)`` over seeds:
    ``<prefix>_return.png`` from ``curves``, ``_rave_diagnostics.png`` and
    ``_rave_model_error.png`` from ``diag`` (metric -> (steps, per-seed values)),
    ``_falling_rate.png`` from ``falling`` and ``_q_bias.png`` from ``q_bias``; an empty
    dict draws nothing."""
    band = "(mean, band: min-max over seeds)"
    figures = []  # (series, file suffix, y label, title, y limits)
    if curves:
        figures.append((curves, "return", f"eval/return {band}", title, None))
    if diag:
        bands = {m: (s, v.mean(0), v.min(0), v.max(0)) for m, (s, v) in diag.items()}
        error = {"world-model transition MSE (normalised)": bands.pop("wm_transition_mse")}
        task = title.split(",")[0]
        figures.append((bands, "rave_diagnostics", f"alpha, horizon weights {band}",
                        f"RAVE diagnostics on {task}", None))  # fmt: skip
        figures.append((error, "rave_model_error", "mean over seeds, band: min-max",
                        f"RAVE's model error on {task}", None))  # fmt: skip
    if falling:
        figures.append((falling, "falling_rate", f"eval/falling_rate {band}",
                        f"{title}: share of evaluation episodes that fell", (-0.05, 1.05)))  # fmt: skip
    if q_bias:
        figures.append((q_bias, "q_bias", f"eval/q_bias, Q - MC {band}",
                        f"{title}: the critics' value bias", None))  # fmt: skip
    for series, suffix, ylabel, name, ylim in figures:
        path = prefix.with_name(f"{prefix.name}_{suffix}.png")
        band_plot(series, path, xlabel="environment frames", ylabel=ylabel, title=name, ylim=ylim)


def plot(data: dict, metric: str, out: Path, title: str | None = None) -> None:
    """Mean over seeds with a ± one-std band."""
    series = {}
    for label, (steps, values) in data.items():
        mean, std = values.mean(0), values.std(0)
        series[f"{label} ({seeds(values.shape[0])})"] = (steps, mean, mean - std, mean + std)
    band_plot(series, out, xlabel="environment frames", ylabel=metric, title=title)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(
        description="Learning curves and a table for groups of rave_mujoco.py runs.",
        epilog="Example: plot_curves.py rave='runs/rave/seed*' ddpg='runs/ddpg/seed*' --at 30000",
    )
    parser.add_argument("groups", nargs="+", help="LABEL=PATTERN (a quoted glob of run dirs)")
    parser.add_argument(
        "--metric", default="eval/return", help="logged metric (default eval/return)"
    )
    parser.add_argument("--at", nargs="*", type=int, default=[], help="frame counts for the table")
    parser.add_argument("--out", type=Path, default=Path("curves.png"), help="PNG to write")
    parser.add_argument("--title", default=None)
    parser.add_argument("--max-frames", type=int, default=None, help="cut the curves here")
    args = parser.parse_args(argv)
    data = curves(parse_groups(args.groups), args.metric)
    if args.max_frames is not None:
        data = {
            label: cut(steps, values, args.max_frames) for label, (steps, values) in data.items()
        }
    at = args.at or [max(int(s[-1]) for s, _ in data.values())]
    plot(data, args.metric, args.out, args.title)
    text = table(data, at, args.metric)
    print(text)
    print(f"figure: {args.out}")
    return text


if __name__ == "__main__":
    main()
