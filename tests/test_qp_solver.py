"""Tests of the batched torch QP solver: accuracy vs cvxpy + Clarabel, robustness, warm starts, gradients."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from a3cqp_rl.qp import QPGradientError, QPShapeError, QPStatus, native, solve_qp
from a3cqp_rl.qp.random_qp import clarabel_reference, random_qp_batch

DT = torch.float64


@pytest.fixture(autouse=True, params=["c", "torch"])
def solver_route(request, monkeypatch):
    """Every test twice: backend "auto" on the C route, and on the torch route (A3CQP_NATIVE_QP=0, the
    documented override), so both keep their coverage through the default call."""
    if request.param == "torch":
        monkeypatch.setenv("A3CQP_NATIVE_QP", "0")
    native._reset()
    yield request.param
    native._reset()


def _active_any(sol) -> torch.Tensor:
    """Instances with at least one active inequality or bound (positive multiplier)."""
    return (sol.z > 0).any(-1) | (sol.z_lb > 0).any(-1) | (sol.z_ub > 0).any(-1)


def _kkt_residuals(qp, sol) -> dict[str, float]:
    """Max KKT violations of a solution (stationarity, primal feasibility, complementarity, dual sign)."""
    x = sol.x
    r = (qp.P @ x.unsqueeze(-1)).squeeze(-1) + qp.q + (qp.G.mT @ sol.z.unsqueeze(-1)).squeeze(-1)
    r = r - sol.z_lb + sol.z_ub
    if qp.A is not None:
        r = r + (qp.A.mT @ sol.y.unsqueeze(-1)).squeeze(-1)
    g = (qp.G @ x.unsqueeze(-1)).squeeze(-1) - qp.h
    return {"stat": r.abs().max().item(), "feas": g.max().item(), "compl": (sol.z * g).abs().max().item()}


# 1000 instances in four families, each compared with cvxpy + Clarabel (tol 1e-12).
FAMILIES = [dict(n=13, m=30), dict(n=13, m=30, p=3), dict(n=13, m=20, bounds=True), dict(n=13, m=24, p=2, bounds=True)]


@pytest.mark.parametrize("family", range(len(FAMILIES)))
def test_random_instances_match_clarabel(family: int) -> None:
    qp = random_qp_batch(250, seed=100 + family, **FAMILIES[family])
    sol = solve_qp(*qp.args())
    x_ref, statuses = clarabel_reference(qp)
    assert set(statuses) == {"optimal"}
    assert bool(sol.solved.all())
    frac_active = _active_any(sol).double().mean().item()
    assert 0.3 <= frac_active <= 0.5, frac_active  # the generator's promise: a mix of both regimes
    assert (sol.x - x_ref).abs().max().item() <= 1e-6
    res = _kkt_residuals(qp, sol)
    assert res["stat"] < 1e-8 and res["feas"] < 1e-8 and res["compl"] < 1e-8, res
    assert (sol.z >= 0).all() and (sol.z_lb >= 0).all() and (sol.z_ub >= 0).all()


def test_heavily_constrained_instances_match_clarabel() -> None:
    # Far from the unconstrained optimum: 5-10 active rows, the interior-point stage does the work.
    qp = random_qp_batch(100, m=30, p=2, bounds=True, spread=0.35, seed=7)
    sol = solve_qp(*qp.args())
    x_ref, _ = clarabel_reference(qp)
    assert bool(sol.solved.all())
    assert (sol.z > 0).sum(-1).float().mean() > 3
    assert (sol.x - x_ref).abs().max().item() <= 1e-6


def test_warm_start_reduces_iterations_and_keeps_answer() -> None:
    qp = random_qp_batch(200, spread=0.3, seed=3)
    cold = solve_qp(*qp.args())
    # The control loop's situation: the next QP is a small perturbation of the previous one.
    q2 = qp.q + 1e-3 * torch.randn(qp.q.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    cold2 = solve_qp(qp.P, q2, G=qp.G, h=qp.h)
    warm2 = solve_qp(qp.P, q2, G=qp.G, h=qp.h, warm_start=cold)
    assert bool(warm2.solved.all())
    assert (warm2.x - cold2.x).abs().max() < 1e-8
    assert warm2.iterations.float().mean() < 0.3 * cold2.iterations.float().mean()
    assert warm2.iterations.float().mean() <= 1.5


def test_forget_starts_only_the_named_instances_cold() -> None:
    qp = random_qp_batch(8, m=30, p=2, bounds=True, spread=0.35, seed=7)
    sol = solve_qp(*qp.args())
    before = [t.clone() for t in (sol.y, sol.z, sol.z_lb, sol.z_ub)]
    assert (before[1][[2, 5]] > 0).any()
    sol.forget([2, 5])
    keep = [0, 1, 3, 4, 6, 7]
    for t, t0 in zip((sol.y, sol.z, sol.z_lb, sol.z_ub), before):
        assert (t[[2, 5]] == 0).all() and torch.equal(t[keep], t0[keep])
    # a warm start from it: instances 2 and 5 take the cold solve's steps, the others the warm one's
    cold = solve_qp(*qp.args())
    warm = solve_qp(*qp.args(), warm_start=sol)
    assert torch.equal(warm.iterations[[2, 5]], cold.iterations[[2, 5]])
    assert (warm.iterations[keep] < cold.iterations[keep]).all()
    assert (warm.x - cold.x).abs().max() < 1e-8


def test_infeasible_instances_are_flagged_and_do_not_poison_the_batch() -> None:
    qp = random_qp_batch(6, n=5, m=8, p=1, seed=4)
    G, h, A, b = qp.G.clone(), qp.h.clone(), qp.A.clone(), qp.b.clone()
    # Instance 1: x0 <= -1 and -x0 <= -1 (x0 >= 1). Instance 3: two parallel inconsistent equalities
    # (written as A x = b with one equality and a contradicting inequality pair).
    G[1, 0], h[1, 0] = torch.eye(5, dtype=DT)[0], -1.0
    G[1, 1], h[1, 1] = -torch.eye(5, dtype=DT)[0], -1.0
    G[3, 0], h[3, 0] = A[3, 0], b[3, 0] - 1.0  # A x = b and A x <= b - 1
    sol = solve_qp(qp.P, qp.q, A, b, G, h)
    assert sol.status[1] == QPStatus.PRIMAL_INFEASIBLE and sol.status[3] == QPStatus.PRIMAL_INFEASIBLE
    assert torch.isfinite(sol.x).all() and torch.isfinite(sol.z).all() and torch.isfinite(sol.y).all()
    good = torch.tensor([0, 2, 4, 5])
    ref = solve_qp(qp.P[good], qp.q[good], A[good], b[good], G[good], h[good])
    assert (sol.status[good] == QPStatus.SOLVED).all()
    assert (sol.x[good] - ref.x).abs().max() < 1e-10


def test_the_c_route_certifies_infeasibility_itself(solver_route, monkeypatch) -> None:
    """Goldfarb-Idnani's infeasibility test gives a Farkas vector; checked like the torch route's, the C route
    answers PRIMAL_INFEASIBLE without handing the instance on."""
    import a3cqp_rl.qp.solver as solver_module

    qp = random_qp_batch(6, n=5, m=8, seed=4)
    G, h = qp.G.clone(), qp.h.clone()
    G[1, 0], h[1, 0] = torch.eye(5, dtype=DT)[0], -1.0  # x0 <= -1 and x0 >= 1
    G[1, 1], h[1, 1] = -torch.eye(5, dtype=DT)[0], -1.0
    if solver_route == "c":
        monkeypatch.setattr(solver_module, "_finish_on_torch", lambda *a, **k: pytest.fail("handed on"))
    sol = solve_qp(qp.P, qp.q, G=G, h=h)
    assert sol.status[1] == QPStatus.PRIMAL_INFEASIBLE and (sol.x[1] == 0).all()
    good = torch.tensor([0, 2, 3, 4, 5])
    ref = solve_qp(qp.P[good], qp.q[good], G=G[good], h=h[good])
    assert (sol.status[good] == QPStatus.SOLVED).all() and torch.equal(sol.x[good], ref.x)


def test_without_hand_on_the_instances_the_c_route_leaves_are_max_iter(solver_route) -> None:
    qp = random_qp_batch(4, n=5, m=8, seed=4)
    P = qp.P.clone()
    P[2] = torch.diag(torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0], dtype=DT))  # semi-definite: the C route hands it on
    lb, ub = -torch.ones(4, 5, dtype=DT), torch.ones(4, 5, dtype=DT)
    full = solve_qp(P, qp.q, lb=lb, ub=ub)
    assert (full.status == QPStatus.SOLVED).all()
    for grad in (False, True):  # the fast path, and the autograd path
        q = qp.q.clone().requires_grad_(grad)
        quick = solve_qp(P, q, lb=lb, ub=ub, hand_on=False)
        good = torch.tensor([0, 1, 3])
        assert (quick.status[good] == QPStatus.SOLVED).all() and torch.equal(quick.x[good].detach(), full.x[good])
        if solver_route == "c":
            assert quick.status[2] == QPStatus.MAX_ITER and (quick.x[2] == 0).all() and (quick.z_ub[2] == 0).all()
        else:  # the torch route decides every instance itself: nothing is left
            assert torch.equal(quick.status, full.status)


def test_infeasible_equalities_and_bounds() -> None:
    n = 3
    P = torch.eye(n, dtype=DT).expand(2, n, n)
    q = torch.zeros(2, n, dtype=DT)
    A = torch.tensor([[1.0, 0, 0], [1.0, 0, 0]], dtype=DT).expand(2, 2, n)
    b = torch.tensor([[1.0, 1.0], [1.0, 2.0]], dtype=DT)  # instance 0 redundant, instance 1 inconsistent
    sol = solve_qp(P, q, A, b)
    assert sol.status.tolist() == [QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE]
    assert torch.allclose(sol.x[0], torch.tensor([1.0, 0, 0], dtype=DT), atol=1e-9)
    assert torch.isfinite(sol.x).all()
    lb = torch.tensor([[0.0, 0, 0], [0.0, 1.0, 0]], dtype=DT)
    ub = torch.tensor([[1.0, 1, 1], [1.0, 0.5, 1]], dtype=DT)  # lb > ub in instance 1
    sol = solve_qp(P, q - 1.0, lb=lb, ub=ub)
    assert sol.status.tolist() == [QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE]
    assert torch.allclose(sol.x[0], torch.ones(n, dtype=DT), atol=1e-9)


def test_unbounded_instance_is_flagged() -> None:
    # P = diag(1, 0): x1 is free with cost -x1 and only bounded below -> unbounded; instance 0 is fine.
    P = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).expand(2, 2, 2)
    q = torch.tensor([[1.0, 1.0], [1.0, -1.0]], dtype=DT)
    G = torch.tensor([[0.0, -1.0]], dtype=DT).expand(2, 1, 2)
    h = torch.zeros(2, 1, dtype=DT)
    sol = solve_qp(P, q, G=G, h=h)
    assert sol.status.tolist() == [QPStatus.SOLVED, QPStatus.DUAL_INFEASIBLE]
    assert torch.isfinite(sol.x).all()
    assert torch.allclose(sol.x[0], torch.tensor([-1.0, 0.0], dtype=DT), atol=1e-8)


def test_degenerate_redundant_and_semidefinite_cases() -> None:
    qp = random_qp_batch(50, n=6, m=10, p=1, spread=0.2, seed=11)
    # Duplicate every row (dependent active constraints) and add an always-redundant row.
    G = torch.cat([qp.G, qp.G, torch.zeros_like(qp.G[:, :1])], 1)
    h = torch.cat([qp.h, qp.h, torch.ones_like(qp.h[:, :1])], 1)
    base = solve_qp(qp.P, qp.q, qp.A, qp.b, qp.G, qp.h)
    dup = solve_qp(qp.P, qp.q, qp.A, qp.b, G, h)
    assert bool(dup.solved.all()) and (dup.x - base.x).abs().max() < 1e-8
    # Weakly active constraint: a row through the unconstrained optimum with zero multiplier.
    P = torch.eye(2, dtype=DT).unsqueeze(0)
    sol = solve_qp(P, torch.tensor([[-1.0, -1.0]], dtype=DT), G=torch.tensor([[[1.0, 0.0]]], dtype=DT), h=torch.tensor([[1.0]], dtype=DT))
    assert bool(sol.solved.all()) and torch.allclose(sol.x, torch.ones(1, 2, dtype=DT), atol=1e-8)
    # P singular but positive definite on the feasible set (x2 fixed by an equality).
    P = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).unsqueeze(0)
    sol = solve_qp(P, torch.tensor([[-2.0, 5.0]], dtype=DT), A=torch.tensor([[[0.0, 1.0]]], dtype=DT), b=torch.tensor([[3.0]], dtype=DT))
    assert bool(sol.solved.all()) and torch.allclose(sol.x, torch.tensor([[2.0, 3.0]], dtype=DT), atol=1e-8)
    assert torch.allclose(sol.y, torch.tensor([[-5.0]], dtype=DT), atol=1e-7)
    # A linear program (P = 0) with bounds: vertex solution.
    sol = solve_qp(torch.zeros(1, 3, 3, dtype=DT), torch.tensor([[1.0, -2.0, 0.5]], dtype=DT), lb=-torch.ones(1, 3, dtype=DT), ub=torch.ones(1, 3, dtype=DT))
    assert bool(sol.solved.all()) and torch.allclose(sol.x, torch.tensor([[-1.0, 1.0, -1.0]], dtype=DT), atol=1e-8)


def test_equality_only_bounds_only_and_infinite_bounds() -> None:
    qp = random_qp_batch(20, n=8, m=1, p=3, seed=5)
    sol = solve_qp(qp.P, qp.q, qp.A, qp.b)
    # Closed form of the equality-constrained QP from the full KKT matrix.
    K = torch.cat([torch.cat([qp.P, qp.A.mT], 2), torch.cat([qp.A, torch.zeros(20, 3, 3, dtype=DT)], 2)], 1)
    xy = torch.linalg.solve(K, torch.cat([-qp.q, qp.b], 1))
    assert (sol.x - xy[:, :8]).abs().max() < 1e-9 and (sol.y - xy[:, 8:]).abs().max() < 1e-8
    assert (sol.iterations == 1).all()
    # Bounds only, some infinite: the solution is the clipped unconstrained minimiser for diagonal P.
    d = torch.rand(20, 8, dtype=DT) + 0.5
    lb = torch.full((20, 8), -0.3, dtype=DT)
    ub = torch.full((20, 8), 0.3, dtype=DT)
    lb[:, 0], ub[:, 1] = -torch.inf, torch.inf
    sol = solve_qp(torch.diag_embed(d), qp.q, lb=lb, ub=ub)
    expected = torch.minimum(torch.maximum(-qp.q / d, lb), ub)
    assert bool(sol.solved.all()) and (sol.x - expected).abs().max() < 1e-9
    assert (sol.z_lb[:, 0] == 0).all() and (sol.z_ub[:, 1] == 0).all()


def test_float32_with_looser_tolerance() -> None:
    qp = random_qp_batch(200, p=2, bounds=True, seed=9)
    ref = solve_qp(*qp.args())
    args32 = [t.float() if t is not None else None for t in qp.args()]
    sol = solve_qp(*args32)
    assert sol.x.dtype == torch.float32
    assert bool(sol.solved.all())
    assert (sol.x.double() - ref.x).abs().max() < 1e-3


def test_unbatched_arguments_broadcast_and_shape_errors() -> None:
    qp = random_qp_batch(5, n=4, m=6, seed=2)
    shared = solve_qp(qp.P[0], qp.q, G=qp.G[0], h=qp.h[0])
    per = solve_qp(qp.P[:1].expand(5, 4, 4), qp.q, G=qp.G[:1].expand(5, 6, 4), h=qp.h[:1].expand(5, 6))
    assert shared.x.shape == (5, 4) and (shared.x - per.x).abs().max() < 1e-12
    with pytest.raises(QPShapeError, match="G must have 4 columns"):
        solve_qp(qp.P, qp.q, G=qp.G[..., :3], h=qp.h)
    with pytest.raises(QPShapeError, match="batch size"):
        solve_qp(qp.P[:2], qp.q)
    with pytest.raises(QPShapeError, match="together"):
        solve_qp(qp.P, qp.q, G=qp.G)
    with pytest.raises(QPShapeError, match="dtype"):
        solve_qp(qp.P.float(), qp.q)


def test_max_iter_status_and_finite_output() -> None:
    # Budgets of the torch route (the C route's Goldfarb-Idnani is finite and certifies these).
    qp = random_qp_batch(10, spread=0.35, seed=6)
    sol = solve_qp(*qp.args(), max_iter=2, active_set_iter=1, backend="torch")
    assert (sol.status == QPStatus.MAX_ITER).any()
    assert torch.isfinite(sol.x).all()


def _small_problem(seed: int):
    g = torch.Generator().manual_seed(seed)
    B, n, m, p = 3, 4, 5, 1
    M = torch.randn(B, n, n, generator=g, dtype=DT)
    P = M @ M.mT + 0.5 * torch.eye(n, dtype=DT)
    q = torch.randn(B, n, generator=g, dtype=DT)
    G = torch.randn(B, m, n, generator=g, dtype=DT)
    h = torch.rand(B, m, generator=g, dtype=DT) * 0.3
    A = torch.randn(B, p, n, generator=g, dtype=DT)
    b = torch.randn(B, p, generator=g, dtype=DT) * 0.1
    lb = -torch.rand(B, n, generator=g, dtype=DT) * 0.3 - 0.2
    ub = torch.rand(B, n, generator=g, dtype=DT) * 0.1 + 0.05
    return [t.requires_grad_() for t in (P, q, A, b, G, h, lb, ub)]


def test_gradcheck_all_arguments() -> None:
    args = _small_problem(1)
    sol = solve_qp(*args)
    # Make sure the instance exercises active inequalities and bounds, so those gradients are non-trivial.
    assert (sol.z > 0).any() and ((sol.z_lb > 0) | (sol.z_ub > 0)).any()
    assert torch.autograd.gradcheck(lambda *a: solve_qp(*a).x, args, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_the_torch_routes_multipliers_are_differentiable_and_its_second_derivatives_right() -> None:
    """Gradients through y, z, z_lb, z_ub (gradcheck), and second derivatives of x through A and G, whose first
    derivatives contain the multipliers (gradgradcheck): both against finite differences on the torch route."""
    args = _small_problem(1)
    assert torch.autograd.gradcheck(
        lambda *a: tuple(getattr(solve_qp(*a, backend="torch"), f) for f in ("x", "y", "z", "z_lb", "z_ub")),
        args, eps=1e-6, atol=1e-5, rtol=1e-4)
    P, q, A, b, G, h, lb, ub = args
    assert torch.autograd.gradgradcheck(lambda A, G: solve_qp(P, q, A, b, G, h, lb, ub, backend="torch").x, (A, G),
                                        eps=1e-6, atol=1e-5, rtol=1e-4)


def test_the_c_routes_multipliers_refuse_a_gradient_instead_of_dropping_it() -> None:
    """On the direct C path only x is differentiated; a loss through a multiplier raises, naming the torch route."""
    if native.load() is None:
        pytest.skip("gi_qp.c was not built (no C compiler)")
    args = _small_problem(2)
    sol = solve_qp(*args)
    (sol.x.sum() + 0.0 * sol.y.sum()).detach()  # reading them is fine
    with pytest.raises(QPGradientError, match="backend='torch'"):
        (sol.x.sum() + sol.z.sum()).backward()


def test_duplicated_active_rows_are_solved_and_certified() -> None:
    """A feasible QP whose equality rows are dependent (one is twice another) and whose active rows come with three
    scaled copies each: the interior point used to stop on its mean complementarity, which the final certificate,
    row by row, then refused (TOLERANCE_NOT_MET for an answer Clarabel gives to 1e-12)."""
    import cvxpy as cp

    d = np.load(Path(__file__).parent / "data" / "qp_duplicate_active_rows.npz")
    args = [torch.from_numpy(d[k])[None] for k in ("P", "q", "A", "b", "G", "h")]
    x = cp.Variable(d["P"].shape[0])
    prob = cp.Problem(cp.Minimize(0.5 * cp.quad_form(x, cp.psd_wrap(d["P"])) + d["q"] @ x),
                      [d["A"] @ x == d["b"], d["G"] @ x <= d["h"]])
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
    for tol in (1e-9, 1e-7, 1e-6):
        sol = solve_qp(*args, tol=tol)
        assert sol.status.item() == QPStatus.SOLVED, (tol, QPStatus(sol.status.item()).name)
        obj = 0.5 * sol.x[0] @ args[0][0] @ sol.x[0] + args[1][0] @ sol.x[0]
        assert abs(float(obj) - prob.value) <= 1e-6 * (1.0 + abs(prob.value)), (tol, float(obj), prob.value)


def test_rows_scaled_by_up_to_a_million_are_solved_with_multipliers_that_meet_stationarity() -> None:
    """Rows of norm 3e-6 to 4e5: the active set's certificate accepted a multiplier of about −1e-3 (within the sign
    test's tol·max|z|, max|z| ≈ 2e6), and the returned, clamped z then missed stationarity by 0.19 relative on the
    torch route (TOLERANCE_NOT_MET for an x right to 5e-15). Stationarity is now certified with z as returned."""
    import cvxpy as cp

    d = np.load(Path(__file__).parent / "data" / "qp_scaled_rows.npz")
    P, q, G, h = (torch.from_numpy(d[k])[None] for k in ("P", "q", "G", "h"))
    x = cp.Variable(d["P"].shape[0])
    prob = cp.Problem(cp.Minimize(0.5 * cp.quad_form(x, cp.psd_wrap(d["P"])) + d["q"] @ x), [d["G"] @ x <= d["h"]])
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
    for tol in (1e-9, 1e-7):
        sol = solve_qp(P, q, G=G, h=h, tol=tol)
        assert sol.status.item() == QPStatus.SOLVED, (tol, QPStatus(sol.status.item()).name)
        assert float((sol.x[0] - torch.from_numpy(x.value)).abs().max()) <= 1e-6 * (1.0 + float(abs(x.value).max()))
        r = P[0] @ sol.x[0] + q[0] + G[0].T @ sol.z[0]
        assert bool((sol.z >= 0).all()) and float(r.abs().max()) <= 1e-6 * (1.0 + float((G[0].abs().T @ sol.z[0]).max()))


def test_gradients_match_cvxpylayers() -> None:
    cvxpylayers_torch = pytest.importorskip("cvxpylayers.torch")
    import cvxpy as cp

    qp = random_qp_batch(8, n=5, m=7, p=1, spread=0.1, seed=12)
    n, m = 5, 7
    x = cp.Variable(n)
    Lt, qv, Gp, hp, Ap, bp = cp.Parameter((n, n)), cp.Parameter(n), cp.Parameter((m, n)), cp.Parameter(m), cp.Parameter((1, n)), cp.Parameter(1)
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(Lt @ x) + qv @ x), [Gp @ x <= hp, Ap @ x == bp])
    layer = cvxpylayers_torch.CvxpyLayer(prob, parameters=[Lt, qv, Gp, hp, Ap, bp], variables=[x])
    L = torch.linalg.cholesky(qp.P)
    leaves = [t.clone().requires_grad_() for t in (L, qp.q, qp.G, qp.h, qp.A, qp.b)]
    w = torch.randn(8, n, generator=torch.Generator().manual_seed(1), dtype=DT)
    (x_ref,) = layer(leaves[0].mT, *leaves[1:], solver_args={"solve_method": "Clarabel", "tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12, "tol_feas": 1e-12, "tol_ktratio": 1e-10})
    (x_ref * w).sum().backward()
    ref_grads = [t.grad.clone() for t in leaves]
    mine = [t.clone().requires_grad_() for t in (L, qp.q, qp.G, qp.h, qp.A, qp.b)]
    sol = solve_qp(mine[0] @ mine[0].mT, mine[1], mine[4], mine[5], mine[2], mine[3])
    (sol.x * w).sum().backward()
    assert (sol.x - x_ref).abs().max() < 1e-5
    for a, r in zip(mine, ref_grads):
        assert torch.allclose(a.grad, r, atol=1e-4, rtol=1e-3), (a.grad - r).abs().max()


def test_large_batch_paths_agree_with_small_batch_paths() -> None:
    # B > 32 uses the Schur-complement active-set step and adjoint; B <= 32 the dense LU ones.
    qp = random_qp_batch(48, n=8, m=12, p=1, bounds=True, spread=0.1, seed=21)
    w = torch.randn(48, 8, generator=torch.Generator().manual_seed(3), dtype=DT)

    def grads(sl: slice):
        leaves = [t[sl].clone().requires_grad_() for t in qp.args()]
        sol = solve_qp(*leaves)
        (sol.x * w[sl]).sum().backward()
        return sol.x.detach(), [t.grad for t in leaves]

    x_big, g_big = grads(slice(0, 48))
    x_a, g_a = grads(slice(0, 24))
    x_b, g_b = grads(slice(24, 48))
    assert (x_big - torch.cat([x_a, x_b])).abs().max() < 1e-9
    for gb, ga, gc in zip(g_big, g_a, g_b):
        assert (gb - torch.cat([ga, gc])).abs().max() < 1e-7


@pytest.mark.parametrize("batch", [4, 40])  # dense-LU path and Schur path
def test_nan_instance_does_not_poison_the_batch(batch: int) -> None:
    qp = random_qp_batch(batch, n=6, m=9, spread=0.1, seed=31)
    q = qp.q.clone()
    q[1, 2] = torch.nan
    sol = solve_qp(qp.P, q, G=qp.G, h=qp.h)
    ref = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    assert sol.status[1] != QPStatus.SOLVED
    assert torch.isfinite(sol.x).all() and torch.isfinite(sol.z).all()
    others = torch.arange(batch) != 1
    assert (sol.status[others] == QPStatus.SOLVED).all()
    assert (sol.x[others] - ref.x[others]).abs().max() < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("n,m,p,bounds,spread", [(5, 8, 1, True, 0.3), (13, 40, 3, True, 0.35), (20, 50, 4, False, 0.5), (13, 30, 0, True, 1.0)])
def test_wide_sweep_against_clarabel(n: int, m: int, p: int, bounds: bool, spread: float) -> None:
    # Heavier families than the default run: many active rows, bigger problems.
    for seed in range(3):
        qp = random_qp_batch(300, n=n, m=m, p=p, bounds=bounds, spread=spread, seed=500 + seed)
        sol = solve_qp(*qp.args())
        x_ref, statuses = clarabel_reference(qp)
        assert set(statuses) == {"optimal"}
        assert bool(sol.solved.all())
        assert (sol.x - x_ref).abs().max().item() <= 1e-6


def test_interior_point_batch_mixing_infeasible_and_hard_feasible_instances() -> None:
    # Regression: the polish after the interior point must index the feasible subset correctly
    # when other instances of the same IPM batch are infeasible (seen in the controller's
    # fallback test).  One active-set iteration forces the hard instances through the IPM.
    qp = random_qp_batch(5, n=6, m=12, spread=0.5, seed=41)
    G, h = qp.G.clone(), qp.h.clone()
    G[2, 0], h[2, 0] = torch.eye(6, dtype=DT)[0], -1.0
    G[2, 1], h[2, 1] = -torch.eye(6, dtype=DT)[0], -1.0
    sol = solve_qp(qp.P, qp.q, G=G, h=h, active_set_iter=1)
    ref = solve_qp(qp.P, qp.q, G=G, h=h)
    others = torch.tensor([0, 1, 3, 4])
    assert sol.status[2] == QPStatus.PRIMAL_INFEASIBLE
    assert (sol.status[others] == QPStatus.SOLVED).all() and (sol.iterations[others] > 1).any()
    assert (sol.x[others] - ref.x[others]).abs().max() < 1e-8


def test_float32_psd_hessians_of_low_rank_are_convex() -> None:
    """JᵀJ of a 6x7 J (the IK Hessian, rank 6) rounded to float32 has λ_min ~ −1e-8 max|λ|: SOLVED, not NON_CONVEX
    (25 of 40 were NON_CONVEX before); a truly indefinite float32 P still is."""
    statuses = []
    for seed in range(40):
        g = torch.Generator().manual_seed(seed)
        J = torch.randn(6, 7, generator=g)
        sol = solve_qp(J.T @ J, torch.randn(7, generator=g), lb=-torch.ones(7), ub=torch.ones(7))
        statuses.append(int(sol.status[0]))
    assert statuses == [int(QPStatus.SOLVED)] * 40
    P = torch.diag(torch.tensor([1.0, -1e-3]))
    assert int(solve_qp(P, torch.zeros(2), lb=-torch.ones(2), ub=torch.ones(2)).status[0]) == int(QPStatus.NON_CONVEX)


@pytest.mark.parametrize("kw,match", [(dict(tol=-1.0), "tol must be"), (dict(tol=float("nan")), "tol must be"),
                                      (dict(max_iter=-5), "max_iter must be"), (dict(max_iter="a"), "max_iter must be"),
                                      (dict(active_set_iter=-1), "active_set_iter must be")])
def test_solver_settings_are_checked(kw: dict, match: str) -> None:
    P = torch.eye(2, dtype=torch.float64).expand(1, 2, 2)
    with pytest.raises(QPShapeError, match=match):
        solve_qp(P, torch.ones(1, 2, dtype=torch.float64), **kw)


def test_a_batch_mismatch_names_every_argument_and_its_batch() -> None:
    P = torch.eye(2, dtype=torch.float64).expand(3, 2, 2).contiguous()
    with pytest.raises(QPShapeError, match=r"batch sizes differ \(P, q: 3; ub: 4\)"):
        solve_qp(P, torch.zeros(3, 2, dtype=torch.float64), ub=torch.ones(4, 2, dtype=torch.float64))


def test_no_variables_is_solved_where_the_constraints_hold_at_zero():
    z = torch.zeros
    sol = solve_qp(z(3, 0, 0, dtype=DT), z(3, 0, dtype=DT), A=z(3, 1, 0, dtype=DT),
                   b=torch.tensor([[0.0], [1.0], [0.0]], dtype=DT), G=z(3, 1, 0, dtype=DT),
                   h=torch.tensor([[1.0], [1.0], [-1.0]], dtype=DT))
    assert sol.x.shape == (3, 0) and sol.y.shape == (3, 1) and sol.z.shape == (3, 1)
    assert sol.status.tolist() == [QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE, QPStatus.PRIMAL_INFEASIBLE]
    assert solve_qp(z(2, 0, 0, dtype=DT), z(2, 0, dtype=DT)).status.tolist() == [QPStatus.SOLVED] * 2


def test_torch_func_transforms_are_refused_and_the_jacobian_comes_from_autograd():
    from a3cqp_rl.qp import QPGradientError

    P = 2.0 * torch.eye(3, dtype=DT).expand(2, 3, 3).clone()
    q = torch.tensor([[1.0, -2.0, 0.5], [0.0, 1.0, 3.0]], dtype=DT)
    for transform in (torch.func.jacrev(lambda q: solve_qp(P, q).x), torch.func.vmap(lambda q: solve_qp(P[0], q).x)):
        with pytest.raises(QPGradientError, match="does not run under torch.func transforms"):
            transform(q)
    J = torch.autograd.functional.jacobian(lambda q: solve_qp(P, q).x, q)  # x = −q / 2: dx/dq = −I / 2 per instance
    torch.testing.assert_close(J[0, :, 0], -0.5 * torch.eye(3, dtype=DT))
    torch.testing.assert_close(J[1, :, 0], torch.zeros(3, 3, dtype=DT))
