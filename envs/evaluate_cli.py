"""`a3cqp evaluate`: learned adaptation policies in closed loop against fixed-weight baselines, on the same episodes.

    a3cqp evaluate --env point_mass --policy PATH [PATH ...] [--episodes N] [--seed S] [--json PATH] [--config YAML]
    a3cqp evaluate --scene peg_in_hole|polishing|guidance ...      (the Panda scenes: envs.panda_eval)

Point mass: prints the closed-loop table (`envs.point_mass_eval`: free / contact / operator / guided contact, the
baselines IK only, admittance only, force control, equal blend and a switching rule), then per policy the literal Fig. 5
region check and pass/fail on the behaviour checks. PATH is a policy.pt, a checkpoint.pt or a run folder; with several
(e.g. runs/sweep/seed_*) the last table is one row per policy: the seed-robustness table.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from a3cqp_rl import worker_start
from a3cqp_rl.cli import error_exit, help_summary, seed_arg
from a3cqp_rl.exceptions import A3CQPError

if TYPE_CHECKING:  # annotations only
    from a3cqp_rl.config import ExperimentConfig

PANDA_WORKER_IMPORTS = ("envs.panda_eval", "envs.panda", "envs.panda_fixed", "algorithms.a2c")
"""What the worker processes of `a3cqp evaluate --scene` import before they simulate (their fork server's preload)."""


def _starts_workers(argv: Sequence[str]) -> bool:
    """Whether `a3cqp evaluate --scene` with these arguments will run worker processes (more than one, not --help)."""
    if any(a in ("-h", "--help") for a in argv):
        return False
    workers = None
    for i, a in enumerate(argv):
        if a == "--workers" and i + 1 < len(argv):
            workers = argv[i + 1]
        elif a.startswith("--workers="):
            workers = a.split("=", 1)[1]
    if workers is None:
        return worker_start.default_workers() > 1
    return workers.strip().isdigit() and int(workers) > 1


def _parser() -> argparse.ArgumentParser:
    """The point-mass evaluation's options (`--scene` hands the command to envs.panda_eval's own)."""
    # no abbreviations: `--scen peg_in_hole` would be taken for --scene here and run the point mass instead
    p = argparse.ArgumentParser(prog="a3cqp evaluate", description=help_summary(__doc__), allow_abbrev=False)
    p.add_argument("--env", default="point_mass", choices=["point_mass"], help="environment (default: %(default)s)")
    p.add_argument("--policy", nargs="*", default=[], help="policy.pt, checkpoint.pt or run folder(s); none: baselines only")
    p.add_argument("--episodes", type=int, default=64, help="episodes per scenario (default: %(default)s)")
    p.add_argument("--seed", type=seed_arg, default=0, help="episode seed (default: %(default)s)")
    p.add_argument("--json", default=None, help="also write the metrics as JSON to this file (-: to standard output, "
                   "the tables then to standard error)")
    p.add_argument("--config", default=None,
                   help="YAML whose dynamics, adaptation and reward the evaluation uses (default: the first policy's)")
    # envs.scenarios.SCENES, spelled out: importing it (torch, MuJoCo) would take seconds of every --help
    # (tests/test_cli.py checks that the two agree)
    p.add_argument("--scene", default=None, choices=["peg_in_hole", "polishing", "guidance"],
                   help="evaluate on the simulated Panda instead; `a3cqp evaluate --scene S --help` lists its options "
                        "(--trials, --controllers, --record-trial, ...)")
    return p


def main(argv: list[str] | None = None) -> int:
    """CLI entry; returns an exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a == "--scene" or a.startswith("--scene=") for a in argv):
        if _starts_workers(argv):  # their imports now run on another core while this process does its own
            try:
                worker_start.start(PANDA_WORKER_IMPORTS)
            except ValueError as exc:
                return error_exit(exc)
        try:
            panda = importlib.import_module("envs.panda_eval")
        except ModuleNotFoundError as exc:
            if exc.name != "envs.panda_eval":
                raise
            print("error: the Panda scenes are not available in this version", file=sys.stderr)
            return 2
        return int(panda.main(argv) or 0)
    p = _parser()
    args, unknown = p.parse_known_args(argv)
    panda_only = sorted({u.split("=", 1)[0] for u in unknown} & PANDA_ONLY)
    if panda_only:  # the Panda's options given without --scene: say so, not just "unrecognized"
        p.error(f"{', '.join(panda_only)} {'is' if len(panda_only) == 1 else 'are'} for the Panda scenes: add --scene "
                "peg_in_hole|polishing|guidance (the point mass takes --episodes, --seed, --config)")
    if unknown:
        p.error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.episodes < 1:
        p.error(f"--episodes must be >= 1, got {args.episodes}")
    from a3cqp_rl.run_folder import RunFolderError, check_output_path

    try:  # before torch's import and the evaluation, not after them
        if args.json and args.json != "-":  # a3cqp_rl.checkpoint.STDOUT (its module imports torch)
            check_output_path(args.json, "--json")
    except (RunFolderError, ValueError) as exc:
        return error_exit(exc)

    import torch

    torch.set_num_threads(1)
    try:
        from a3cqp_rl.checkpoint import STDOUT
        from a3cqp_rl.config import load_config

        config = load_config(args.config) if args.config else None
        report(args.policy, config=config, episodes=args.episodes, seed=args.seed, json_path=args.json,
               out=sys.stderr if args.json == STDOUT else None)  # stdout: the JSON alone, for a pipe
    except (A3CQPError, FileNotFoundError, ValueError) as exc:
        return error_exit(exc)
    return 0


FLAT = 0.05
"""Rates whose magnitudes all stay below this read as flat in the report: a sign test on ±0.01 says little."""


def _verdict(passed: bool, rates, yes: str, no: str) -> str:  # noqa: ANN001
    """The report's word for a sign test, with "flat" where every rate it tests is within ±FLAT."""
    word = yes if passed else no
    return f"{word}, but flat: |rates| < {FLAT}" if max(abs(float(r)) for r in rates) < FLAT else word


PANDA_ONLY = {"--trials", "--seeds", "--controllers", "--controller-config", "--record-trial", "--out", "--cache",
              "--workers", "--threads", "--cycles", "--set", "--no-park", "--quiet"}
"""`a3cqp evaluate --scene`'s options that the point-mass evaluation does not take (tests/test_cli.py checks it
against both parsers)."""


def _names(paths: Sequence[Path], reserved: Iterable[str] = ()) -> list[str]:
    """Row names: the run folder's name (seed_3, ...), made unique; one that is `reserved` (a baseline's) gets _run."""
    names: list[str] = []
    reserved = set(reserved)
    for path in paths:
        base = path.parent.name if path.name in ("policy.pt", "checkpoint.pt") else path.stem
        base = base or "policy"
        base = f"{base}_run" if base in reserved else base
        name, k = base, 2
        while name in names or name in reserved:
            name, k = f"{base}_{k}", k + 1
        names.append(name)
    return names


PANDA_HINT = ("(A policy that does not raise IK there rarely inserts a peg on the Panda, and one that resists does not "
              "let the operator guide it. The Panda configs name a shipped policy that passes both, in policies/; `make "
              "policy` retrains it. configs/point_mass_a2c_fig5_fd_1e6.yaml chooses among a run's parameters on the Panda "
              "(a2c.select_policy: panda): 15 of its 16 runs on seeds 16-31 insert at least 25 of 26 pegs.)")
"""Printed under the Panda lines when a policy fails either."""
PANDA_CHECK = "Passing both does not yet make a policy insert; check on the Panda: a3cqp evaluate --scene peg_in_hole " \
              "--controllers learned"
"""Printed with the paths of the policies that pass both Panda rules."""


def report(policies: Sequence[str | Path], config: ExperimentConfig | None = None, episodes: int = 64, seed: int = 0,
           json_path: str | Path | None = None, out: TextIO | None = None) -> dict[str, dict[str, bool]]:
    """Evaluate the saved policies with the baselines; print the table, regions and checks (to `out`, default the
    current sys.stdout); return the checks per policy.

    `config` (an ExperimentConfig) gives the dynamics, adaptation and reward; default: the first policy's training
    config (the paper's without a policy).
    """
    from a3cqp_rl.checkpoint import STDOUT, load_checkpoint
    from a3cqp_rl.config import config_from_dict
    from a3cqp_rl.regions import check_fig5_regions, format_regions
    from a3cqp_rl.run_folder import policy_file
    from algorithms.policy import load_agent_policy
    from a3cqp_rl.transfer import FREE_MOTION_E, free_motion_rates, guided_rates, raises_ik, yields
    from envs.point_mass_eval import CHECKS, baseline_policies, behaviour_checks, evaluate

    out = sys.stdout if out is None else out  # looked up per call: a default bound at import outlives a redirect
    paths = [policy_file(p) for p in policies]
    baselines = baseline_policies()
    names = _names(paths, reserved=baselines)
    # each loaded before any episode: a Pendulum policy, say, is named here
    learned = {n: load_agent_policy(path, "the point mass's agent needs") for n, path in zip(names, paths)}
    if config is None and paths:
        saved = load_checkpoint(paths[0], ("config",))["config"]
        config = config_from_dict(saved, str(paths[0]))
    result = evaluate({**learned, **baselines}, episodes=episodes, seed=seed, config=config)
    alpha = ", ".join(f"{a:g}" for a in result.alpha)
    print(f"Closed loop, point mass: {episodes} episodes per scenario (seed {seed}), the same for every policy; "
          f"returns with eq. 30 alpha = ({alpha})", file=out)
    print(result.table(), file=out)
    checks: dict[str, dict[str, bool]] = {}
    regions: dict[str, int] = {}
    for n in learned:
        res = check_fig5_regions(learned[n])
        regions[n] = sum(r.literal for r in res)
        checks[n] = behaviour_checks(result, n, regions[n], against=list(baselines))
        if len(learned) == 1:
            print(format_regions(res), file=out)
    if learned:
        print("\nChecks (regions: all four literal Fig. 5 regions; reaches: >= 90 % of free targets within 2 cm; "
              "bounded: >= 90 % of contact episodes in the force band; yields: |f_ope| <= 1.5 x admittance-only's "
              "+ 0.5 N; best_return: mean return above every baseline's)", file=out)
        print("| policy | " + " | ".join(CHECKS) + " | all |", file=out)
        print("|---|" + "---|" * (len(CHECKS) + 1), file=out)
        for n, c in checks.items():
            print(f"| {n} | " + " | ".join("pass" if c[k] else "FAIL" for k in CHECKS) + f" | {'pass' if all(c.values()) else 'FAIL'} |",
                  file=out)
        if len(learned) > 1:
            print(f"all checks on {sum(all(c.values()) for c in checks.values())} of {len(learned)} policies; per check: "
                  + ", ".join(f"{k} {sum(c[k] for c in checks.values())}" for k in CHECKS), file=out)
    # on the Panda a policy that does not raise w1 at small force-free errors lets the reference go, and one that
    # does not raise w2 and lower f_d under the operator's force pushes back against the hand (docs/panda.md)
    free_rates = {n: free_motion_rates(pol) for n, pol in learned.items()}
    guided_all = {n: guided_rates(pol) for n, pol in learned.items()}
    free_motion = {n: float(r[0]) for n, r in free_rates.items()}
    guided = {n: r[[1, 3]].tolist() for n, r in guided_all.items()}
    raises = {n: raises_ik(r) for n, r in free_rates.items()}
    yielding = {n: yields(r) for n, r in guided_all.items()}
    if learned:
        print(f"\nPanda free motion (|e|/ē {FREE_MOTION_E[0]}-{FREE_MOTION_E[-1]}, no force; a policy must raise "
              "IK's weight over admittance's there to follow the Panda's references, docs/panda.md): "
              + ", ".join(f"{n} ẇ1 {r[0]:+.2f} ẇ2 {r[1]:+.2f} "
                          f"({_verdict(raises[n], r[:2], 'raises IK', 'does not raise IK')})"
                          for n, r in free_rates.items()), file=out)
        print("Panda guidance (|f_ope|/f̄_ope 0.1-0.5; a policy must raise w2 and lower f_d there to let the operator "
              "guide it): " + ", ".join(f"{n} ẇ2 {a:+.2f} ḟd {d:+.2f} "
                                        f"({_verdict(yielding[n], (a, d), 'yields', 'resists')})"
                                        for n, (a, d) in guided.items()), file=out)
        if not (all(raises.values()) and all(yielding.values())):
            print(PANDA_HINT, file=out)
        both = [str(path.parent if path.name == "policy.pt" else path) for n, path in zip(names, paths)
                if raises[n] and yielding[n]]
        if both:  # the two rules are necessary, not sufficient: the Panda itself decides
            print(f"{PANDA_CHECK} --policy {' '.join(both)}", file=out)
    if json_path:
        result.write_json(json_path, {"checks": checks, "literal_regions": regions, "free_motion_w1_rate": free_motion,
                                      "free_motion_w2_rate": {n: float(r[1]) for n, r in free_rates.items()},
                                      "guided_w2_fd_rates": guided,
                                      "policy_files": {n: str(p) for n, p in zip(names, paths)}})
        if str(json_path) != STDOUT:
            print(f"wrote {json_path}", file=out)
    return checks


if __name__ == "__main__":
    raise SystemExit(main())
