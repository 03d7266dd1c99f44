"""Tests of `qp_vjp` (gradients of a C-route solution without autograd): equal to autograd on both routes and to
finite differences, argument shapes kept, declined instances and unsolved ones, and its errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import a3cqp_rl.qp.vjp as vjp_mod
from a3cqp_rl.qp import QPGradientError, QPShapeError, QPStatus, native, qp_vjp, solve_qp
from a3cqp_rl.qp.random_qp import random_qp_batch
from a3cqp_rl.qp.vjp import GRAD_NAMES

DT = torch.float64
pytestmark = pytest.mark.skipif(native.load() is None, reason="gi_qp.c was not built (no C compiler)")


def autograd_grads(args: list, gx: torch.Tensor, backend: str) -> list:
    """Gradients of Σ gx·x of every argument by autograd on `backend`."""
    leaves = [None if t is None else t.detach().clone().requires_grad_(True) for t in args]
    x = solve_qp(*leaves, backend=backend).x
    (x * gx).sum().backward()
    return [None if t is None else t.grad for t in leaves]


def assert_same(g, ref: list, tol: float = 1e-8) -> None:
    for k, nm in enumerate(GRAD_NAMES):
        a, r = getattr(g, nm), ref[k]
        if r is None:
            assert a is None, nm
            continue
        assert a.shape == r.shape, (nm, a.shape, r.shape)
        err = float((a - r).abs().max()) / (1.0 + float(r.abs().max()))
        assert err < tol, (nm, err)


@pytest.mark.parametrize("B,p,bounds,spread", [(1, 0, False, 0.3), (1, 2, True, 0.3), (7, 0, True, 0.5),
                                               (40, 3, False, 0.4), (40, 2, True, 0.3)])
def test_vjp_equals_autograd_on_both_routes(B: int, p: int, bounds: bool, spread: float) -> None:
    qp = random_qp_batch(B, 13, 30, p=p, bounds=bounds, spread=spread, seed=100 + B + p)
    args = list(qp.args())
    gx = torch.randn(B, 13, dtype=DT, generator=torch.Generator().manual_seed(B))
    sol = solve_qp(*args)
    assert bool(sol.solved.all()) and bool((sol.z > 0).any())  # active rows: the adjoint has work to do
    g = qp_vjp(sol, gx)
    for backend in ("c", "torch"):
        assert_same(g, autograd_grads(args, gx, backend))
    assert g.A is None if p == 0 else g.A.shape == (B, p, 13)


def test_shared_arguments_get_summed_gradients() -> None:
    # Unbatched P and G (shared by the batch) and a batch-1 h: gradients in those shapes, summed as autograd does.
    qp = random_qp_batch(6, 13, 30, bounds=True, spread=0.4, seed=7)
    args = [qp.P[0], qp.q, None, None, qp.G[0], qp.h[:1].clone(), qp.lb, qp.ub]
    gx = torch.randn(6, 13, dtype=DT)
    sol = solve_qp(*args)
    g = qp_vjp(sol, gx)
    assert g.P.shape == (13, 13) and g.G.shape == (30, 13) and g.h.shape == (1, 30) and g.q.shape == (6, 13)
    assert_same(g, autograd_grads(args, gx, "torch"))


def test_vjp_matches_finite_differences() -> None:
    rng = np.random.default_rng(3)
    n, m, p = 5, 8, 1
    M = rng.standard_normal((n, n))
    P, q = M @ M.T + 0.5 * np.eye(n), rng.standard_normal(n)
    A, G = rng.standard_normal((p, n)), rng.standard_normal((m, n))
    x_u = -np.linalg.solve(P, q)
    b, h = A @ x_u, G @ x_u - rng.uniform(-0.3, 0.3, m)  # about half the rows cut the unconstrained minimiser
    lb, ub = x_u - 0.05 * rng.uniform(0, 2, n), x_u + 1.0
    data = [torch.tensor(a[None], dtype=DT) for a in (P, q, A, b, G, h, lb, ub)]
    gx = torch.tensor(rng.standard_normal((1, n)), dtype=DT)
    sol = solve_qp(*data)
    assert bool(sol.solved.all()) and int((sol.z > 1e-6).sum() + (sol.z_lb > 1e-6).sum()) >= 2
    g = qp_vjp(sol, gx)
    eps = 1e-6
    for k, nm in enumerate(GRAD_NAMES):
        fd = torch.zeros_like(data[k])
        flat = fd.view(-1)
        for j in range(flat.numel()):
            f = []
            for s in (eps, -eps):
                d = [t.clone() for t in data]
                d[k].view(-1)[j] += s
                f.append(float((solve_qp(*d).x * gx).sum()))
            flat[j] = (f[0] - f[1]) / (2 * eps)
        assert torch.allclose(getattr(g, nm), fd, atol=1e-6, rtol=1e-5), nm


def test_declined_instances_get_the_torch_adjoint(monkeypatch) -> None:
    # P only semi-definite in instance 2 (its last variable linear, held by a bound): the C adjoint declines it.
    qp = random_qp_batch(5, 13, 30, bounds=True, spread=0.4, seed=11)
    P = qp.P.clone()
    P[2, -1, :] = P[2, :, -1] = 0.0
    q = qp.q.clone()
    q[2, -1] = 5.0
    args = [P, q, None, None, qp.G, qp.h, qp.lb, qp.ub]
    calls = []
    real = vjp_mod._declined
    monkeypatch.setattr(vjp_mod, "_declined", lambda *a: calls.append(1) or real(*a))
    sol = solve_qp(*args)
    assert bool(sol.solved.all())
    gx = torch.randn(5, 13, dtype=DT)
    g = qp_vjp(sol, gx)
    assert calls
    assert_same(g, autograd_grads(args, gx, "torch"), tol=1e-7)


def test_unsolved_instances_get_zero_gradients() -> None:
    qp = random_qp_batch(3, 13, 30, spread=0.3, seed=5)
    h = qp.h.clone()
    h[1, 0] = -1e3  # the first row alone with another one that contradicts it: infeasible
    G = qp.G.clone()
    G[1, 1] = -G[1, 0]
    h[1, 1] = -1e3
    sol = solve_qp(qp.P, qp.q, G=G, h=h)
    assert sol.status.tolist() == [0, int(QPStatus.PRIMAL_INFEASIBLE), 0]
    g = qp_vjp(sol, torch.ones(3, 13, dtype=DT))
    assert float(g.q[1].abs().max()) == 0.0 and float(g.G[1].abs().max()) == 0.0
    assert float(g.q[0].abs().max()) > 0.0


def test_errors_and_wrt() -> None:
    qp = random_qp_batch(2, 13, 30, spread=0.3, seed=9)
    sol = solve_qp(*qp.args(), backend="torch")
    with pytest.raises(QPGradientError, match="C route"):
        qp_vjp(sol, torch.ones(2, 13, dtype=DT))
    h = qp.h.clone()
    sol = solve_qp(qp.P, qp.q, G=qp.G, h=h)
    with pytest.raises(QPShapeError, match=r"gx must be \[2, 13\]"):
        qp_vjp(sol, torch.ones(3, 13, dtype=DT))
    g = qp_vjp(sol, torch.ones(2, 13), wrt=("q", "h"))  # float32 gx is converted
    assert g.P is None and g.G is None and g.q.shape == (2, 13) and g.h.shape == (2, 30)
    assert torch.allclose(g.h, qp_vjp(sol, torch.ones(2, 13, dtype=DT)).h)
    assert qp_vjp(sol, torch.ones(2, 13, dtype=DT), wrt=["G"]).q is None
    with pytest.raises(QPShapeError, match="wrt"):
        qp_vjp(sol, torch.ones(2, 13, dtype=DT), wrt=("Q",))
    h[0, 0] += 1.0  # in place after the solve
    with pytest.raises(QPGradientError, match="h was changed in place"):
        qp_vjp(sol, torch.ones(2, 13, dtype=DT))


def test_autograd_on_both_c_paths_equals_the_torch_route(monkeypatch) -> None:
    # Batched contiguous arguments take the direct path (x differentiable through qp_vjp); an unbatched P takes
    # the general path, whose backward is gi_qp_vjp on the stacked rows.  Neither may use the torch adjoint.
    import a3cqp_rl.qp.solver as solver_mod

    qp = random_qp_batch(4, 13, 30, p=1, bounds=True, spread=0.4, seed=21)
    gx = torch.randn(4, 13, dtype=DT)
    for args in (list(qp.args()), [qp.P[0]] + list(qp.args())[1:]):
        ref = autograd_grads(args, gx, "torch")
        with monkeypatch.context() as mp:
            mp.setattr(solver_mod, "_backward_torch", lambda *a, **k: pytest.fail("torch adjoint taken"))
            mp.setattr(vjp_mod, "_backward_torch", lambda *a, **k: pytest.fail("torch adjoint taken"))
            got = autograd_grads(args, gx, "c")
        for a, r in zip(got, ref):
            assert (a is None) == (r is None)
            if r is not None:
                assert a.shape == r.shape and float((a - r).abs().max()) <= 1e-8 * (1.0 + float(r.abs().max()))


def test_empty_batch_gives_empty_gradients() -> None:
    P = torch.eye(3, dtype=DT).expand(0, 3, 3).contiguous()
    q, G, h = torch.zeros(0, 3, dtype=DT), torch.zeros(0, 2, 3, dtype=DT), torch.zeros(0, 2, dtype=DT)
    g = qp_vjp(solve_qp(P, q, G=G, h=h), torch.zeros(0, 3, dtype=DT))
    assert g.P.shape == (0, 3, 3) and g.q.shape == (0, 3) and g.G.shape == (0, 2, 3) and g.h.shape == (0, 2)
    q = q.clone().requires_grad_()
    solve_qp(P, q, G=G, h=h).x.sum().backward()
    assert q.grad.shape == (0, 3)


def test_fields_changed_in_place_are_refused() -> None:
    qp = random_qp_batch(2, 13, 30, spread=0.3, seed=9)
    sol = solve_qp(*qp.args())
    sol.z.clamp_(max=0.0)  # the duals qp_vjp reads its working set from
    with pytest.raises(QPGradientError, match="solution's z was changed in place"):
        qp_vjp(sol, torch.ones(2, 13, dtype=DT))
    q = qp.q.clone().requires_grad_()
    sol = solve_qp(qp.P, q, G=qp.G, h=qp.h)
    x = sol.x
    sol.z.mul_(2.0)
    with pytest.raises(QPGradientError, match="solution's z"):
        x.sum().backward()
    sol = solve_qp(qp.P, q, G=qp.G, h=qp.h)
    x = sol.x
    del sol  # the node falls back on its own view of the buffer
    x.sum().backward()
    assert q.grad is not None and bool(torch.isfinite(q.grad).all())


def test_x_changed_in_place_refuses_the_backward_even_without_the_solution_object() -> None:
    """`x = solve_qp(...).x; x.add_(10)`: the adjoint reads x's buffer, so autograd's version check must refuse (it
    computed a wrong P.grad before, without a word)."""
    P0 = torch.tensor([[[2.0, 0.5], [0.5, 1.0]]], dtype=torch.float64)
    P = P0.clone().requires_grad_()
    q = torch.tensor([[-1.0, -3.0]], dtype=torch.float64, requires_grad=True)
    x = solve_qp(P, q).x
    x.add_(10.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        x.sum().backward()


@pytest.mark.parametrize("backend", ["auto", "c", "torch"])
def test_second_derivatives_are_right_or_refused(backend: str) -> None:
    """d/dq of (∂/∂q Σ x³ + |q|²) for an unconstrained QP, x = −P⁻¹q: the torch route's double backward matches the
    closed form; the C route's adjoint is not differentiable and says so instead of returning the |q|² part only."""
    P = torch.tensor([[[2.0, 0.5], [0.5, 1.0]]], dtype=torch.float64)
    q = torch.tensor([[-1.0, -3.0]], dtype=torch.float64, requires_grad=True)
    Pinv = torch.linalg.inv(P[0])

    def closed(qv: torch.Tensor) -> torch.Tensor:
        xv = -(Pinv @ qv)
        return (-(Pinv.T @ (3.0 * xv**2))).sum() + (qv**2).sum()

    want = torch.autograd.functional.jacobian(closed, q[0].detach())
    x = solve_qp(P, q, backend=backend).x
    if backend == "torch":
        g, = torch.autograd.grad((x**3).sum(), q, create_graph=True)
        got, = torch.autograd.grad(g.sum() + (q**2).sum(), q)
        torch.testing.assert_close(got[0], want, rtol=1e-8, atol=1e-10)
    else:
        with pytest.raises(QPGradientError, match="first derivatives only"):
            torch.autograd.grad((x**3).sum(), q, create_graph=True)
