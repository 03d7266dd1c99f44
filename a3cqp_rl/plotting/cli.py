"""`a3cqp plot policy-map POLICY [--out F] [--fixed e --levels 0,0.05,0.3]` and
`a3cqp plot loss-curves RUN [RUN ...] [--out F]` and `a3cqp plot regions RUN [RUN ...] [--out F]`
(PNG by default; --pdf or a .pdf name for PDF)."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from a3cqp_rl.exceptions import A3CQPError

POLICY_LOADER = "algorithms.a2c:load_policy"
"""'module:function' turning a policy file into obs [..., 3] -> action [..., 4] (resolved on use: plotting does not
import the algorithms)."""


def _load_policy(path: Path):
    module, func = POLICY_LOADER.split(":")
    return getattr(importlib.import_module(module), func)(path)


def main(argv: list[str] | None = None) -> int:
    """CLI entry for the plot sub-commands; returns an exit code."""
    p = argparse.ArgumentParser(prog="a3cqp plot", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    pm = sub.add_parser("policy-map", help="paper Fig. 5: actions over the normalised state space")
    pm.add_argument("policy", help="OUT/policy.pt or OUT/checkpoint.pt (or a run folder)")
    pm.add_argument("--x", default="f_ope", choices=["e", "f_env", "f_ope"])
    pm.add_argument("--y", default="f_env", choices=["e", "f_env", "f_ope"])
    pm.add_argument("--fixed", default="e", choices=["e", "f_env", "f_ope"])
    pm.add_argument("--levels", default="0,0.05,0.3", help="comma-separated levels of the fixed variable in [0, 1]")
    pm.add_argument("--out", default=None)
    pm.add_argument("--pdf", action="store_true")
    for name, text in (("loss-curves", "paper Fig. 4: policy/value loss, mean and IQR over runs"),
                       ("regions", "Fig. 5 regions passed over training (metrics.csv region checks)")):
        runs = sub.add_parser(name, help=text)
        runs.add_argument("runs", nargs="+", help="run folders holding metrics.csv (e.g. runs/sweep/seed_*)")
        runs.add_argument("--out", default=None)
        runs.add_argument("--pdf", action="store_true")
    args = p.parse_args(argv)
    ext = ".pdf" if args.pdf else ".png"
    try:
        if args.what == "policy-map":
            from a3cqp_rl.plotting.policy_map import plot_policy_map

            src = Path(args.policy)
            if src.is_dir():
                src = src / "policy.pt"
            levels = [float(v) for v in args.levels.split(",")]
            out = Path(args.out) if args.out else src.with_name("policy_map" + ext)
            plot_policy_map(_load_policy(src), out, args.x, args.y, args.fixed, levels, title=str(src))
        elif args.what == "loss-curves":
            from a3cqp_rl.plotting.loss_curves import plot_loss_curves

            out = Path(args.out) if args.out else Path(args.runs[0]).parent / ("loss_curves" + ext)
            plot_loss_curves(args.runs, out)
        else:
            from a3cqp_rl.plotting.region_history import plot_region_history

            out = Path(args.out) if args.out else Path(args.runs[0]).parent / ("regions" + ext)
            plot_region_history(args.runs, out)
    except (A3CQPError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0
