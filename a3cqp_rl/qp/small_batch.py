"""Small-batch CPU fast path: a dual active set (Goldfarb-Idnani) and the adjoint solve, per instance in numpy.

Why numpy: at B = 1 eager torch costs ~4-7 µs per op whatever the size, and a warm-started solve
through the batched torch code is ~60 ops (180-400 µs).  numpy calls on views of the same data
cost ~1 µs (LAPACK `dgesv` on the 13-18 × 13-18 working-set KKT matrix ~2-3 µs), so a
warm-started QP is ~30 calls.  A Python loop over instances grows linearly with B while the
batched torch path is nearly flat, so `solver.py` uses this path only for small CPU batches
(`SMALL_BATCH_MAX`, crossover measured there).

Why Goldfarb-Idnani rather than the batched path's primal-dual active set: one instance at a
time there is no batch to keep in lockstep, and the dual method is finite: from a dual-feasible
start (the minimiser on a working set whose multipliers are ≥ 0) it adds the most violated row
(relative to its norm), dropping a working row whenever its multiplier would cross zero, so the
working rows stay linearly independent and every KKT system stays nonsingular.  The semismooth
Newton iteration adds all violated rows at once, which on heavily constrained instances (8-10
active rows of 13 variables) gives singular systems or cycles; measured on 200 such instances
per family (m = 30-50, spread 0.35-1.0) it certified 1-77 %, this method 100 % (10-18 solves
on average).
Each add is first tried as a full step (one solve on W + j; accepted iff its multipliers are
≥ 0, which is exactly when G-I takes the full step), which leaves exact iterates; only when a
row must be dropped does it take the incremental G-I steps, then re-solves the final working set.
Warm start: the previous working set {z0 > 0}, less the rows whose multipliers come out
negative; in the control loop that is one KKT solve.

Fast path (`_range_space`, every instance with P ≻ 0): the same method in the range space of P.
P = L Lᵀ is factored once, S = C P⁻¹ Cᵀ formed once, and each step solves S_WW λ = C_W x₀ − d_W
(k × k, k = |W|) instead of an LU of the (n + k)-sized KKT matrix; a cold start guesses W from
the rows the unconstrained minimiser violates (trimmed to positive multipliers, so the start is
dual feasible: 7.9 instead of 9.9 solves on heavily constrained instances).  Its answer is
certified on the original KKT system; anything it does not certify runs the LU-based method
below from scratch, so outcomes are unchanged.

The answer is certified exactly as in `active_set.py` (KKT residual of the working set, primal
feasibility of every row, multipliers ≥ 0, all within tol).  Anything not certified — P singular
(LPs: G-I needs P ≻ 0 on the working set's null space), dependent equalities, an infeasible
instance (a row in the span of the working rows with no multiplier to drop), NaN data, or the
step budget spent — is reported back and handed to the batched torch path, which has the
augmented-Lagrangian fallback, the interior point and its infeasibility certificates, so statuses
are the batched path's.  Always computes in float64 (float32 inputs are upcast; the cast is free
at this size).

Native (C) version: even so, a cold heavily constrained solve is ~12 G-I steps × ~10 numpy/LAPACK
calls at 0.5-3 µs each (~250-450 µs on the shared box) for a few µs of arithmetic.  So the
range-space method, cold and warm-started (working set {z0 > 0} trimmed to positive multipliers,
then the same G-I steps), is also written in C (`native/gi_qp.c`, one ctypes call per batch, the
same decisions, tolerances and certificate): 25-45 µs per controller QP including the wrapper.
Every instance it does not certify runs the numpy code here from scratch, so outcomes are
unchanged; without a compiler, or with A3CQP_NATIVE_QP=0, only the numpy code runs.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import lapack

from a3cqp_rl.qp import native

COLD_ROUNDS = 2
"""Cold-start rounds of "add the violated rows, trim to positive multipliers" before the G-I steps
(measured on 300 instances: 1.07 / 6.60 / 12.07 solves at spread 0.015 / 0.35 / 1.0 with 2 rounds,
1.07 / 7.73 / 12.98 with 1, 9.6 / 14.6 for the LU method from W = ∅)."""
NATIVE = True
"""Use the C version of the cold/warm range-space solve (`native/gi_qp.c`) when it can be built;
False (or env A3CQP_NATIVE_QP=0) runs the numpy code only."""
__all__ = ["SINGULAR", "CERTIFIED", "EXHAUSTED", "active_set_small", "adjoint_small", "gradients_native"]

CERTIFIED, SINGULAR, EXHAUSTED = 0, 1, 2
"""Per-instance outcome of `active_set_small`: certified optimal; singular or non-finite
working-set system (go to the torch active set, which has the augmented Lagrangian); iteration
budget spent (go straight to the interior point)."""


def _kkt_solve(Kfull: np.ndarray, rhs_full: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, float]:
    """Solve the KKT system restricted to rows/columns `idx` of Kfull by LU; returns (solution, max residual)."""
    K = Kfull[idx[:, None], idx]
    rhs = rhs_full[idx]
    _, _, sol, info = lapack.dgesv(K, rhs)
    if info != 0:  # exactly singular pivot: no solution to certify
        return sol, np.inf
    # A posteriori residual: ill-conditioned (nearly dependent) systems show up here, not in info.
    # Its 2-norm (one dot product, cheaper than abs + max here) bounds the max-norm from above.
    e = K @ sol - rhs
    return sol, float(np.sqrt(e @ e))


def _dual_active_set(
    Kfull: np.ndarray, rhs_full: np.ndarray, n: int, p: int, G: np.ndarray, h: np.ndarray, W0: np.ndarray,
    tol_p: float, tol_d: float, tol_r: float, max_steps: int,
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Goldfarb-Idnani on one instance; returns (solution of the final KKT system, its rows, outcome, solves)."""
    m = G.shape[0]
    head = np.arange(n + p)

    def solve(rows: np.ndarray, rhs: np.ndarray = rhs_full) -> tuple[np.ndarray, float]:
        return _kkt_solve(Kfull, rhs, np.concatenate([head, n + p + rows]))

    # Warm start: the working set {z0 > 0} minus rows whose multipliers come out negative, so that
    # the start is dual feasible (x minimises the QP with only those rows, as G-I requires).
    rows = np.flatnonzero(W0)
    sol, res = solve(rows)
    solves = 1
    while rows.size and res <= tol_r and not (sol[n + p :] > 0).all():
        rows = rows[sol[n + p :] > 0]
        sol, res = solve(rows)
        solves += 1
    if not res <= tol_r and rows.size:  # dependent warm rows: start cold
        rows = rows[:0]
        sol, res = solve(rows)
        solves += 1
    if not res <= tol_r:  # P singular on the equality null space, or dependent equalities
        return sol, rows, SINGULAR, solves
    v = G @ sol[:n] - h  # > 0: violated
    if m == 0 or float(v.max()) <= tol_p:
        # Feasible, multipliers > 0 and the KKT residual checked by the solve: certified.  The
        # warm-started control loop ends here after one solve.
        return sol, rows, CERTIFIED, solves
    W = np.zeros(m, dtype=bool)
    W[rows] = True
    gnorm = np.sqrt(np.einsum("ij,ij->i", G, G)) + 1e-300
    x = nu = None  # the incremental G-I state, built only when a step needs it
    steps = 0
    while True:
        j = int(np.argmax(v / gnorm))
        vj = float(v[j])
        if vj <= tol_p:
            break
        steps += 1
        if steps > max_steps:
            return sol, rows, EXHAUSTED, solves
        if x is None:
            # Optimistic full step: the G-I path ends at the KKT point of W + j exactly when no
            # multiplier crosses zero on the way, i.e. when that point's multipliers are ≥ 0, so
            # one solve does the step and leaves an exact (not incrementally updated) iterate.
            W[j] = True
            rows_j = np.flatnonzero(W)
            sol_j, res = solve(rows_j)
            solves += 1
            if res <= tol_r and (sol_j[n + p :] >= 0).all():
                rows, sol = rows_j, sol_j
                v = G @ sol[:n] - h
                continue
            W[j] = False
            # Multipliers over all rows (equalities first, zero off the working set), so that
            # adding and dropping a row is a scalar write (np.append/np.delete cost ~5 µs each).
            x = sol[:n].copy()
            nu = np.zeros(p + m)
            nu[:p], nu[p + rows] = sol[n : n + p], sol[n + p :]
            scale = float(np.abs(np.diagonal(Kfull)[:n]).max()) + 1e-300  # curvature scale of P
            rhs_dir = np.zeros_like(rhs_full)
        # G-I step for row j: raise its multiplier from 0 along the direction that keeps the
        # working rows tight and the point stationary, P dx + C_Wᵀ dν = −g_j, C_W dx = 0; a working
        # row whose multiplier reaches zero first is dropped (partial step), until row j is tight.
        gj = G[j]
        rhs_dir[:n] = -gj
        while True:
            d, res = solve(rows, rhs_dir)
            solves += 1
            if not res <= 1e-9 * (1.0 + float(gnorm[j])):
                return sol, rows, SINGULAR, solves
            dx, dz = d[:n], d[n + p :]
            t1, l = np.inf, -1
            shrinking = np.flatnonzero(dz < 0)
            if shrinking.size:
                ratios = nu[p + rows[shrinking]] / -dz[shrinking]
                k = int(np.argmin(ratios))
                t1, l = max(float(ratios[k]), 0.0), int(rows[shrinking[k]])
            curv = -float(gj @ dx)  # = dxᵀ P dx ≥ 0: how fast the violation of row j falls
            t2 = vj / curv if curv > 1e-13 * float(gnorm[j]) ** 2 / scale else np.inf
            if t1 == np.inf and t2 == np.inf:  # g_j in the span of the working rows: infeasible
                return sol, rows, SINGULAR, solves
            t = min(t1, t2)
            x += t * dx
            nu[:p] += t * d[n : n + p]
            nu[p + rows] += t * dz
            nu[p + j] += t
            if t2 <= t1:  # row j is tight: it joins the working set
                W[j] = True
                rows = np.flatnonzero(W)
                break
            W[l] = False
            nu[p + l] = 0.0
            rows = np.flatnonzero(W)
            steps += 1
            if steps > max_steps:
                return sol, rows, EXHAUSTED, solves
            vj = float(gj @ x) - float(h[j])
        v = G @ x - h
    if x is None:  # only optimistic steps: `sol` is the exact KKT solution of `rows`
        return sol, rows, CERTIFIED, solves
    # Exact solution of the final working set: the certificate is checked on it, and it removes
    # the rounding the incremental updates accumulated.
    sol, res = solve(rows)
    solves += 1
    # Certificate, as in the batched stage: KKT residual of the working set, every row feasible,
    # multipliers ≥ 0.
    zW = sol[n + p :]
    if not res <= tol_r or float((G @ sol[:n] - h).max()) > tol_p or (rows.size and float(zW.min()) < -tol_d):
        return sol, rows, SINGULAR, solves
    return sol, rows, CERTIFIED, solves


