"""Draws one ``LearnToRun-v0`` episode: the runner as stick figures, and its pelvis height.

python recipes/plot_runner.py --out runner.png                        # no excitation: a fall
python recipes/plot_runner.py --run outputs/.../rave --out runner.png # a trained policy

With ``--run``, the run directory's latest checkpoint drives the runner with its
deterministic policy (the env's settings come from the run's config); without it the
muscles get a constant excitation ``--excitation`` (0 by default: the runner folds and
falls). A stick figure (head, torso, pelvis; each leg from hip to toes) is drawn every
``--every`` steps, later ones darker; the right panel is the pelvis height against time
with the 0.65 m fall line.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torchrl.envs.utils import ExplorationType, set_exploration_type  # noqa: E402

from torchrl_rave.envs.families import import_env_family  # noqa: E402
from torchrl_rave.recipe.agent import load_agent  # noqa: E402
from torchrl_rave.recipe.trust import add_trust_flag  # noqa: E402


def constant_policy(level: float):
    return lambda obs: np.full(18, level)


def trained_policy(run_dir: str, trust: bool = False):
    cfg, agent = load_agent(run_dir, trust=trust)
    if cfg.env.name != "LearnToRun-v0":
        raise ValueError(f"{run_dir} trained on {cfg.env.name!r}, not LearnToRun-v0")
    actor = agent.actor

    def act(obs: np.ndarray) -> np.ndarray:
        td = TensorDict(observation=torch.as_tensor(obs, dtype=torch.float32))
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return actor(td)["action"].numpy().astype(np.float64)

    return act, dict(cfg.env.kwargs or {})


def play(policy, env_kwargs: dict, seed: int, max_steps: int) -> dict:
    """One episode: the skeleton at every step, pelvis heights, return, and whether it fell."""
    import_env_family("LearnToRun-v0")
    env = gym.make("LearnToRun-v0", **env_kwargs)
    obs, info = env.reset(seed=seed)
    frames, heights, total = [env.unwrapped.skeleton()], [info["pelvis_height"]], 0.0
    terminated = truncated = False
    while not (terminated or truncated) and len(heights) <= max_steps:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        frames.append(env.unwrapped.skeleton())
        heights.append(info["pelvis_height"])
        total += reward
    env.close()
    return {"frames": frames, "heights": heights, "return": total, "fell": terminated}


def draw(episode: dict, every: int, title: str, out: str) -> None:
    fig, (ax, ax_h) = plt.subplots(
        1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2.2, 1]}, constrained_layout=True
    )
    shown = list(range(0, len(episode["frames"]), every))
    if shown[-1] != len(episode["frames"]) - 1:
        shown.append(len(episode["frames"]) - 1)
    for n, t in enumerate(shown):
        shade = 0.25 + 0.75 * n / max(1, len(shown) - 1)
        colours = ["0.3", "tab:red", "tab:blue"]  # torso, right leg, left leg
        for line, colour in zip(episode["frames"][t], colours, strict=True):
            ax.plot(line[:, 0], line[:, 1], color=colour, alpha=shade, lw=1.5)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{title}: every {every} steps (red: right leg, blue: left)")
    seconds = 0.01 * np.arange(len(episode["heights"]))
    ax_h.plot(seconds, episode["heights"], color="k")
    ax_h.axhline(0.65, color="tab:red", ls="--", lw=1, label="fall height 0.65 m")
    ax_h.set_xlabel("time (s)")
    ax_h.set_ylabel("pelvis height (m)")
    outcome = "fell" if episode["fell"] else "did not fall"
    ax_h.set_title(f"return {episode['return']:.1f}, {len(seconds) - 1} steps, {outcome}")
    ax_h.legend(loc="lower left")
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", help="a run directory trained on LearnToRun-v0")
    parser.add_argument("--excitation", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--max-steps", type=int, default=1000)
    parser.add_argument("--out", default="runner.png")
    add_trust_flag(parser)
    args = parser.parse_args(argv)
    if args.every < 1:
        parser.error(f"--every must be >= 1, got {args.every}")
    if args.max_steps < 1:
        parser.error(f"--max-steps must be >= 1, got {args.max_steps}")
    if args.run:
        policy, kwargs = trained_policy(args.run, args.trust)
        title = f"policy of {args.run}"
    else:
        if not 0.0 <= args.excitation <= 1.0:
            parser.error(f"--excitation must lie in [0, 1], got {args.excitation}")
        policy, kwargs = constant_policy(args.excitation), {}
        title = f"excitation {args.excitation:g}"
    episode = play(policy, kwargs, args.seed, args.max_steps)
    draw(episode, args.every, title, args.out)
    print(f"{args.out}: return {episode['return']:.2f}, {len(episode['heights']) - 1} steps")
    return episode


if __name__ == "__main__":
    main()
