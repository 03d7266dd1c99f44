"""CPU time of the C A2C iteration's trainings: the GA's trial (configs/ga_point_mass.yaml, 4 envs, 1e6 steps) at
n = 1, 4 and 32, and the steps/s of `make train`'s config (configs/point_mass_a2c_default.yaml, shortened).

CPU seconds (this process's user + system time around `train`) do not depend on what else runs on the machine;
wall-clock steps/s do. Medians of `--repeats` runs, one after the other in this process (torch with one thread, as
a GA worker).

Usage: python bench/a2c_cpu.py [--repeats 3] [--steps 1000000] [--default-steps 4000000] [--only ga|default]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(_ROOT))


def _config(path: str, overrides: dict):
    from a3cqp_rl.config import load_config

    return load_config(_ROOT / "configs" / path, overrides)


def _run(cfg, steps: int) -> tuple[float, float, float]:
    """(CPU s, wall s, steps/s) of one training."""
    from algorithms.a2c import train

    c0, w0 = time.process_time(), time.perf_counter()
    res = train(cfg, None, total_steps=steps)
    return time.process_time() - c0, time.perf_counter() - w0, res.steps_per_second


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--steps", type=int, default=1_000_000, help="steps per GA-trial training")
    p.add_argument("--default-steps", type=int, default=4_000_000, help="steps of the make-train config run")
    p.add_argument("--n", type=int, nargs="+", default=[1, 4, 32], help="n_steps values of the GA trial")
    p.add_argument("--only", choices=("ga", "default"), default=None)
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    if args.only != "default":
        for n in args.n:
            cfg = _config("ga_point_mass.yaml", {"a2c": {"n_steps": n, "region_checks": 0}})
            runs = [_run(cfg, args.steps) for _ in range(args.repeats)]
            cpu, wall = statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)
            print(f"GA trial n = {n:2d}: {cpu:6.2f} CPU s, {wall:6.2f} wall s per {args.steps:,} steps "
                  f"({args.steps / cpu:,.0f} steps per CPU s); runs {[round(r[0], 2) for r in runs]}")
    if args.only != "ga":
        cfg = _config("point_mass_a2c_default.yaml", {})
        runs = [_run(cfg, args.default_steps) for _ in range(args.repeats)]
        cpu, sps = statistics.median(r[0] for r in runs), statistics.median(r[2] for r in runs)
        print(f"make train config: {sps:,.0f} steps/s (wall), {args.default_steps / cpu:,.0f} steps per CPU s over "
              f"{args.default_steps:,} steps; projected {2e7 / sps:.0f} s for its 2e7 steps; runs "
              f"{[round(r[2]) for r in runs]}")
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
