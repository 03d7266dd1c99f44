"""`a3cqp train`: train a policy with A2C from a YAML config, on the point mass or any gymnasium task; one seed or a
sweep of seeds.

    a3cqp train [--config configs/point_mass_a2c_default.yaml] [--env NAME] [--steps N] [--seed S | --seeds 0-19]
                [--out runs/NAME] [--resume [--override] | --force] [--no-compile] [--no-plots] [--timings] [--debug]

Writes under OUT (per seed OUT/seed_S when sweeping): config.yaml, metrics.csv, checkpoint.pt (atomic, every
`a2c.checkpoint_every` updates and on Ctrl-C or SIGTERM), policy.pt, and plots: loss_curves.png, and on the point mass
policy_map.png and regions.png (the Fig. 5 regions checked over training). A folder holding a run is not started
again: `--resume` continues it (no lost or repeated steps; a sweep resumes seed by seed), `--force` starts over,
`--override` lets a resume change the config (recorded in OUT/overrides.log). One process writes a folder at a time.
On the point mass the policies then run in closed loop against the baselines (`a3cqp evaluate`; OUT/evaluation.json):
with --seeds, one row per seed, the seed-robustness table.
"""

from __future__ import annotations

import argparse
import collections
import math
import signal
import sys
from pathlib import Path

from a3cqp_rl.cli import add_set_option, error_exit, help_summary, seed_arg
from a3cqp_rl.config import MAX_SEED
from a3cqp_rl.exceptions import A3CQPError

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "point_mass_a2c_default.yaml"
"""The checkout's default training (the one `make train` runs, docs/point_mass.md); where it is absent (an installed
wheel) the built-in defaults, the paper's settings (configs/point_mass_a2c.yaml), are used."""


MAX_SEEDS = 10_000
"""The most seeds one list may name (a typo such as 0-99999999 would otherwise run for days)."""


def parse_seeds(text: str) -> list[int]:
    """'0-19' -> [0..19]; '1,3,5' -> [1, 3, 5]; '7' -> [7]; each seed once, in [0, 2**63 - 1], at most MAX_SEEDS."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            if "-" in part:
                a, b = part.split("-")
                if int(b) < int(a):
                    raise ValueError
                if len(seeds) + int(b) - int(a) + 1 > MAX_SEEDS:
                    raise argparse.ArgumentTypeError(f"seed list {text!r} names more than {MAX_SEEDS:,} seeds")
                seeds += list(range(int(a), int(b) + 1))
            else:
                seeds.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid seed list {text!r}; use e.g. 0-19 or 1,3,5") from None
    if len(seeds) > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"seed list {text!r} names more than {MAX_SEEDS:,} seeds")
    twice = sorted(s for s, n in collections.Counter(seeds).items() if n > 1)
    if twice:
        raise argparse.ArgumentTypeError(f"seed list {text!r} names seed(s) {twice} more than once")
    outside = [s for s in seeds if not 0 <= s <= MAX_SEED]
    if outside:
        raise argparse.ArgumentTypeError(f"seed list {text!r}: seed(s) {outside[:3]} outside [0, 2**63 - 1]")
    return seeds


def _count(text: str) -> int:
    """A whole count written as an integer or in scientific notation (2e5)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid count {text!r}: expected an integer, e.g. 200000 or 2e5") from None
    if not value.is_integer():
        raise argparse.ArgumentTypeError(f"invalid count {text!r}: not a whole number")
    return int(value)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="a3cqp train", description=help_summary(__doc__))
    p.add_argument("--config", default=None, help=f"YAML config (default: {DEFAULT_CONFIG.name} on the point mass, "
                                                    "the paper's Table IV settings (configs/point_mass_a2c.yaml) "
                                                    "on other envs)")
    p.add_argument("--env", default=None, help="environment: point_mass or a gymnasium id, e.g. Pendulum-v1 "
                                               "(default: the config's env)")
    add_set_option(p, "a2c.learning_rate=1e-4", "the run folder's config.yaml keeps the result")
    p.add_argument("--steps", type=_count, default=None, help="total agent steps, e.g. 200000 or 2e5 (default: "
                   "a2c.total_steps)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--seed", type=seed_arg, default=None, help="random seed (default: the config's)")
    g.add_argument("--seeds", type=parse_seeds, default=None, help="sweep, e.g. 0-19: one run per seed in OUT/seed_S")
    p.add_argument("--out", default=None, help="output folder (default: runs/<config name>, with --env "
                                               "runs/<config name>_<env>)")
    r = p.add_mutually_exclusive_group()
    r.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt (a sweep: each seed that "
                                                         "has one; the others start)")
    r.add_argument("--force", action="store_true", help="start over in a folder that holds a run (deletes its files)")
    p.add_argument("--override", action="store_true", help="with --resume: accept a changed config or seed")
    p.add_argument("--no-compile", action="store_true", help="skip torch.compile (slower steps, no compile wait)")
    p.add_argument("--no-plots", action="store_true", help="do not draw policy map / loss curves at the end")
    p.add_argument("--timings", action="store_true", help="print where the time went (start-up, named loop blocks)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-eval", action="store_true", help="skip the closed-loop evaluation at the end (point mass)")
    p.add_argument("--debug", action="store_true",
                   help="show the full traceback of errors (any command: A3CQP_DEBUG=1)")
    return p


