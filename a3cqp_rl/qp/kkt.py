"""Batched solves of equality-constrained KKT systems [[P, C_Wᵀ], [C_W, 0]] on a working set W.

Three routes to the same answer, chosen by the callers for latency or throughput: a dense LU of
the masked KKT matrix (small batches), a Schur complement on the gathered working rows (large
batches, P definite), and a proximal augmented Lagrangian (any PSD P, dependent rows).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["mv", "mtv", "cholesky_safe", "diag_scale", "eq_solve_alm", "kkt_lu", "kkt_schur", "kkt_certified",
           "row_thresholds", "RHO", "RHO_FAST", "MAX_SWEEPS", "LU_MAX_BATCH"]


def mv(M: Tensor, v: Tensor) -> Tensor:
    """Batched matrix-vector product [B, r, c] x [B, c] -> [B, r]."""
    return (M @ v.unsqueeze(-1)).squeeze(-1)


def mtv(M: Tensor, v: Tensor) -> Tensor:
    """Batched transposed product Mᵀv: [B, r, c] x [B, r] -> [B, c]."""
    # Broadcast-multiply and reduce: for these tiny matrices ~2x faster than a [B, 1, r] bmm.
    return (M * v.unsqueeze(-1)).sum(-2)


def row_thresholds(G: Tensor, h: Tensor, x: Tensor, tol: float) -> Tensor:
    """Per-row feasibility tolerance [B, m]: tol (1 + |h_i| + Σ_j |G_ij x_j|), the size of the row's own terms."""
    return tol * (1.0 + h.abs() + mv(G.abs(), x.abs()))


def kkt_certified(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, x: Tensor, y: Tensor, z: Tensor, tol: float,
) -> Tensor:
    """Whether (x, y, z) satisfies the KKT conditions within tol, row by row [B] (bool).

    Each residual is measured against the magnitude of its own terms, so one large right-hand side
    loosens only its own row: stationarity |(Px + q + Aᵀy + Gᵀz)_j| ≤ tol (1 + |q_j| + Σ|P_jk x_k| +
    Σ|A_ij y_i| + Σ|G_ij z_i|), equalities and inequalities as in `row_thresholds`, multipliers
    z ≥ −tol (1 + max|z|), complementarity z_i · slack_i ≤ tol (1 + max|z|) (1 + |h_i| + Σ|G_ij x_j|).
    The C route certifies with the same inequalities (gi_qp.c, `certify`).
    """
    ax = x.abs()
    # stationarity with the multipliers as returned (clamped at 0): a slightly negative z_i that the sign test
    # accepts can be worth a large residual on a row of large norm
    zc = z.clamp_min(0.0)
    r = mv(P, x) + q + mtv(G, zc)
    mag = 1.0 + q.abs() + mv(P.abs(), ax) + mtv(G.abs(), zc)
    if A.shape[1]:
        r = r + mtv(A, y)
        mag = mag + mtv(A.abs(), y.abs())
    ok = (r.abs() <= tol * mag).all(-1)
    if A.shape[1]:
        ok &= ((mv(A, x) - b).abs() <= row_thresholds(A, b, x, tol)).all(-1)
    if G.shape[1]:
        thr = row_thresholds(G, h, x, tol)
        viol = mv(G, x) - h
        zs = 1.0 + z.abs().amax(-1, keepdim=True)
        ok &= (viol <= thr).all(-1) & (z >= -tol * zs).all(-1)
        ok &= (z.clamp_min(0.0) * (-viol).clamp_min(0.0) <= thr * zs).all(-1)
    return ok


def cholesky_safe(H: Tensor, scale: Tensor) -> Tensor:
    """Cholesky factor of a batch of SPD matrices, re-regularising the few that fail."""
    L, info = torch.linalg.cholesky_ex(H)
    if bool((info != 0).any()):
        # Numerically indefinite (e.g. P singular along a free direction): add a larger diagonal to
        # the failed ones only; the outer iterations correct the resulting inexact steps.
        eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
        bump = torch.where(info != 0, 1e-7 * scale, torch.zeros_like(scale))
        L, info = torch.linalg.cholesky_ex(H + bump[:, None, None] * eye)
        if bool((info != 0).any()):
            L = torch.where((info != 0)[:, None, None], eye.expand_as(H), L)
    return L


