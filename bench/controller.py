"""Benchmark: µs per A3CQP control step (kinematics + QP + torque) for N = 1 and N = 64 Panda arms, and the
aggregate real-time factor of the simulated arms (controller + MuJoCo) on this machine.

Closed loop at 1 kHz: every arm gets random softmax task weights switching every 50 ms, a random Cartesian target
and desired forces (no contact). Reported per N (medians over the timed steps):
  ctrl   µs per step for all N arms (kinematics + QP build + a3cqp_rl.qp solve + torque law), and per arm
  split  of ctrl: kin (torch kinematics; 0 with --kin mujoco, where MuJoCo's own kinematics come with `sim`),
         asm (context, task residuals, limit rows, stacking), qp (solve_qp), rest (input checks, torque law eq. 4-7)
  sim    MuJoCo (one mj_step1 + mj_step2 for all N arms in one MjData; B(q), site Jacobian/J̇ gathered batched)
  RTF    aggregate real-time factor N · Δt / (ctrl + sim)
Peer measured in the same run: the same QPs solved one by one by Clarabel (direct API, no cvxpy) -> "qp speed-up".
Targets: N = 1 under 1000 µs per step; N = 64 at least 20x real time in aggregate.

    python bench/controller.py [--quick] [--threads T] [--sizes 1 64] [--kin mujoco|torch] [--repeats R] [--clock cpu]
                               [--backend both|native|python]

Backends (ControllerOptions.backend): "native" evaluates the default tasks, limits and torque law in C
(control/native); "python" the objects of tasks.py / limits.py (numpy on CPU), the baseline "vs python" is taken
against in the same run.

--clock cpu times with this thread's CPU time instead of wall time: on a machine shared with other jobs it leaves out
the time the process waits for a core (the RTF is then what an unshared core would give).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch

import a3cqp_rl.control.controller as controller_module
from a3cqp_rl.cli import help_summary
from a3cqp_rl.control import A3CQPController, ControllerOptions
from a3cqp_rl.robot import PandaSim
from bench.arm_loop import PartTimer, drive


def clarabel_solve(P: np.ndarray, c: np.ndarray, G: np.ndarray, h: np.ndarray) -> np.ndarray:
    """One QP min ½xᵀPx + cᵀx s.t. Gx ≤ h with Clarabel's direct API (the peer)."""
    import clarabel
    from scipy import sparse

    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(sparse.csc_matrix(np.triu(P)), c, sparse.csc_matrix(G), h,
                                    [clarabel.NonnegativeConeT(G.shape[0])], settings)
    return np.asarray(solver.solve().x)