def main(argv: list[str] | None = None) -> int:
    """CLI entry: parse arguments, train each seed, plot; returns an exit code."""
    args = _parser().parse_args(argv)
    if args.override and not args.resume:
        print("error: --override only applies with --resume", file=sys.stderr)
        return 2
    try:
        return _run(args)
    except KeyboardInterrupt as exc:
        print(f"\n{str(exc) or 'interrupted'}", file=sys.stderr)  # (config.yaml holds --steps: a plain --resume)
        return 128 + int(getattr(exc, "signum", signal.SIGINT))  # 130 after Ctrl-C (SIGINT), 143 after SIGTERM
    except (A3CQPError, OSError, ValueError) as exc:
        if args.debug:
            raise
        return error_exit(exc, _one_line(exc))


def _run(args: argparse.Namespace) -> int:
    import torch

    from a3cqp_rl.config import load_config, parse_overrides, project_path
    from algorithms.a2c import train

    torch.set_num_threads(1)  # tiny networks: threads cost more than they give
    overrides: dict = parse_overrides([*args.overrides, *(["a2c.compile=false"] if args.no_compile else [])])
    if args.env:
        overrides["env"] = args.env
    # the default config trains the point mass; another env without --config starts from the paper's settings
    point_mass = args.env in (None, "point_mass")
    config = (project_path(args.config) if args.config else  # configs/... found from any working directory
              DEFAULT_CONFIG if DEFAULT_CONFIG.is_file() and point_mass else None)
    cfg = load_config(config, overrides)
    name = Path(config).stem if config else "point_mass_a2c"
    out = Path(args.out or Path("runs") / (name if not args.env else f"{name}_{args.env}"))
    sweep = args.seeds is not None
    if args.seed is not None and "seed" in overrides and overrides["seed"] != args.seed:
        raise A3CQPError(f"--seed {args.seed} and --set seed={overrides['seed']} disagree; give one")
    seed = cfg.seed if args.seed is None else args.seed
    saved_run = out / "config.yaml"
    if args.resume and not sweep and args.seed is None and "seed" not in overrides and saved_run.is_file():
        seed = load_config(saved_run).seed  # a plain --resume continues the run's own seed, not the config's
    seeds = args.seeds if sweep else [seed]
    run_dirs, results, passed, run_cfgs = [], [], [], []
    if sweep and args.force:  # the sweep's own plots and table describe the old runs (each seed's folder: RunFolder)
        from a3cqp_rl.run_folder import remove_outputs

        remove_outputs(out)
    for seed in seeds:
        run_dir = out / f"seed_{seed}" if sweep else out
        # a resume without --config continues with the config the run recorded (OUT/config.yaml), not the default
        saved = run_dir / "config.yaml"
        run_config = saved if args.resume and args.config is None and saved.is_file() else config
        run_cfg = load_config(run_config, {**overrides, "seed": seed})
        # a sweep resumes seed by seed: seeds that never started (no checkpoint) start now
        resume = args.resume and (not sweep or (run_dir / "checkpoint.pt").is_file())
        steps = args.steps
        # the length the run was started with (--steps or --set a2c.total_steps changes it)
        if resume and steps is None and saved.is_file() and "total_steps" not in overrides.get("a2c", {}):
            steps = load_config(saved).a2c.total_steps
        if len(seeds) > 1:
            print(f"[seed {seed}] -> {run_dir}{' (resumed)' if resume else ''}")
        res = train(run_cfg, run_dir, total_steps=steps, resume=resume, force=args.force,
                    override=args.override, progress=not args.quiet)
        run_dirs.append(run_dir)
        results.append(res)
        run_cfgs.append(run_cfg)
        if res.resumed_steps == res.steps:  # a finished run resumed: no rate or reward to report from this call
            print(f"{run_dir} had already trained its {res.steps:,} steps: nothing left to train (--steps N goes on "
                  "to N)")
        else:
            done = (f"trained {res.steps:,} steps" if not res.resumed_steps else
                    f"trained steps {res.resumed_steps:,} to {res.steps:,} (resumed)")
            print(f"ran on {res.route}")
            print(f"{done} in {res.seconds:.1f} s ("
                  + (f"{res.compile_seconds:.0f} s of it compiling; {res.steps_per_second:,.0f} steps/s after that"
                     if res.compile_seconds else f"{res.steps_per_second:,.0f} steps/s") + "); "
                  + _reward_text(res.final_metrics.get("episode_reward", float("nan")))
                  + (f" (--steps {steps:,} rounded up to whole updates)" if steps and res.steps != steps else ""))
        if res.selected_update is not None:
            print(_selection_text(res, run_cfg.a2c.select_last))
        if args.timings:
            blocks = ", ".join(f"{k} {v:.2f} s" for k, v in res.timings.items())
            print(f"timings: start-up {res.startup_seconds:.2f} s (process start to the first update); {blocks}")
        if res.fig5_applies:  # (the closed-loop report below prints a single run's table itself)
            passed.append(_print_regions(res.policy_path, show=sweep or args.no_eval or cfg.env != "point_mass"))
    if len(seeds) > 1 and passed:
        print(f"Fig. 5 regions (literal): all four on {passed.count(4)} of {len(passed)} seeds, at least three on "
              f"{sum(k >= 3 for k in passed)}")
    if cfg.env == "point_mass" and not args.no_eval:  # the closed-loop table against the baselines
        from envs.evaluate_cli import report

        print()
        # the runs' own reward and dynamics: a resume without --config scores with the run's config.yaml
        report([d / "policy.pt" for d in run_dirs], config=run_cfgs[0], json_path=out / "evaluation.json")
    plots = [] if args.no_plots else _plot(run_dirs, out, results, cfg.a2c.region_checks)
    print(f"results in {out}/{'seed_*/' if sweep else ''}: policy.pt (load with algorithms.a2c.load_policy / "
          f"load_actor), checkpoint.pt, metrics.csv" + (f"; plots {', '.join(plots)}" if plots else ""))
    return 0


