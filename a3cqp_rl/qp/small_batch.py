"""Small-batch CPU fast path: the active-set stage and the adjoint solve, one instance at a time in numpy.

Why: at B = 1 eager torch costs ~4-7 µs per op whatever the size, and a warm-started solve through
the batched torch code is ~60 ops (180-400 µs).  The same primal-dual active-set iteration on
numpy views of the data costs ~1 µs per call (a LAPACK `dgesv` on the 13-18 × 13-18 working-set
KKT matrix is ~2 µs), so a warm-started QP is ~20 µs of arithmetic plus the torch wrapper.  A
Python loop over instances grows linearly with B while the batched torch path is nearly flat, so
`solver.py` uses this path only up to `SMALL_BATCH_MAX` instances on CPU (crossover measured
there).

Same algorithm and the same certificate as `active_set.py` (KKT residual of the working set,
primal feasibility of every row, multipliers ≥ 0, all within tol), so a certified answer is as
exact as the batched one; only the working-set solve differs (exactly the working rows, one
`dgesv`).  Anything this path does not certify — a singular working-set system (dependent rows,
P singular on their null space), NaN data, or no certificate within the iteration budget — is
reported back and handed to the batched torch path, which has the augmented-Lagrangian fallback
and the interior point.  Always computes in float64 (float32 inputs are upcast; it is exact
enough either way and the cast is free at this size).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

__all__ = ["SINGULAR", "CERTIFIED", "EXHAUSTED", "active_set_small", "adjoint_small"]

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


def active_set_small(
    P: np.ndarray, q: np.ndarray, A: np.ndarray, b: np.ndarray, G: np.ndarray, h: np.ndarray,
    z0: np.ndarray | None, tol: float, max_iter: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Primal-dual active set per instance (float64 numpy, P symmetric); returns x, y, z, outcome, iterations.

    Shapes: P [B, n, n], q [B, n], A [B, p, n], b [B, p], G [B, m, n], h [B, m], z0 [B, m] or None
    (warm-start multipliers; the working set starts as {z0 > 0}).  `outcome` [B] holds CERTIFIED,
    SINGULAR or EXHAUSTED; x, y, z are only meaningful where CERTIFIED.
    """
    B, n = q.shape
    p, m = A.shape[1], G.shape[1]
    r = n + p + m
    x_out, y_out, z_out = np.zeros((B, n)), np.zeros((B, p)), np.zeros((B, m))
    outcome = np.full(B, EXHAUSTED, dtype=np.int64)
    iters = np.full(B, max_iter, dtype=np.int64)
    head = np.arange(n + p)  # x and the equality multipliers are always in the system
    # Tolerance scales as in `residual_scales`: 1 + |(b, h)|∞ (primal), 1 + |q|∞ (dual).
    sp = 1.0 + (np.abs(np.concatenate([b, h], 1)).max(1) if p + m else np.zeros(B))
    sd = 1.0 + np.abs(q).max(1)
    for i in range(B):
        Pi, qi, Ai, bi, Gi, hi = P[i], q[i], A[i], b[i], G[i], h[i]
        # Full KKT matrix [[P, Aᵀ, Gᵀ], [A, 0, 0], [G, 0, 0]] once per instance; each iteration
        # gathers the working rows/columns from it (one fancy index instead of four block copies).
        Kfull = np.zeros((r, r))
        Kfull[:n, :n] = Pi
        Kfull[:n, n : n + p] = Ai.T
        Kfull[n : n + p, :n] = Ai
        Kfull[:n, n + p :] = Gi.T
        Kfull[n + p :, :n] = Gi
        rhs_full = np.concatenate([-qi, bi, hi])
        tol_p, tol_d = tol * float(sp[i]), tol * float(sd[i])
        tol_r = min(tol_p, tol_d) if p + m else tol_d
        W = z0[i] > 0 if z0 is not None else np.zeros(m, dtype=bool)
        for k in range(max_iter):
            rows = np.flatnonzero(W)
            sol, res = _kkt_solve(Kfull, rhs_full, np.concatenate([head, n + p + rows]))
            if not res <= tol_r:  # also catches NaN
                outcome[i] = SINGULAR
                break
            x = sol[:n]
            vG = Gi @ x - hi  # > 0: violated
            zW = sol[n + p :]
            if (m == 0 or vG.max() <= tol_p) and (rows.size == 0 or zW.min() >= -tol_d):
                x_out[i], y_out[i] = x, sol[n : n + p]
                z_out[i, rows] = zW
                outcome[i], iters[i] = CERTIFIED, k + 1
                break
            # Semismooth Newton step on min(z, h − Gx) = 0: keep working rows with positive
            # multipliers, add the violated rows.
            keep = np.zeros(m, dtype=bool)
            keep[rows[zW > 0]] = True
            W = keep | (~W & (vG > tol_p))
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
    r = n + p + m
    wx, wy, wz = np.zeros((B, n)), np.zeros((B, p)), np.zeros((B, m))
    active = z > np.maximum(h - (G @ x[:, :, None])[..., 0], 0.0)
    head = np.arange(n + p)
    for i in range(B):
        Kfull = np.zeros((r, r))
        Kfull[:n, :n] = P[i]
        Kfull[:n, n : n + p] = A[i].T
        Kfull[n : n + p, :n] = A[i]
        Kfull[:n, n + p :] = G[i].T
        Kfull[n + p :, :n] = G[i]
        rhs_full = np.zeros(r)
        rhs_full[:n] = gx[i]
        rows = np.flatnonzero(active[i])
        sol, res = _kkt_solve(Kfull, rhs_full, np.concatenate([head, n + p + rows]))
        # Same acceptance test as the torch backward.
        tol_w = 1e-12 * (1.0 + float(np.abs(gx[i]).max()))
        if not res <= tol_w * (1.0 + (float(np.abs(sol[n:]).max()) if sol.size > n else 0.0)):
            return None
        wx[i], wy[i] = sol[:n], sol[n : n + p]
        wz[i, rows] = sol[n + p :]
    return wx, wy, wz, active