def _range_space(
    P: np.ndarray, q: np.ndarray, C: np.ndarray, d: np.ndarray, p: int,
    tol_p: float, tol_d: float, tol_r: float, max_steps: int,
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Cold Goldfarb-Idnani in the range space of P ≻ 0 (the fast path); returns (x, multipliers of all rows, solves) or None.

    Rows C x ≤ d (the first p of them equalities, always working).  With P = L Lᵀ factored once,
    x₀ = −P⁻¹q and S = C P⁻¹ Cᵀ = (L⁻¹Cᵀ)ᵀ(L⁻¹Cᵀ) (one triangular solve, one product), the KKT
    point of a working set W has multipliers S_WW λ_W = C_W x₀ − d_W and row values
    C x − d = (C x₀ − d) − S_{:W} λ_W, so every step is a k × k Cholesky solve (k = |W| ≤ 10, ~2 µs)
    plus one product, instead of an LU of the (n + k)-sized KKT matrix; x is formed once at the end.
    The answer is certified on the original KKT system (residual, feasibility, multipliers ≥ 0);
    None (not P ≻ 0, dependent working rows, infeasible, step budget, or no certificate) hands
    the instance to the LU-based `_dual_active_set`, which decides its outcome as before.

    Per call this costs ~1-3 µs of numpy overhead whatever the size, so the bookkeeping is
    arranged for few calls: the working set is an unordered index buffer with its multipliers
    alongside (adding or dropping a row is a scalar write, no flatnonzero/append), rows of the
    symmetric S are gathered once per step and serve both the k × k solve and the new row values,
    and max/min/all are argmax/argmin plus an index (numpy's reductions cost ~3 µs, argmax ~0.5).
    """
    r = C.shape[0]
    L, info = lapack.dpotrf(P, lower=1)
    if info != 0:
        return None
    # L⁻¹ explicitly (dtrtri, ~2 µs) and products with it: OpenBLAS runs a triangular solve with
    # many right-hand sides (dtrtrs/dtrsm) on its thread pool, which on the loaded shared box
    # stalled for ~10 ms a call; small products and one-vector solves stay single-threaded.
    Li, info = lapack.dtrtri(L, lower=1)
    if info != 0:
        return None
    x0 = (Li @ -q) @ Li  # −L⁻ᵀL⁻¹q
    if r == 0:
        e_d = P @ x0 + q
        return (x0, np.zeros(0), 1) if math.sqrt(e_d @ e_d) <= tol_r else None
    v0 = C @ x0 - d
    if p == 0 and not v0[v0.argmax()] > tol_p:
        # The unconstrained minimiser is feasible (the easy cold case): certify it, skip S.
        e_d = P @ x0 + q
        return (x0, np.zeros(r), 1) if math.sqrt(e_d @ e_d) <= tol_r else None
    M = Li @ C.T
    S = M.T @ M

    def solve(rows: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
        _, sol, inf = lapack.dposv(S.take(rows, 0).take(rows, 1), rhs, lower=1)
        return None if inf != 0 else sol

    # Working set: buf[:k] (equalities first, the rest unordered; buf[k] holds a row on trial),
    # lw its multipliers, W membership.
    buf = np.arange(r)
    k = p
    W = np.zeros(r, dtype=bool)
    W[:p] = True
    ginv = 1.0 / (np.sqrt(np.einsum("ij,ij->i", C[p:], C[p:])) + 1e-300)  # violation relative to the row norm
    v, lw = v0, v0[:0]
    solves = 0
    # Cold start: add the rows the current point violates (the most violated relative to their
    # norms, up to n − p working rows), then trim the set to positive multipliers, so that the
    # start is dual feasible, as G-I requires; repeated COLD_ROUNDS times from the new point.
    for rnd in range(COLD_ROUNDS):
        if rnd:
            vp = v[p:]
            if not vp.size or not vp[vp.argmax()] > tol_p:  # no inequalities, or the previous round's point is feasible
                break
        rel = v[p:] * ginv
        room = len(q) - k
        viol = ((rel > tol_p) & ~W[p:]).nonzero()[0] if rnd else (rel > tol_p).nonzero()[0]
        add = viol if viol.size <= room else rel.argsort()[::-1][:room]  # argsort(−rel) up to ties
        if add.size == 0 and rnd:
            break
        if add.size:
            buf[k : k + add.size] = p + add
            W[p + add] = True
            k += add.size
        solves += 1
        while k:
            rows = buf[:k]
            lw = solve(rows, v0.take(rows))
            if lw is None:
                if k == p:  # dependent equalities (or ill-conditioned): LU path
                    return None
                W[buf[p:k]] = False
                k = p
                solves += 1
                continue
            if k == p or lw[p + lw[p:].argmin()] > 0:
                break
            keep = lw > 0
            keep[:p] = True
            W[rows[~keep]] = False
            kept = rows[keep]
            k = kept.size
            buf[:k] = kept
            solves += 1
        if k:
            v = v0 - lw @ S.take(buf[:k], 0)
        else:
            v, lw = v0, v0[:0]
    solves = max(solves, 1)
    exact = True  # lw holds the exact multipliers of buf[:k] (no incremental update since)
    steps = 0
    while r > p:
        rel = v[p:] * ginv
        j = p + int(rel.argmax())
        vj = float(v[j])
        if not vj > tol_p:
            break
        steps += 1
        if steps > max_steps:
            return None
        # Optimistic full step: the G-I path ends at the KKT point of W + j exactly when no
        # multiplier crosses zero on the way, i.e. when its multipliers are ≥ 0.  Its rows of S
        # (gathered once) give both the solve and, if accepted, the new row values.
        buf[k] = j
        rows_j = buf[: k + 1]
        S_j = S.take(rows_j, 0)
        _, lw_j, inf = lapack.dposv(S_j.take(rows_j, 1), v0.take(rows_j), lower=1)
        solves += 1
        if inf == 0 and lw_j[p + lw_j[p:].argmin()] >= 0:
            k += 1
            W[j] = True
            lw, exact = lw_j, True
            v = v0 - lw @ S_j
            continue
        exact = False
        # G-I steps for row j: raise λ_j, keeping the working rows tight (dλ_W = −S_WW⁻¹ S_Wj
        # per unit); a working inequality whose multiplier reaches zero first is dropped.
        Sjj = float(S[j, j])
        lam_j = 0.0
        while True:
            if k:
                rows = buf[:k]
                S_W = S.take(rows, 0)
                sWj = S_W[:, j]
                _, dl, inf = lapack.dposv(S_W.take(rows, 1), sWj, lower=1)
                solves += 1
                if inf != 0:
                    return None
                curv = Sjj - float(sWj @ dl)
                # Ratio test on the shrinking inequality multipliers (k ≤ n: scalar Python).
                t1, i_l = math.inf, -1
                for i, (lam_i, dl_i) in enumerate(zip(lw[p:].tolist(), dl[p:].tolist()), p):
                    if dl_i > 0 and lam_i / dl_i < t1:
                        t1, i_l = lam_i / dl_i, i
                t1 = max(t1, 0.0)
            else:
                curv, t1, i_l = Sjj, math.inf, -1
            t2 = vj / curv if curv > 1e-12 * Sjj else math.inf
            if t1 == math.inf and t2 == math.inf:  # row j in the span of the working rows: infeasible
                return None
            t = min(t1, t2)
            if k:
                lw -= t * dl
            lam_j += t
            if t2 <= t1:  # row j is tight: it joins (it sits at buf[k] already)
                W[j] = True
                lw = np.append(lw, lam_j)
                k += 1
                break
            # Drop the working row at position i_l: the last working row takes its place, and
            # j (on trial at buf[k]) moves down with it.
            W[buf[i_l]] = False
            last = k - 1
            buf[i_l], buf[last] = buf[last], j
            lw[i_l] = lw[last]
            lw = lw[:last]
            k = last
            vj -= t * curv
            steps += 1
            if steps > max_steps:
                return None
        v = v0 - lw @ S.take(buf[:k], 0)
    rows = buf[:k]
    if not exact:  # exact multipliers of the final working set (drops the incremental rounding)
        lw = solve(rows, v0.take(rows))
        solves += 1
        if lw is None:
            return None
    # x from the multipliers, then the certificate on the original KKT system: residual of the
    # working set, every row feasible, multipliers ≥ 0.
    lam = np.zeros(r)
    if k:
        lam[rows] = lw
        g = lw @ C.take(rows, 0)  # C_Wᵀ λ_W
        x = x0 - (Li @ g) @ Li
        e_d = P @ x + q + g
        vfin = C @ x - d
        e_p = vfin.take(rows)
        if not math.sqrt(e_d @ e_d + e_p @ e_p) <= tol_r or (k > p and lw[p + lw[p:].argmin()] < -tol_d):
            return None
    else:  # x₀ itself (v0 holds its row values)
        x, vfin = x0, v0
        e_d = P @ x + q
        if not math.sqrt(e_d @ e_d) <= tol_r:
            return None
    if r > p and vfin[p + vfin[p:].argmax()] > tol_p:
        return None
    return x, lam, solves


def _warm_one_solve(
    P: np.ndarray, q: np.ndarray, A: np.ndarray, b: np.ndarray, G: np.ndarray, h: np.ndarray, rows: np.ndarray,
    tol_p: float, tol_r: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The control loop's case: the warm working set `rows` is still the optimal one; returns (x, y, z) or None.

    Exactly the first solve and the certificate of `_dual_active_set` (KKT system of the working
    rows, residual ≤ tol, multipliers > 0, every row feasible), but with the KKT matrix built for
    these rows only: the full matrix and its gather are only worth building when more solves follow.
    None: `_dual_active_set` takes the instance from the start.
    """
    n, p = q.shape[0], A.shape[0]
    GW = G.take(rows, 0)
    C = np.concatenate([A, GW]) if p else GW
    r = n + C.shape[0]
    K = np.zeros((r, r))
    K[:n, :n] = P
    K[:n, n:] = C.T
    K[n:, :n] = C
    rhs = np.concatenate([-q, b, h.take(rows)] if p else [-q, h.take(rows)])
    _, _, sol, info = lapack.dgesv(K, rhs)
    if info != 0:
        return None
    e = K @ sol - rhs
    if not math.sqrt(e @ e) <= tol_r:
        return None
    zW = sol[n + p :]
    if rows.size and not zW[zW.argmin()] > 0:
        return None
    x = sol[:n]
    if G.shape[0]:
        v = G @ x - h
        if v[v.argmax()] > tol_p:
            return None
    z = np.zeros(G.shape[0])
    z[rows] = zW
    return x, sol[n : n + p], z


def active_set_small(
    P: np.ndarray, q: np.ndarray, A: np.ndarray, b: np.ndarray, G: np.ndarray, h: np.ndarray,
    z0: np.ndarray | None, tol: float, max_steps: int, numpy_retry: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dual active set per instance (float64 numpy, P symmetric); returns x, y, z, outcome, KKT solves.

    Shapes: P [B, n, n], q [B, n], A [B, p, n], b [B, p], G [B, m, n], h [B, m], z0 [B, m] or None
    (warm-start multipliers; the working set starts as {z0 > 0}).  `outcome` [B] holds CERTIFIED,
    SINGULAR or EXHAUSTED; x, y, z are only meaningful where CERTIFIED.  The batch goes through the
    native routine first when it is available (`NATIVE`); the numpy code below solves what it
    leaves uncertified (with `numpy_retry=False` those are returned SINGULAR instead: large batches).
    """
    B, n = q.shape
    p, m = A.shape[1], G.shape[1]
    r = n + p + m
    solve_native = native.load() if NATIVE else None
    if solve_native is not None:
        # The same range-space G-I (cold, or warm from {z0 > 0}) and certificate in one C call for
        # the whole batch; only what it does not certify runs the numpy code below, from scratch,
        # so outcomes are the numpy code's.
        x_out, y_out, z_out, outcome, iters = solve_native(P, q, A, b, G, h, z0, tol, max_steps)
        if not outcome[outcome.argmax()]:  # all certified (= 0): argmax + index, cheaper than any()
            return x_out, y_out, z_out, outcome, iters
        todo = outcome.nonzero()[0]
        x_out[todo], y_out[todo], z_out[todo] = 0.0, 0.0, 0.0
        outcome[todo] = SINGULAR
        if not numpy_retry:
            return x_out, y_out, z_out, outcome, iters
    else:
        x_out, y_out, z_out = np.zeros((B, n)), np.zeros((B, p)), np.zeros((B, m))
        outcome = np.full(B, SINGULAR, dtype=np.int64)
        iters = np.zeros(B, dtype=np.int64)
        todo = range(B)
    # Tolerance scales as in `residual_scales`: 1 + |(b, h)|∞ (primal), 1 + |q|∞ (dual).
    sp = 1.0 + (np.abs(np.concatenate([b, h], 1)).max(1) if p + m else np.zeros(B))
    sd = 1.0 + np.abs(q).max(1)
    no_warm = np.zeros(m, dtype=bool)
    for i in todo:
        Pi, qi, Ai, bi, Gi, hi = P[i], q[i], A[i], b[i], G[i], h[i]
        tol_p, tol_d = tol * float(sp[i]), tol * float(sd[i])
        tol_r = min(tol_p, tol_d) if p + m else tol_d
        # Cold (P ≻ 0): G-I in the range space of P, k × k solves on the working rows.  Warm
        # starts keep the LU method here: it certifies the control loop's QP in one solve, with
        # less set-up than the range space (Cholesky, L⁻¹, S) needs in numpy.  (In C that set-up
        # costs ~1 µs, so the native routine warm-starts in the range space as well.)
        fast = None
        if z0 is None:
            C, dC = (np.concatenate([Ai, Gi]), np.concatenate([bi, hi])) if p else (Gi, hi)
            fast = _range_space(Pi, qi, C, dC, p, tol_p, tol_d, tol_r, max_steps)
        if fast is not None:
            x_out[i], lam, iters[i] = fast
            y_out[i], z_out[i] = lam[:p], lam[p:]
            outcome[i] = CERTIFIED
            continue
        extra = 0
        if z0 is not None:
            sol = _warm_one_solve(Pi, qi, Ai, bi, Gi, hi, (z0[i] > 0).nonzero()[0], tol_p, tol_r)
            if sol is not None:
                x_out[i], y_out[i], z_out[i] = sol
                outcome[i], iters[i] = CERTIFIED, 1
                continue
            extra = 1
        # Full KKT matrix [[P, Aᵀ, Gᵀ], [A, 0, 0], [G, 0, 0]] once per instance; each solve
        # gathers the working rows/columns from it (one fancy index instead of four block copies).
        Kfull = np.zeros((r, r))
        Kfull[:n, :n] = Pi
        Kfull[:n, n : n + p] = Ai.T
        Kfull[n : n + p, :n] = Ai
        Kfull[:n, n + p :] = Gi.T
        Kfull[n + p :, :n] = Gi
        rhs_full = np.concatenate([-qi, bi, hi])
        W0 = z0[i] > 0 if z0 is not None else no_warm
        sol, rows, outcome[i], iters[i] = _dual_active_set(Kfull, rhs_full, n, p, Gi, hi, W0, tol_p, tol_d, tol_r, max_steps)
        iters[i] += extra
        if outcome[i] == CERTIFIED:
            x_out[i], y_out[i] = sol[:n], sol[n : n + p]
            z_out[i, rows] = sol[n + p :]
    return x_out, y_out, z_out, outcome, iters


def adjoint_small(
    P: np.ndarray, A: np.ndarray, G: np.ndarray, h: np.ndarray, x: np.ndarray, z: np.ndarray, gx: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Adjoint of the KKT conditions per instance: returns (wx [B, n], wy [B, p], wz [B, m], active [B, m]) or None.

    Solves [[P, C_Wᵀ], [C_W, 0]] (wx, wν) = (gx, 0) on the equality rows and the strictly
    complementary active rows (z > h − Gx), exactly as the torch backward; None when any
    instance's system is singular (the caller then uses the torch backward, which has the
    augmented-Lagrangian fallback).
    """
    B, n = gx.shape
    p, m = A.shape[1], G.shape[1]
    wx, wy, wz = np.zeros((B, n)), np.zeros((B, p)), np.zeros((B, m))
    active = np.zeros((B, m), dtype=bool)
    for i in range(B):
        Gi = G[i]
        slack = h[i] - Gi @ x[i]
        act = z[i] > np.maximum(slack, 0.0, out=slack)
        active[i] = act
        rows = act.nonzero()[0]
        # Only the working rows: [[P, Aᵀ, G_Wᵀ], [A, 0, 0], [G_W, 0, 0]].
        C = np.concatenate([A[i], Gi.take(rows, 0)]) if p else Gi.take(rows, 0)
        r = n + C.shape[0]
        K = np.zeros((r, r))
        K[:n, :n] = P[i]
        K[:n, n:] = C.T
        K[n:, :n] = C
        rhs = np.zeros(r)
        rhs[:n] = gx[i]
        _, _, sol, info = lapack.dgesv(K, rhs)
        e = K @ sol - rhs
        # Same acceptance test as the torch backward (2-norm of the residual: stricter); max |·|
        # by argmax + index (a numpy max reduction costs ~5x more at this size).
        ag = np.abs(gx[i])
        tol_w = 1e-12 * (1.0 + float(ag[ag.argmax()]))
        anu = np.abs(sol[n:])
        if info != 0 or not math.sqrt(e @ e) <= tol_w * (1.0 + (float(anu[anu.argmax()]) if r > n else 0.0)):
            return None
        wx[i], wy[i] = sol[:n], sol[n : n + p]
        wz[i, rows] = sol[n + p :]
    return wx, wy, wz, active


def gradients_native(
    P: np.ndarray, A: np.ndarray, G: np.ndarray, h: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, gx: np.ndarray,
) -> tuple[np.ndarray, ...] | None:
    """Gradients (P, q, A, b, G, h) of Σ gx·x by the C adjoint (`native/gi_qp.c`), or None.

    The same working rows, equations, acceptance test and closed forms as `adjoint_small` and
    `solver._backward_small`, in one call instead of ~30 numpy calls; solved in the range space of
    P, so None (use `adjoint_small`) when P is not definite, a system is not accepted, or the
    native routine is unavailable.
    """
    fn = native.load_adjoint() if NATIVE else None
    return None if fn is None else fn(P, A, G, h, x, y, z, gx)
