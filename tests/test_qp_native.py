"""Tests of the C dual active set (a3cqp_rl/qp/native): same answers, multipliers and statuses as the numpy path and Clarabel, and its fallbacks."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch

import a3cqp_rl.qp.small_batch as small
import a3cqp_rl.qp.solver as solver_mod
from a3cqp_rl.qp import QPStatus, native, solve_qp
from a3cqp_rl.qp.random_qp import RandomQP, clarabel_reference, random_qp_batch

DT = torch.float64
needs_lib = pytest.mark.skipif(native.load() is None, reason="gi_qp.c was not built at install time (no C compiler; "
                              "tests/test_native_build.py fails where a compiler exists and the library is missing)")


@pytest.fixture
def numpy_only(monkeypatch):
    """Context in which the small-batch path runs its numpy code (the reference)."""

    def use(flag: bool) -> None:
        monkeypatch.setattr(small, "NATIVE", not flag)

    return use


@pytest.fixture
def fresh_native(monkeypatch):
    """A forgotten native routine; restored (forgotten again) afterwards."""
    native._reset()
    yield
    monkeypatch.undo()
    native._reset()


def stacked(qp: RandomQP) -> tuple[np.ndarray, ...]:
    """(P, q, A, b, G, h) float64 numpy with bounds stacked under G, as solve_qp hands them to active_set_small."""
    B, n = qp.q.shape
    A = qp.A.numpy() if qp.A is not None else np.zeros((B, 0, n))
    b = qp.b.numpy() if qp.b is not None else np.zeros((B, 0))
    G, h = qp.G.numpy(), qp.h.numpy()
    if qp.lb is not None:
        eye = np.broadcast_to(np.eye(n), (B, n, n))
        G = np.concatenate([G, -eye, eye], 1)
        h = np.concatenate([h, -qp.lb.numpy(), qp.ub.numpy()], 1)
    return qp.P.numpy(), qp.q.numpy(), A, b, np.ascontiguousarray(G), np.ascontiguousarray(h)


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
    assert native.load() is not None and small.NATIVE

    def fail(*args, **kwargs):
        raise AssertionError("numpy path taken")

    for name in ("_range_space", "_warm_one_solve", "_dual_active_set"):
        monkeypatch.setattr(small, name, fail)
    qp = random_qp_batch(1, spread=0.35, seed=1001)  # the instance bench/qp.py times at B = 1
    cold = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    warm = solve_qp(qp.P, qp.q + 1e-6, G=qp.G, h=qp.h, warm_start=cold)
    assert bool(cold.solved.all()) and bool(warm.solved.all()) and warm.iterations.tolist() == [1]
    x_ref, _ = clarabel_reference(qp)
    assert (cold.x - x_ref).abs().max().item() <= 1e-9


@needs_lib
@pytest.mark.parametrize("family", range(len(FAMILIES)))
def test_native_matches_numpy_and_clarabel(family: int, numpy_only) -> None:
    # 520 instances in all; every one certified by the C routine, with the numpy path's working
    # set (same x and multipliers up to rounding) and Clarabel's x.
    kw, B = FAMILIES[family]
    qp = random_qp_batch(B, seed=500 + family, **kw)
    args = stacked(qp)
    solve = native.load()
    x, y, z, status, solves = solve(*args, None, 1e-9, 100)
    assert (status == native.CERTIFIED).all()
    numpy_only(True)
    x_np, y_np, z_np, outcome, solves_np = small.active_set_small(*args, None, 1e-9, 100)
    assert (outcome == small.CERTIFIED).all()
    assert np.abs(x - x_np).max() <= 1e-10
    assert np.abs(z - z_np).max() <= 1e-8 and (np.abs(y - y_np).max() if y.size else 0.0) <= 1e-8
    assert ((z > 0) == (z_np > 0)).all() and (z >= 0).all()
    # At most the numpy path's KKT solves (it also tries k + 1 > n rows, which the C code skips).
    assert (solves <= solves_np).all() and solves.mean() >= 0.9 * solves_np.mean()
    x_ref, statuses = clarabel_reference(qp)
    assert set(statuses) == {"optimal"}
    assert np.abs(x - x_ref.numpy()).max() <= 1e-8
    # Warm start from the solution: one solve; from the solution of a perturbed q: the cold answer.
    xw, _, zw, sw, solves_w = solve(*args, z, 1e-9, 100)
    assert (sw == 0).all() and (solves_w == 1).all() and np.abs(xw - x).max() <= 1e-10
    P, q, A, b, G, h = args
    q2 = q + 0.05 * np.random.default_rng(family).standard_normal(q.shape)
    x2, y2, z2, s2, _ = solve(P, q2, A, b, G, h, z, 1e-9, 100)
    x2c, y2c, z2c, s2c, _ = solve(P, q2, A, b, G, h, None, 1e-9, 100)
    x2n, y2n, z2n, o2n, _ = small.active_set_small(P, q2, A, b, G, h, z, 1e-9, 100)  # numpy, warm
    assert (s2 == 0).all() and (s2c == 0).all() and (o2n == small.CERTIFIED).all()
    assert np.abs(x2 - x2c).max() <= 1e-10 and np.abs(z2 - z2c).max() <= 1e-8
    assert np.abs(x2 - x2n).max() <= 1e-10 and np.abs(z2 - z2n).max() <= 1e-8
    assert (np.abs(y2 - y2n).max() if y2.size else 0.0) <= 1e-8


GRAD_FAMILIES = [
    dict(n=8, m=12, p=1, bounds=True, spread=0.2),
    dict(m=30, spread=0.35),
    dict(m=30, p=3, spread=1.0),
    dict(n=20, m=50, p=4, spread=0.5),
]


@needs_lib
@pytest.mark.parametrize("family", range(len(GRAD_FAMILIES)))
def test_solve_qp_with_and_without_native_agree_including_gradients(family: int, numpy_only) -> None:
    # Forward (cold and warm) and backward (the C adjoint vs the numpy one): same statuses,
    # solutions, multipliers and gradients of all QP data.
    qp = random_qp_batch(6, seed=40 + family, **GRAD_FAMILIES[family])
    w = torch.randn(qp.q.shape, generator=torch.Generator().manual_seed(3), dtype=DT)

    def run(warm=None):
        leaves = [t.clone().requires_grad_() if t is not None else None for t in qp.args()]
        sol = solve_qp(*leaves, warm_start=warm)
        (sol.x * w).sum().backward()
        return sol, [t.grad for t in leaves if t is not None]

    sol, g = run()
    warm, gw = run(sol)
    numpy_only(True)
    sol_np, g_np = run()
    warm_np, gw_np = run(sol_np)
    assert (sol.z > 0).any()  # active rows: the adjoint has work to do
    for a, b in ((sol, sol_np), (warm, warm_np)):
        assert (a.status == b.status).all() and bool(a.solved.all())
        for f in ("x", "y", "z", "z_lb", "z_ub"):
            assert torch.allclose(getattr(a, f), getattr(b, f), rtol=0.0, atol=1e-9)
    for a, b in zip(g + gw, g_np + gw_np):
        if a is None:
            assert b is None
            continue
        assert (a - b).abs().max() <= 1e-8 * (1.0 + b.abs().max())


@needs_lib
def test_native_backward_is_taken_and_falls_back_for_singular_p(monkeypatch, numpy_only) -> None:
    qp = random_qp_batch(2, spread=0.35, seed=8)
    leaves = [t.clone().requires_grad_() for t in (qp.P, qp.q, qp.G, qp.h)]
    monkeypatch.setattr(small, "adjoint_small", lambda *a, **k: pytest.fail("numpy adjoint taken"))
    monkeypatch.setattr(solver_mod, "adjoint_small", lambda *a, **k: pytest.fail("numpy adjoint taken"))
    solve_qp(leaves[0], leaves[1], G=leaves[2], h=leaves[3]).x.sum().backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves)
    monkeypatch.undo()
    # P = diag(1, 0) (semidefinite) with x1 held by an active row: the C adjoint (range space of
    # P) declines, the numpy LU adjoint gives the gradient, as without the native routine.
    P = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).expand(1, 2, 2).clone()
    q, G, h = torch.tensor([[1.0, -1.0]], dtype=DT), torch.tensor([[[0.0, 1.0]]], dtype=DT), torch.tensor([[2.0]], dtype=DT)

    def grads():
        lv = [t.clone().requires_grad_() for t in (P, q, G, h)]
        sol = solve_qp(*lv[:2], G=lv[2], h=lv[3])
        (sol.x * torch.tensor([[0.3, 0.7]], dtype=DT)).sum().backward()
        return sol, [t.grad for t in lv]

    sol, g = grads()
    assert bool(sol.solved.all()) and torch.allclose(sol.x, torch.tensor([[-1.0, 2.0]], dtype=DT))
    numpy_only(True)
    _, g_np = grads()
    for a, b in zip(g, g_np):
        assert (a - b).abs().max() <= 1e-12


@needs_lib
def test_float32_inputs(numpy_only) -> None:
    qp = random_qp_batch(8, p=2, bounds=True, spread=0.35, seed=9)
    args32 = [t.float() for t in qp.args()]
    sol = solve_qp(*args32)
    numpy_only(True)
    ref = solve_qp(*args32)
    assert sol.x.dtype == torch.float32 and sol.z.dtype == torch.float32 and bool(sol.solved.all())
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
def test_infeasible_unbounded_nan_and_singular_instances_fall_back_with_the_same_statuses(numpy_only) -> None:
    P, q, G, h = _hard_batch()
    status = native.load()(*(t.numpy() for t in (P, q)), np.zeros((6, 0, 5)), np.zeros((6, 0)), G.numpy(), h.numpy(), None, 1e-9, 100)[3]
    assert (status[[1, 2, 3, 5]] != native.CERTIFIED).all()  # infeasible, NaN, P singular, P indefinite
    sol = solve_qp(P, q, G=G, h=h)
    assert sol.status[1] == QPStatus.PRIMAL_INFEASIBLE and sol.status[2] != QPStatus.SOLVED
    assert torch.isfinite(sol.x).all() and torch.isfinite(sol.z).all()
    # Unbounded: P = diag(1, 0), x1 free with cost −x1 and only bounded below.
    Pu = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).expand(2, 2, 2)
    unb_args = (Pu, torch.tensor([[1.0, 1.0], [1.0, -1.0]], dtype=DT))
    unb_kw = dict(G=torch.tensor([[0.0, -1.0]], dtype=DT).expand(2, 1, 2), h=torch.zeros(2, 1, dtype=DT))
    unb = solve_qp(*unb_args, **unb_kw)
    assert unb.status.tolist() == [QPStatus.SOLVED, QPStatus.DUAL_INFEASIBLE]
    numpy_only(True)
    ref = solve_qp(P, q, G=G, h=h)
    assert sol.status.tolist() == ref.status.tolist()
    ok = ref.solved
    assert (sol.x[ok] - ref.x[ok]).abs().max() <= 1e-9
    assert solve_qp(*unb_args, **unb_kw).status.tolist() == unb.status.tolist()


@needs_lib
def test_dependent_warm_rows_restart_cold(numpy_only) -> None:
    # Both copies of a duplicated active row carry multipliers in the warm start: S_WW is singular,
    # the C code starts cold, and the answer is the one without the copy.
    qp = random_qp_batch(8, n=6, m=10, p=1, spread=0.2, seed=11)
    G, h = torch.cat([qp.G, qp.G], 1), torch.cat([qp.h, qp.h], 1)
    base = solve_qp(qp.P, qp.q, qp.A, qp.b, qp.G, qp.h)
    z_dup = torch.cat([base.z, base.z], 1)
    warm = solve_qp(qp.P, qp.q, qp.A, qp.b, G, h, warm_start=type(base)(base.x, base.y, z_dup, base.z_lb, base.z_ub, base.status, base.iterations))
    assert bool(warm.solved.all()) and (warm.x - base.x).abs().max() < 1e-9


def test_missing_library_falls_back_to_numpy_with_one_warning(fresh_native, monkeypatch, caplog, numpy_only) -> None:
    monkeypatch.setattr(native._library, "source", Path("/no-such-dir/gi_qp.c"))  # as if built without a compiler
    qp = random_qp_batch(4, spread=0.35, seed=7)
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.qp.native"):
        assert native.load() is None
        sol = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
        sol2 = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, warm_start=sol)
        assert native.load() is None
    warnings = [r for r in caplog.records if r.name == "a3cqp_rl.qp.native"]
    assert len(warnings) == 1 and "numpy path" in warnings[0].getMessage()
    assert "not compiled at install time" in warnings[0].getMessage()
    numpy_only(True)
    ref = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    assert bool(sol.solved.all()) and bool(sol2.solved.all())
    assert (sol.x - ref.x).abs().max() == 0 and (sol.z - ref.z).abs().max() == 0 and (sol2.x - ref.x).abs().max() < 1e-10


def test_env_switch_disables_native(fresh_native, monkeypatch, caplog) -> None:
    monkeypatch.setenv("A3CQP_NATIVE_QP", "0")
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.qp.native"):
        assert native.load() is None
    assert not caplog.records


@pytest.mark.parametrize("use_native", [True, False])
def test_equality_only_qp_on_the_small_path(use_native: bool, numpy_only) -> None:
    # No inequality rows at all (m = 0): x = argmin ½|x|² + 1ᵀx s.t. Σx = 0 is x = 0 with y = −1.
    numpy_only(not use_native)
    P, q = torch.eye(3, dtype=DT).expand(2, 3, 3), torch.ones(2, 3, dtype=DT)
    sol = solve_qp(P, q, torch.ones(2, 1, 3, dtype=DT), torch.zeros(2, 1, dtype=DT))
    assert bool(sol.solved.all()) and sol.x.abs().max() <= 1e-12 and torch.allclose(sol.y, -torch.ones(2, 1, dtype=DT))


@needs_lib
def test_more_equalities_than_variables_fall_back(numpy_only) -> None:
    # p = n + 1 consistent equalities (dependent): the C routine declines, the numpy path and the
    # batched path decide, exactly as without it.
    qp = random_qp_batch(3, n=4, m=12, p=5, spread=0.5, seed=13)
    status = native.load()(*stacked(qp), None, 1e-9, 100)[3]
    assert (status != native.CERTIFIED).all()
    sol = solve_qp(*qp.args())
    numpy_only(True)
    ref = solve_qp(*qp.args())
    assert sol.status.tolist() == ref.status.tolist()
    assert torch.allclose(sol.x, ref.x, rtol=0.0, atol=1e-12)


@needs_lib
def test_large_batches_take_the_native_path_and_send_what_it_leaves_to_the_batched_path(monkeypatch) -> None:
    """B = 64 > SMALL_BATCH_MAX: certified in one C call (no batched solve), answers as Clarabel; with some
    infeasible instances those alone go to the batched path, with the statuses of the C-free route."""
    assert native.load() is not None and 64 > solver_mod.SMALL_BATCH_MAX
    qp = random_qp_batch(64, spread=0.35, seed=11)
    x_ref, _ = clarabel_reference(qp)
    seen = []
    batched = solver_mod._solve_batched
    monkeypatch.setattr(solver_mod, "_solve_batched", lambda *a, **k: seen.append(a[1].shape[0]) or batched(*a, **k))
    P = qp.P.clone().requires_grad_(True)
    sol = solve_qp(P, qp.q, G=qp.G, h=qp.h, lb=qp.lb, ub=qp.ub)
    assert seen == [] and bool((sol.status == QPStatus.SOLVED).all())
    assert (sol.x - x_ref).abs().max().item() <= 1e-8
    sol.x.sum().backward()  # the native adjoint over the whole batch
    assert torch.isfinite(P.grad).all()

    G, h = qp.G.clone(), qp.h.clone()
    for i in (3, 40):  # g x <= -1 and -g x <= -1: infeasible
        G[i, 1], h[i, :2] = -G[i, 0], -1.0
    sol = solve_qp(qp.P, qp.q, G=G, h=h, lb=qp.lb, ub=qp.ub)
    assert seen and sum(seen) == 2  # only the two uncertified instances left C
    monkeypatch.setattr(small, "NATIVE", False)
    ref = solve_qp(qp.P, qp.q, G=G, h=h, lb=qp.lb, ub=qp.ub)
    assert torch.equal(sol.status, ref.status) and int((sol.status != QPStatus.SOLVED).sum()) == 2
    ok = sol.status == QPStatus.SOLVED
    assert (sol.x[ok] - ref.x[ok]).abs().max().item() <= 1e-8
