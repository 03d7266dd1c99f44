"""Per-instance outcome codes of the batched QP solver.

Which inputs give which status (every route: C, torch; any batch size; one instance's status never
depends on the rest of its batch):

| status | value | when | x |
|---|---:|---|---|
| SOLVED | 0 | KKT conditions certified a posteriori within `tol`, each row relative to its own data | the solution |
| MAX_ITER | 1 | the interior point used its `max_iter` iterations without a certificate either way; with `hand_on=False`, an instance the C route could not decide | last iterate (finite); 0 |
| PRIMAL_INFEASIBLE | 2 | a Farkas certificate (z ≥ 0, Gᵀz + Aᵀy ≈ 0, hᵀz + bᵀy < 0) was found; or a row h_i ≤ −1e20, a bound lb_j ≥ 1e20 or ub_j ≤ −1e20 (−inf/+inf of the wrong sign), or lb_j > ub_j; the C route finds it where Goldfarb-Idnani's test fires (a violated row that is a combination of the working rows, no dual step left), with the same test on that vector | 0 |
| DUAL_INFEASIBLE | 3 | the objective is unbounded below: a direction d with P d ≈ 0, A d ≈ 0, G d ≤ 0, qᵀd < 0 was found | 0 |
| NON_CONVEX | 4 | P (symmetrised) is not positive semi-definite: its smallest eigenvalue is below −1e-9·max|λ| | 0 |
| INVALID_INPUT | 5 | NaN anywhere, or ±inf in P, q, A, b or G (h, lb, ub may be ±inf) | 0 |
| TOLERANCE_NOT_MET | 6 | float32 (or float16/bfloat16) input: the float64 solution, rounded to the input's dtype, misses `tol`; or an answer the solver's stages reached that the final KKT certificate refuses (none seen in the sweeps of docs/qp.md since 2026-12-03) | the rounded solution; the last iterate |

A right-hand side or bound with |value| ≥ 1e20 (or ±inf) of the "no constraint" sign is dropped, as
peers write "no bound" as ±1e20.  Tolerances are per row: row i of Gx ≤ h is satisfied when
G_i x − h_i ≤ tol·(1 + |h_i| + Σ_j |G_ij x_j|), so one large bound does not loosen the others.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = ["QPStatus"]


class QPStatus(IntEnum):
    """Per-instance outcome codes stored in `QPSolution.status` (see the module docstring's table)."""

    SOLVED = 0
    """Optimal to the requested tolerance (KKT conditions certified a posteriori)."""
    MAX_ITER = 1
    """Iteration budget exhausted without a certificate; x is the last iterate (finite)."""
    PRIMAL_INFEASIBLE = 2
    """No x satisfies the constraints (a Farkas certificate, or a bound of the wrong sign at infinity)."""
    DUAL_INFEASIBLE = 3
    """The objective is unbounded below on the feasible set (a recession direction was found)."""
    NON_CONVEX = 4
    """P is not positive semi-definite: the QP is not convex and no answer is given."""
    INVALID_INPUT = 5
    """NaN in the data, or ±inf where only finite values make sense (P, q, A, b, G)."""
    TOLERANCE_NOT_MET = 6
    """The answer (rounded to the input's lower precision, if any) misses the tolerance of the final certificate."""
