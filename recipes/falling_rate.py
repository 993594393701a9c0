"""Falling rate: the fraction of episodes that end by termination (the agent fell) before
the time limit, with a binomial confidence interval; the paper's figure 5.

python recipes/falling_rate.py rave='outputs/compare/Hopper-v5/rave/seed*' \
    steve='outputs/compare/Hopper-v5/steve/seed*' ddpg='outputs/compare/Hopper-v5/ddpg/seed*' \
    --episodes 50 --out falling_rate.png

Each positional argument is ``LABEL=PATTERN``; the run directories matching the glob are
the seeds of one algorithm. Two results:

- **final**: the latest checkpoint of every run plays ``--episodes`` deterministic
  episodes; falls are pooled over a group's seeds (``k`` of ``n``) and reported as
  ``k / n`` with a 95 % Wilson score interval (``--episodes 0`` skips this);
- **over training**: the falling rates every run logged at its periodic evaluations
  (``eval/falling_rate``, over ``eval.episodes`` episodes each) pooled over seeds at each
  step, drawn with the same interval as a band.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import tqdm
from plot_curves import band_plot
from q_vs_return import load_run

from torchrl_rave.recipe.checkpoint import saved_config
from torchrl_rave.recipe.evaluate import evaluate
from torchrl_rave.recipe.runs import parse_groups, read_scalar
from torchrl_rave.recipe.stats import wilson_interval
from torchrl_rave.recipe.trust import add_trust_flag


def final_falls(
    run_dir: Path, episodes: int, seed: int, label: str = "", trust: bool = False
) -> int:
    """Falls in ``episodes`` deterministic episodes of the run's latest checkpoint, one
    episode at a time (the same episodes as one ``evaluate`` call) behind a progress bar."""
    _, env, actor, _ = load_run(run_dir, trust)
    env.set_seed(seed)
    falls = 0
    with tqdm.tqdm(range(episodes), desc=f"{label} {run_dir.name}".strip(), unit="ep") as bar:
        for _ in bar:
            falls += round(evaluate(env, actor, 1)["eval/falling_rate"])
            bar.set_postfix(fell=falls)
    return falls


def logged_falls(
    run_dirs: list[Path], eval_episodes: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps every run logged, and the falls and episodes pooled over runs at each."""
    data = []
    for run in run_dirs:
        steps, rates = read_scalar(run, "eval/falling_rate")
        n = eval_episodes if eval_episodes else int(saved_config(run).eval.episodes)
        data.append((steps, np.rint(rates * n).astype(int), n))
    common = sorted(set.intersection(*(set(s.tolist()) for s, _, _ in data)))
    falls = sum(k[np.searchsorted(s, common)] for s, k, _ in data)
    episodes = sum(n for _, _, n in data)
    return np.array(common), np.asarray(falls), np.full(len(common), episodes)


def plot(over_training: dict, out: Path, title: str | None) -> None:
    series = {}
    for label, (steps, falls, episodes) in over_training.items():
        bounds = [wilson_interval(int(k), int(n)) for k, n in zip(falls, episodes, strict=True)]
        low, high = [b[0] for b in bounds], [b[1] for b in bounds]
        series[label] = (steps, falls / episodes, low, high)
    band_plot(
        series,
        out,
        xlabel="environment steps",
        ylabel="falling rate (episodes that terminate)",
        title=title or "Falling rate over training (band: 95% Wilson interval)",
        ylim=(-0.02, 1.02),
        marker="o",
    )


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(
        description="Falling rate per algorithm with a 95%% Wilson interval, and over training."
    )
    parser.add_argument("groups", nargs="+", help="LABEL=PATTERN (a glob of run directories)")
    parser.add_argument(
        "--episodes",
        type=int,
        default=50,
        help="evaluation episodes per run from its latest checkpoint (0: logged rates only)",
    )
    parser.add_argument("--seed", type=int, default=2024, help="evaluation env seed")
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        help="episodes behind each logged rate, >= 1 (default: the run's eval.episodes)",
    )
    parser.add_argument("--out", type=Path, default=Path("falling_rate.png"))
    parser.add_argument("--title", default=None)
    add_trust_flag(parser)
    args = parser.parse_args(argv)
    if args.episodes < 0:
        parser.error("--episodes must be >= 0")
    if args.eval_episodes is not None and args.eval_episodes < 1:
        parser.error("--eval-episodes must be >= 1 (leave it out to read each run's eval.episodes)")
    try:
        groups = parse_groups(args.groups)
    except (ValueError, FileNotFoundError) as e:
        parser.error(str(e))

    lines = []
    if args.episodes:
        lines += [
            "| run | seeds | falls / episodes | falling rate | 95% interval |",
            "| --- | --- | --- | --- | --- |",
        ]
        for label, runs in groups.items():
            torch.manual_seed(args.seed)
            k = sum(final_falls(run, args.episodes, args.seed, label, args.trust) for run in runs)
            n = args.episodes * len(runs)
            lo, hi = wilson_interval(k, n)
            lines.append(
                f"| {label} | {len(runs)} | {k} / {n} | {k / n:.3f} | [{lo:.3f}, {hi:.3f}] |"
            )
    over_training = {
        label: logged_falls(runs, args.eval_episodes) for label, runs in groups.items()
    }
    plot(over_training, args.out, args.title)
    lines.append("")
    lines.append("last logged evaluation (pooled over seeds):")
    for label, (steps, falls, episodes) in over_training.items():
        lo, hi = wilson_interval(int(falls[-1]), int(episodes[-1]))
        lines.append(
            f"  {label}: step {steps[-1]}, {falls[-1]} / {episodes[-1]} fell "
            f"({falls[-1] / episodes[-1]:.3f}, 95% [{lo:.3f}, {hi:.3f}])"
        )
    text = "\n".join(lines).strip("\n")
    print(text)
    print(f"figure: {args.out}")
    return text


if __name__ == "__main__":
    main()
