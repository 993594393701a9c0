"""Noisy-target distillation of a trained run (the paper's supplement, Learn to Move).

    python recipes/distill.py outputs/DATE/TIME --out outputs/distilled --frames 20000
    python recipes/rave_mujoco.py resume=outputs/distilled collector.total_frames=2000000

Collects (observation, action) pairs from the run's latest deterministic policy, fits a
freshly built actor of the run's config on them with the target part of each observation
(``--target START:STOP``; by default the env's own ``target_observation``, the 2 x 11 x 11
target-velocity field of ``LearnToMove-v0``) replaced by uniform noise over the range the
task can produce (``--low``/``--high`` to set it), and
writes a new run directory whose checkpoint is the source's with that actor, ready for
``resume=``. See :mod:`torchrl_rave.recipe.distill`.
"""

from __future__ import annotations

import argparse

from torchrl_rave.recipe.distill import distill_run
from torchrl_rave.recipe.trust import add_trust_flag


def target_slice(text: str) -> slice | None:
    """``START:STOP``, or ``None`` for ``auto`` (the env's own ``target_observation``)."""
    if text == "auto":
        return None
    start, colon, stop = text.partition(":")
    try:
        if not colon:
            raise ValueError
        return slice(int(start) if start else None, int(stop) if stop else None)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected START:STOP (integers, either may be left out) or auto"
        ) from None


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="the trained run directory")
    parser.add_argument("--out", required=True, help="the new run directory (must not exist)")
    parser.add_argument(
        "--target", default="auto", type=target_slice,
        help="START:STOP of the observation's target part (default auto: the env's own)",
    )  # fmt: skip
    parser.add_argument("--frames", type=int, default=10_000, help="pairs to collect")
    parser.add_argument("--steps", type=int, default=2000, help="Adam steps of the fit")
    parser.add_argument(
        "--low", type=float,
        help="the noise's low end (default: the env's target_range, or for a --target "
        "slice each entry's minimum in the pairs)",
    )  # fmt: skip
    parser.add_argument("--high", type=float, help="its high end (default: as --low)")
    parser.add_argument("--seed", type=int, default=0)
    add_trust_flag(parser)
    args = parser.parse_args(argv)
    result = distill_run(
        args.run, args.out, args.target, frames=args.frames, low=args.low, high=args.high,
        steps=args.steps, seed=args.seed, trust=args.trust,
    )  # fmt: skip
    print(
        f"distilled {args.run} into {args.out}: {result['pairs']} pairs, target "
        f"{result['target'][0]}:{result['target'][1]}, "
        f"loss {result['first_loss']:.4g} -> {result['last_loss']:.4g}; train on with "
        f"resume={args.out}"
    )
    return result


if __name__ == "__main__":
    main()
