"""Tests of the C route (a3cqp_rl/qp/native): same answers, multipliers, statuses and gradients as the torch route and Clarabel, and its fallbacks."""

from __future__ import annotations

import logging
from pathlib import Path

import cvxpy as cp
import numpy as np
import pytest
import torch

import a3cqp_rl.qp.batched as batched_mod
import a3cqp_rl.qp.solver as solver_mod
from a3cqp_rl.qp import QPStatus, native, solve_qp
from a3cqp_rl.qp.random_qp import RandomQP, clarabel_reference, random_qp_batch

DT = torch.float64
needs_lib = pytest.mark.skipif(native.load() is None, reason="gi_qp.c was not built at install time (no C compiler; "
                              "tests/test_native_build.py fails where a compiler exists and the library is missing)")


@pytest.fixture
def fresh_native(monkeypatch):
    """A forgotten native routine; restored (forgotten again) afterwards."""
    native._reset()
    yield
    monkeypatch.undo()
    native._reset()


def stacked(qp: RandomQP) -> tuple[np.ndarray, ...]:
    """(P, q, A, b, G, h) float64 numpy with bounds stacked under G (the canonical rows)."""
    B, n = qp.q.shape
    A = qp.A.numpy() if qp.A is not None else np.zeros((B, 0, n))
    b = qp.b.numpy() if qp.b is not None else np.zeros((B, 0))
    G, h = qp.G.numpy(), qp.h.numpy()
    if qp.lb is not None:
        eye = np.broadcast_to(np.eye(n), (B, n, n))
        G = np.concatenate([G, -eye, eye], 1)
        h = np.concatenate([h, -qp.lb.numpy(), qp.ub.numpy()], 1)
    return qp.P.numpy(), qp.q.numpy(), A, b, np.ascontiguousarray(G), np.ascontiguousarray(h)


def c_solve(P, q, A, b, G, h, z0=None, tol=1e-9):  # noqa: ANN001
    """gi_qp_solve on canonical numpy data through the solver's own call: x, y, z, status, solves."""
    t = [torch.from_numpy(np.ascontiguousarray(a)) for a in (P, q, A, b, G, h)]
    B, n = q.shape
    p, m = A.shape[1], G.shape[1]
    warm = None
    if z0 is not None:
        z0 = np.ascontiguousarray(np.concatenate([z0, np.zeros((B, 2 * n))], 1))
        warm = (z0, solver_mod.address(z0), m + 2 * n)
    buf, addr, _, _ = solver_mod._forward_c(native.load(), *t, None, None, B, n, p, m, warm, tol)
    sol = solver_mod.QPSolution._from_buffer(buf, addr, B, n, p, m)
    return (sol._np("_x"), sol._np("_y"), sol._np("_z"), sol._np("_status"), sol._np("_iterations"))


# Controller-sized families: easy, heavily constrained, equality-constrained (with bounds), larger.
FAMILIES = [
    (dict(m=30), 100),
    (dict(m=30, spread=0.35), 100),
    (dict(m=30, spread=1.0), 100),
    (dict(m=40, p=3, bounds=True, spread=0.35), 100),
    (dict(m=30, p=5, spread=1.0), 60),
    (dict(n=20, m=50, p=4, spread=0.5), 60),
]


@needs_lib
def test_native_routine_is_built_and_taken(monkeypatch) -> None:
    assert native.load() is not None
    monkeypatch.setattr(solver_mod, "solve_torch", lambda *a, **k: pytest.fail("torch route taken"))
    qp = random_qp_batch(1, spread=0.35, seed=1001)  # the instance bench/qp.py times at B = 1
    cold = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    warm = solve_qp(qp.P, qp.q + 1e-6, G=qp.G, h=qp.h, warm_start=cold)
    assert bool(cold.solved.all()) and bool(warm.solved.all()) and warm.iterations.tolist() == [1]
    x_ref, _ = clarabel_reference(qp)
    assert (cold.x - x_ref).abs().max().item() <= 1e-9


