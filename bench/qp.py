"""Benchmark: batched QP solves, a3cqp_rl.qp vs DAQP, quadprog, PIQP, cvxpylayers, qpth, ProxSuite and OSQP on the same QPs.

Instances: `random_qp_batch` (n = 13 variables, m = 30 inequality rows, the controller's size;
30-50 % of instances have active constraints).  For every solver and batch size B it prints the
median over repeats (timed round-robin across solvers, so load changes on a shared machine hit
all of them alike) of µs per QP for the forward solve and for forward + backward (gradient of
Σ w·x with respect to all QP data, where the peer supports it), and the max |x − x_ref| against
cvxpy + Clarabel (tol 1e-12).  Ratios are computed against peers measured in the same run only.
DAQP, quadprog and PIQP are called once per instance from Python on numpy arrays prepared beforehand,
as a user of those packages would call them (`pip install .[bench]`).

    python bench/qp.py [--quick] [--threads T] [--batches 1 64 1024] [--spread 0.35] [--clock cpu]
    python bench/qp.py --check [--sweep 30]
    python bench/qp.py --blocks [--clock cpu]      # B = 1, each variant in blocks of 100 consecutive calls

--clock cpu times with this thread's CPU time instead of wall time: on a machine shared with other jobs a 2 ms
sample (B = 1024) that waits one 4 ms scheduler tick for a core reads 3x slower, and medians of wall time then
measure the load (the peers here run in this thread: threads = 1).

--check: instead of timings, the statuses: every problem of `a3cqp_rl.qp.problems` (other projects' test
problems and the failure families) alone and in a mixed batch on each route, and `--sweep` random members of
each random family per route, against cvxpy + Clarabel; a table per family (ok, silent wrong, other status).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

# The checkout this file is in, ahead of an installed copy (`python bench/qp.py` puts bench/ first on the path, and
# an editable install elsewhere would otherwise be what is measured).
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from a3cqp_rl.cli import help_summary
from a3cqp_rl.qp import qp_vjp, solve_qp  # noqa: E402
from a3cqp_rl.qp.random_qp import RandomQP, clarabel_reference, random_qp_batch  # noqa: E402

N_VARS, N_ROWS = 13, 30


@dataclass
class Row:
    """One solver at one batch size: µs/QP (median), accuracy, notes."""

    solver: str
    batch: int
    fwd_us: float | None = None
    fwd_bwd_us: float | None = None
    max_err: float | None = None
    notes: list[str] = field(default_factory=list)


def _weights(qp: RandomQP) -> torch.Tensor:
    return torch.linspace(-1.0, 1.0, qp.q.shape[1], dtype=qp.q.dtype).expand_as(qp.q)


# ------------------------------------------------------------------------------------------------
# Solvers: each returns (forward fn -> x tensor, forward+backward fn or None)
# ------------------------------------------------------------------------------------------------


def ours(qp: RandomQP, warm: bool = False, vjp: bool = False):
    """a3cqp_rl.qp.solve_qp (cold, or warm-started from the solution of the same batch); backward by autograd, or
    with `vjp` by `qp_vjp` (the same gradients of Σ w·x with respect to P, q, G, h, without an autograd graph)."""
    sol0 = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h) if warm else None

    def fwd():
        return solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, warm_start=sol0).x

    w = _weights(qp).contiguous()

    if vjp:
        def fwd_vjp():
            sol = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, warm_start=sol0)
            g = qp_vjp(sol, w)
            g.P, g.q, g.G, g.h  # noqa: B018 (every gradient made into a tensor, as autograd's .grad are)
            return sol.x

        return fwd, fwd_vjp

    def fwd_bwd():
        leaves = [t.detach().clone().requires_grad_() for t in (qp.P, qp.q, qp.G, qp.h)]
        x = solve_qp(leaves[0], leaves[1], G=leaves[2], h=leaves[3], warm_start=sol0).x
        (x * w).sum().backward()
        return x

    return fwd, fwd_bwd


def qpth_solver(qp: RandomQP):
    """qpth (OptNet) batched PDIPM, eps 1e-12."""
    from qpth.qp import QPFunction

    e = torch.empty(0, dtype=qp.q.dtype)
    w = _weights(qp)

    def fwd():
        return QPFunction(verbose=-1, eps=1e-12, maxIter=50)(qp.P, qp.q, qp.G, qp.h, e, e)

    def fwd_bwd():
        leaves = [t.detach().clone().requires_grad_() for t in (qp.P, qp.q, qp.G, qp.h)]
        x = QPFunction(verbose=-1, eps=1e-12, maxIter=50)(*leaves, e, e)
        (x * w).sum().backward()
        return x

    return fwd, fwd_bwd


def proxsuite_torch(qp: RandomQP):
    """proxsuite.torch QPFunction (dense ProxQP per instance, OpenMP over the batch), eps 1e-9."""
    from proxsuite.torch.qplayer import QPFunction

    B = qp.q.shape[0]
    e = torch.empty(0, dtype=qp.q.dtype)
    lower = torch.full_like(qp.h, -1e20)
    w = _weights(qp)
    f = QPFunction(eps=1e-9, omp_parallel=True)

    def fwd():
        return f(qp.P, qp.q, e, e, qp.G, lower, qp.h)[0]

    def fwd_bwd():
        leaves = [t.detach().clone().requires_grad_() for t in (qp.P, qp.q, qp.G, qp.h)]
        x = f(leaves[0], leaves[1], e, e, leaves[2], lower, leaves[3])[0]
        (x * w).sum().backward()
        return x

    del B
    return fwd, fwd_bwd


def proxsuite_parallel(qp: RandomQP, threads: int):
    """ProxSuite dense BatchQP + solve_in_parallel (forward only), including setup from numpy."""
    from proxsuite import proxqp

    P, q, G, h = (t.numpy() for t in (qp.P, qp.q, qp.G, qp.h))
    B, n = q.shape
    m = G.shape[1]
    lower = np.full(m, -1e20)

    def fwd():
        batch = proxqp.dense.BatchQP(B)
        for i in range(B):
            sub = batch.init_qp_in_place(n, 0, m)
            sub.settings.eps_abs = 1e-9
            sub.settings.eps_rel = 0.0
            sub.init(P[i], q[i], None, None, G[i], lower, h[i])
        proxqp.dense.solve_in_parallel(batch, threads)
        return torch.as_tensor(np.stack([batch.get(i).results.x for i in range(B)]))

    return fwd, None


def daqp_solver(qp: RandomQP):
    """DAQP (dual active set, C), one `daqp.solve` call per instance on numpy arrays, forward only."""
    import daqp

    P, q, G, h = (np.ascontiguousarray(t.numpy()) for t in (qp.P, qp.q, qp.G, qp.h))
    B, n = q.shape
    lower = np.full(G.shape[1], -1e30)

    def fwd():
        xs = np.empty((B, n))
        for i in range(B):
            x, _f, flag, _info = daqp.solve(P[i], q[i], G[i], h[i], lower)
            if flag < 1:
                raise RuntimeError(f"daqp exitflag {flag}")
            xs[i] = x
        return torch.as_tensor(xs)

    return fwd, None


def quadprog_solver(qp: RandomQP):
    """quadprog (Goldfarb-Idnani, Fortran), one `quadprog.solve_qp` call per instance, forward only."""
    import quadprog

    P, q, G, h = (t.numpy() for t in (qp.P, qp.q, qp.G, qp.h))
    B, n = q.shape
    # quadprog's form: min ½xᵀPx − aᵀx s.t. Cᵀx ≥ b, C of shape (n, m): prepared once, as a user would.
    a, C, bq = [np.ascontiguousarray(-q[i]) for i in range(B)], [np.ascontiguousarray(-G[i].T) for i in range(B)], [np.ascontiguousarray(-h[i]) for i in range(B)]
    Ps = [np.ascontiguousarray(P[i]) for i in range(B)]

    def fwd():
        xs = np.empty((B, n))
        for i in range(B):
            xs[i] = quadprog.solve_qp(Ps[i], a[i], C[i], bq[i])[0]
        return torch.as_tensor(xs)

    return fwd, None


def piqp_solver(qp: RandomQP):
    """PIQP dense (proximal interior point, C++), one setup + solve per instance, eps 1e-9, forward only."""
    import piqp

    P, q, G, h = (t.numpy() for t in (qp.P, qp.q, qp.G, qp.h))
    B, n = q.shape
    Ps, Gs = [np.asfortranarray(P[i]) for i in range(B)], [np.asfortranarray(G[i]) for i in range(B)]

    def fwd():
        xs = np.empty((B, n))
        for i in range(B):
            s = piqp.DenseSolver()
            s.settings.eps_abs, s.settings.eps_rel = 1e-9, 0.0
            s.setup(Ps[i], q[i], None, None, Gs[i], None, h[i])
            s.solve()
            xs[i] = s.result.x
        return torch.as_tensor(xs)

    return fwd, None


@contextlib.contextmanager
def _quiet_c_stdout():
    """Silence prints from C extensions (OSQP's polish messages) by pointing fd 1 at /dev/null."""
    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def osqp_solver(qp: RandomQP):
    """OSQP 1.x, one setup + solve per instance (eps 1e-9, polish), forward only."""
    import osqp
    import scipy.sparse as sp

    P, q, G, h = (t.numpy() for t in (qp.P, qp.q, qp.G, qp.h))
    B, n = q.shape
    lower = np.full(G.shape[1], -np.inf)
    Ps = [sp.csc_matrix(np.triu(P[i])) for i in range(B)]
    Gs = [sp.csc_matrix(G[i]) for i in range(B)]

    def fwd():
        xs = np.empty((B, n))
        with _quiet_c_stdout():
            for i in range(B):
                s = osqp.OSQP()
                s.setup(Ps[i], q[i], Gs[i], lower, h[i], eps_abs=1e-9, eps_rel=0.0, polishing=True, verbose=False, max_iter=20000)
                xs[i] = s.solve().x
        return torch.as_tensor(xs)

    return fwd, None


def cvxpylayers_solver(qp: RandomQP):
    """cvxpylayers 1.x CvxpyLayer at its default solver settings."""
    import cvxpy as cp
    from cvxpylayers.torch import CvxpyLayer

    n, m = qp.q.shape[1], qp.G.shape[1]
    x = cp.Variable(n)
    Lt, qv, Gp, hp = cp.Parameter((n, n)), cp.Parameter(n), cp.Parameter((m, n)), cp.Parameter(m)
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(Lt @ x) + qv @ x), [Gp @ x <= hp])
    layer = CvxpyLayer(prob, parameters=[Lt, qv, Gp, hp], variables=[x])
    Lt_val = torch.linalg.cholesky(qp.P).mT.contiguous()
    w = _weights(qp)

    def fwd():
        return layer(Lt_val, qp.q, qp.G, qp.h)[0]

    def fwd_bwd():
        leaves = [t.detach().clone().requires_grad_() for t in (Lt_val, qp.q, qp.G, qp.h)]
        xv = layer(*leaves)[0]
        (xv * w).sum().backward()
        return xv

    return fwd, fwd_bwd


