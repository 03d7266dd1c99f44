"""`a3cqp train`: train the adaptation policy with A2C from a YAML config; one seed or a sweep of seeds.

    a3cqp train --config configs/point_mass_a2c.yaml [--steps N] [--seed S | --seeds 0-19]
                [--out runs/NAME] [--resume] [--no-compile] [--no-plots]

Writes under OUT (per seed OUT/seed_S when sweeping): config.yaml, metrics.csv, checkpoint.pt
(atomic, every `a2c.checkpoint_every` updates), policy.pt, and the plots policy_map.png,
loss_curves.png and regions.png (the Fig. 5 regions checked over training). `--resume` continues
a killed run from OUT/checkpoint.pt with no lost or repeated steps. At the end the policies run in
closed loop against the baselines (`a3cqp evaluate`; OUT/evaluation.json): with --seeds, one row per
seed, the seed-robustness table.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from a3cqp_rl.exceptions import A3CQPError


def parse_seeds(text: str) -> list[int]:
    """'0-19' -> [0..19]; '1,3,5' -> [1, 3, 5]; '7' -> [7]."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            if "-" in part:
                a, b = part.split("-")
                if int(b) < int(a):
                    raise ValueError
                seeds += list(range(int(a), int(b) + 1))
            else:
                seeds.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid seed list {text!r}; use e.g. 0-19 or 1,3,5") from None
    return seeds


def main(argv: list[str] | None = None) -> int:
    """CLI entry: parse arguments, train each seed, plot; returns an exit code."""
    p = argparse.ArgumentParser(prog="a3cqp train", description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/point_mass_a2c.yaml", help="YAML config (default: %(default)s)")
    p.add_argument("--steps", type=int, default=None, help="total agent steps (default: a2c.total_steps)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--seed", type=int, default=None, help="random seed (default: the config's)")
    g.add_argument("--seeds", type=parse_seeds, default=None, help="sweep, e.g. 0-19: one run per seed in OUT/seed_S")
    p.add_argument("--out", default=None, help="output folder (default: runs/<config name>)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--no-compile", action="store_true", help="skip torch.compile (slower steps, no compile wait)")
    p.add_argument("--no-plots", action="store_true", help="do not draw policy map / loss curves at the end")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-eval", action="store_true", help="skip the closed-loop evaluation at the end (point mass)")
    args = p.parse_args(argv)

    import torch

    from a3cqp_rl.config import load_config
    from algorithms.a2c import train

    torch.set_num_threads(1)  # tiny networks: threads cost more than they give
    try:
        overrides: dict = {}
        if args.no_compile:
            overrides["a2c"] = {"compile": False}
        cfg = load_config(args.config, overrides)
        out = Path(args.out or Path("runs") / Path(args.config).stem)
        seeds = args.seeds if args.seeds is not None else [cfg.seed if args.seed is None else args.seed]
        run_dirs, passed = [], []
        for seed in seeds:
            run_cfg = load_config(args.config, {**overrides, "seed": seed})
            run_dir = out / f"seed_{seed}" if args.seeds is not None else out
            if len(seeds) > 1:
                print(f"[seed {seed}] -> {run_dir}")
            res = train(run_cfg, run_dir, total_steps=args.steps, resume=args.resume, progress=not args.quiet)
            run_dirs.append(run_dir)
            print(f"trained {res.steps:,} steps in {res.seconds:.1f} s ({res.steps_per_second:,.0f} steps/s"
                  f"{f', plus {res.compile_seconds:.0f} s compiling' if res.compile_seconds else ''}); "
                  + _reward_text(res.final_metrics.get("episode_reward", float("nan"))))
            passed.append(_print_regions(res.policy_path))
        if len(seeds) > 1:
            print(f"Fig. 5 regions (literal): all four on {passed.count(4)} of {len(seeds)} seeds, at least three on "
                  f"{sum(n >= 3 for n in passed)}")
        if cfg.env == "point_mass" and not args.no_eval:  # the closed-loop table against the baselines
            from envs.evaluate_cli import report

            print()
            report([d / "policy.pt" for d in run_dirs], config=cfg, json_path=out / "evaluation.json")
        if not args.no_plots:
            from a3cqp_rl.plotting.loss_curves import plot_loss_curves
            from a3cqp_rl.plotting.policy_map import plot_policy_map
            from a3cqp_rl.plotting.region_history import plot_region_history

            for d in run_dirs:
                plot_policy_map(d / "policy.pt", d / "policy_map.png")
            plot_loss_curves(run_dirs, out / "loss_curves.png")
            if cfg.a2c.region_checks:
                plot_region_history(run_dirs, out / "regions.png")
        maps = f"{out}/policy_map.png" if args.seeds is None else f"{out}/seed_*/policy_map.png"
        print(f"results in {out}/: policy.pt (load with algorithms.a2c.load_policy), checkpoint.pt, metrics.csv"
              + ("" if args.no_plots else f"; plots {out}/loss_curves.png, {maps}"
                   + (f" and {out}/regions.png (Fig. 5 regions over training)" if cfg.a2c.region_checks else "")))
    except (A3CQPError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def _reward_text(r: float) -> str:
    """The final message's episode-reward part; says so when no episode has ended yet (short runs)."""
    if math.isnan(r):
        return "no episode finished yet (episodes are longer than this run per env)"
    return f"last mean episode reward {r:.2f}"


def _print_regions(policy_path: Path) -> int:
    """Print both Fig. 5 region checks of the saved policy (a3cqp_rl.regions); returns how many pass the literal one."""
    from a3cqp_rl.regions import check_fig5_regions, format_regions
    from algorithms.a2c import load_policy

    results = check_fig5_regions(load_policy(policy_path))
    print(format_regions(results))
    return sum(r.literal for r in results)