@needs_lib
@pytest.mark.parametrize("family", range(len(FAMILIES)))
def test_native_matches_the_torch_route_and_clarabel(family: int) -> None:
    # 520 instances in all; every one certified by the C routine, with the torch route's active set
    # (same x and multipliers up to rounding) and Clarabel's x.
    kw, B = FAMILIES[family]
    qp = random_qp_batch(B, seed=500 + family, **kw)
    args = stacked(qp)
    x, y, z, status, solves = c_solve(*args)
    assert (status == 0).all()
    ref = solve_qp(*qp.args(), backend="torch")
    assert bool(ref.solved.all())
    z_ref = torch.cat([ref.z] + ([ref.z_lb, ref.z_ub] if qp.lb is not None else []), 1).numpy()
    assert np.abs(x - ref.x.numpy()).max() <= 1e-8
    assert np.abs(z - z_ref).max() <= 1e-6 and (np.abs(y - ref.y.numpy()).max() if y.size else 0.0) <= 1e-6
    assert (z >= 0).all()
    x_ref, statuses = clarabel_reference(qp)
    assert set(statuses) == {"optimal"}
    assert np.abs(x - x_ref.numpy()).max() <= 1e-8
    # Warm start from the solution: one solve; from the solution of a perturbed q: the cold answer.
    xw, _, zw, sw, solves_w = c_solve(*args, z0=z)
    assert (sw == 0).all() and (solves_w == 1).all() and np.abs(xw - x).max() <= 1e-10
    P, q, A, b, G, h = args
    q2 = q + 0.05 * np.random.default_rng(family).standard_normal(q.shape)
    x2, y2, z2, s2, _ = c_solve(P, q2, A, b, G, h, z0=z)
    x2c, y2c, z2c, s2c, _ = c_solve(P, q2, A, b, G, h)
    assert (s2 == 0).all() and (s2c == 0).all()
    assert np.abs(x2 - x2c).max() <= 1e-10 and np.abs(z2 - z2c).max() <= 1e-8


GRAD_FAMILIES = [
    dict(n=8, m=12, p=1, bounds=True, spread=0.2),
    dict(m=30, spread=0.35),
    dict(m=30, p=3, spread=1.0),
    dict(n=20, m=50, p=4, spread=0.5),
]


@needs_lib
@pytest.mark.parametrize("family", range(len(GRAD_FAMILIES)))
def test_c_and_torch_routes_agree_including_gradients(family: int) -> None:
    # Forward (cold and warm) and backward (the C adjoint vs the torch one): same statuses,
    # solutions, multipliers and gradients of all QP data.
    qp = random_qp_batch(6, seed=40 + family, **GRAD_FAMILIES[family])
    w = torch.randn(qp.q.shape, generator=torch.Generator().manual_seed(3), dtype=DT)

    def run(backend, warm=None):  # noqa: ANN001
        leaves = [t.clone().requires_grad_() if t is not None else None for t in qp.args()]
        sol = solve_qp(*leaves, warm_start=warm, backend=backend)
        (sol.x * w).sum().backward()
        return sol, [t.grad for t in leaves if t is not None]

    sol, g = run("c")
    warm, gw = run("c", sol)
    sol_t, g_t = run("torch")
    warm_t, gw_t = run("torch", sol_t)
    assert (sol.z > 0).any()  # active rows: the adjoint has work to do
    for a, b in ((sol, sol_t), (warm, warm_t)):
        assert (a.status == b.status).all() and bool(a.solved.all())
        for f in ("x", "y", "z", "z_lb", "z_ub"):
            assert torch.allclose(getattr(a, f), getattr(b, f), rtol=0.0, atol=1e-7)
    for a, b in zip(g + gw, g_t + gw_t):
        if a is None:
            assert b is None
            continue
        assert (a - b).abs().max() <= 1e-6 * (1.0 + b.abs().max())