# ------------------------------------------------------------------------------------------------


def _prepare(name: str, make: Callable, qp: RandomQP, x_ref: torch.Tensor) -> tuple[Row, Callable | None, Callable | None]:
    """Build one solver's closures, run it once (warm-up) and record its accuracy; failures are noted."""
    row = Row(name, qp.q.shape[0])
    try:
        fwd, fwd_bwd = make(qp)
        x = fwd()
        row.max_err = float((x.detach().double() - x_ref).abs().nan_to_num(nan=float("inf")).max())
        if fwd_bwd is not None:
            fwd_bwd()
        return row, fwd, fwd_bwd
    except ImportError as exc:
        row.notes.append(f"skipped: not installed ({exc.name})")
    except Exception as exc:  # a peer failing must not stop the benchmark
        row.notes.append(f"failed: {type(exc).__name__}: {str(exc)[:120]}")
    return row, None, None


def _inner_calls(fn: Callable | None, batch: int) -> int:
    """Calls per timing sample: enough for ~0.5 ms, so that µs-scale B = 1 solves are not timer noise, and short
    enough that most samples fall between two preemptions on a shared machine (the median then ignores them)."""
    if fn is None:
        return 1
    t0 = time.perf_counter()
    fn()
    dt = time.perf_counter() - t0
    return max(1, min(500, int(5e-4 / max(dt, 1e-7))))


