"""`a3cqp plot KIND ...`: the paper's figures from policies and run folders (PNG by default; --pdf or a .pdf name for
PDF).

    a3cqp plot policy-map POLICY [--out F] [--fixed e --levels 0,0.05,0.3]       (Fig. 5)
    a3cqp plot loss-curves RUN [RUN ...] [--out F]                               (Fig. 4)
    a3cqp plot regions RUN [RUN ...] [--out F]
    a3cqp plot transfer RUN [RUN ...] [--out F]                                  (the Panda transfer checks)
    a3cqp plot episode RUN [--controller learned] [--axis z] [--strip] [--out F] (a Panda episode, Fig. 7/8)
    a3cqp plot ga DIR [--out F]
    a3cqp plot pareto DIR [--out F]
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

from a3cqp_rl.cli import error_exit, help_summary
from a3cqp_rl.exceptions import A3CQPError
from a3cqp_rl.run_folder import check_output_path, policy_file

POLICY_LOADER = "algorithms.a2c:load_policy"
"""'module:function' turning a policy file into obs [..., 3] -> action [..., 4] (resolved on use: plotting does not
import the algorithms)."""


def _load_policy(path: Path):
    module, func = POLICY_LOADER.split(":")
    return getattr(importlib.import_module(module), func)(path)


def _plot_parser(sub, name: str, text: str, first: str, help_first: str, **first_kwargs) -> argparse.ArgumentParser:
    """A plot sub-command: its input argument, then the --out FILE and --pdf options every plot takes."""
    q = sub.add_parser(name, help=text)
    q.add_argument(first, help=help_first, **first_kwargs)
    q.add_argument("--out", default=None, help="output image path (default: beside the input)")
    q.add_argument("--pdf", action="store_true", help="write PDF instead of PNG")
    return q


def _output_image(text: str, pdf: bool) -> Path:
    """`--out` as the file the plot will be: the format's suffix added to a name without one; ValueError for a folder
    or a suffix that contradicts --pdf."""
    out = Path(text)
    if out.is_dir() or text.endswith(("/", os.sep)):  # (Path drops a trailing slash: a folder to be)
        raise ValueError(f"--out {out} is a folder: give the image's file name, e.g. {out / 'plot.png'}")
    check_output_path(out, "--out")
    if not out.suffix:
        return out.with_suffix(".pdf" if pdf else ".png")
    if pdf and out.suffix.lower() != ".pdf":
        raise ValueError(f"--pdf asks for a PDF but --out {out} names a {out.suffix} file")
    return out


def _beside_runs(runs: list[str], name: str) -> Path:
    """Where a plot of run folders goes by default: inside the run for one (as `a3cqp train` writes it), in the
    first run's parent for several (a sweep's folder)."""
    return Path(runs[0]) / name if len(runs) == 1 else Path(runs[0]).parent / name


def _expand_sweeps(runs: list[str]) -> list[str]:
    """Run folders as given, a sweep's folder (`a3cqp train --seeds`: no metrics.csv, seed_S/metrics.csv inside)
    replaced by its seeds' folders in seed order."""
    out: list[str] = []
    for run in runs:
        seeds = sorted(Path(run).glob("seed_*/metrics.csv"), key=lambda p: (len(p.parent.name), p.parent.name))
        if Path(run).is_dir() and not (Path(run) / "metrics.csv").exists() and seeds:
            out += [str(p.parent) for p in seeds]
        else:
            out.append(run)
    return out


def _run_provenance(folder: Path, controller: str) -> str:
    """The seed and, for the learned controller, the policy that the run folder's results.json names ("" without)."""
    import json

    try:
        res = json.loads((folder / "results.json").read_text())
    except (OSError, ValueError):
        return ""
    seeds = res.get("seeds") or []
    parts = [f"seed {seeds[0]}" if len(seeds) == 1 else ""]
    if controller == "learned" and res.get("policy"):
        parts.append(f"policy {res['policy']} ({res.get('policy_fingerprint', '?')})")
    text = ", ".join(p for p in parts if p)
    return f"; {text}" if text else ""


def _episode_controller(src: Path, given: str | None) -> str:
    """The controller whose episode `plot episode` draws: `given` (default learned) in a run folder; an
    episode_<controller>.npz's own name, which a different `given` contradicts."""
    if src.is_dir() or not src.name.startswith("episode_"):
        return given or "learned"
    own = src.stem.removeprefix("episode_")
    if given is not None and given != own:
        raise ValueError(f"--controller {given}: {src.name} is the {own} controller's episode")
    return own


def _levels(text: str) -> list[float]:
    """`--levels 0,0.05,0.3` as numbers; ValueError naming the flag."""
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--levels {text!r}: expected comma-separated numbers in [0, 1], e.g. 0,0.05,0.3") from None