@needs_lib
def test_native_backward_is_taken_and_falls_back_for_singular_p(monkeypatch) -> None:
    qp = random_qp_batch(2, spread=0.35, seed=8)
    leaves = [t.clone().requires_grad_() for t in (qp.P, qp.q, qp.G, qp.h)]
    monkeypatch.setattr(solver_mod, "_backward_torch", lambda *a, **k: pytest.fail("torch adjoint taken"))
    solve_qp(leaves[0], leaves[1], G=leaves[2], h=leaves[3]).x.sum().backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves)
    monkeypatch.undo()
    # P = diag(1, 0) (semidefinite) with x1 held by an active row: the C route hands the instance to
    # the torch route, whose adjoint gives the gradient, as with backend="torch".
    P = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).expand(1, 2, 2).clone()
    q, G, h = torch.tensor([[1.0, -1.0]], dtype=DT), torch.tensor([[[0.0, 1.0]]], dtype=DT), torch.tensor([[2.0]], dtype=DT)

    def grads(backend):  # noqa: ANN001
        lv = [t.clone().requires_grad_() for t in (P, q, G, h)]
        sol = solve_qp(*lv[:2], G=lv[2], h=lv[3], backend=backend)
        (sol.x * torch.tensor([[0.3, 0.7]], dtype=DT)).sum().backward()
        return sol, [t.grad for t in lv]

    sol, g = grads("c")
    assert bool(sol.solved.all()) and torch.allclose(sol.x, torch.tensor([[-1.0, 2.0]], dtype=DT))
    _, g_t = grads("torch")
    for a, b in zip(g, g_t):
        assert (a - b).abs().max() <= 1e-12


@needs_lib
def test_float32_inputs() -> None:
    qp = random_qp_batch(8, p=2, bounds=True, spread=0.35, seed=9)
    args32 = [t.float() for t in qp.args()]
    sol = solve_qp(*args32, backend="c")
    ref = solve_qp(*args32, backend="torch")
    assert sol.x.dtype == torch.float32 and sol.z.dtype == torch.float32
    assert bool(sol.solved.all()) and sol.status.tolist() == ref.status.tolist()
    assert (sol.x - ref.x).abs().max() <= 1e-6 and (sol.z - ref.z).abs().max() <= 1e-5
    assert (sol.x.double() - solve_qp(*qp.args()).x).abs().max() < 1e-3


def _hard_batch() -> tuple[torch.Tensor, ...]:
    """Feasible, infeasible, NaN, singular-P (LP) and dependent-row instances in one batch."""
    qp = random_qp_batch(6, n=5, m=8, spread=0.2, seed=4)
    P, q, G, h = qp.P.clone(), qp.q.clone(), qp.G.clone(), qp.h.clone()
    G[1, 0], h[1, 0] = torch.eye(5, dtype=DT)[0], -1.0  # x0 ≤ −1 and x0 ≥ 1: infeasible
    G[1, 1], h[1, 1] = -torch.eye(5, dtype=DT)[0], -1.0
    q[2, 0] = torch.nan
    P[3] = 0.0  # LP, bounded by a box below
    G[3, :5], h[3, :5] = torch.eye(5, dtype=DT), torch.ones(5, dtype=DT)
    G[3, 5:], h[3, 5:] = -torch.eye(5, dtype=DT)[:3], torch.ones(3, dtype=DT)
    G[4, 1], h[4, 1] = G[4, 0], h[4, 0]  # a duplicated row
    P[5, 0, 0] = -1.0  # indefinite
    return P, q, G, h