def _plot(run_dirs: list[Path], out: Path, results: list, region_checks: int) -> list[str]:
    """Loss curves of all runs; on the point mass, each run's policy map and the Fig. 5 regions over training; for
    per-axis policies, the Panda transfer checks over training."""
    from a3cqp_rl.plotting.loss_curves import plot_loss_curves
    from algorithms.a2c import load_policy

    made = [str(plot_loss_curves(run_dirs, out / "loss_curves.png"))]
    if all(r.fig5_applies for r in results):
        from a3cqp_rl.plotting.policy_map import plot_policy_map

        for d in run_dirs:
            plot_policy_map(load_policy(d / "policy.pt"), d / "policy_map.png", title=str(d / "policy.pt"))
        made.append(f"{out}/policy_map.png" if len(run_dirs) == 1 else f"{out}/seed_*/policy_map.png")
    if region_checks and all(r.fig5_applies for r in results):
        from a3cqp_rl.plotting.region_history import plot_region_history

        made.append(f"{plot_region_history(run_dirs, out / 'regions.png')} (Fig. 5 regions over training)")
    if all(math.isfinite(r.final_metrics.get("transfer_margin", math.nan)) for r in results):
        from a3cqp_rl.plotting.transfer_history import plot_transfer_history

        made.append(f"{plot_transfer_history(run_dirs, out / 'transfer.png')} (Panda transfer checks over training)")
    return made


def _one_line(exc: BaseException) -> str:
    """An error as one line (config errors list their fields after a colon)."""
    text = str(exc) or type(exc).__name__
    out = ""
    for part in (p.strip() for p in text.splitlines() if p.strip()):
        out += ("" if not out else " " if out.endswith(":") else "; ") + part
    return out


def _reward_text(r: float) -> str:
    """The final message's episode-reward part; says so when no episode has ended yet (short runs)."""
    if math.isnan(r):
        return "no episode finished yet (episodes are longer than this run per env)"
    return f"last mean episode reward {r:.2f}"


def _selection_text(res, select_last: float) -> str:  # noqa: ANN001
    """The line(s) saying which parameters `a2c.select_policy` transfer or panda kept in policy.pt."""
    if res.panda_selection:
        from algorithms.panda_select import format_selection

        rows = res.panda_selection
        chosen = next(i for i, r in enumerate(rows) if r["update"] == res.selected_update)
        r = rows[chosen]
        text = (f"policy.pt: the parameters after update {r['update']:,} of {res.updates:,}, which inserted the most "
                f"pegs (then yields, then fastest) of the {len(rows)} largest transfer margins over the last "
                f"{select_last:.0%} of the run, on {r['trials']} peg-in-hole trials (seed {r['seed']}; "
                "a2c.select_policy: panda):\n" + format_selection(rows, chosen))
        if r["successes"] < r["insertions"]:
            text += (f"\nno candidate inserted every peg (the best {r['successes']} of {r['insertions']}): the policy "
                     "will probably miss pegs on the Panda (docs/panda.md)")
        return text
    text = (f"policy.pt: the parameters after update {res.selected_update:,} of {res.updates:,}, the largest transfer "
            f"margin ({res.transfer_margin:+.2f}) over the last {select_last:.0%} of the run (a2c.select_policy: transfer)")
    if res.transfer_margin <= 0:
        text += ("; at no log row did the policy both raise IK over admittance in the Panda's free motion and yield to "
                 "the operator: it will probably not drive the Panda (docs/panda.md)")
    return text


def _print_regions(policy_path: Path, show: bool = True) -> int:
    """Print (if `show`) both Fig. 5 region checks of the saved policy (a3cqp_rl.regions); returns how many pass the
    literal one."""
    from a3cqp_rl.regions import check_fig5_regions, format_regions
    from algorithms.a2c import load_policy

    results = check_fig5_regions(load_policy(policy_path))
    if show:
        print(format_regions(results))
    return sum(r.literal for r in results)


if __name__ == "__main__":
    raise SystemExit(main())
