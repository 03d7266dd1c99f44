"""Tests of QPLayer: cvxpy declaration -> batched torch solve, against cvxpy + Clarabel and finite differences."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import torch

from a3cqp_rl.qp import NotAQPError, NotDPPError, QPInfeasibleError, QPLayer, QPShapeError, QPStatus

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
    single, Y1 = layer(*[v[0] for v in vals])  # unbatched in, unbatched out (as cvxpylayers)
    assert single.shape == (5,) and Y1.shape == (2, 3)
    assert (single - layer(*[v[:1] for v in vals])[0][0]).abs().max() < 1e-12
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


def _attributes_problem():
    x = cp.Variable(3, nonneg=True)
    y = cp.Variable(2, bounds=[-1, 1])
    p = cp.Parameter(3)
    c1, c2, c3 = x[0] + y[0] <= 1, 0.5 == x[1], 2 * x[0] - x[2] == 1
    prob = cp.Problem(cp.Minimize(cp.sum_squares(x - p) + cp.sum_squares(y) + 3 * y[1]), [c1, c2, c3])
    return prob, p, [x, y], [c1, c2, c3]


def test_variable_attributes_and_duals_match_cvxpy() -> None:
    prob, p, (x, y), cons = _attributes_problem()
    layer = QPLayer(prob, [p], [x, y] + [c.dual_variables[0] for c in cons])
    g = torch.Generator().manual_seed(4)
    vals = torch.randn(6, 3, generator=g, dtype=DT) * 2
    outs = layer(vals)
    assert outs[0].shape == (6, 3) and outs[1].shape == (6, 2) and outs[2].shape == (6,)
    for i in range(6):
        p.value = vals[i].numpy()
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
        assert np.abs(outs[0][i].numpy() - x.value).max() < 1e-6 and np.abs(outs[1][i].numpy() - y.value).max() < 1e-6
        for k, c in enumerate(cons):
            assert abs(float(outs[2 + k][i]) - float(c.dual_value)) < 1e-6, (i, k)


def test_solver_args_at_construction_and_per_call() -> None:
    prob, p, (x, y), _ = _attributes_problem()
    layer = QPLayer(prob, [p], [x], solver_args={"eps": 1e-10, "backend": "torch"})
    v = torch.tensor([1.0, 0.2, -0.3], dtype=DT)
    (x1,) = layer(v)
    (x2,) = layer(v, solver_args={"tol": 1e-8, "max_iters": 80, "backend": "auto"})
    assert (x1 - x2).abs().max() < 1e-7
    with pytest.raises(QPShapeError, match="unknown solver_args key 'verbose'"):
        layer(v, solver_args={"verbose": True})


def test_infeasible_parameters_raise_by_default_or_give_nan_and_status() -> None:
    x = cp.Variable(2)
    lo = cp.Parameter(2)
    prob = cp.Problem(cp.Minimize(cp.sum_squares(x)), [x >= lo, cp.sum(x) <= 1])
    vals = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=DT)  # the second: x ≥ 1, Σx ≤ 1 is infeasible
    layer = QPLayer(prob, [lo], [x])
    with pytest.raises(QPInfeasibleError, match=r"\[1\].*PRIMAL_INFEASIBLE"):
        layer(vals)
    nan_layer = QPLayer(prob, [lo], [x], on_failure="nan")
    xs, status = nan_layer(vals.requires_grad_())
    assert status.tolist() == [QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE]
    assert torch.isnan(xs[1]).all() and torch.allclose(xs[0], torch.zeros(2, dtype=DT))
    xs[0].sum().backward()  # the solved instance still has a gradient
    assert torch.isfinite(vals.grad).all()
    x1, s1 = nan_layer(torch.tensor([1.0, 1.0], dtype=DT))
    assert x1.shape == (2,) and s1.shape == () and int(s1) == QPStatus.PRIMAL_INFEASIBLE
    # Unbounded: an LP with a free direction.
    c = cp.Parameter(2)
    lp = cp.Problem(cp.Minimize(c @ x), [x[0] >= 0])
    with pytest.raises(QPInfeasibleError, match="DUAL_INFEASIBLE"):
        QPLayer(lp, [c], [x])(torch.tensor([1.0, 1.0], dtype=DT))


def test_requested_multipliers_warn_that_they_carry_no_gradient() -> None:
    import warnings

    import cvxpy as cp

    from a3cqp_rl.qp import QPLayer

    x, c = cp.Variable(2), cp.Parameter(2)
    con = x >= 0
    layer = QPLayer(cp.Problem(cp.Minimize(cp.sum_squares(x) + c @ x), [con]), parameters=[c],
                    variables=[x, con.dual_variables[0]])
    cv = torch.tensor([1.0, -1.0], dtype=torch.float64, requires_grad=True)
    with pytest.warns(UserWarning, match="multipliers without gradient"):
        xv, yv = layer(cv)
    assert xv.requires_grad and not yv.requires_grad
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per layer
        layer(cv)


def test_an_empty_batch_gives_empty_values_with_a_graph():
    x, p, M = cp.Variable(2), cp.Parameter(2), cp.Parameter((2, 2))
    layer = QPLayer(cp.Problem(cp.Minimize(cp.sum_squares(M @ x - p)), [x >= 0, cp.sum(x) == 1]), [M, p], [x])
    (v,) = layer(torch.zeros(0, 2, 2, dtype=DT), torch.zeros(0, 2, dtype=DT))
    assert v.shape == (0, 2)
    q = torch.zeros(0, 2, dtype=DT, requires_grad=True)
    (v,) = layer(torch.eye(2, dtype=DT), q)  # one fixed M, an empty batch of p
    v.sum().backward()
    assert v.shape == (0, 2) and q.grad.shape == (0, 2)
