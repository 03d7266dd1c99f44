"""Random batches of controller-sized QPs with a known feasible point, shared by tests and bench."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["RandomQP", "random_qp_batch"]


@dataclass
class RandomQP:
    """A batch of QPs in `solve_qp` form (A/b, lb/ub may be None) and a strictly feasible point."""

    P: Tensor
    q: Tensor
    A: Tensor | None
    b: Tensor | None
    G: Tensor
    h: Tensor
    lb: Tensor | None
    ub: Tensor | None
    x_feasible: Tensor

    def args(self) -> tuple[Tensor | None, ...]:
        """Positional arguments (P, q, A, b, G, h, lb, ub) for `solve_qp`."""
        return self.P, self.q, self.A, self.b, self.G, self.h, self.lb, self.ub


def random_qp_batch(
    batch: int,
    n: int = 13,
    m: int = 30,
    p: int = 0,
    bounds: bool = False,
    spread: float = 0.015,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> RandomQP:
    """Random strictly convex QPs shaped like the controller's (n vars, m rows, p equalities).

    A point x_f near the unconstrained minimiser x_u is made strictly feasible (slacks U(0, 1));
    `spread` (distance of x_f from x_u, in units of a standard normal step) sets how many
    instances have active constraints: 0.015 gives roughly 30-50 % with m = 30.
    """
    g = torch.Generator().manual_seed(seed)
    M = torch.randn(batch, n, n, generator=g, dtype=dtype)
    P = M @ M.mT / n + 0.5 * torch.eye(n, dtype=dtype)  # (B, n, n), eigenvalues ~0.5-4.5
    q = torch.randn(batch, n, generator=g, dtype=dtype)
    x_u = -torch.linalg.solve(P, q)
    x_f = x_u + spread * torch.randn(batch, n, generator=g, dtype=dtype)
    G = torch.randn(batch, m, n, generator=g, dtype=dtype)
    h = (G @ x_f.unsqueeze(-1)).squeeze(-1) + torch.rand(batch, m, generator=g, dtype=dtype)
    A = b = lb = ub = None
    if p:
        A = torch.randn(batch, p, n, generator=g, dtype=dtype)
        b = (A @ x_f.unsqueeze(-1)).squeeze(-1)
    if bounds:
        lb = x_f - 0.2 - torch.rand(batch, n, generator=g, dtype=dtype)
        ub = x_f + 0.2 + torch.rand(batch, n, generator=g, dtype=dtype)
    return RandomQP(P, q, A, b, G, h, lb, ub, x_f)


def clarabel_reference(qp: RandomQP, tol: float = 1e-12) -> tuple[Tensor, list[str]]:
    """Solve each instance with cvxpy + Clarabel (one DPP problem, re-parametrised); returns x [B, n], statuses."""
    import cvxpy as cp
    import numpy as np

    B, n = qp.q.shape
    x = cp.Variable(n)
    Lt, qv = cp.Parameter((n, n)), cp.Parameter(n)
    Gp, hp = cp.Parameter(qp.G.shape[1:]), cp.Parameter(qp.h.shape[1])
    cons = [Gp @ x <= hp]
    params = [(Lt, torch.linalg.cholesky(qp.P).mT), (qv, qp.q), (Gp, qp.G), (hp, qp.h)]
    if qp.A is not None:
        Ap, bp = cp.Parameter(qp.A.shape[1:]), cp.Parameter(qp.b.shape[1])
        cons.append(Ap @ x == bp)
        params += [(Ap, qp.A), (bp, qp.b)]
    if qp.lb is not None:
        lp, up = cp.Parameter(n), cp.Parameter(n)
        cons += [x >= lp, x <= up]
        params += [(lp, qp.lb), (up, qp.ub)]
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(Lt @ x) + qv @ x), cons)
    xs, statuses = np.zeros((B, n)), []
    values = [(par, val.detach().double().cpu().numpy()) for par, val in params]
    for i in range(B):
        for par, val in values:
            par.value = val[i]
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol, tol_ktratio=1e-8)
        statuses.append(prob.status)
        xs[i] = x.value if x.value is not None else np.nan
    return torch.as_tensor(xs, dtype=qp.q.dtype), statuses
