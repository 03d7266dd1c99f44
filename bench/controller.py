"""Benchmark: µs per A3CQP control step (kinematics + QP + torque) for N = 1 and N = 64 Panda arms, and the
aggregate real-time factor of the simulated arms (controller + MuJoCo) on this machine.

Closed loop at 1 kHz: every arm gets random softmax task weights switching every 50 ms, a random Cartesian target
and desired forces (no contact). Reported per N (medians over the timed steps):
  ctrl   µs per step for all N arms (kinematics + QP build + a3cqp_rl.qp solve + torque law), and per arm
  qp     the part spent in solve_qp
  sim    MuJoCo (mj_step1 + B(q) + mj_step2 for N MjData, a Python loop)
  RTF    aggregate real-time factor N · Δt / (ctrl + sim)
Peer measured in the same run: the same QPs solved one by one by Clarabel (direct API, no cvxpy) -> "qp speed-up".
Targets (issue 6): N = 1 under 1000 µs per step; N = 64 at least 20x real time in aggregate.

    python bench/controller.py [--quick] [--threads T] [--sizes 1 64]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch

import a3cqp_rl.control.controller as controller_module
from a3cqp_rl.control import A3CQPController
from a3cqp_rl.robot import PandaSim


def clarabel_solve(P: np.ndarray, c: np.ndarray, G: np.ndarray, h: np.ndarray) -> np.ndarray:
    """One QP min ½xᵀPx + cᵀx s.t. Gx ≤ h with Clarabel's direct API (the peer)."""
    import clarabel
    from scipy import sparse

    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solver = clarabel.DefaultSolver(sparse.csc_matrix(np.triu(P)), c, sparse.csc_matrix(G), h,
                                    [clarabel.NonnegativeConeT(G.shape[0])], settings)
    return np.asarray(solver.solve().x)


def run(n: int, steps: int, warmup: int, seed: int = 0) -> dict[str, float]:
    """Closed-loop run of n arms; returns median timings (µs) and the QP peer's time."""
    gen = torch.Generator().manual_seed(seed)
    sim, ctrl = PandaSim(n), A3CQPController(n)
    s = sim.observe()
    pos0, rot0 = ctrl.model.fk(s.q.clone())
    pos_d = pos0 + 0.2 * (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5)
    qp_times: list[float] = []
    qp_problems: list[tuple] = []
    real_solve = controller_module.solve_qp

    def timed_solve(P, q, **kw):  # noqa: ANN001, ANN003, ANN202
        t = time.perf_counter()
        out = real_solve(P, q, **kw)
        qp_times.append(time.perf_counter() - t)
        if len(qp_problems) < 20 and len(qp_times) > warmup:
            qp_problems.append((P[0].numpy().copy(), q[0].numpy().copy(), kw["G"][0].numpy().copy(),
                                kw["h"][0].numpy().copy()))
        return out

    controller_module.solve_qp = timed_solve
    ctrl_t, sim_t = [], []
    try:
        for k in range(warmup + steps):
            if k % 50 == 0:
                w = torch.softmax(6.0 * (torch.rand(n, 6, 3, generator=gen, dtype=torch.float64) - 0.5), -1)
                f_d = 10.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
            t0 = time.perf_counter()
            out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot0, f_env=s.f_env)
            t1 = time.perf_counter()
            sim.step(out.tau)
            s = sim.observe()
            t2 = time.perf_counter()
            if k >= warmup:
                ctrl_t.append(t1 - t0)
                sim_t.append(t2 - t1)
    finally:
        controller_module.solve_qp = real_solve
    peer = []
    for prob in qp_problems:
        t = time.perf_counter()
        clarabel_solve(*prob)
        peer.append(time.perf_counter() - t)
    med = lambda v: 1e6 * statistics.median(v)  # noqa: E731
    return {"ctrl": med(ctrl_t), "qp": med(qp_times[warmup:]), "sim": med(sim_t),
            "peer_qp_per_arm": med(peer), "fallbacks": ctrl.fallback_count, "dt": sim.dt}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one row per N; returns 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few steps (smoke test)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64], help="numbers of arms N")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(args.threads)
    steps, warmup = (60, 20) if args.quick else (1000, 100)
    print(f"A3CQP controller benchmark: torch {torch.__version__}, {args.threads} thread(s), {steps} timed steps")
    print(f"{'N':>4} {'ctrl µs/step':>13} {'µs/arm':>8} {'qp µs':>8} {'sim µs':>8} {'RTF':>7} "
          f"{'Clarabel µs/arm':>16} {'qp speed-up':>12} {'target':>22}")
    for n in args.sizes:
        r = run(n, steps, warmup)
        rtf = n * r["dt"] * 1e6 / (r["ctrl"] + r["sim"])
        speedup = r["peer_qp_per_arm"] * n / r["qp"]
        if n == 1:
            target = f"<1000 µs: {'met' if r['ctrl'] < 1000 else 'NOT met'}"
        else:
            target = f">=20x RT: {'met' if rtf >= 20 else 'NOT met'}"
        print(f"{n:>4} {r['ctrl']:>13.0f} {r['ctrl'] / n:>8.1f} {r['qp']:>8.0f} {r['sim']:>8.0f} {rtf:>6.2f}x "
              f"{r['peer_qp_per_arm']:>16.0f} {speedup:>11.2f}x {target:>22}"
              + (f"  ({r['fallbacks']} fallbacks)" if r["fallbacks"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