@needs_lib
def test_infeasible_unbounded_nan_and_singular_instances_get_the_same_statuses_on_both_routes() -> None:
    P, q, G, h = _hard_batch()
    B, n = q.shape
    status = c_solve(P.numpy(), q.numpy(), np.zeros((B, 0, n)), np.zeros((B, 0)), G.numpy(), h.numpy())[3]
    assert status[2] == QPStatus.INVALID_INPUT  # decided in C
    assert status[1] == QPStatus.PRIMAL_INFEASIBLE  # decided in C too: its Farkas vector checked
    assert (status[[3, 5]] >= native.HANDED_ON).all()  # P singular, P indefinite: handed on
    sol = solve_qp(P, q, G=G, h=h, backend="c")
    assert sol.status.tolist() == [QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE, QPStatus.INVALID_INPUT,
                                   QPStatus.SOLVED, QPStatus.SOLVED, QPStatus.NON_CONVEX]
    assert torch.isfinite(sol.x).all() and torch.isfinite(sol.z).all()
    ref = solve_qp(P, q, G=G, h=h, backend="torch")
    assert sol.status.tolist() == ref.status.tolist()
    ok = ref.solved
    assert (sol.x[ok] - ref.x[ok]).abs().max() <= 1e-8
    # Unbounded: P = diag(1, 0), x1 free with cost −x1 and only bounded below.
    Pu = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).expand(2, 2, 2)
    unb_args = (Pu, torch.tensor([[1.0, 1.0], [1.0, -1.0]], dtype=DT))
    unb_kw = dict(G=torch.tensor([[0.0, -1.0]], dtype=DT).expand(2, 1, 2), h=torch.zeros(2, 1, dtype=DT))
    for backend in ("c", "torch"):
        assert solve_qp(*unb_args, **unb_kw, backend=backend).status.tolist() == [QPStatus.SOLVED, QPStatus.DUAL_INFEASIBLE]


@needs_lib
def test_dependent_warm_rows_restart_cold() -> None:
    # Both copies of a duplicated active row carry multipliers in the warm start: S_WW is singular,
    # the C code starts cold, and the answer is the one without the copy.
    qp = random_qp_batch(8, n=6, m=10, p=1, spread=0.2, seed=11)
    G, h = torch.cat([qp.G, qp.G], 1), torch.cat([qp.h, qp.h], 1)
    base = solve_qp(qp.P, qp.q, qp.A, qp.b, qp.G, qp.h)
    z_dup = torch.cat([base.z, base.z], 1)
    warm = solve_qp(qp.P, qp.q, qp.A, qp.b, G, h, warm_start=type(base)(base.x, base.y, z_dup, base.z_lb, base.z_ub, base.status, base.iterations))
    assert bool(warm.solved.all()) and (warm.x - base.x).abs().max() < 1e-9


def test_missing_library_falls_back_to_the_torch_route_with_one_warning(fresh_native, monkeypatch, caplog) -> None:
    monkeypatch.setattr(native._library, "source", Path("/no-such-dir/gi_qp.c"))  # as if built without a compiler
    qp = random_qp_batch(4, spread=0.35, seed=7)
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.qp.native"):
        assert native.load() is None
        sol = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
        sol2 = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, warm_start=sol)
        assert native.load() is None
        with pytest.raises(solver_mod.QPBackendError, match="unavailable"):
            solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, backend="c")
    warnings = [r for r in caplog.records if r.name == "a3cqp_rl.qp.native"]
    assert len(warnings) == 1 and "torch route" in warnings[0].getMessage()
    assert "not compiled at install time" in warnings[0].getMessage()
    ref = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, backend="torch")
    assert bool(sol.solved.all()) and bool(sol2.solved.all())
    assert (sol.x - ref.x).abs().max() == 0 and (sol.z - ref.z).abs().max() == 0 and (sol2.x - ref.x).abs().max() < 1e-10


def test_env_switch_disables_native(fresh_native, monkeypatch, caplog) -> None:
    monkeypatch.setenv("A3CQP_NATIVE_QP", "0")
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.qp.native"):
        assert native.load() is None
    assert not caplog.records


@pytest.mark.parametrize("backend", ["c", "torch"])
def test_equality_only_qp(backend: str) -> None:
    # No inequality rows at all (m = 0): x = argmin ½|x|² + 1ᵀx s.t. Σx = 0 is x = 0 with y = −1.
    if backend == "c" and native.load() is None:
        pytest.skip("no C routine")
    P, q = torch.eye(3, dtype=DT).expand(2, 3, 3), torch.ones(2, 3, dtype=DT)
    sol = solve_qp(P, q, torch.ones(2, 1, 3, dtype=DT), torch.zeros(2, 1, dtype=DT), backend=backend)
    assert bool(sol.solved.all()) and sol.x.abs().max() <= 1e-12 and torch.allclose(sol.y, -torch.ones(2, 1, dtype=DT))


