"""The torch route of `solve_qp`: the whole batch in batched torch ops (any device), every status decided.

On canonical data (P, q, A, b, G, h with the bounds already stacked as rows), float64:

1. Input checks per instance (`screen`): NaN anywhere or ±inf in P, q, A, b, G → INVALID_INPUT; a row
   with h ≤ −1e20 → PRIMAL_INFEASIBLE; rows with h ≥ 1e20 become inert (0·x ≤ 1).
2. Convexity: a batched Cholesky of ½(P + Pᵀ); only where it fails, eigenvalues decide between
   positive semi-definite (go on) and NON_CONVEX (λ_min < −1e-9 max|λ|).
3. Primal-dual active set (`active_set.py`) from the warm start's active set, each candidate
   certified by `kkt.kkt_certified`; what it leaves goes to
4. the interior point (`interior_point.py`, with its Farkas and recession-direction certificates),
   whose strictly complementary active set seeds an exact polish.
5. A final gate: an instance reported SOLVED must pass `kkt_certified`, else TOLERANCE_NOT_MET.

One instance never changes another's answer: each step either acts per instance or drops finished
instances from the working batch.
"""

from __future__ import annotations

import torch
from torch import Tensor

from a3cqp_rl.qp.active_set import active_set_stage, residual_scales
from a3cqp_rl.qp.interior_point import interior_point
from a3cqp_rl.qp.kkt import LU_MAX_BATCH, kkt_certified, mv
from a3cqp_rl.qp.status import QPStatus

__all__ = ["NO_BOUND", "screen", "solve_torch"]

NO_BOUND = 1e20
"""|right-hand side| at and above which a row means "no constraint" (h ≥ 1e20) or "infeasible" (h ≤ −1e20)."""
NON_CONVEX_REL = 1e-9
"""P is non-convex when λ_min(½(P + Pᵀ)) < −NON_CONVEX_REL · max|λ| (rounding of a PSD product stays above)."""
_IPM_POLISH_TOL = 1e-6
"""Complementarity at which the interior point hands its active set to the exact polish."""


