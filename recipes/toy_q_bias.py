"""The paper's toy study (section 4): how far do DDPG, MVE, STEVE and RAVE put Q(s_0, a)
from the truth, in a deterministic (k = 0) and a stochastic (k = 1) 1-D environment?

python recipes/toy_q_bias.py                  # 4 methods x 2 noise levels x 4 seeds
python recipes/toy_q_bias.py quick=true       # one short run per method and k (CI)

Every run is an ordinary ``rave_mujoco.py`` training on ``RAVEToy-v0`` (overrides in
``toy.yaml``), launched by the grid launcher of ``torchrl_rave.recipe.runs``; after each
collector batch it logs ``q/plus`` and ``q/minus`` (``logger.q_points``): ``Q-hat(s_0, +1)``
and ``Q-hat(s_0, -1)``, the mean over the learner's critics in reward units. The study writes ``toy_q_bias.png``
(curves, seed spread, exact ground truth) and ``toy_q_bias.md`` (final estimates, truth,
bias) into its output directory.
"""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from torchrl_rave.envs import ground_truth_q
from torchrl_rave.recipe.runs import Cell, GridStopped, launch_grid, read_scalar

RECIPE = Path(__file__).resolve().parent / "rave_mujoco.py"
ACTIONS = {"plus": 1.0, "minus": -1.0}
# logger.q_points: Q-hat at s_0 = 0 for both actions, logged after every batch
Q_POINTS = "logger.q_points={plus:[[0.0],[1.0]],minus:[[0.0],[-1.0]]}"


def read_curve(run_dir: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    return read_scalar(run_dir, f"q/{name}")


def summarise(out: Path, cfg: DictConfig, frames: int, seeds: list[int]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = {k: ground_truth_q(0.0, 1.0, k=k) for k in cfg.noise}
    fig, axes = plt.subplots(
        len(ACTIONS), len(cfg.noise), figsize=(5 * len(cfg.noise), 7), squeeze=False
    )
    lines = [
        f"Final Q-hat(s_0, a) after {frames:,} environment steps, mean ± std over "
        f"{len(seeds)} seed(s); truth = exact optimal Q (same for a = +1 and -1 by symmetry).",
        "",
        "| k | method | Q-hat(s_0, +1) | Q-hat(s_0, -1) | truth | bias (mean of both) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for col, k in enumerate(cfg.noise):
        q_true, err = truth[k]
        for method in cfg.methods:
            finals = {}
            for row, name in enumerate(ACTIONS):
                curves = [read_curve(out / f"k{k:g}" / method / f"seed{s}", name) for s in seeds]
                steps = curves[0][0]
                values = np.stack([c[1] for c in curves])
                ax = axes[row, col]
                mean, std = values.mean(0), values.std(0)
                (line,) = ax.plot(steps, mean, label=method)
                ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
                finals[name] = values[:, -1]
            both = (finals["plus"] + finals["minus"]) / 2
            lines.append(
                f"| {k:g} | {method} | {finals['plus'].mean():.1f} ± {finals['plus'].std():.1f} "
                f"| {finals['minus'].mean():.1f} ± {finals['minus'].std():.1f} "
                f"| {q_true:.1f} | {both.mean() - q_true:+.1f} |"
            )
        for row, a in enumerate(ACTIONS.values()):
            ax = axes[row, col]
            ax.axhline(q_true, color="black", linestyle="--", label="ground truth")
            ax.set_title(f"Q-hat(s_0, a = {a:+g}), k = {k:g}")
            ax.set_xlabel("environment steps")
            ax.set_ylim(q_true - 150, q_true + 150)
            ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "toy_q_bias.png", dpi=120)
    table = "\n".join(lines)
    (out / "toy_q_bias.md").write_text(table + "\n")
    return table


@hydra.main(config_path=".", config_name="toy", version_base="1.3")
def main(cfg: DictConfig) -> str:
    unknown = sorted(set(cfg.methods) - {"ddpg", "mve", "steve", "rave", "rave_constant"})
    if unknown:
        raise ValueError(
            f"methods: unknown {unknown}; choose from ddpg, mve, steve, rave, rave_constant"
        )
    frames, seeds = (600, list(cfg.seeds)[:1]) if cfg.quick else (cfg.frames, list(cfg.seeds))
    out = Path(cfg.out or HydraConfig.get().runtime.output_dir)
    cells = [
        Cell(
            out / f"k{k:g}" / method / f"seed{seed}",
            frames,
            (
                *cfg.train,
                Q_POINTS,
                f"env.kwargs={{k:{k}}}",
                f"algorithm={method}",
                f"env.seed={seed}",
                f"eval.interval={frames}",
                f"checkpoint.interval={frames}",
            ),
        )
        for k in cfg.noise
        for method in cfg.methods
        for seed in seeds
    ]
    print(f"{len(cells)} runs of {frames} frames, {cfg.jobs} at a time, into {out}")
    try:
        codes = launch_grid(RECIPE, cells, cfg.jobs)
    except GridStopped as stop:
        raise SystemExit(str(stop)) from None
    failed = [c.run_dir for c, code in codes.items() if code != 0]
    if failed:
        raise SystemExit(f"{len(failed)} run(s) failed; see {failed[0] / 'stdout.log'}")
    table = summarise(out, cfg, frames, seeds)
    print(table)
    print(f"figure: {out / 'toy_q_bias.png'}")
    return table


if __name__ == "__main__":
    main()