@needs_lib
def test_more_equalities_than_variables_are_handed_on() -> None:
    # p = n + 1 consistent equalities (dependent): the C routine declines, the torch route decides.
    qp = random_qp_batch(3, n=4, m=12, p=5, spread=0.5, seed=13)
    status = c_solve(*stacked(qp))[3]
    assert (status >= native.HANDED_ON).all()
    sol = solve_qp(*qp.args(), backend="c")
    ref = solve_qp(*qp.args(), backend="torch")
    assert sol.status.tolist() == ref.status.tolist()
    assert torch.allclose(sol.x, ref.x, rtol=0.0, atol=1e-12)


@needs_lib
def test_large_batches_send_only_what_c_leaves_to_the_torch_route(monkeypatch) -> None:
    """B = 64: certified in one C call (no torch solve), answers as Clarabel; with some infeasible instances
    (decided in C) and some with a singular P, the singular ones alone go to the torch route, and every status is
    backend='torch''s."""
    qp = random_qp_batch(64, spread=0.35, seed=11)
    x_ref, _ = clarabel_reference(qp)
    seen = []
    real = solver_mod.solve_torch
    monkeypatch.setattr(solver_mod, "solve_torch", lambda *a, **k: seen.append(a[1].shape[0]) or real(*a, **k))
    P = qp.P.clone().requires_grad_(True)
    sol = solve_qp(P, qp.q, G=qp.G, h=qp.h, lb=qp.lb, ub=qp.ub)
    assert seen == [] and bool((sol.status == QPStatus.SOLVED).all())
    assert (sol.x - x_ref).abs().max().item() <= 1e-8
    sol.x.sum().backward()  # the native adjoint over the whole batch
    assert torch.isfinite(P.grad).all()

    G, h, P = qp.G.clone(), qp.h.clone(), qp.P.clone()
    for i in (3, 40):  # g x <= -1 and -g x <= -1: infeasible
        G[i, 1], h[i, :2] = -G[i, 0], -1.0
    for i in (7, 50):  # P semi-definite (one direction held by the bounds only)
        P[i, :, 0] = P[i, 0, :] = 0.0
    for fast in (True, False):  # no-grad (straight to C) and autograd (canonical rows) calls
        seen.clear()
        sol = solve_qp(P.requires_grad_(not fast), qp.q, G=G, h=h, lb=qp.lb, ub=qp.ub)
        assert sum(seen) == 2  # only the two uncertified instances left C
        P.requires_grad_(False)
    ref = solve_qp(P, qp.q, G=G, h=h, lb=qp.lb, ub=qp.ub, backend="torch")
    assert torch.equal(sol.status, ref.status) and (sol.status != QPStatus.SOLVED).nonzero().flatten().tolist() == [3, 40]
    ok = sol.status == QPStatus.SOLVED
    assert (sol.x[ok] - ref.x[ok]).abs().max().item() <= 1e-8


@needs_lib
def test_non_finite_entries_are_invalid_before_any_infeasible_row() -> None:
    """P and G are tested for inf/NaN while symmetrised and copied: rows without a constraint (h ≥ 1e20) and
    infeasible rows (h ≤ −1e20) are tested too, and INVALID_INPUT wins over PRIMAL_INFEASIBLE, on both routes."""
    n, m = 3, 4
    P = torch.eye(n, dtype=DT).expand(6, n, n).clone()
    q = torch.ones(6, n, dtype=DT)
    G = torch.ones(6, m, n, dtype=DT)
    h = torch.ones(6, m, dtype=DT)
    G[0, 1, 2] = float("inf")  # in a row that is no constraint
    h[0, 1] = float("inf")
    G[1, 2, 0] = float("nan")  # in an infeasible row
    h[1, 2] = -float("inf")
    h[2, 3] = -1e20  # infeasible, every entry finite
    P[3, 0, 1], P[3, 1, 0] = float("inf"), -float("inf")  # ½(P + Pᵀ) would be NaN, P itself is not finite
    P[4, 2, 1] = float("nan")  # below the diagonal: read as P[1, 2]'s partner too
    want = [QPStatus.INVALID_INPUT, QPStatus.INVALID_INPUT, QPStatus.PRIMAL_INFEASIBLE, QPStatus.INVALID_INPUT,
            QPStatus.INVALID_INPUT, QPStatus.SOLVED]
    for backend in ("c", "torch"):
        sol = solve_qp(P, q, G=G, h=h, backend=backend)
        assert sol.status.tolist() == [int(s) for s in want], backend
    assert torch.allclose(solve_qp(P[5:], q[5:], G=G[5:], h=h[5:], backend="c").x, -torch.ones(1, n, dtype=DT))


