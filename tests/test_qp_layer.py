"""Tests of QPLayer: cvxpy declaration -> batched torch solve, against cvxpy + Clarabel and finite differences."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import torch

from a3cqp_rl.qp import NotAQPError, NotDPPError, QPLayer, QPShapeError

DT = torch.float64


def _controller_like_problem(n: int = 5):
    """Weighted least-squares tasks + bounds + a coupling equality, as the controller builds them."""
    x = cp.Variable(n)
    Y = cp.Variable((2, 3))
    J, r = cp.Parameter((3, n)), cp.Parameter(3)  # task Jacobian and reference
    Gp, hp = cp.Parameter((4, n)), cp.Parameter(4)
    C = cp.Parameter((2, 3))
    P_reg = np.diag(np.arange(1.0, n + 1)) + 0.3 * np.ones((n, n))  # constant, dense off-diagonals
    objective = cp.sum_squares(J @ x - r) + 0.5 * cp.quad_form(x, P_reg) + cp.sum_squares(Y - C)
    cons = [Gp @ x <= hp, x >= -1, x <= 1, Y[:, 0] == x[:2], cp.sum(Y) <= 1]
    return cp.Problem(cp.Minimize(objective), cons), [J, r, Gp, hp, C], [x, Y]


def _random_values(batch: int, n: int, seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [
        torch.randn(batch, 3, n, generator=g, dtype=DT),
        torch.randn(batch, 3, generator=g, dtype=DT) * 2,
        torch.randn(batch, 4, n, generator=g, dtype=DT),
        torch.rand(batch, 4, generator=g, dtype=DT) * 0.5,
        torch.randn(batch, 2, 3, generator=g, dtype=DT),
    ]


def test_layer_matches_cvxpy_clarabel() -> None:
    prob, params, variables = _controller_like_problem()
    layer = QPLayer(prob, parameters=params, variables=variables)
    vals = _random_values(12, 5, seed=0)
    (xs, Ys), sol = layer.solve(*vals)
    assert bool(sol.solved.all())
    assert xs.shape == (12, 5) and Ys.shape == (12, 2, 3)
    n_active = 0
    for i in range(12):
        for p, v in zip(params, vals):
            p.value = v[i].numpy()
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
        assert np.abs(xs[i].numpy() - variables[0].value).max() < 1e-6
        assert np.abs(Ys[i].numpy() - variables[1].value).max() < 1e-6
        n_active += int(np.abs(variables[0].value).max() > 1 - 1e-7 or (prob.constraints[0].dual_value > 1e-7).any())
    assert n_active >= 3  # the instances exercise the constraints, not only the unconstrained optimum


def test_layer_unbatched_parameters_and_broadcast() -> None:
    prob, params, variables = _controller_like_problem()
    layer = QPLayer(prob, parameters=params, variables=variables)
    vals = _random_values(4, 5, seed=1)
    mixed = [vals[0][0]] + vals[1:]  # one shared Jacobian, the rest batched
    xs, _ = layer(*mixed)
    xs_full, _ = layer(vals[0][:1].expand(4, 3, 5), *vals[1:])
    assert xs.shape == (4, 5) and (xs - xs_full).abs().max() < 1e-12
    single, _ = layer(*[v[0] for v in vals])
    assert single.shape == (1, 5) and (single[0] - layer(*[v[:1] for v in vals])[0][0]).abs().max() < 1e-12
    with pytest.raises(QPShapeError):
        layer(vals[0][:2], *vals[1:])


def test_layer_gradients_match_finite_differences() -> None:
    prob, params, variables = _controller_like_problem(n=3)
    layer = QPLayer(prob, parameters=params, variables=variables)
    vals = [v.requires_grad_() for v in _random_values(2, 3, seed=2)]
    w = torch.randn(2, 3, dtype=DT)
    assert torch.autograd.gradcheck(lambda *a: (layer(*a)[0] * w).sum(-1) + layer(*a)[1].sum((-1, -2)), vals, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_layer_rejects_non_qp_and_non_dpp() -> None:
    x, t = cp.Variable(3), cp.Variable()
    a = cp.Parameter(3)
    soc = cp.Problem(cp.Minimize(t + a @ x), [cp.norm(x, 2) <= t, x >= -1])
    with pytest.raises(NotAQPError, match="not a QP"):
        QPLayer(soc, parameters=[a], variables=[x])
    b = cp.Parameter(nonneg=True)
    non_dpp = cp.Problem(cp.Minimize(cp.sum_squares(x) + (a * b) @ x))
    with pytest.raises(NotDPPError):
        QPLayer(non_dpp, parameters=[a, b], variables=[x])
    with pytest.raises(QPShapeError, match="exactly the parameters"):
        QPLayer(soc, parameters=[], variables=[x])