def main(argv: list[str] | None = None) -> int:
    """CLI entry for the plot sub-commands; returns an exit code."""
    p = argparse.ArgumentParser(prog="a3cqp plot", description=help_summary(__doc__))
    sub = p.add_subparsers(dest="what", required=True)
    pm = _plot_parser(sub, "policy-map", "paper Fig. 5: actions over the normalised state space", "policy",
                      "OUT/policy.pt or OUT/checkpoint.pt (or a run folder)")
    pm.add_argument("--x", default="f_ope", choices=["e", "f_env", "f_ope"], help="state on the x axis")
    pm.add_argument("--y", default="f_env", choices=["e", "f_env", "f_ope"], help="state on the y axis")
    pm.add_argument("--fixed", default=None, choices=["e", "f_env", "f_ope"],
                    help="state held at each of --levels (default: the one --x and --y leave)")
    pm.add_argument("--levels", default="0,0.05,0.3", help="comma-separated levels of the fixed variable in [0, 1]")
    for name, text in (("loss-curves", "paper Fig. 4: policy/value loss, mean and IQR over runs"),
                       ("regions", "Fig. 5 regions passed over training (metrics.csv region checks)"),
                       ("transfer", "the Panda transfer checks over training, a panel per run, the kept update")):
        _plot_parser(sub, name, text, "runs", "run folders holding metrics.csv (e.g. runs/sweep/seed_*)", nargs="+")
    ep = _plot_parser(sub, "episode", "paper Fig. 7/8: one Panda episode of `a3cqp evaluate --scene ... --out RUN`",
                      "run", "RUN folder (or an episode_<controller>.npz)")
    ep.add_argument("--controller", default=None, help="which controller's episode in RUN (default: learned; an "
                                                       "episode_<controller>.npz names its own)")
    ep.add_argument("--axis", default="z", choices=["x", "y", "z", "rx", "ry", "rz"], help="local axis (default z)")
    ep.add_argument("--strip", action="store_true", help="also an image strip of the scene (needs EGL or OSMesa)")
    for name, text, command in (("ga", "GA run (a3cqp tune): fitness per generation, best and spread, genes", "tune"),
                                ("pareto", "NSGA-II run (a3cqp pareto): evaluations and Pareto front, 2-D (and 3-D)",
                                 "pareto")):
        _plot_parser(sub, name, text, "run", f"the run's folder (OUT of a3cqp {command})")
    args = p.parse_args(argv)
    if getattr(args, "strip", False):
        os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen; read when MuJoCo is first imported
    ext = ".pdf" if args.pdf else ".png"
    try:
        if args.out is not None:
            args.out = str(_output_image(args.out, args.pdf))
        if args.what == "policy-map":
            from a3cqp_rl.plotting.policy_map import plot_policy_map

            src = policy_file(args.policy)
            levels = _levels(args.levels)
            if args.x == args.y:
                raise ValueError(f"--x and --y both name {args.x}: give two different states")
            fixed = args.fixed or next(n for n in ("e", "f_env", "f_ope") if n not in (args.x, args.y))
            if fixed in (args.x, args.y):
                raise ValueError(f"--fixed {fixed} is also on an axis: fix the state --x and --y leave")
            # checkpoint.pt holds the last parameters, policy.pt the kept ones: their maps must not replace each other
            name = "policy_map" if src.name == "policy.pt" else f"policy_map_{src.stem}"
            out = Path(args.out) if args.out else src.with_name(name + ext)
            from a3cqp_rl.plotting.transfer_history import kept_update

            policy = _load_policy(src)
            kept = kept_update(src.parent) if src.name == "policy.pt" else None  # a2c.select_policy's choice
            plot_policy_map(policy, out, args.x, args.y, fixed, levels,
                            title=str(src) + (f" (the parameters of update {int(kept):,}, a2c.select_policy)"
                                              if kept is not None else ""))
        elif args.what == "loss-curves":
            from a3cqp_rl.plotting.loss_curves import plot_loss_curves

            args.runs = _expand_sweeps(args.runs)
            out = Path(args.out) if args.out else _beside_runs(args.runs, "loss_curves" + ext)
            plot_loss_curves(args.runs, out)
        elif args.what == "episode":
            from a3cqp_rl.plotting.episode import load_episode, plot_episode, render_strip

            src = Path(args.run)
            controller = _episode_controller(src, args.controller)
            npz = src / f"episode_{controller}.npz" if src.is_dir() else src
            data = load_episode(npz)
            base = npz.parent / f"episode_{controller}" if src.is_dir() else npz.with_suffix("")
            out = Path(args.out) if args.out else base.with_suffix(ext)
            trial = f", trial {int(data['trial'])}" if "trial" in data else ""  # `evaluate --record-trial`
            plot_episode(data, out, axis=args.axis,
                         title=f"{data.get('scene', '')}: {controller}{trial}, axis {args.axis}"
                               + _run_provenance(npz.parent, controller))
            if args.strip:
                try:
                    strip = render_strip(data, out.with_name(out.stem + "_strip.png"))
                    print(f"wrote {strip}")
                except RuntimeError as exc:
                    print(f"no image strip: {exc}", file=sys.stderr)
        elif args.what == "transfer":
            from a3cqp_rl.plotting.transfer_history import plot_transfer_history

            args.runs = _expand_sweeps(args.runs)
            out = Path(args.out) if args.out else _beside_runs(args.runs, "transfer" + ext)
            plot_transfer_history(args.runs, out)
        elif args.what == "ga":
            from a3cqp_rl.plotting.ga_history import plot_ga_run

            out = plot_ga_run(args.run, Path(args.out) if args.out else Path(args.run) / ("ga" + ext))
        elif args.what == "pareto":
            from a3cqp_rl.plotting.pareto import plot_pareto_run

            written = plot_pareto_run(args.run, Path(args.out) if args.out else Path(args.run) / ("pareto" + ext))
            out = ", ".join(map(str, written))
        else:
            from a3cqp_rl.plotting.region_history import plot_region_history

            args.runs = _expand_sweeps(args.runs)
            out = Path(args.out) if args.out else _beside_runs(args.runs, "regions" + ext)
            plot_region_history(args.runs, out)
    except (A3CQPError, FileNotFoundError, ValueError) as exc:
        return error_exit(exc)
    print(f"wrote {out}")
    return 0
