"""Predicted Q versus the Monte-Carlo return that followed (the paper's figure 4).

python recipes/q_vs_return.py rave=outputs/compare/Hopper-v5/rave/seed0 \
    steve=outputs/compare/Hopper-v5/steve/seed0 ddpg=outputs/compare/Hopper-v5/ddpg/seed0 \
    --episodes 10 --out q_vs_return.png

Each ``LABEL=RUN_DIR`` names a ``rave_mujoco.py`` run; its latest checkpoint is loaded
(config, policy, critics). The deterministic policy plays ``--episodes`` episodes; at each
visited ``(s_t, a_t)`` the script records the critic's ``Q(s_t, a_t)`` (the mean over an
ensemble's critics, in environment reward units) and the discounted return that actually
followed, ``sum_{t' >= t} gamma^(t' - t) r_t'``. Episodes cut by the time limit have no
return beyond the cut, so their last ``--drop-tail`` states are left out. It prints bias
(mean of predicted - true), RMSE and correlation per run, and draws 1- and 2-sigma
confidence ellipses of (true, predicted), both axes normalised by the pooled mean and std of
the true returns, with the identity line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from torchrl_rave.recipe.agent import critic_mean, load_agent, make_env
from torchrl_rave.recipe.evaluate import discounted_returns, value_error
from torchrl_rave.recipe.trust import add_trust_flag


def load_run(run_dir: Path, trust: bool = False):
    """A run's config, an env for its task, its deterministic policy and its loss (critics),
    from its latest checkpoint (``trust`` as for ``load_agent``)."""
    cfg, agent = load_agent(run_dir, trust=trust)
    return cfg, make_env(cfg, torch.device("cpu")), agent.actor, agent.loss


@torch.no_grad()
def collect(
    run_dir: Path, episodes: int, drop_tail: int, seed: int, trust: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(true discounted returns, predicted Q) at the kept states of ``episodes`` episodes."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    cfg, env, actor, loss = load_run(run_dir, trust)
    env.set_seed(seed)
    true, pred = [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            rollout = env.rollout(1_000_000, actor, break_when_any_done=True)
            # the env's rewards are scaled for learning, like the critic: both in env units
            rewards = rollout["next", "reward"].squeeze(-1).double().numpy() / cfg.env.reward_scale
            g = discounted_returns(rewards, cfg.optim.gamma)
            q = critic_mean(loss, rollout).double().numpy() / cfg.env.reward_scale
            keep = len(g)
            if not rollout["next", "terminated"][-1].item():
                keep = max(0, keep - drop_tail)
            true.append(g[:keep])
            pred.append(q[:keep])
    return np.concatenate(true), np.concatenate(pred)


def statistics(true: np.ndarray, pred: np.ndarray) -> dict[str, float]:
    s = value_error(pred, true)
    return {
        "states": int(s["eval/q_states"]),
        "bias": s["eval/q_bias"],
        "rmse": s["eval/q_rmse"],
        "correlation": s["eval/q_corr"],
    }


def ellipse(x: np.ndarray, y: np.ndarray, n_sigma: float, points: int = 100) -> np.ndarray:
    """Boundary ``[points, 2]`` of the ``n_sigma`` covariance ellipse of the points (x, y)."""
    mean = np.array([x.mean(), y.mean()])
    cov = np.cov(np.stack([x, y]), bias=True)
    eigval, eigvec = np.linalg.eigh(cov)
    radii = n_sigma * np.sqrt(np.clip(eigval, 0.0, None))
    angle = np.linspace(0, 2 * np.pi, points)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return mean + (circle * radii) @ eigvec.T


def plot(results: dict[str, tuple[np.ndarray, np.ndarray]], out: Path, title: str | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pooled = np.concatenate([t for t, _ in results.values()])
    mu, sd = pooled.mean(), pooled.std() or 1.0
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    lo, hi = np.inf, -np.inf
    for label, (true, pred) in results.items():
        x, y = (true - mu) / sd, (pred - mu) / sd
        color = None
        for n_sigma, style in ((1, "-"), (2, "--")):
            e = ellipse(x, y, n_sigma)
            (line,) = ax.plot(
                e[:, 0], e[:, 1], style, color=color, label=label if n_sigma == 1 else None
            )
            color = line.get_color()
            lo, hi = min(lo, e.min()), max(hi, e.max())
        ax.scatter(x, y, s=2, alpha=0.15, color=color)
    ax.plot([lo, hi], [lo, hi], color="black", linewidth=1, label="predicted = true")
    ax.set_xlabel("discounted Monte-Carlo return (normalised)")
    ax.set_ylabel("predicted Q (normalised)")
    ax.set_title(title or "Q vs return: 1 sigma (solid), 2 sigma (dashed)")
    ax.legend()
    ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(
        description="Predicted Q vs Monte-Carlo return for trained runs (confidence ellipses)."
    )
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR of a rave_mujoco.py run")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument(
        "--drop-tail",
        type=int,
        default=300,
        help="states cut from the end of truncated episodes, >= 0",
    )
    parser.add_argument("--seed", type=int, default=12345, help="evaluation env seed")
    parser.add_argument("--out", type=Path, default=Path("q_vs_return.png"))
    parser.add_argument("--title", default=None)
    add_trust_flag(parser)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    if args.drop_tail < 0:
        parser.error("--drop-tail must be >= 0")
    results = {}
    for spec in args.runs:
        if "=" not in spec:
            parser.error(f"{spec!r}: expected LABEL=RUN_DIR")
        label, run = spec.split("=", 1)
        true, pred = collect(Path(run), args.episodes, args.drop_tail, args.seed, args.trust)
        if len(true) < 2:
            raise ValueError(f"{label}: fewer than 2 states left; lower --drop-tail")
        results[label] = (true, pred)
    lines = [
        "| run | states | bias (pred - true) | RMSE | correlation |",
        "| --- | --- | --- | --- | --- |",
    ]
    for label, (true, pred) in results.items():
        s = statistics(true, pred)
        lines.append(
            f"| {label} | {s['states']} | {s['bias']:.2f} | {s['rmse']:.2f} | {s['correlation']:.3f} |"
        )
    plot(results, args.out, args.title)
    text = "\n".join(lines)
    print(text)
    print(f"figure: {args.out}")
    return text


if __name__ == "__main__":
    main()