@needs_lib
def test_module_takes_addresses_or_arrays_and_refuses_a_wrong_call() -> None:
    """The extension's entry points read an address as an int or as a contiguous numpy array alike; a wrong number
    of arguments or a non-contiguous array raises instead of reading memory."""
    lib = native.load()
    qp = random_qp_batch(4, 13, 30, spread=0.35, seed=77)
    B, n, m = 4, 13, 30
    strides = np.array([n * n, n, 0, 0, m * n, m, n, n, 0], dtype=np.int64)
    args = (qp.P.data_ptr(), qp.q.data_ptr(), 0, 0, qp.G.data_ptr(), qp.h.data_ptr(), 0, 0, 0)
    out_int, out_arr = np.empty(B * (3 * n + m + 2)), np.empty(B * (3 * n + m + 2))
    lib.solve(B, n, 0, m, *args, solver_mod.address(strides), 1e-9, 100, solver_mod.address(out_int))
    lib.solve(B, n, 0, m, *args, strides, 1e-9, 100, out_arr)
    assert np.array_equal(out_int, out_arr)
    assert np.array_equal(out_arr[: B * n].reshape(B, n), solve_qp(qp.P, qp.q, G=qp.G, h=qp.h).x.numpy())
    with pytest.raises(TypeError, match="17 arguments"):
        lib.solve(B, n, 0, m, *args, strides, 1e-9, 100)
    with pytest.raises((BufferError, ValueError, TypeError)):
        lib.solve(B, n, 0, m, *args, strides, 1e-9, 100, np.empty((B * (3 * n + m + 2), 2))[:, 0])


def test_a_violated_row_the_range_space_values_hide_is_found_by_the_certificate() -> None:
    """A controller QP under random switching weights (13 variables, 58 rows, multipliers up to 5.6e5, |x₀| ~1e6):
    the range-space row values round at ~5e-3 there, so G-I stopped with a total-acceleration row violated by
    3.6e-3 and the certificate failed (handed on; the controller braked). The C route now adds the row the
    certificate's direct C x − d shows violated and solves it alone, as the torch route and Clarabel do."""
    d = np.load(Path(__file__).parent / "data" / "qp_coarse_row_values.npz")
    P, q, G, h = (torch.from_numpy(d[k])[None] for k in ("P", "q", "G", "h"))
    c = solve_qp(P, q, G=G, h=h, hand_on=False)  # the C route alone: an undecided instance would say MAX_ITER
    t = solve_qp(P, q, G=G, h=h, backend="torch")
    assert c.status.item() == QPStatus.SOLVED and t.status.item() == QPStatus.SOLVED
    assert torch.allclose(c.x, t.x, rtol=0, atol=1e-8 * float(t.x.abs().max()))
    assert float((G[0] @ c.x[0] - h[0]).max()) <= 1e-9 * float(h.abs().max())
    x = cp.Variable(13)
    cp.Problem(cp.Minimize(0.5 * cp.quad_form(x, cp.psd_wrap(d["P"])) + d["q"] @ x), [d["G"] @ x <= d["h"]]).solve(
        solver="CLARABEL")
    assert np.allclose(c.x[0].numpy(), x.value, rtol=0, atol=1e-6 * float(np.abs(x.value).max()))