_clock = time.perf_counter


def _time_interleaved(jobs: list[tuple[Row, Callable | None, Callable | None, int]]) -> None:
    """Median µs/QP of every solver, timed round-robin so load changes hit all solvers alike."""
    samples: dict[tuple[int, str], list[float]] = {}
    inner = {(k, kind): _inner_calls(fn, row.batch)
             for k, (row, fwd, fwd_bwd, _r) in enumerate(jobs) for kind, fn in (("fwd", fwd), ("fwd_bwd", fwd_bwd))}
    for rep in range(max(j[3] for j in jobs)):
        for k, (row, fwd, fwd_bwd, repeats) in enumerate(jobs):
            if rep >= repeats:
                continue
            for kind, fn in (("fwd", fwd), ("fwd_bwd", fwd_bwd)):
                if fn is None:
                    continue
                calls = inner[(k, kind)]
                fn()  # untimed: every solver starts its sample with warm caches, whoever ran before it
                t0 = _clock()
                for _ in range(calls):
                    fn()
                samples.setdefault((k, kind), []).append((_clock() - t0) / calls / row.batch * 1e6)
    for k, (row, *_rest) in enumerate(jobs):
        row.fwd_us = statistics.median(samples[(k, "fwd")]) if (k, "fwd") in samples else None
        row.fwd_bwd_us = statistics.median(samples[(k, "fwd_bwd")]) if (k, "fwd_bwd") in samples else None


