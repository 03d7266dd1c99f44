"""`QPLayer`: a cvxpy-declared parametric QP evaluated in batch by the torch solver (cvxpylayers API).

cvxpy canonicalises the problem once (its DPP path for a QP-capable conic solver), which gives the
problem data as *affine* maps of the stacked parameter vector θ (last entry 1):

    vec(P) = M_P θ,   [q; d] = M_q θ,   vec([A_cone  b_cone]) = M_A θ   (column-major),

with constraints A_cone x + b_cone ∈ {0}^p × R₊^m.  We keep the three maps as sparse torch
matrices; a batch of parameter tensors then costs three sparse-dense products to build
(P, q, A, b, G, h) = (P, q, A_0, −b_0, −A_+, b_+), one `solve_qp`, and a column gather to return the
requested variables.  Gradients flow back through the same products, so the layer is
differentiable with respect to every parameter (through the primal variables; requested multipliers are
returned as values without gradient).

As cvxpylayers' `CvxpyLayer`: variables with attributes (nonneg, bounds=...) are supported (cvxpy
lowers them to fresh variables and constraints; the maps of the canonicalisation chain say where
each ended up), `variables` may list constraints' dual variables (`con.dual_variables[0]`), an
unbatched call returns unbatched values, `solver_args` are accepted at construction and per call, and
an instance without a solution raises (`QPInfeasibleError`, naming the status) unless the layer was
built with `on_failure="nan"`, which returns NaN for those instances and the status tensor last.
"""

from __future__ import annotations

import math
import warnings
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from a3cqp_rl.qp.exceptions import NotAQPError, NotDPPError, QPInfeasibleError, QPShapeError
from a3cqp_rl.qp.solver import QPSolution, solve_qp
from a3cqp_rl.qp.status import QPStatus

__all__ = ["QPLayer"]


def _sparse(mat, dtype: torch.dtype) -> Tensor:
    """scipy sparse matrix -> torch sparse COO tensor."""
    coo = mat.tocoo()
    idx = torch.as_tensor(np.vstack([coo.row, coo.col]), dtype=torch.long)
    return torch.sparse_coo_tensor(idx, torch.as_tensor(coo.data, dtype=dtype), coo.shape, check_invariants=True).coalesce()


_SOLVER_ARGS = {"tol": "tol", "eps": "tol", "max_iter": "max_iter", "max_iters": "max_iter",
                "active_set_iter": "active_set_iter", "backend": "backend", "warm_start": "warm_start"}
"""solver_args keys accepted (cvxpylayers' names eps / max_iters included) -> `solve_qp` keyword."""


def _solver_kwargs(args: dict | None) -> dict:
    """`solve_qp` keywords from a solver_args dict; unknown keys are refused by name."""
    out = {}
    for k, v in (args or {}).items():
        if k not in _SOLVER_ARGS:
            raise QPShapeError(f"unknown solver_args key {k!r}; accepted: {sorted(_SOLVER_ARGS)}")
        out[_SOLVER_ARGS[k]] = v
    return out


