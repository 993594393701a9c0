"""The paper's toy study (section 4): how far do DDPG, MVE, STEVE and RAVE put Q(s_0, a)
from the truth, in a deterministic (k = 0) and a stochastic (k = 1) 1-D environment?

python recipes/toy_q_bias.py                  # 4 methods x 2 noise levels x 4 seeds
python recipes/toy_q_bias.py quick=true       # one short run per method and k (CI)

Every run is an ordinary ``rave_mujoco.py`` training on ``RAVEToy-v0`` (overrides in
``toy.yaml``); after each collector batch it records ``Q-hat(s_0, +1)`` and
``Q-hat(s_0, -1)``, the mean over the learner's critics. The study writes ``toy_q_bias.png``
(curves, seed spread, exact ground truth) and ``toy_q_bias.md`` (final estimates, truth,
bias) into its output directory.
"""

from __future__ import annotations

import csv
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from tensordict import TensorDict

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from torchrl_rave.envs import ground_truth_q  # noqa: E402

ACTIONS = {"plus": 1.0, "minus": -1.0}


class QProbe:
    """Returns ``toy/q_plus`` and ``toy/q_minus``: the critics' mean Q at ``s_0 = 0``, in
    environment reward units (the learner's scaled values divided by ``reward_scale``)."""

    def __init__(self, reward_scale: float) -> None:
        self.reward_scale = reward_scale

    def __call__(self, frames: int, loss) -> dict[str, float]:
        from utils import critic_mean

        out = {}
        with torch.no_grad():
            for name, a in ACTIONS.items():
                td = TensorDict(
                    {"observation": torch.zeros(1, 1), "action": torch.full((1, 1), a)}, [1]
                )
                out[f"toy/q_{name}"] = critic_mean(loss, td).item() / self.reward_scale
        return out


def run_one(job: tuple[str, float, int, list[str], str]) -> str:
    """One training run (in a worker process): returns its directory."""
    torch.set_num_threads(1)
    method, k, seed, overrides, run_dir = job
    import rave_mujoco
    from hydra import initialize_config_dir

    with initialize_config_dir(
        config_dir=os.path.dirname(os.path.abspath(__file__)), version_base="1.3"
    ):
        cfg = compose("config", overrides=overrides)
    rave_mujoco.train(cfg, run_dir, probe=QProbe(cfg.env.reward_scale))
    return run_dir


def read_curve(run_dir: Path, method: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    with open(run_dir / method / "scalars" / "toy" / f"q_{name}.csv") as f:
        rows = np.array([[float(x) for x in row] for row in csv.reader(f)])
    return rows[:, 0], rows[:, 1]


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
                curves = [
                    read_curve(out / f"k{k:g}" / method / f"seed{s}", method, name) for s in seeds
                ]
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
    jobs = []
    for k in cfg.noise:
        for method in cfg.methods:
            for seed in seeds:
                run_dir = out / f"k{k:g}" / method / f"seed{seed}"
                overrides = [
                    *cfg.train,
                    f"env.kwargs={{k:{k}}}",
                    f"algorithm={method}",
                    f"env.seed={seed}",
                    f"collector.total_frames={frames}",
                    f"eval.interval={frames}",
                    f"checkpoint.interval={frames}",
                ]
                jobs.append((method, k, seed, overrides, str(run_dir)))
    print(f"{len(jobs)} runs of {frames} frames, {cfg.jobs} at a time, into {out}")
    with ProcessPoolExecutor(cfg.jobs, mp_context=get_context("spawn")) as pool:
        for done in pool.map(run_one, jobs):
            print("done:", done)
    table = summarise(out, cfg, frames, seeds)
    print(table)
    print(f"figure: {out / 'toy_q_bias.png'}")
    return table


if __name__ == "__main__":
    main()