def _time_in_child(name: str, make: Callable, qp: RandomQP, x_ref: torch.Tensor, repeats: int) -> Row:
    """Prepare and time one solver in a forked child process.

    ProxSuite's OpenMP batch solves (BatchQP + solve_in_parallel, proxsuite.torch with omp_parallel) leave the
    process that ran them 2-4x slower for other solvers timed after them (measured 2026-11-24: a3cqp_rl's C route,
    until some other library's work happened to undo it), so they run apart and the others are timed undisturbed."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe()

    def work() -> None:
        row, fwd, fwd_bwd = _prepare(name, make, qp, x_ref)
        if fwd is not None:
            _time_interleaved([(row, fwd, fwd_bwd, repeats)])
        child.send(row)

    proc = ctx.Process(target=work)
    proc.start()
    row = parent.recv() if parent.poll(600) else Row(name, qp.q.shape[0], notes=["failed: no result from the child"])
    proc.join(10)
    return row


def _fmt(v: float | None, spec: str) -> str:
    return format(v, spec) if v is not None else "-"


def _verdict(p, ref, status: int, x: np.ndarray) -> str:  # noqa: ANN001
    """ok / silent wrong / other status, against the reference (status, x, value)."""
    from a3cqp_rl.qp import QPStatus
    from a3cqp_rl.qp.problems import max_violation, objective

    st_ref, _, f_ref = ref
    if status != st_ref:
        return "silent wrong" if status == QPStatus.SOLVED else f"{QPStatus(status).name} (reference {st_ref.name})"
    if status != QPStatus.SOLVED:
        return "ok"
    f = objective(p, x)
    ok = np.isfinite(f) and abs(f - f_ref) <= 1e-6 * (1 + abs(f_ref)) and max_violation(p, x) <= 1e-6
    return "ok" if ok else "silent wrong"


def check(sweep: int) -> int:
    """Statuses of the peer problems and of random family members on each route (see the module docstring)."""
    import collections

    from a3cqp_rl.qp import native
    from a3cqp_rl.qp.problems import RANDOM_FAMILIES, companion, peer_problems, random_problem, reference

    routes = ["c", "torch"] if native.load() is not None else ["torch"]

    def run(args, route):  # noqa: ANN001, ANN202
        return solve_qp(*(None if a is None else torch.as_tensor(np.asarray(a)) for a in args), backend=route)

    def stacked(ps):  # noqa: ANN001, ANN202
        return [None if ps[0].args()[k] is None else np.stack([p.args()[k] for p in ps]) for k in range(8)]

    def table(title: str, tab: dict) -> None:
        print(f"\n{title}\n| family | runs | ok | silent wrong | other status |\n|---|---:|---:|---:|---:|")
        for fam, c in tab.items():
            other = sum(v for k, v in c.items() if k not in ("ok", "silent wrong"))
            print(f"| {fam} | {sum(c.values())} | {c['ok']} | {c['silent wrong']} | {other} |")

    tab = collections.defaultdict(collections.Counter)
    for p in peer_problems():
        ref = reference(p)
        for route in routes:
            alone = run(p.args(), route)
            c = companion(p)
            batch = run(stacked([p, c, p]), route)
            verdicts = [_verdict(p, ref, int(alone.status[0]), alone.x[0].numpy()),
                        _verdict(p, ref, int(batch.status[0]), batch.x[0].numpy())]
            if _verdict(c, reference(c), int(batch.status[1]), batch.x[1].numpy()) != "ok":
                verdicts[1] = "silent wrong"  # a neighbour's answer changed
            for v in verdicts:
                tab[p.family][v if v in ("ok", "silent wrong") else "other"] += 1
                if v != "ok":
                    print(f"  {p.family}: {p.name} [{route}]: {v}")
    table(f"Peer problems ({len(peer_problems())}), routes {routes}, alone and in a mixed batch:", tab)
    if sweep:
        tab = collections.defaultdict(collections.Counter)
        for fam in RANDOM_FAMILIES:
            rng = np.random.default_rng(12345)
            for _ in range(sweep):
                p = random_problem(fam, rng)
                ref = reference(p)
                for route in routes:
                    sol = run(p.args(), route)
                    v = _verdict(p, ref, int(sol.status[0]), sol.x[0].numpy())
                    tab[fam][v if v in ("ok", "silent wrong") else v] += 1
        table(f"Random family members ({sweep} per family and route, seed 12345), routes {routes}:", tab)
        for fam, c in tab.items():
            others = {k: v for k, v in c.items() if k not in ("ok", "silent wrong")}
            if others:
                print(f"  {fam}: {others}")
    return 0


def blocks(repeats: int = 21, calls: int = 100) -> int:
    """B = 1 timed in blocks of `calls` consecutive calls per variant (medians over `repeats` rounds; CPU clock).

    The round robin of `main` runs each solver right after the others, which at B = 1 costs every one of them
    cache and branch-predictor warmth (its medians move by 1-2 µs with the position in the round); here each
    variant runs alone for its block, as in a control loop that calls one solver again and again."""
    import daqp

    qp = random_qp_batch(1, N_VARS, N_ROWS, seed=1001)
    w = _weights(qp).contiguous()
    P, q, G, h = qp.P, qp.q, qp.G, qp.h
    H, f, C, bu = (np.ascontiguousarray(t[0].numpy()) for t in (P, q, G, h))
    bl, sense = np.full(N_ROWS, -1e30), np.zeros(N_ROWS, dtype=np.int32)

    def autograd_harness(solve: Callable) -> Callable:
        def run() -> None:
            leaves = [t.detach().clone().requires_grad_() for t in (P, q, G, h)]
            (solve(*leaves) * w).sum().backward()
        return run

    def fwd_vjp() -> None:
        g = qp_vjp(solve_qp(P, q, G=G, h=h), w)
        g.P, g.q, g.G, g.h  # noqa: B018 (every gradient made into a tensor, as autograd's .grad are)

    variants = {
        "DAQP daqp.solve": lambda: daqp.solve(H, f, C, bu, bl, sense),
        "ours forward (solve_qp(...).x)": lambda: solve_qp(P, q, G=G, h=h).x,
        "ours forward + qp_vjp (P, q, G, h)": fwd_vjp,
        "ours forward + autograd backward": autograd_harness(lambda P_, q_, G_, h_: solve_qp(P_, q_, G=G_, h=h_).x),
        "autograd harness alone (x = q · 1)": autograd_harness(lambda P_, q_, G_, h_: q_ * 1.0),
    }
    samples: dict[str, list[float]] = {k: [] for k in variants}
    for fn in variants.values():
        fn()
    for _ in range(repeats):
        for name, fn in variants.items():
            t0 = _clock()
            for _ in range(calls):
                fn()
            samples[name].append((_clock() - t0) / calls * 1e6)
    daqp_us = statistics.median(samples["DAQP daqp.solve"])
    print(f"B = 1 in blocks of {calls} calls, medians of {repeats} rounds, {'cpu' if _clock is time.thread_time else 'wall'} clock:")
    for name, v in samples.items():
        us = statistics.median(v)
        print(f"  {name:38s} {us:7.1f} µs   {us / daqp_us:5.2f}x DAQP")
    med = {k: statistics.median(v) / daqp_us for k, v in samples.items()}
    print("Targets (our time / DAQP's):")
    for label, key, limit in (("B = 1 forward", "ours forward (solve_qp(...).x)", 1.5),
                              ("B = 1 forward + qp_vjp", "ours forward + qp_vjp (P, q, G, h)", 3.0),
                              ("B = 1 forward + autograd", "ours forward + autograd backward", 3.0)):
        print(f"  {label:26s} {med[key]:5.2f}x  (≤ {limit}x: {'met' if med[key] <= limit else 'missed'})")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the QP benchmark and print the table and ratios (or, with --check, the status tables); returns 0."""
    parser = argparse.ArgumentParser(prog="a3cqp bench qp", description=help_summary(__doc__))
    parser.add_argument("--quick", action="store_true", help="B = 1, 64 only and fewer repeats")
    parser.add_argument("--batches", type=int, nargs="+", default=None, help="batch sizes (default 1 64 1024)")
    parser.add_argument("--threads", type=int, default=1, help="torch / ProxSuite threads (default 1: on a shared 2-core box, OpenMP batch loops with 2 threads stall for ms)")
    parser.add_argument("--skip", nargs="*", default=[], help="solvers to skip (daqp quadprog piqp cvxpylayers qpth proxsuite osqp)")
    parser.add_argument("--spread", type=float, default=0.015, help="instance generator spread (0.35: many active rows)")
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall", help="wall time or this thread's CPU time")
    parser.add_argument("--check", action="store_true", help="status tables of the peer problems instead of timings")
    parser.add_argument("--sweep", type=int, default=30, help="with --check: random members per family and route")
    parser.add_argument("--blocks", action="store_true", help="B = 1 only, each variant timed in blocks of consecutive calls")
    args = parser.parse_args(argv)
    if args.check:
        return check(args.sweep)
    global _clock
    _clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    if args.blocks:
        torch.set_num_threads(args.threads or 1)
        return blocks(5 if args.quick else 21)
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    batches = args.batches or ([1, 64] if args.quick else [1, 64, 1024])
    print(f"QP benchmark: n={N_VARS}, m={N_ROWS}, float64, torch {torch.__version__}, {threads} thread(s), {args.clock} clock",
          flush=True)

    peers: list[tuple[str, Callable, str]] = [
        ("a3cqp_rl.qp (cold)", lambda qp: ours(qp), "ours"),
        ("a3cqp_rl.qp (warm)", lambda qp: ours(qp, warm=True), "ours"),
        ("a3cqp_rl.qp (cold, qp_vjp)", lambda qp: ours(qp, vjp=True), "ours"),
        ("daqp (loop)", daqp_solver, "daqp"),
        ("quadprog (loop)", quadprog_solver, "quadprog"),
        ("piqp (loop)", piqp_solver, "piqp"),
        ("proxsuite.torch", proxsuite_torch, "proxsuite"),
        ("proxsuite parallel", lambda qp: proxsuite_parallel(qp, threads), "proxsuite"),
        ("qpth", qpth_solver, "qpth"),
        ("osqp (loop)", osqp_solver, "osqp"),
        ("cvxpylayers (defaults)", cvxpylayers_solver, "cvxpylayers"),
    ]
    import importlib.util

    missing = sorted({key for _n, _m, key in peers if key != "ours" and key not in args.skip
                      and importlib.util.find_spec(key) is None})
    if missing:  # said first: the ratios below are against the peers that did run
        print(f"peers not installed, skipped: {', '.join(missing)} (pip install -e '.[bench]'; qpth separately: it "
              "requires numpy < 2)", flush=True)
    rows: list[Row] = []
    for B in batches:
        qp = random_qp_batch(B, N_VARS, N_ROWS, spread=args.spread, seed=1000 + B)
        x_ref, statuses = clarabel_reference(qp)
        n_active = int((((qp.G @ x_ref.unsqueeze(-1)).squeeze(-1) - qp.h) > -1e-7).any(-1).sum())
        print(f"\nB={B}: {n_active}/{B} instances with active constraints; Clarabel statuses {sorted(set(statuses))}", flush=True)
        jobs, isolated = [], []
        for name, make, key in peers:
            if key in args.skip:
                continue
            slow = key in ("cvxpylayers", "osqp")
            if slow and B >= 1024 and args.quick:
                continue
            repeats = (5 if args.quick else 31) if B <= 64 else (3 if slow else 21)
            if key == "proxsuite":  # OpenMP batch solves that slow this process down afterwards: see _time_in_child
                isolated.append((name, make))
                continue
            row, fwd, fwd_bwd = _prepare(name, make, qp, x_ref)
            jobs.append((row, fwd, fwd_bwd, repeats))
        _time_interleaved(jobs)
        for name, make in isolated:
            jobs.append((_time_in_child(name, make, qp, x_ref, repeats), None, None, 0))
        for row, *_rest in jobs:
            rows.append(row)
            print(
                f"  {row.solver:24s} fwd {_fmt(row.fwd_us, '10.1f')} µs/QP   fwd+bwd {_fmt(row.fwd_bwd_us, '10.1f')} µs/QP"
                f"   max|x-x_ref| {_fmt(row.max_err, '.1e')}  {' '.join(row.notes)}",
                flush=True,
            )

    print("\n| solver | B | forward µs/QP | forward+backward µs/QP | max abs error vs Clarabel |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r.solver} | {r.batch} | {_fmt(r.fwd_us, '.1f')} | {_fmt(r.fwd_bwd_us, '.1f')} | {_fmt(r.max_err, '.1e')} |")

    print("\nRatios (fastest peer time / our cold time; > 1 means we are faster; peers at ≤ 1e-6 error only):")
    for B in batches:
        mine = next((r for r in rows if r.batch == B and r.solver.startswith("a3cqp_rl.qp (cold)")), None)
        warm = next((r for r in rows if r.batch == B and r.solver.startswith("a3cqp_rl.qp (warm)")), None)
        others = [r for r in rows if r.batch == B and not r.solver.startswith("a3cqp_rl") and r.fwd_us is not None]
        accurate = [r for r in others if r.max_err is not None and r.max_err <= 1e-6]
        for kind, attr in (("forward", "fwd_us"), ("forward+backward", "fwd_bwd_us")):
            for label, pool in (("any accuracy", others), ("accurate", accurate)):
                cands = [r for r in pool if getattr(r, attr) is not None]
                if mine is None or getattr(mine, attr) is None:
                    continue
                if not cands:  # said, not left out: a missing line would read as nothing to compare
                    print(f"  B={B:5d} {kind:17s} no peer ({label}) ran: none installed or none within 1e-6")
                    continue
                best = min(cands, key=lambda r: getattr(r, attr))
                ratio = getattr(best, attr) / getattr(mine, attr)
                extra = f"; warm-started: {getattr(best, attr) / getattr(warm, attr):.2f}x" if warm and getattr(warm, attr) else ""
                print(f"  B={B:5d} {kind:17s} vs fastest peer ({label}: {best.solver}, {getattr(best, attr):.1f} µs): {ratio:.2f}x{extra}")
    # Targets against DAQP called from Python (the fastest small dense solver a user would pick):
    # B = 1 forward ≤ 1.5x its time, forward+backward ≤ 3x, B = 1024 forward at least 3x faster.
    if not any(r.solver == "daqp (loop)" and r.fwd_us for r in rows):
        print("\nAgainst DAQP and its targets: DAQP did not run (not installed? pip install -e '.[bench]')")
        return 0
    print("\nAgainst DAQP (loop), same instances, same run (our time / DAQP's; < 1 means we are faster):")
    for B in batches:
        dq = next((r for r in rows if r.batch == B and r.solver == "daqp (loop)" and r.fwd_us), None)
        if dq is None:
            continue
        for r in rows:
            if r.batch == B and r.solver.startswith("a3cqp_rl.qp") and r.fwd_us:
                bwd = f", forward+backward {r.fwd_bwd_us / dq.fwd_us:.2f}x" if r.fwd_bwd_us else ""
                print(f"  B={B:5d} {r.solver:20s} forward {r.fwd_us / dq.fwd_us:.2f}x{bwd}  (DAQP {dq.fwd_us:.2f} µs/QP)")
    print("\nTargets (our cold time against DAQP's, same run):")
    for B in batches:
        dq = next((r for r in rows if r.batch == B and r.solver == "daqp (loop)" and r.fwd_us), None)
        cold = next((r for r in rows if r.batch == B and r.solver == "a3cqp_rl.qp (cold)" and r.fwd_us), None)
        vjp = next((r for r in rows if r.batch == B and r.solver == "a3cqp_rl.qp (cold, qp_vjp)" and r.fwd_bwd_us), None)
        if dq is None or cold is None:
            continue
        if B == 1:
            checks = [("B = 1 forward", cold.fwd_us / dq.fwd_us, "≤ 1.5x", cold.fwd_us / dq.fwd_us <= 1.5)]
            if cold.fwd_bwd_us:
                checks.append(("B = 1 forward + autograd", cold.fwd_bwd_us / dq.fwd_us, "≤ 3x", cold.fwd_bwd_us / dq.fwd_us <= 3))
            if vjp is not None:
                checks.append(("B = 1 forward + qp_vjp", vjp.fwd_bwd_us / dq.fwd_us, "≤ 3x", vjp.fwd_bwd_us / dq.fwd_us <= 3))
        elif B == 1024:
            checks = [("B = 1024 forward, DAQP / ours", dq.fwd_us / cold.fwd_us, "≥ 3x", dq.fwd_us / cold.fwd_us >= 3)]
        else:
            continue
        for label, v, limit, ok in checks:
            print(f"  {label:30s} {v:5.2f}x  ({limit}: {'met' if ok else 'missed'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