def screen(P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-instance input status [B] (SOLVED = go on, INVALID_INPUT, PRIMAL_INFEASIBLE) and (G, h) with inert rows.

    Rows with h ≥ 1e20 (or +inf), and every row of a decided instance, become 0·x ≤ 1, so the data
    handed on is finite."""
    def finite(t: Tensor) -> Tensor:
        return torch.isfinite(t).flatten(1).all(-1) if t.numel() else torch.ones(t.shape[0], dtype=torch.bool, device=t.device)

    valid = finite(P) & finite(q) & finite(A) & finite(b) & finite(G) & ~torch.isnan(h).any(-1)
    infeasible = (h <= -NO_BOUND).any(-1) & valid
    status = torch.zeros(q.shape[0], dtype=torch.long, device=q.device)
    status = torch.where(valid, status, int(QPStatus.INVALID_INPUT))
    status = torch.where(infeasible, int(QPStatus.PRIMAL_INFEASIBLE), status)
    live = (h < NO_BOUND) & (h > -NO_BOUND) & (status == 0).unsqueeze(-1)
    if not bool(live.all()):
        G = torch.where(live.unsqueeze(-1), G, torch.zeros((), dtype=G.dtype, device=G.device))
        h = torch.where(live, h, torch.ones((), dtype=h.dtype, device=h.device))
    return status, G, h


def _non_convex(P: Tensor) -> Tensor:
    """Instances whose symmetric P is not positive semi-definite [B] (bool); eigenvalues only where Cholesky fails."""
    _, info = torch.linalg.cholesky_ex(P)
    bad = (info != 0).nonzero().squeeze(-1)
    out = torch.zeros(P.shape[0], dtype=torch.bool, device=P.device)
    if bad.numel():
        lam = torch.linalg.eigvalsh(P.index_select(0, bad))
        out[bad] = lam[:, 0] < -NON_CONVEX_REL * lam.abs().amax(-1)
    return out


def _ipm_polished(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, sp: Tensor, sd: Tensor,
    tol_ipm: float, tol: float, max_iter: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Interior point to tol_ipm, then an active-set polish to tol; returns x, y, z, status, iterations, polished."""
    nb, n = q.shape
    m = G.shape[1]
    # Unit-norm rows for the interior point: one tolerance fits all rows and its Farkas test is
    # scale-free; multipliers are scaled back below.
    nA = A.norm(dim=-1).clamp_min(1e-30)
    nG = G.norm(dim=-1)
    nG = torch.where(nG > 0, nG, torch.ones((), dtype=q.dtype))
    Gs, hs = G / nG.unsqueeze(-1), h / nG
    xi, yi, zi, si, ii = interior_point(P, q, A / nA.unsqueeze(-1), b / nA, Gs, hs, tol_ipm, max_iter)
    yi = yi / nA
    # Active set decided in the normalised rows, where multipliers and slacks are comparable.
    act_ipm = zi > (hs - mv(Gs, xi))
    zi = zi / nG
    polished = torch.zeros(nb, dtype=torch.bool, device=q.device)
    good = (si == QPStatus.SOLVED).nonzero().squeeze(-1)
    if good.numel():
        # Polish: the IPM's strictly complementary active set (z > s) seeds an active-set solve,
        # which returns the exact solution of that active set and multipliers that are zero on
        # inactive rows (an IPM stopped at μ leaves O(√μ) errors on degenerate rows).
        z_act = torch.where(act_ipm, zi, torch.zeros((), dtype=q.dtype))
        sub = [t.index_select(0, good) for t in (P, q, A, b, G, h, z_act, sp, sd)]
        xp, yp, zp, okp, itp = active_set_stage(*sub, tol, 2)
        sel = good[okp]
        xi[sel], zi[sel], yi[sel], polished[sel] = xp[okp], zp[okp], yp[okp], True
        ii[good] = ii[good] + itp.clamp(max=2)
    return xi, yi, zi, si, ii, polished


def _farkas(A: Tensor, b: Tensor, G: Tensor, h: Tensor, tol: float, max_iter: int) -> tuple[Tensor, Tensor]:
    """Instances proven infeasible by a Farkas certificate [B] (bool), and the iterations spent.

    The certificate (z ≥ 0, y) with Gᵀz + Aᵀy = 0 and hᵀz + bᵀy = −1 exists exactly when no x satisfies
    Ax = b, Gx ≤ h; the one of least norm solves the strictly convex QP
    min ½(|z|² + |y|²) s.t. those n + 1 equalities, z ≥ 0 — solved by this route (rows scaled to unit
    norm first).  Its equalities held to tol mean every feasible x would need |x|₁ ≳ 1 / tol."""
    B, m, n = G.shape
    p = A.shape[1]
    nG = G.norm(dim=-1)
    nG = torch.where(nG > 0, nG, torch.ones((), dtype=G.dtype))
    nA = A.norm(dim=-1).clamp_min(1e-30)
    Gs, hs, As, bs = G / nG.unsqueeze(-1), h / nG, A / nA.unsqueeze(-1), b / nA
    k = m + p
    Mt = torch.cat([Gs, As], 1).mT  # (B, n, k): Gᵀz + Aᵀy
    top = torch.cat([hs, bs], 1).unsqueeze(1)  # (B, 1, k): hᵀz + bᵀy
    Aeq = torch.cat([Mt, top], 1)
    beq = torch.cat([G.new_zeros(B, n), G.new_full((B, 1), -1.0)], 1)
    eye = torch.eye(k, dtype=G.dtype, device=G.device).expand(B, k, k)
    Gin = -eye[:, :m]  # −z ≤ 0
    _, _, _, st, it = solve_torch(eye, G.new_zeros(B, k), Aeq, beq, Gin, G.new_zeros(B, m), None, tol, max_iter, None,
                                  farkas=False)
    return st == int(QPStatus.SOLVED), it


def _solve_convex(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, z_warm: Tensor | None,
    tol: float, max_iter: int, active_set_iter: int | None, farkas: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Active-set stage on the whole batch, interior point for what it leaves; x, y, z, status, iterations."""
    B, n = q.shape
    if active_set_iter is None:
        active_set_iter = 15 if B <= LU_MAX_BATCH else 10
    sp, sd = residual_scales(q, b, h)
    z0 = z_warm if z_warm is not None else q.new_zeros(B, G.shape[1])
    x, y, z, ok, iters = active_set_stage(P, q, A, b, G, h, z0, sp, sd, tol, active_set_iter)
    status = torch.zeros(B, dtype=torch.long, device=q.device)
    if bool(ok.all()):
        return x, y, z, status, iters
    bad = ok.logical_not().nonzero().squeeze(-1)
    sub = [t.index_select(0, bad) for t in (P, q, A, b, G, h, sp, sd)]
    # The IPM only has to find the active set: stopped at a looser μ, its strictly complementary
    # set seeds the polish, which is exact.  Only where that polish fails (degenerate or weakly
    # active rows) is the IPM rerun to the full tolerance.
    tol_ipm = max(tol, _IPM_POLISH_TOL)
    xi, yi, zi, si, ii, pol = _ipm_polished(*sub, tol_ipm, tol, max_iter)
    redo = ((si == QPStatus.SOLVED) & ~pol).nonzero().squeeze(-1) if tol_ipm > tol else pol[:0].nonzero().squeeze(-1)
    if redo.numel():
        xr, yr, zr, sr, ir, _ = _ipm_polished(*(t.index_select(0, redo) for t in sub), tol, tol, max_iter)
        xi[redo], yi[redo], zi[redo], si[redo], ii[redo] = xr, yr, zr, sr, ii[redo] + ir
    # Without a verdict, or with a recession direction: is there a feasible point at all?  An LP can
    # be both infeasible and have a recession direction (infeasible is then the answer, as
    # Clarabel's), and an interior point can stall on an infeasible instance without its Farkas
    # certificate; `_farkas` looks for that certificate directly.
    again = ((si == int(QPStatus.MAX_ITER)) | (si == int(QPStatus.DUAL_INFEASIBLE))).nonzero().squeeze(-1)
    if again.numel() and farkas:
        A_, b_, G_, h_ = (t.index_select(0, again) for t in sub[2:6])
        infeasible, itf = _farkas(A_, b_, G_, h_, tol, max_iter)
        si[again] = torch.where(infeasible, int(QPStatus.PRIMAL_INFEASIBLE), si[again])
        ii[again] += itf
    x[bad], y[bad], z[bad], status[bad], iters[bad] = xi, yi, zi, si, iters[bad] + ii
    return x, y, z, status, iters


def solve_torch(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, z_warm: Tensor | None,
    tol: float, max_iter: int, active_set_iter: int | None, farkas: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Solve a canonical float64 batch (see the module docstring); returns x, y, z, status, iterations.

    `farkas`: look for a Farkas certificate where the interior point ends without a verdict or with a
    recession direction (False inside that search itself).

    Instances not SOLVED get x = 0, y = 0, z = 0 unless they stopped at MAX_ITER or
    TOLERANCE_NOT_MET (then x is the last iterate, finite)."""
    B, n = q.shape
    p = A.shape[1]
    P = 0.5 * (P + P.mT)
    status, G, h = screen(P, q, A, b, G, h)
    x, y, z = q.new_zeros(B, n), q.new_zeros(B, p), q.new_zeros(B, G.shape[1])
    iters = torch.zeros(B, dtype=torch.long, device=q.device)
    go = status == 0
    if n == 0:  # nothing to choose: x = () is the answer where 0 = b and 0 <= h hold
        sp = residual_scales(q, b, h)[0].unsqueeze(-1)
        bad = (b.abs() > tol * sp).any(-1) | (h < -tol * sp).any(-1)
        return x, y, z, torch.where(go & bad, int(QPStatus.PRIMAL_INFEASIBLE), status), iters
    if bool(go.any()):
        go_all = bool(go.all())
        idx = go.nonzero().squeeze(-1)
        sub = (P, q, A, b, G, h) if go_all else tuple(t.index_select(0, idx) for t in (P, q, A, b, G, h))
        nc = _non_convex(sub[0])
        if bool(nc.any()):
            status[idx[nc]] = int(QPStatus.NON_CONVEX)
            keep = (~nc).nonzero().squeeze(-1)
            idx, sub, go_all = idx[keep], tuple(t.index_select(0, keep) for t in sub), False
        if idx.numel():
            Ps, qs, As, bs, Gs, hs = sub
            if Gs.shape[1] == 0:  # no rows: one inert row keeps every stage's shapes non-empty
                Gs, hs = qs.new_zeros(qs.shape[0], 1, n), qs.new_ones(qs.shape[0], 1)
            zw = None
            if z_warm is not None and G.shape[1]:
                zw = z_warm if go_all else z_warm.index_select(0, idx)
            xs, ys, zs, ss, its = _solve_convex(Ps, qs, As, bs, Gs, hs, zw, tol, max_iter, active_set_iter, farkas)
            zs = zs[:, : G.shape[1]]
            # Never hand NaN/inf to the caller: a failed instance keeps a finite (if meaningless) x.
            xs, ys = torch.nan_to_num(xs, nan=0.0, posinf=0.0, neginf=0.0), torch.nan_to_num(ys, nan=0.0, posinf=0.0, neginf=0.0)
            zs = torch.nan_to_num(zs.clamp_min(0.0), nan=0.0, posinf=0.0, neginf=0.0)
            # Final gate: SOLVED only with the KKT certificate; certificates of infeasibility or
            # unboundedness carry no primal answer.
            solved = ss == int(QPStatus.SOLVED)
            if bool(solved.any()):
                cert = kkt_certified(Ps, qs, As, bs, Gs[:, : G.shape[1]], hs[:, : G.shape[1]], xs, ys, zs, tol)
                ss = torch.where(solved & ~cert, int(QPStatus.TOLERANCE_NOT_MET), ss)
            certain = (ss == int(QPStatus.PRIMAL_INFEASIBLE)) | (ss == int(QPStatus.DUAL_INFEASIBLE))
            if bool(certain.any()):
                xs = torch.where(certain.unsqueeze(-1), 0.0, xs)
                ys = torch.where(certain.unsqueeze(-1), 0.0, ys)
                zs = torch.where(certain.unsqueeze(-1), 0.0, zs)
            if go_all and idx.numel() == B:
                return xs, ys, zs, ss, its
            x[idx], y[idx], z[idx], status[idx], iters[idx] = xs, ys, zs, ss, its
    return x, y, z, status, iters
