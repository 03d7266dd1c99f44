"""Point-mass env throughput: natively batched PointMassEnv vs 4 single envs in a TorchRL ParallelEnv.

Prints samples/s (agent steps × envs per second, median of repeats) for
  - PointMassEnv(4) and PointMassEnv(4096) through the TorchRL `rollout` API,
  - the same env's functional step (`envs.point_mass.agent_step`), eager and torch.compile'd with
    auto-reset (`fused_functions`, what the fused trainer runs inside its compiled graph),
  - ParallelEnv(4 × PointMassEnv(1)), the usual way to run 4 envs in TorchRL,
and the ratios against the ParallelEnv baseline, all measured in this run.

Usage: python bench/env_throughput.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time

import torch

from a3cqp_rl.cli import help_summary


def _median_rate(fn, samples_per_call: int, repeats: int) -> float:
    fn()  # warm-up
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(samples_per_call / (time.perf_counter() - t0))
    return statistics.median(rates)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print a table of samples/s and ratios; returns 0."""
    from torchrl.envs import ParallelEnv

    from envs.point_mass import PointMassEnv, agent_step

    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    args = p.parse_args(argv)
    steps, repeats = (50, 3) if args.quick else (200, 5)
    torch.set_num_threads(1)
    rows: list[tuple[str, float]] = []

    for n in (4, 4096):
        env = PointMassEnv(n, seed=0)
        rows.append((f"PointMassEnv({n}) rollout", _median_rate(
            lambda env=env: env.rollout(steps, break_when_any_done=False), steps * n, repeats)))
        env.reset()
        state, sched = env.functional()
        action = torch.zeros(n, 4, dtype=torch.float64)

        def raw(env=env, state=state, sched=sched, action=action):
            s = state
            for _ in range(steps):
                s, _r = agent_step(s, action, sched, env.cfg, env.adapt, env.rew)

        rows.append((f"PointMassEnv({n}) functional step", _median_rate(raw, steps * n, repeats)))
        step_fn, _ = env.fused_functions()
        compiled = torch.compile(step_fn, dynamic=False)
        _, pending, _ = env.fused_inputs()

        def fused(compiled=compiled, state=state, pending=pending, sched=sched, action=action.float()):
            s = state
            for _ in range(steps):
                s = compiled(s, pending, sched, action)[0]

        rows.append((f"PointMassEnv({n}) compiled fused step", _median_rate(fused, steps * n, repeats)))

    penv = ParallelEnv(4, functools.partial(PointMassEnv, 1, seed=0))
    try:
        penv.set_seed(0)
        base = _median_rate(lambda: penv.rollout(steps, break_when_any_done=False), steps * 4, repeats)
    finally:
        penv.close()
    rows.append(("ParallelEnv(4 x PointMassEnv(1))", base))

    print(f"{'configuration':<40} {'samples/s':>12} {'vs ParallelEnv':>15}")
    for name, rate in rows:
        print(f"{name:<40} {rate:>12,.0f} {rate / base:>14.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
