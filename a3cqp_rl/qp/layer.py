"""`QPLayer`: a cvxpy-declared parametric QP evaluated in batch by the torch solver (cvxpylayers API).

cvxpy canonicalises the problem once (its DPP path for a QP-capable conic solver), which gives the
problem data as *affine* maps of the stacked parameter vector θ (last entry 1):

    vec(P) = M_P θ,   [q; d] = M_q θ,   vec([A_cone  b_cone]) = M_A θ   (column-major),

with constraints A_cone x + b_cone ∈ {0}^p × R₊^m.  We keep the three maps as sparse torch
matrices; a batch of parameter tensors then costs three sparse-dense products to build
(P, q, A, b, G, h) = (P, q, A_0, −b_0, −A_+, b_+), one `solve_qp`, and a column gather to return the
requested variables.  Gradients flow back through the same products, so the layer is
differentiable with respect to every parameter.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from a3cqp_rl.qp.exceptions import NotAQPError, NotDPPError, QPShapeError
from a3cqp_rl.qp.solver import QPSolution, solve_qp

__all__ = ["QPLayer"]


def _sparse(mat, dtype: torch.dtype) -> Tensor:
    """scipy sparse matrix -> torch sparse COO tensor."""
    coo = mat.tocoo()
    idx = torch.as_tensor(np.vstack([coo.row, coo.col]), dtype=torch.long)
    return torch.sparse_coo_tensor(idx, torch.as_tensor(coo.data, dtype=dtype), coo.shape, check_invariants=True).coalesce()


class QPLayer(torch.nn.Module):
    """Differentiable batched QP declared with cvxpy: layer(*parameter_tensors) -> variable values.

    Args:
        problem: a DPP-compliant `cvxpy.Problem` whose canonical form is a QP (quadratic or linear
            objective, affine equalities and inequalities); SOC/exponential/PSD cones are rejected.
        parameters: the problem's `cvxpy.Parameter`s, in the order their tensors are passed.
        variables: the `cvxpy.Variable`s whose values the layer returns, in that order.
        dtype: dtype of the extracted maps (float64 by default); inputs are cast to it.
    """

    def __init__(
        self,
        problem,
        parameters: Sequence,
        variables: Sequence,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        import cvxpy as cp

        if not problem.is_dcp(dpp=True):
            if problem.is_dcp():
                raise NotDPPError("problem is DCP but not DPP: parameters must enter affinely (see cvxpy's DPP rules)")
            raise NotAQPError("problem is not DCP, so it is not a convex QP")
        if set(p.id for p in parameters) != set(p.id for p in problem.parameters()):
            raise QPShapeError("`parameters` must list exactly the parameters of the problem")
        if not set(v.id for v in variables) <= set(v.id for v in problem.variables()):
            raise QPShapeError("`variables` must be variables of the problem")
        data, _, _ = problem.get_problem_data(cp.CLARABEL)
        prog = data[cp.settings.PARAM_PROB]
        dims = prog.cone_dims
        if dims.exp or dims.soc or dims.psd or getattr(dims, "p3d", None) or getattr(dims, "pnd", None):
            raise NotAQPError(f"problem is not a QP: its canonical form has cones beyond equalities and inequalities ({dims})")
        if data.get("lower_bounds") is not None or data.get("upper_bounds") is not None:
            raise NotAQPError("variable `bounds=` attributes are not supported; write the bounds as constraints")
        missing = [p.name() for p in parameters if p.id not in prog.param_id_to_col]
        if missing:
            raise QPShapeError(
                f"parameters {missing} were replaced during canonicalisation (attributes such as "
                "symmetric/PSD/nonneg are not supported on parameters); declare plain Parameters"
            )
        self.n = int(prog.x.size)
        self.p, self.m = int(dims.zero), int(dims.nonneg)
        self.param_shapes = [tuple(p.shape) for p in parameters]
        self.param_cols = [int(prog.param_id_to_col[p.id]) for p in parameters]
        self.theta_size = int(prog.total_param_size) + 1
        self.const_col = int(prog.param_id_to_col[-1])  # cvxpy's CONSTANT_ID column holds the 1
        n1 = self.n + 1
        self.register_buffer("M_q", _sparse(prog.q, dtype), persistent=False)
        self.register_buffer("M_A", _sparse(prog.A, dtype), persistent=False)
        if prog.P is not None:
            self.register_buffer("M_P", _sparse(prog.P, dtype), persistent=False)
        else:
            self.M_P = None
        self.var_slices = [(int(prog.var_id_to_col[v.id]), int(v.size), tuple(v.shape)) for v in variables]
        self.dtype = dtype
        self._n1 = n1

    def _theta(self, params: Sequence[Tensor]) -> tuple[Tensor, int]:
        """Stack the (batched or not) parameter tensors into θ [B, T + 1] in cvxpy's column-major order."""
        if len(params) != len(self.param_shapes):
            raise QPShapeError(f"expected {len(self.param_shapes)} parameter tensors, got {len(params)}")
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
            t = torch.as_tensor(t, dtype=self.dtype, device=device)
            if tuple(t.shape[int(bt):]) != shape:
                raise QPShapeError(f"parameter tensor of shape {tuple(t.shape)} does not match {shape} (optionally batched)")
            if not bt:
                t = t.unsqueeze(0).expand(batch, *shape)
            # cvxpy flattens parameter values in Fortran (column-major) order.
            flat = t.permute(0, *range(t.dim() - 1, 0, -1)).reshape(batch, -1) if len(shape) > 1 else t.reshape(batch, -1)
            pieces.append(flat)
            cols.append(torch.arange(col, col + flat.shape[1], device=device))
        cols.append(torch.tensor([self.const_col], device=device))
        pieces.append(torch.ones(batch, 1, dtype=self.dtype, device=device))
        # index_copy is differentiable with respect to the copied values.
        theta = theta.index_copy(1, torch.cat(cols), torch.cat(pieces, 1))
        return theta, batch

    def problem_data(self, *params: Tensor) -> dict[str, Tensor]:
        """Batched canonical data (P, q, A, b, G, h) of the QP for these parameter values."""
        theta, batch = self._theta(params)
        thT = theta.mT  # (T + 1, B)
        n, n1, p = self.n, self._n1, self.p
        qd = torch.sparse.mm(self.M_q, thT).mT  # (B, n + 1)
        if self.M_P is not None:
            P = torch.sparse.mm(self.M_P, thT).mT.reshape(batch, n, n).mT  # column-major vec
        else:
            P = theta.new_zeros(batch, n, n)
        Ab = torch.sparse.mm(self.M_A, thT).mT.reshape(batch, n1, -1).mT  # (B, rows, n + 1)
        A_cone, b_cone = Ab[..., :n], Ab[..., n]
        return {
            "P": P,
            "q": qd[:, :n],
            "A": A_cone[:, :p],
            "b": -b_cone[:, :p],
            "G": -A_cone[:, p:],
            "h": b_cone[:, p:],
        }

    def solve(self, *params: Tensor, **solver_kwargs) -> tuple[tuple[Tensor, ...], QPSolution]:
        """Solve for a batch of parameter values; returns (variable tensors, full QPSolution)."""
        d = self.problem_data(*params)
        A, b = (d["A"], d["b"]) if self.p else (None, None)
        G, h = (d["G"], d["h"]) if self.m else (None, None)
        sol = solve_qp(d["P"], d["q"], A, b, G, h, **solver_kwargs)
        outs = []
        for col, size, shape in self.var_slices:
            v = sol.x[:, col : col + size]
            # back from cvxpy's column-major vectorisation to the variable's shape
            v = v.reshape(v.shape[0], *reversed(shape)).permute(0, *range(len(shape), 0, -1)) if len(shape) > 1 else v.reshape(v.shape[0], *shape)
            outs.append(v)
        return tuple(outs), sol

    def forward(self, *params: Tensor, **solver_kwargs) -> tuple[Tensor, ...]:
        """Values [B, *var.shape] of the requested variables at the QP's solution (differentiable)."""
        return self.solve(*params, **solver_kwargs)[0]
