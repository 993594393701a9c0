"""The paper's alpha ablation (figure 6): RAVE with a constant alpha of 0, 0.5 and 2.0 and
with the dynamic alpha of eq. 12, same env and seeds, learning curves side by side.

python recipes/alpha_ablation.py --env Hopper-v5 --seeds 0 1 --frames 30000 --jobs 2 \
    --out outputs/compare

Runs live in ``<out>/<env>/<variant>/seed<k>`` (variants ``rave_alpha0``, ``rave_alpha0.5``,
``rave_alpha2``, and ``rave`` for the dynamic alpha, the layout of ``compare.py``, so a
``compare.py`` grid's RAVE runs are reused). Finished runs are skipped and interrupted ones
resumed. It writes ``<out>/<env>/alpha_ablation.png`` (eval return, mean ± std over seeds)
and prints a table of the return at ``--at`` frames. Extra ``key=value`` arguments after
``--`` go to every run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from compare import cell, run, run_dir
from plot_curves import plot, table

from torchrl_rave.recipe.runs import curves

# variant -> (algorithm, overrides, legend label)
VARIANTS = {
    "rave_alpha0": ("rave_constant", ["estimator.alpha=0.0"], "alpha = 0 (constant)"),
    "rave_alpha0.5": ("rave_constant", ["estimator.alpha=0.5"], "alpha = 0.5 (constant)"),
    "rave_alpha2": ("rave_constant", ["estimator.alpha=2.0"], "alpha = 2.0 (constant)"),
    "rave": ("rave", [], "dynamic alpha (eq. 12, alpha = 1.5)"),
}


def main(argv: list[str] | None = None) -> str:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(
        description="RAVE with constant alpha 0 / 0.5 / 2.0 and the dynamic alpha; curves."
    )
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--frames", type=int, default=30_000)
    parser.add_argument("--jobs", type=int, default=1, help="runs side by side (1 thread each)")
    parser.add_argument("--out", type=Path, default=Path("outputs/compare"))
    parser.add_argument(
        "--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS), metavar="VARIANT"
    )
    parser.add_argument("--at", nargs="*", type=int, default=None, help="frames for the table")
    parser.add_argument("--plot-only", action="store_true", help="run nothing, plot what exists")
    args = parser.parse_args(argv)

    cells = [
        cell(args.out, args.env, VARIANTS[v][0], seed, args.frames, [*extra, *VARIANTS[v][1]], v)
        for v in args.variants
        for seed in args.seeds
    ]
    if not args.plot_only:
        run(cells, args.jobs)

    groups = {
        VARIANTS[v][2]: [run_dir(args.out, args.env, v, s) for s in args.seeds]
        for v in args.variants
    }
    data = curves(groups, "eval/return")
    out = args.out / args.env / "alpha_ablation.png"
    plot(data, "eval/return", out, title=f"RAVE alpha ablation on {args.env}")
    text = table(data, args.at or [args.frames], "eval/return")
    print(text)
    print(f"figure: {out}")
    return text


if __name__ == "__main__":
    main()
