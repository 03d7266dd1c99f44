"""Stage 2 of the solver: batched Mehrotra predictor-corrector interior point with infeasibility detection."""

from __future__ import annotations

import torch
from torch import Tensor

from a3cqp_rl.qp.kkt import cholesky_safe, diag_scale, mtv, mv, row_thresholds
from a3cqp_rl.qp.active_set import residual_scales
from a3cqp_rl.qp.status import QPStatus

__all__ = ["NormalEquations", "max_step", "interior_point"]


STATIC_REG = 1e-9
"""Static regularisation of the Newton matrix P + GᵀDG, relative to 1 + max diag(P) (rows are unit-norm
here).  Where P is singular along directions no row fixes (LPs, optimal faces), the matrix is singular
there; a regularisation tied to P's mean curvature (zero for an LP) left those directions to rounding
and the steps collapsed (measured: 6 of 30 random LPs with unbounded optimal faces stalled at
MAX_ITER); relative to the whole matrix (whose diagonal grows as z/s ~ 1/μ on active rows) it swamped
the inactive directions and the dual residual stalled instead."""


class NormalEquations:
    """Factorisation of [[H, Aᵀ], [A, 0]] via H + ρAᵀA (kept SPD) and a p × p Schur complement."""

    def __init__(self, H: Tensor, A: Tensor, scale: Tensor) -> None:
        self.A = A
        self.p = A.shape[1]
        if self.p:
            # Adding ρAᵀA does not change the solution (A dx is fixed) but keeps the matrix SPD
            # when P is only positive semi-definite on the null space of A.
            self.rho = scale[:, None, None]
            H = H + self.rho * (A.mT @ A)
        self.L = cholesky_safe(H, scale)
        if self.p:
            self.X = torch.cholesky_solve(A.mT, self.L)  # (B, n, p) = H⁻¹Aᵀ
            S = A @ self.X
            eps = 1e-12 * S.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-30)
            S = S + eps[:, None, None] * torch.eye(self.p, dtype=H.dtype, device=H.device)
            self.Ls = cholesky_safe(S, eps * 1e12)

    def solve(self, rx: Tensor, ry: Tensor) -> tuple[Tensor, Tensor]:
        """Solve H dx + Aᵀ dy = rx, A dx = ry for (dx [B, n], dy [B, p])."""
        if not self.p:
            return torch.cholesky_solve(rx.unsqueeze(-1), self.L).squeeze(-1), ry
        u = torch.cholesky_solve((rx + self.rho[:, :, 0] * mtv(self.A, ry)).unsqueeze(-1), self.L)
        dy = torch.cholesky_solve(self.A @ u - ry.unsqueeze(-1), self.Ls)
        return (u - self.X @ dy).squeeze(-1), dy.squeeze(-1)


def max_step(s: Tensor, ds: Tensor, z: Tensor, dz: Tensor) -> Tensor:
    """Largest α ∈ [0, 1] with s + α ds ≥ 0 and z + α dz ≥ 0 (s, z > 0), per instance [B]."""
    # α_max = 1 / max(1, max_i(−dv_i / v_i)): no masking needed since v > 0.
    worst = (torch.cat([ds, dz], -1) / torch.cat([s, z], -1)).amin(-1)  # most negative dv / v
    return (-worst).clamp_min(1.0).reciprocal()