def run(n: int, steps: int, warmup: int, seed: int = 0, kin_source: str = "mujoco",
        clock=time.perf_counter, backend: str = "auto") -> dict[str, float]:  # noqa: ANN001
    """Closed-loop run of n arms; returns median timings (µs) and the QP peer's time."""
    sim = PandaSim(n, control_site="tcp" if kin_source == "mujoco" else None)
    ctrl = A3CQPController(n, options=ControllerOptions(backend=backend))
    qp_times: list[float] = []
    qp_problems: list[tuple] = []
    real_solve = controller_module.solve_qp

    def timed_solve(P, q, **kw):  # noqa: ANN001, ANN003, ANN202
        t = clock()
        out = real_solve(P, q, **kw)
        qp_times.append(clock() - t)
        if len(qp_problems) < 20 and len(qp_times) > warmup:
            qp_problems.append((P[0].numpy().copy(), q[0].numpy().copy(), kw["G"][0].numpy().copy(),
                                kw["h"][0].numpy().copy()))
        return out

    # the assembly (build_context + build_qp) and the torch kinematics inside step()
    timer = PartTimer(clock)
    for name in ("build_context", "build_qp", "assemble_native"):
        timer.wrap(ctrl, name, "asm")
    timer.wrap(ctrl.model, "kinematics", "kin")
    ctrl_t, sim_t, asm_t, kin_t = [], [], [], []

    def record(t_ctrl: float, t_sim: float) -> None:
        ctrl_t.append(t_ctrl)
        sim_t.append(t_sim)
        asm_t.append(timer.parts["asm"] - timer.parts["kin"])  # kinematics run inside build_context
        kin_t.append(timer.parts["kin"])

    controller_module.solve_qp = timed_solve
    try:
        drive(ctrl, sim, steps, warmup, timer, record, seed)
    finally:
        controller_module.solve_qp = real_solve
    peer = []
    for prob in qp_problems:
        t = clock()
        clarabel_solve(*prob)
        peer.append(clock() - t)
    med = lambda v: 1e6 * statistics.median(v)  # noqa: E731
    rest = [c - a - k - q for c, a, k, q in zip(ctrl_t, asm_t, kin_t, qp_times[warmup:])]
    return {"ctrl": med(ctrl_t), "qp": med(qp_times[warmup:]), "sim": med(sim_t), "asm": med(asm_t),
            "kin": med(kin_t), "rest": med(rest),
            "peer_qp_per_arm": med(peer), "fallbacks": ctrl.fallback_count, "dt": sim.dt}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one row per N; returns 0."""
    parser = argparse.ArgumentParser(description=help_summary(__doc__))
    parser.add_argument("--quick", action="store_true", help="few steps (smoke test)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64], help="numbers of arms N")
    parser.add_argument("--kin", choices=["mujoco", "torch"], default="mujoco",
                        help="site kinematics from PandaSim's MuJoCo step (default) or PandaModel (torch)")
    parser.add_argument("--repeats", type=int, default=1, help="runs per N; the row shows the median run")
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall", help="wall time or this thread's CPU time")
    parser.add_argument("--backend", choices=["both", "native", "python"], default="both",
                        help="controller backend (ControllerOptions.backend); both: native, then the Python objects "
                             "as the in-run baseline")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(args.threads)
    steps, warmup = (60, 20) if args.quick else (1000, 100)
    print(f"A3CQP controller benchmark: torch {torch.__version__}, {args.threads} thread(s), {steps} timed steps, "
          f"kinematics from {args.kin}, {args.clock} clock, median of {args.repeats} run(s)")
    print(f"{'N':>4} {'backend':>8} {'ctrl µs/step':>13} {'µs/arm':>8} {'kin':>6} {'asm':>6} {'qp µs':>7} "
          f"{'rest':>6} {'sim µs':>8} {'RTF':>7} {'vs python':>10} {'Clarabel µs/arm':>16} {'qp speed-up':>12} "
          f"{'target':>22}")
    backends = ["native", "python"] if args.backend == "both" else [args.backend]
    for n in args.sizes:
        clock = time.thread_time if args.clock == "cpu" else time.perf_counter
        medians = {}
        for backend in backends:
            runs = sorted((run(n, steps, warmup, kin_source=args.kin, clock=clock, backend=backend)
                           for _ in range(args.repeats)), key=lambda r: r["ctrl"] + r["sim"])
            medians[backend] = runs[len(runs) // 2]
        for backend in backends:
            r = medians[backend]
            rtf = n * r["dt"] * 1e6 / (r["ctrl"] + r["sim"])
            speedup = r["peer_qp_per_arm"] * n / r["qp"]
            vs = f"{medians['python']['ctrl'] / r['ctrl']:.2f}x" if "python" in medians else "-"
            if n == 1:
                target = f"<1000 µs: {'met' if r['ctrl'] < 1000 else 'NOT met'}"
            else:
                target = f">=20x RT: {'met' if rtf >= 20 else 'NOT met'}"
            print(f"{n:>4} {backend:>8} {r['ctrl']:>13.0f} {r['ctrl'] / n:>8.1f} {r['kin']:>6.0f} {r['asm']:>6.0f} "
                  f"{r['qp']:>7.0f} {r['rest']:>6.0f} {r['sim']:>8.0f} {rtf:>6.2f}x {vs:>10} "
                  f"{r['peer_qp_per_arm']:>16.0f} {speedup:>11.2f}x {target:>22}"
                  + (f"  ({r['fallbacks']} fallbacks)" if r["fallbacks"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