class QPLayer(torch.nn.Module):
    """Differentiable batched QP declared with cvxpy: layer(*parameter_tensors) -> variable values.

    Args:
        problem: a DPP-compliant `cvxpy.Problem` whose canonical form is a QP (quadratic or linear
            objective, affine equalities and inequalities); SOC/exponential/PSD cones are rejected.
        parameters: the problem's `cvxpy.Parameter`s, in the order their tensors are passed.
        variables: the `cvxpy.Variable`s whose values the layer returns, in that order; a constraint's
            dual variable (`con.dual_variables[0]`) returns that constraint's multipliers (≥ 0 for
            inequalities, cvxpy's sign convention). Multipliers are values only: gradients flow through the
            primal variables, never through a multiplier (a warning says so when parameters require grad).
        dtype: dtype of the extracted maps (float64 by default); inputs are cast to it.
        solver_args: default `solve_qp` keywords (tol / eps, max_iter / max_iters, active_set_iter,
            backend, warm_start); a call's own solver_args override them.
        on_failure: "raise" (default): an instance that is not SOLVED raises QPInfeasibleError;
            "nan": its values are NaN and forward returns the status tensor [B] after the values.
    """

    def __init__(
        self,
        problem,
        parameters: Sequence,
        variables: Sequence,
        dtype: torch.dtype = torch.float64,
        solver_args: dict | None = None,
        on_failure: str = "raise",
    ) -> None:
        super().__init__()
        import cvxpy as cp

        if on_failure not in ("raise", "nan"):
            raise QPShapeError(f"on_failure must be 'raise' or 'nan', got {on_failure!r}")
        self.solver_args = _solver_kwargs(solver_args)
        self.on_failure = on_failure
        if not problem.is_dcp(dpp=True):
            if problem.is_dcp():
                raise NotDPPError("problem is DCP but not DPP: parameters must enter affinely (see cvxpy's DPP rules)")
            raise NotAQPError("problem is not DCP, so it is not a convex QP")
        if set(p.id for p in parameters) != set(p.id for p in problem.parameters()):
            raise QPShapeError("`parameters` must list exactly the parameters of the problem")
        duals = {dv.id: con for con in problem.constraints for dv in con.dual_variables}
        primal_ids = {v.id for v in problem.variables()}
        for v in variables:
            if v.id not in primal_ids and v.id not in duals:
                raise QPShapeError(f"`variables` must be variables of the problem or its constraints' dual variables, got {v}")
        data, chain, _ = problem.get_problem_data(cp.CLARABEL)
        prog = data[cp.settings.PARAM_PROB]
        dims = prog.cone_dims
        if dims.exp or dims.soc or dims.psd or getattr(dims, "p3d", None) or getattr(dims, "pnd", None):
            raise NotAQPError(f"problem is not a QP: its canonical form has cones beyond equalities and inequalities ({dims})")
        if data.get("lower_bounds") is not None or data.get("upper_bounds") is not None:
            raise NotAQPError("variable bounds passed to the solver as bounds (not as constraints) are not supported")
        param_map = {k: v[0] for k, v in chain.compose_param_id_map().items()} if hasattr(chain, "compose_param_id_map") else {}
        cols = {}
        for p in parameters:
            pid = param_map.get(p.id, p.id)
            if pid not in prog.param_id_to_col or getattr(p, "_has_dim_reducing_attr", False):
                raise QPShapeError(
                    f"parameter {p.name()!r} was replaced during canonicalisation (attributes such as "
                    "symmetric/PSD/nonneg are not supported on parameters); declare plain Parameters"
                )
            cols[p.id] = int(prog.param_id_to_col[pid])
        self.n = int(prog.x.size)
        self.p, self.m = int(dims.zero), int(dims.nonneg)
        self.param_shapes = [tuple(p.shape) for p in parameters]
        self.param_cols = [cols[p.id] for p in parameters]
        self.theta_size = int(prog.total_param_size) + 1
        self.const_col = int(prog.param_id_to_col[-1])  # cvxpy's CONSTANT_ID column holds the 1
        n1 = self.n + 1
        self.register_buffer("M_q", _sparse(prog.q, dtype), persistent=False)
        self.register_buffer("M_A", _sparse(prog.A, dtype), persistent=False)
        if prog.P is not None:
            self.register_buffer("M_P", _sparse(prog.P, dtype), persistent=False)
        else:
            self.M_P = None
        # Where each requested value lives: ("x", column) in the primal vector, or ("dual", row) in the
        # stacked multipliers [y; z] of the canonical rows (Zero cone first, then NonNeg), as cvxpy
        # orders them; ids through the chain's maps, since lowered variables get fresh ids.
        var_map = {k: v[0] for k, v in chain.compose_var_id_map().items()}
        con_map = chain.compose_constr_id_map() if hasattr(chain, "compose_constr_id_map") else {}
        row_of, row = {}, 0
        for cone in (cp.constraints.Zero, cp.constraints.NonNeg):
            for c in prog.constr_map.get(cone, []):
                row_of[c.id] = row
                row += c.size
        self.var_slices = []
        for v in variables:
            if v.id in primal_ids:
                self.var_slices.append(("x", int(prog.var_id_to_col[var_map.get(v.id, v.id)]), int(v.size), tuple(v.shape)))
            else:
                con = duals[v.id]
                start = row_of[con_map.get(con.id, con.id)]
                self.var_slices.append(("dual", start, int(v.size), tuple(v.shape)))
        self.dtype = dtype
        self._n1 = n1

    def _theta(self, params: Sequence[Tensor]) -> tuple[Tensor, int, bool]:
        """θ [B, T + 1] in cvxpy's column-major order from (batched or not) parameter tensors; B; any batched."""
        if len(params) != len(self.param_shapes):
            raise QPShapeError(f"expected {len(self.param_shapes)} parameter tensors, got {len(params)}")
        params = [torch.as_tensor(t, dtype=self.dtype) if not isinstance(t, Tensor) else t for t in params]
        batched = [t.dim() == len(s) + 1 for t, s in zip(params, self.param_shapes)]
        sizes = {t.shape[0] for t, bt in zip(params, batched) if bt}
        if len(sizes) > 1:
            raise QPShapeError(f"batched parameters disagree on the batch size: {sorted(sizes)}")
        batch = sizes.pop() if sizes else 1
        ref = next((t for t in params), None)
        device = ref.device if ref is not None else None
        theta = torch.zeros(batch, self.theta_size, dtype=self.dtype, device=device)
        pieces, cols = [], []
        for t, shape, col, bt in zip(params, self.param_shapes, self.param_cols, batched):
            t = t.to(dtype=self.dtype, device=device)
            if tuple(t.shape[int(bt):]) != shape:
                raise QPShapeError(f"parameter tensor of shape {tuple(t.shape)} does not match {shape} (optionally batched)")
            if not bt:
                t = t.unsqueeze(0).expand(batch, *shape)
            # cvxpy flattens parameter values in Fortran (column-major) order.
            size = math.prod(shape)  # (not -1: a batch of 0 leaves it ambiguous)
            flat = t.permute(0, *range(t.dim() - 1, 0, -1)).reshape(batch, size) if len(shape) > 1 else t.reshape(batch, size)
            pieces.append(flat)
            cols.append(torch.arange(col, col + flat.shape[1], device=device))
        cols.append(torch.tensor([self.const_col], device=device))
        pieces.append(torch.ones(batch, 1, dtype=self.dtype, device=device))
        # index_copy is differentiable with respect to the copied values.
        theta = theta.index_copy(1, torch.cat(cols), torch.cat(pieces, 1))
        return theta, batch, any(batched)

    def problem_data(self, *params: Tensor) -> dict[str, Tensor]:
        """Batched canonical data (P, q, A, b, G, h) of the QP for these parameter values."""
        return self._data(params)[0]

    def _data(self, params: Sequence[Tensor]) -> tuple[dict[str, Tensor], bool]:
        theta, batch, any_batched = self._theta(params)
        thT = theta.mT  # (T + 1, B)
        n, n1, p = self.n, self._n1, self.p
        qd = torch.sparse.mm(self.M_q, thT).mT  # (B, n + 1)
        if self.M_P is not None:
            P = torch.sparse.mm(self.M_P, thT).mT.reshape(batch, n, n).mT  # column-major vec
        else:
            P = theta.new_zeros(batch, n, n)
        Ab = torch.sparse.mm(self.M_A, thT).mT.reshape(batch, n1, self.M_A.shape[0] // n1).mT  # (B, rows, n + 1)
        A_cone, b_cone = Ab[..., :n], Ab[..., n]
        data = {"P": P, "q": qd[:, :n], "A": A_cone[:, :p], "b": -b_cone[:, :p], "G": -A_cone[:, p:], "h": b_cone[:, p:]}
        return data, any_batched

    def solve(self, *params: Tensor, solver_args: dict | None = None, **solver_kwargs) -> tuple[tuple[Tensor, ...], QPSolution]:
        """Solve for a batch of parameter values; returns (values [B, *shape], full QPSolution), never raising on status."""
        values, sol, _ = self._solve(params, solver_args, solver_kwargs)
        return values, sol

    def _solve(self, params: Sequence[Tensor], solver_args: dict | None, solver_kwargs: dict) -> tuple[tuple[Tensor, ...], QPSolution, bool]:
        d, any_batched = self._data(params)
        A, b = (d["A"], d["b"]) if self.p else (None, None)
        G, h = (d["G"], d["h"]) if self.m else (None, None)
        kw = {**self.solver_args, **_solver_kwargs(solver_args), **solver_kwargs}
        sol = solve_qp(d["P"], d["q"], A, b, G, h, **kw)
        outs = []
        for kind, col, size, shape in self.var_slices:
            if kind == "x":
                v = sol.x[:, col : col + size]
            elif col < self.p:  # an equality's multiplier: cvxpy's sign is opposite to y of yᵀ(Ax − b)
                v = -sol.y[:, col : col + size].detach()  # (multipliers without gradient, as `forward` warns)
            else:
                v = sol.z[:, col - self.p : col - self.p + size].detach()
            # back from cvxpy's column-major vectorisation to the variable's shape
            v = v.reshape(v.shape[0], *reversed(shape)).permute(0, *range(len(shape), 0, -1)) if len(shape) > 1 else v.reshape(v.shape[0], *shape)
            outs.append(v)
        return tuple(outs), sol, any_batched

    def forward(self, *params: Tensor, solver_args: dict | None = None) -> tuple[Tensor, ...]:
        """Values [B, *var.shape] (or [*var.shape] when no parameter is batched) at the QP's solution (differentiable).

        Raises QPInfeasibleError for an instance that is not SOLVED, unless the layer was built with
        on_failure="nan" (then those values are NaN and the status tensor [B] (or []) comes last)."""
        outs, sol, any_batched = self._solve(params, solver_args, {})
        if (not getattr(self, "_dual_warned", False) and torch.is_grad_enabled()
                and any(kind == "dual" for kind, *_ in self.var_slices)
                and any(isinstance(t, Tensor) and t.requires_grad for t in params)):
            self._dual_warned = True
            warnings.warn("QPLayer returns constraints' multipliers without gradient: a loss that uses them gets "
                          "no gradient through them (the primal variables carry it)", stacklevel=2)
        status = sol.status
        bad = status != QPStatus.SOLVED
        if bool(bad.any()):
            if self.on_failure == "raise":
                idx = bad.nonzero().squeeze(-1).tolist()
                names = sorted({QPStatus(int(s)).name for s in status[bad].tolist()})
                raise QPInfeasibleError(f"QP instances {idx[:10]}{'...' if len(idx) > 10 else ''} have no solution: "
                                        f"{', '.join(names)} (pass on_failure='nan' to get NaN and the status instead)")
            outs = tuple(torch.where(bad.view(-1, *([1] * (v.dim() - 1))), torch.full((), float("nan"), dtype=v.dtype), v)
                         for v in outs)
        if not any_batched:
            outs = tuple(v[0] for v in outs)
            status = status[0]
        return (*outs, status) if self.on_failure == "nan" else outs