def interior_point(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, tol: float, max_iter: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Interior-point stage; returns x, y, z, status, iterations for each instance."""
    B, n = q.shape
    p, m = A.shape[1], G.shape[1]
    dt = q.dtype
    eye = torch.eye(n, dtype=dt, device=q.device)
    scale = diag_scale(P)
    # Static regularisation on the scale of the data (unit-norm rows, P's largest curvature), not of
    # the Newton matrix, whose diagonal grows with the barrier weights z/s of the active rows.
    reg = (STATIC_REG * (1.0 + P.diagonal(dim1=-2, dim2=-1).abs().amax(-1)))[:, None, None] * eye
    _, sd = residual_scales(q, b, h)
    tol_d = tol * sd  # complementarity (μ), per instance

    # Cold start (as CVXOPT): least-squares point of the KKT system with unit weights, then shift
    # slacks and multipliers into the positive orthant.
    kkt = NormalEquations(torch.baddbmm(P + reg, G.mT, G), A, scale)
    x, y = kkt.solve(mtv(G, h) - q, b)
    s = h - mv(G, x)
    z = -s
    s = s + torch.where(s.amin(-1, keepdim=True) < 1e-8, 1.0 - s.amin(-1, keepdim=True), 0.0)
    z = z + torch.where(z.amin(-1, keepdim=True) < 1e-8, 1.0 - z.amin(-1, keepdim=True), 0.0)
    dx = torch.zeros_like(x)
    Gdx = torch.zeros_like(h)

    idx = torch.arange(B, device=q.device)
    x_out, y_out, z_out = q.new_zeros(B, n), q.new_zeros(B, p), q.new_zeros(B, m)
    st_out = torch.full((B,), int(QPStatus.MAX_ITER), dtype=torch.long, device=q.device)
    it_out = torch.full((B,), max_iter, dtype=torch.long, device=q.device)

    def emit(mask: Tensor, status: Tensor, it: int) -> None:
        sel = idx[mask]
        x_out[sel], y_out[sel], z_out[sel] = x[mask], y[mask], z[mask]
        st_out[sel], it_out[sel] = status[mask], it

    for it in range(max_iter + 1):
        ray = mtv(G, z) + mtv(A, y) if p else mtv(G, z)  # Gᵀz + Aᵀy
        rd = torch.baddbmm(q.unsqueeze(-1), P, x.unsqueeze(-1)).squeeze(-1) + ray
        if p:
            rp = mv(A, x) - b
        ri = mv(G, x) + s - h
        mu = (s * z).sum(-1) / m
        # Residuals row by row, each against the size of its own terms (kkt.row_thresholds).
        ax = x.abs()
        thr_g = row_thresholds(G, h, x, tol)
        ok_p = (ri.abs() <= thr_g).all(-1)
        if p:
            ok_p &= (rp.abs() <= row_thresholds(A, b, x, tol)).all(-1)
        mag_d = 1.0 + q.abs() + mv(P.abs(), ax) + mtv(G.abs(), z) + (mtv(A.abs(), y.abs()) if p else 0.0)
        # complementarity row by row as the final certificate (kkt_certified) measures it, on the slack h − Gx: the
        # mean μ alone let an iterate through that the certificate then refused (dependent active rows)
        compl = (z * (s - ri).clamp_min(0.0) <= thr_g * (1.0 + z.abs().amax(-1, keepdim=True))).all(-1)
        solved = ok_p & (rd.abs() <= tol * mag_d).all(-1) & (mu <= tol_d) & compl
        # Farkas certificate: z ≥ 0, Gᵀz + Aᵀy ≈ 0 and hᵀz + bᵀy < 0, relative to |hᵀz + bᵀy|, which
        # bounds the norm of any feasible point from below by 1/1e-7.
        gap = (h * z).sum(-1) + ((b * y).sum(-1) if p else 0.0)
        pinf = (gap < 0) & (ray.abs().amax(-1) <= -1e-7 * gap) & ~solved
        # Recession direction from the last step: P d ≈ 0, A d ≈ 0, G d ≤ 0 and qᵀd < 0.
        qd = (q * dx).sum(-1)
        dref = -1e-7 * qd
        dinf = (qd < 0) & (mv(P, dx).abs().amax(-1) <= dref) & (Gdx.amax(-1) <= dref) & ~solved & ~pinf
        if p:
            dinf = dinf & (mv(A, dx).abs().amax(-1) <= dref)
        done = solved | pinf | dinf
        if bool(done.any()) or it == max_iter:
            status = torch.where(solved, 0, torch.where(pinf, int(QPStatus.PRIMAL_INFEASIBLE), int(QPStatus.DUAL_INFEASIBLE)))
            emit(done, status, it)
            if it == max_iter or bool(done.all()):
                if it == max_iter and not bool(done.all()):
                    emit(~done, torch.full_like(status, int(QPStatus.MAX_ITER)), it)
                break
            keep = ~done
            idx, P, q, A, b, G, h, x, y, z, s, dx, Gdx = (t[keep] for t in (idx, P, q, A, b, G, h, x, y, z, s, dx, Gdx))
            rd, ri, mu, tol_d, scale, reg = rd[keep], ri[keep], mu[keep], tol_d[keep], scale[keep], reg[keep]
            if p:
                rp = rp[keep]
        ry = -rp if p else y
        kkt = NormalEquations(torch.baddbmm(P + reg, G.mT, G * (z / s).unsqueeze(-1)), A, scale)

        def direction(rc: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
            # Eliminate ds, dz: (P + GᵀDG) dx + Aᵀdy = −rd − Gᵀ S⁻¹(−rc + Z ri), D = Z S⁻¹.
            ddx, ddy = kkt.solve(-rd - mtv(G, (z * ri - rc) / s), ry)
            dds = -ri - mv(G, ddx)
            ddz = (-rc - z * dds) / s
            return ddx, ddy, dds, ddz

        # Predictor (affine scaling) then Mehrotra corrector with centring σ = (μ_aff / μ)³.
        dx, dy, ds, dz = direction(s * z)
        a = max_step(s, ds, z, dz).unsqueeze(-1)
        mu_aff = ((s + a * ds) * (z + a * dz)).sum(-1) / m
        sigma = (mu_aff / mu).clamp(0.0, 1.0) ** 3
        dx, dy, ds, dz = direction(s * z + ds * dz - (sigma * mu).unsqueeze(-1))
        a = (0.99 * max_step(s, ds, z, dz)).unsqueeze(-1)
        dx = a * dx
        Gdx = a * (-ri - ds)  # = G dx, from the eliminated row G dx + ds = −ri (saves a pass over G)
        x, s, z = x + dx, s + a * ds, z + a * dz
        if p:
            y = y + a * dy
        # Keep the iterate strictly interior despite rounding.
        s, z = s.clamp_min(1e-300), z.clamp_min(1e-300)
    return x_out, y_out, z_out, st_out, it_out
