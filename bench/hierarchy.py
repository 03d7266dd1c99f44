"""Benchmark: µs per A3CQP control step with strict priority levels (a cascade of QPs, paper 002 eq. 2) against the
single weighted QP, for N = 1 and N = 64 Panda arms.

Closed loop at 1 kHz as bench/controller.py: random softmax task weights switching every 50 ms, a random Cartesian
target, desired forces, no contact; MuJoCo's site kinematics. Rows per N (medians over the timed steps):
  default     levels=None, backend auto: today's controller (the C step on CPU)
  1 level     levels=None, backend python: the same QP through the task/limit objects (what the cascade builds on)
  2 levels    (ik + cartesian_regularizer) / (ac + fc + jc)
  3 levels    (ik + cartesian_regularizer) / (ac + fc) / (jc)
Columns: ctrl µs per step for all N arms and per arm; asm (context, residuals, level costs, limit rows), qp (solve_qp,
or the cascade: one solve_qp per level plus the null-space projections), rest (input checks, torque law); the ratio
to "default" and to "1 level" measured in the same run.

    python bench/hierarchy.py [--quick] [--sizes 1 64] [--threads T] [--repeats R] [--clock wall|cpu]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from a3cqp_rl.cli import help_summary
from a3cqp_rl.control import A3CQPController, ControllerOptions
from a3cqp_rl.robot import PandaSim
from bench.arm_loop import PartTimer, drive

STACKS = {
    "default": (None, "auto"),
    "1 level": (None, "python"),
    "2 levels": (dict(ik=1, cartesian_regularizer=1, ac=2, fc=2, jc=2), "python"),
    "3 levels": (dict(ik=1, cartesian_regularizer=1, ac=2, fc=2, jc=3), "python"),
}


def run(n: int, levels: dict | None, backend: str, steps: int, warmup: int, seed: int = 0,
        clock=time.perf_counter) -> dict[str, float]:  # noqa: ANN001
    """Closed-loop run of n arms; returns the median µs per step of the whole step and of its parts."""
    sim = PandaSim(n, control_site="tcp")
    ctrl = A3CQPController(n, options=ControllerOptions(backend=backend), levels=levels)
    timer = PartTimer(clock)
    for name, part in (("build_context", "asm"), ("build_qp", "asm"), ("build_levels", "asm"),
                       ("assemble_native", "asm"), ("_solve", "qp"), ("_solve_levels", "qp")):
        timer.wrap(ctrl, name, part)
    rows: dict[str, list[float]] = {"ctrl": [], "asm": [], "qp": []}

    def record(t_ctrl: float, t_sim: float) -> None:
        rows["ctrl"].append(t_ctrl)
        rows["asm"].append(timer.parts["asm"])
        rows["qp"].append(timer.parts["qp"])

    drive(ctrl, sim, steps, warmup, timer, record, seed)
    med = {key: 1e6 * statistics.median(v) for key, v in rows.items()}
    med["rest"] = 1e6 * statistics.median([c - a - q for c, a, q in zip(rows["ctrl"], rows["asm"], rows["qp"])])
    med["fallbacks"] = ctrl.fallback_count
    med["native"] = float(ctrl._native is not None and ctrl.hierarchy.is_flat and backend != "python")
    return med


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one row per (N, stack); returns 0."""
    parser = argparse.ArgumentParser(description=help_summary(__doc__))
    parser.add_argument("--quick", action="store_true", help="few steps (smoke test)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64], help="numbers of arms N")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--repeats", type=int, default=1, help="runs per row; the row shows the median run")
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall", help="wall time or this thread's CPU time")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(args.threads)
    steps, warmup = (60, 20) if args.quick else (1000, 100)
    clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    print(f"A3CQP strict-priority benchmark: torch {torch.__version__}, {args.threads} thread(s), {steps} timed steps, "
          f"{args.clock} clock, median of {args.repeats} run(s)")
    print(f"{'N':>4} {'stack':>9} {'ctrl µs/step':>13} {'µs/arm':>8} {'asm':>6} {'qp':>6} {'rest':>6} "
          f"{'vs default':>11} {'vs 1 level':>11}")
    for n in args.sizes:
        med = {}
        for name, (levels, backend) in STACKS.items():
            runs = sorted((run(n, levels, backend, steps, warmup, clock=clock) for _ in range(args.repeats)),
                          key=lambda r: r["ctrl"])
            med[name] = runs[len(runs) // 2]
        for name, r in med.items():
            label = name + (" (C)" if r["native"] else "")
            print(f"{n:>4} {label:>9} {r['ctrl']:>13.0f} {r['ctrl'] / n:>8.1f} {r['asm']:>6.0f} {r['qp']:>6.0f} "
                  f"{r['rest']:>6.0f} {r['ctrl'] / med['default']['ctrl']:>10.2f}x "
                  f"{r['ctrl'] / med['1 level']['ctrl']:>10.2f}x"
                  + (f"  ({r['fallbacks']} fallbacks)" if r["fallbacks"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
