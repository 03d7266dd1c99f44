"""Stage 1 of the solver: batched primal-dual active-set (semismooth Newton) iterations with certification."""

from __future__ import annotations

import torch
from torch import Tensor

from a3cqp_rl.qp.kkt import LU_MAX_BATCH, RHO_FAST, eq_solve_alm, kkt_certified, kkt_lu, kkt_schur, mv, row_thresholds

__all__ = ["residual_scales", "active_set_stage"]


def residual_scales(q: Tensor, b: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
    """Per-instance scales [B] of the primal and dual tolerances: 1 + |(b, h)|∞ and 1 + |q|∞."""
    bh = torch.cat([b, h], -1) if b.shape[-1] else h
    sp = 1.0 + (bh.abs().amax(-1) if bh.shape[-1] else q.new_zeros(q.shape[0]))
    sd = 1.0 + (q.abs().amax(-1) if q.shape[-1] else q.new_zeros(q.shape[0]))
    return sp, sd


def active_set_stage(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, z0: Tensor,
    sp: Tensor, sd: Tensor, tol: float, max_iter: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Active-set stage on the whole batch; returns x, y, z, certified-optimal mask, iterations.

    z0 [B, m] seeds the working set W = {z0 > 0}; sp, sd [B] scale the tolerance of the working-set
    solves; a candidate counts as optimal only when `kkt_certified` (per-row tolerances) accepts it.
    """
    B, n = q.shape
    p, m = A.shape[1], G.shape[1]
    C = torch.cat([A, G], 1) if p else G  # (B, p + m, n)
    d = torch.cat([b, h], 1) if p else h
    W = z0 > 0  # (B, m) working set
    z = torch.cat([q.new_zeros(B, p), z0], 1) if p else z0
    x = row_sq = L = x_u = None
    idx = out = None
    chol_ok = True
    tol_r = tol * torch.minimum(sp, sd) if p or m else tol * sd
    for k in range(max_iter):
        mask = torch.cat([W.new_ones(W.shape[0], p), W], 1) if p else W
        direct = False
        if q.shape[0] <= LU_MAX_BATCH:
            x_d, z_d, res = kkt_lu(P, q, C, d, mask)
            direct = True
        elif chol_ok:
            if L is None:
                L, info = torch.linalg.cholesky_ex(P)
                chol_ok = bool((info == 0).all())  # P only semi-definite somewhere: use the ALM
                x_u = torch.cholesky_solve(-q.unsqueeze(-1), L).squeeze(-1)
            if chol_ok:
                x_d, z_d, res = kkt_schur(L, x_u, P, q, C, d, mask)
                direct = True
        if direct:
            # Certified optimum: KKT residual of the working set small, every row feasible,
            # inequality multipliers ≥ 0.
            vG = mv(G, x_d) - h  # (b, m): > 0 means violated
            zG = z_d[:, p:]
            ok = (res <= tol_r) & kkt_certified(P, q, A, b, G, h, x_d, z_d[:, :p], zG, tol)
            if out is None and bool(ok.all()):
                # Fast exit (the warm-started control loop, or a single instance): every instance
                # certified in the same iteration, so no bookkeeping ops at all.
                return x_d, z_d[:, :p], zG, ok, torch.full((B,), k + 1, dtype=torch.long, device=q.device)
            # A singular working-set system (dependent rows, more rows than variables, P singular
            # on their null space) leaves its instance uncertified.  Small batches then retry with
            # the augmented Lagrangian, which copes with all three; large batches go on (those
            # instances change working set or reach the interior point) rather than pay it.
            direct = q.shape[0] > LU_MAX_BATCH or bool((res <= tol_r).all())
            x, z = (x_d, z_d) if direct else (x, z)
        if not direct:
            # Singular or ill-conditioned KKT matrix (dependent working rows, P singular on their
            # null space): the proximal augmented Lagrangian handles both.
            x = x if x is not None else q.new_zeros(q.shape[0], n)
            if row_sq is None:
                row_sq = (C * C).sum(-1)
            x, z, stat, viol = eq_solve_alm(P, q, C, d, mask, z, x, 1e-2 * tol, row_sq, RHO_FAST)
            res = torch.maximum(stat, (viol * mask).abs().amax(-1))
            vG, zG = viol[:, p:], z[:, p:]
            ok = (res <= tol_r) & kkt_certified(P, q, A, b, G, h, x, z[:, :p], zG, tol)
        n_ok = int(ok.sum())
        if n_ok and out is None and n_ok == ok.shape[0]:
            return x, z[:, :p], z[:, p:], ok, torch.full((B,), k + 1, dtype=torch.long, device=q.device)
        if n_ok and out is None:
            # First partial success: from now on certified instances are written out and dropped.
            idx = torch.arange(B, device=q.device)
            out = (q.new_zeros(B, n), q.new_zeros(B, p + m), torch.zeros(B, dtype=torch.bool, device=q.device),
                   torch.full((B,), max_iter, dtype=torch.long, device=q.device))
        if n_ok:
            ok_i = ok.nonzero().squeeze(-1)
            sel = idx[ok_i]
            out[0][sel], out[1][sel], out[2][sel], out[3][sel] = x[ok_i], z[ok_i], True, k + 1
        if n_ok == ok.shape[0] or k == max_iter - 1:
            break
        # Semismooth Newton step on min(z, h − Gx) = 0: keep working rows with positive
        # multipliers, add the violated rows.
        # "Violated" as in the certificate: beyond the row's own tolerance at the current point.
        W = (W & (zG > 0)) | (~W & (vG > row_thresholds(G, h, x, tol)))
        if n_ok:
            # Drop certified instances (one integer index, reused; C and d alias G and h if p = 0).
            keep = (~ok).nonzero().squeeze(-1)
            idx, P, q, G, h, x, z, W, tol_r = (
                t.index_select(0, keep) for t in (idx, P, q, G, h, x, z, W, tol_r)
            )
            A, b = A.index_select(0, keep), b.index_select(0, keep)
            C, d = (torch.cat([A, G], 1), torch.cat([b, h], 1)) if p else (G, h)
            row_sq = row_sq.index_select(0, keep) if row_sq is not None else None
            L, x_u = (L.index_select(0, keep), x_u.index_select(0, keep)) if L is not None else (None, None)
    if out is None:  # nothing certified: every instance goes on to the interior point
        return q.new_zeros(B, n), q.new_zeros(B, p), q.new_zeros(B, m), torch.zeros(B, dtype=torch.bool, device=q.device), torch.full(
            (B,), max_iter, dtype=torch.long, device=q.device)
    return out[0], out[1][:, :p], out[1][:, p:], out[2], out[3]
