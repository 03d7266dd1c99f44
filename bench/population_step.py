"""One control step of a PopulationController: the C step (per-robot gains, one C call per level) vs the objects.

N arms on random states (the controller tests' `random_inputs`), random per-robot gains, two populations: "flat"
(every robot one level, tasks randomly off: the single QP) and "strict" (random levels 1-3/off per task: the
cascade, one group per level count). Median ms per step over R repeats of 20 steps, single-threaded torch (as the
NSGA-II objective runs); both backends in the same run, so the ratio is what to read under a shared load.

Usage: python bench/population_step.py [--arms N] [--repeats R] [--quick]   (or `a3cqp bench population`)
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from a3cqp_rl.cli import help_summary

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(_ROOT), str(_ROOT / "tests")]


def main(argv: list[str] | None = None) -> int:
    """Print ms per step for each population and backend, and the ratio."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--arms", type=int, default=16)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--quick", action="store_true", help="3 repeats")
    args = p.parse_args(argv)
    if args.quick:
        args.repeats = 3
    torch.set_num_threads(1)
    logging.disable(logging.WARNING)  # random states make a few robots fall back: not what is timed
    from test_control_native import random_inputs

    from a3cqp_rl.control import ControllerOptions
    from a3cqp_rl.control.population import TASKS, PopulationController, RobotGains

    n = args.arms
    inputs, model = random_inputs(n, seed=3)
    rng = np.random.default_rng(0)
    gains = RobotGains(kp=rng.uniform(20, 600, n), k_theta=rng.uniform(5, 100, n), lambda_d=rng.uniform(1, 20, n),
                       c_d=rng.uniform(1, 30, n), kq=rng.uniform(1, 50, n), jc_weight=10 ** rng.uniform(-1, 1, n),
                       cartesian_regularization=10 ** rng.uniform(-3, -1, n))
    flat = np.minimum(rng.integers(0, 4, (n, len(TASKS))), 1)
    flat[:, 0] = 1
    populations = {"flat": flat, "strict": rng.integers(0, 4, (n, len(TASKS)))}
    print(f"PopulationController.step, {n} arms, median of {args.repeats} x 20 steps; "
          f"load before: {os.getloadavg()[0]:.2f}")
    print("| population | level counts (1/2/3) | objects [ms] | C step [ms] | ratio |\n|---|---|---:|---:|---:|")
    for name, levels in populations.items():
        ms = {}
        for backend in ("python", "native"):
            opt = ControllerOptions(backend=backend, wrench_blend="weighted_sum", cartesian_regularization=1.0)
            pop = PopulationController(n, model=model, options=opt, gains=gains, levels=levels)
            for _ in range(5):
                pop.step(**inputs)
            ts = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                for _ in range(20):
                    pop.step(**inputs)
                ts.append((time.perf_counter() - t0) / 20)
            ms[backend] = 1e3 * statistics.median(ts)
        counts = np.bincount(pop.level_count, minlength=4)[1:].tolist()
        print(f"| {name} | {counts} | {ms['python']:.2f} | {ms['native']:.2f} | {ms['python'] / ms['native']:.2f}x |")
    print(f"load after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