def diag_scale(P: Tensor) -> Tensor:
    """Typical curvature of P per instance [B] (mean diagonal, floored so LPs get a sane scale)."""
    return P.diagonal(dim1=-2, dim2=-1).mean(-1).abs().clamp_min(1e-6)


RHO = 1e3
"""Augmented-Lagrangian penalty relative to P's curvature and each row's squared norm: a sweep
shrinks the constraint error ~1e3-fold while the Cholesky solve keeps x accurate to ~1e-13, which
finite-difference gradient checks need.  The batched forward stage uses RHO_FAST (fewer sweeps,
x accurate to ~1e-11, still 100× inside the default tolerance)."""
RHO_FAST = 1e5
MAX_SWEEPS = 8


def eq_solve_alm(
    P: Tensor, q: Tensor, C: Tensor, d: Tensor, mask: Tensor, z: Tensor, x: Tensor, tol: float,
    row_sq: Tensor | None = None, rho_rel: float = RHO,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Solve min ½xᵀPx + qᵀx s.t. C_i x = d_i for rows with mask_i, by proximal augmented Lagrangian.

    One Cholesky of P + C_Wᵀ diag(ρ) C_W + δI, then multiplier sweeps until |C_W x − d_W| ≤ tol (at
    most MAX_SWEEPS); the matrix stays positive definite for PSD P and for dependent rows.
    `row_sq` [B, r] (squared row norms) may be passed to save a pass over C.  Returns x [B, n],
    z [B, r] (zero on unmasked rows), the stationarity residual [B] (P x + q + Cᵀz = δ(x_prev − x)
    by construction) and C x − d [B, r] for all rows.
    """
    n = P.shape[-1]
    scale = diag_scale(P)
    if row_sq is None:
        row_sq = (C * C).sum(-1)
    maskf = mask.to(P.dtype)
    # Penalty per row relative to its squared norm, so the conditioning does not depend on how the
    # rows are scaled; zero on rows outside the working set, which therefore never enter H.
    rho = (rho_rel * scale)[:, None] * maskf / row_sq.clamp_min(1e-30)  # [B, r]
    delta = (1e-10 * scale)[:, None]
    eye = torch.eye(n, dtype=P.dtype, device=P.device)
    H = torch.baddbmm(P + delta.unsqueeze(-1) * eye, C.mT, C * rho.unsqueeze(-1))
    L = cholesky_safe(H, scale)
    z = z * maskf
    # Masking vectors instead of C: each sweep reads C twice (Cᵀv, Cx), the bandwidth floor.
    for k in range(MAX_SWEEPS):
        # H x = −q − C_Wᵀ(z − ρd) + δ x_prev : minimiser of the augmented, proximal Lagrangian.
        rhs = delta * x - q - mtv(C, z - rho * d)
        x_prev = x
        x = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1)
        viol = mv(C, x) - d
        err = viol * maskf
        z = z + rho * err
        if k >= 1 and (err.numel() == 0 or bool(err.abs().amax() <= tol)):
            break
    # Stationarity residual left by the proximal term: P x + q + Cᵀz = δ (x_prev − x).  It is only
    # large where P is singular along a direction no active row fixes (unbounded or not yet bounded).
    return x, z, (delta * (x - x_prev)).abs().amax(-1), viol


LU_MAX_BATCH = 32
"""Up to this batch size the active-set KKT system is solved directly by one batched LU (fewest
torch ops, i.e. lowest latency); above it, by the augmented-Lagrangian Cholesky (fewest flops)."""


def kkt_lu(P: Tensor, q: Tensor, C: Tensor, d: Tensor, mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Solve [[P, C_Wᵀ], [C_W, 0]] (x, z_W) = (−q, d_W) by LU; unmasked rows get z = 0.

    Returns (x, z, residual [B]): the max-norm residual of the whole KKT system, computed a
    posteriori, so a singular or ill-conditioned matrix (dependent working rows, P singular on
    their null space) shows up as a large or NaN residual and the caller falls back.
    """
    n = P.shape[-1]
    if C.shape[0] == 1:
        # Single instance (the control loop): keep only the working rows, an (n + k) × (n + k)
        # system with k ≈ 0-5 instead of n + r ≈ 40-70 (LU cost is cubic).
        rows = mask[0].nonzero().squeeze(-1)  # (k,)
        Cw = C[:, rows]
        K = torch.cat([torch.cat([P, Cw.mT], 2), torch.cat([Cw, Cw.new_zeros(1, rows.shape[0], rows.shape[0])], 2)], 1)
        rhs = torch.cat([-q, d[:, rows]], 1)
        sol = torch.linalg.solve_ex(K, rhs)[0]
        res = torch.baddbmm(rhs.unsqueeze(-1), K, sol.unsqueeze(-1), beta=-1.0).abs().amax((-2, -1))
        return sol[:, :n], torch.zeros_like(d).index_copy_(1, rows, sol[:, n:]), res
    maskf = mask.to(P.dtype)
    Cm = C * maskf.unsqueeze(-1)  # (B, r, n)
    # Inactive rows become −z_i = 0, so every instance keeps the same (n + r) × (n + r) shape.
    K = torch.cat([torch.cat([P, Cm.mT], 2), torch.cat([Cm, torch.diag_embed(maskf - 1.0)], 2)], 1)
    rhs = torch.cat([-q, d * maskf], 1)
    sol = torch.linalg.solve_ex(K, rhs)[0]
    res = torch.baddbmm(rhs.unsqueeze(-1), K, sol.unsqueeze(-1), beta=-1.0).abs().amax((-2, -1))
    return sol[:, :n], sol[:, n:], res


def kkt_schur(L: Tensor, x_u: Tensor, P: Tensor, q: Tensor, C: Tensor, d: Tensor, mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Solve the working-set KKT system through the Schur complement on the working rows only.

    With L = chol(P) and x_u = −P⁻¹q computed once per solve, only the k = max |W| working rows are
    gathered (k is a handful while C has 30+ rows), so each active-set iteration costs O(n²k)
    instead of O(n²m) and needs no sweeps: S = C_W P⁻¹ C_Wᵀ, S z_W = C_W x_u − d_W,
    x = x_u − P⁻¹ C_Wᵀ z_W.  Returns (x, z, KKT residual [B]); singular S gives a large or NaN
    residual and the caller falls back.
    """
    B, r, n = C.shape
    k = int(mask.sum(-1).max()) if r else 0
    if k == 0:
        res = torch.baddbmm(q.unsqueeze(-1), P, x_u.unsqueeze(-1)).abs().amax((-2, -1))
        return x_u, torch.zeros_like(d), res
    order = torch.argsort(mask.to(torch.int8), dim=1, descending=True, stable=True)[:, :k]  # (B, k)
    mkf = mask.gather(1, order).to(P.dtype)  # 1 on working rows, 0 on padding
    Ck = C.gather(1, order.unsqueeze(-1).expand(B, k, n)) * mkf.unsqueeze(-1)  # (B, k, n)
    dk = d.gather(1, order) * mkf
    Y = torch.linalg.solve_triangular(L, Ck.mT, upper=False)  # (B, n, k) = L⁻¹C_Wᵀ
    S = torch.baddbmm(torch.diag_embed(1.0 - mkf), Y.mT, Y)  # padding rows: identity, z = 0
    Ls, info = torch.linalg.cholesky_ex(S)
    zk = torch.cholesky_solve((mv(Ck, x_u) - dk).unsqueeze(-1), Ls) * mkf.unsqueeze(-1)  # (B, k, 1)
    x = x_u - torch.linalg.solve_triangular(L.mT, Y @ zk, upper=True).squeeze(-1)
    zk = zk.squeeze(-1)
    z = torch.zeros_like(d).scatter(1, order, zk)
    stat = (torch.baddbmm(q.unsqueeze(-1), P, x.unsqueeze(-1)).squeeze(-1) + mtv(Ck, zk)).abs().amax(-1)
    res = torch.maximum(stat, (mv(Ck, x) - dk).abs().amax(-1))
    return x, z, torch.where(info == 0, res, torch.full_like(res, torch.inf))
