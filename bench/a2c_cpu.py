"""CPU time of A2C trainings on the C iteration: the GA's trial (configs/ga_point_mass.yaml: Table IV, 4 envs, 1e6
steps) at n = 1, 4 and 32, and the steps/s of `make train`'s config (configs/point_mass_a2c_default.yaml, shortened).

The baseline in the same run: the same training with one C call per update (`FusedRollout.max_updates` held at 1,
how the loop ran before many updates went into one call; same numbers, checked). Runs alternate between the two.
A short training first takes the process's one-time costs (~1.5 s: first imports and calls). CPU seconds (this
process's user + system time around `train`) depend less on the machine's other jobs than wall
time does (though not entirely: a busy sibling core slows this one). Medians of `--repeats` runs, torch with one
thread (as a GA worker).

Usage: python bench/a2c_cpu.py [--repeats 3] [--steps 1000000] [--default-steps 4000000] [--n 1 4 32]
                               [--only ga|default] [--quick]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from a3cqp_rl.cli import help_summary

_ROOT = Path(__file__).resolve().parents[1]
if str(_ROOT) not in sys.path:
    sys.path.insert(0, str(_ROOT))


def _config(path: str, overrides: dict):
    from a3cqp_rl.config import load_config

    return load_config(_ROOT / "configs" / path, overrides)


@contextmanager
def _one_update_per_call(enabled: bool):
    """Hold FusedRollout.max_updates at 1 (the per-update loop) while `enabled`."""
    from algorithms.a2c import FusedRollout

    saved = FusedRollout.max_updates
    if enabled:
        FusedRollout.max_updates = lambda self: 1
    try:
        yield
    finally:
        FusedRollout.max_updates = saved


def _run(cfg, steps: int, per_update: bool) -> tuple[float, float, float, float]:
    """(CPU s, wall s, steps/s, mean of the episode returns) of one training."""
    from algorithms.a2c import train

    with _one_update_per_call(per_update):
        c0, w0 = time.process_time(), time.perf_counter()
        res = train(cfg, None, total_steps=steps)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    returns = res.episode_returns
    return cpu, wall, res.steps_per_second, sum(returns) / max(len(returns), 1)


def _pair(cfg, steps: int, repeats: int) -> dict[str, list[tuple]]:
    """`repeats` runs of each loop shape, alternating; checks they trained the same."""
    runs: dict[str, list[tuple]] = {"batched": [], "per update": []}
    for _ in range(repeats):
        runs["batched"].append(_run(cfg, steps, False))
        runs["per update"].append(_run(cfg, steps, True))
    if runs["batched"][0][3] != runs["per update"][0][3]:
        raise SystemExit(f"the two loops trained differently: {runs['batched'][0][3]} vs {runs['per update'][0][3]}")
    return runs


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--steps", type=int, default=1_000_000, help="steps per GA-trial training")
    p.add_argument("--default-steps", type=int, default=4_000_000, help="steps of the make-train config run")
    p.add_argument("--n", type=int, nargs="+", default=[1, 4, 32], help="n_steps values of the GA trial")
    p.add_argument("--only", choices=("ga", "default"), default=None)
    p.add_argument("--quick", action="store_true", help="1 repeat, 1e5-step trials, 2e5 steps of the default config")
    args = p.parse_args(argv)
    if args.quick:
        args.repeats, args.steps, args.default_steps = 1, 100_000, 204_800
    import torch

    torch.set_num_threads(1)
    print(f"A2C on the C iteration, CPU time per training (median of {args.repeats}); load {_load()}", flush=True)
    _run(_config("ga_point_mass.yaml", {"a2c": {"region_checks": 0}}), 4_000, False)  # the process's one-time costs
    med = statistics.median
    if args.only != "default":
        for n in args.n:
            cfg = _config("ga_point_mass.yaml", {"a2c": {"n_steps": n, "region_checks": 0}})
            runs = _pair(cfg, args.steps, args.repeats)
            new, old = med(r[0] for r in runs["batched"]), med(r[0] for r in runs["per update"])
            print(f"  GA trial n = {n:2d}, {args.steps:,} steps: {new:6.2f} CPU s ({args.steps / new:,.0f} steps per "
                  f"CPU s); one C call per update {old:6.2f} CPU s; {old / new:.2f}x; runs "
                  f"{[round(r[0], 2) for r in runs['batched']]} / {[round(r[0], 2) for r in runs['per update']]}",
                  flush=True)
    if args.only != "ga":
        cfg = _config("point_mass_a2c_default.yaml", {"a2c": {"region_checks": 0}})
        runs = _pair(cfg, args.default_steps, args.repeats)
        for name, rs in runs.items():
            cpu, sps = med(r[0] for r in rs), med(r[2] for r in rs)
            print(f"  make train config ({name}), {args.default_steps:,} steps: {sps:,.0f} steps/s wall, "
                  f"{args.default_steps / cpu:,.0f} steps per CPU s; 2e7 steps: {2e7 / sps:.0f} s at this load, "
                  f"{2e7 * cpu / args.default_steps:.0f} s of CPU", flush=True)
    print(f"  load after: {_load()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
