"""Every failure mode gets its status, per instance, on every route; arguments and backends are checked."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from a3cqp_rl.qp import QPBackendError, QPShapeError, QPStatus, native, solve_qp
from a3cqp_rl.qp.random_qp import clarabel_reference, random_qp_batch

DT = torch.float64
S = QPStatus
ROUTES = ["c", "torch"]


@pytest.fixture(params=ROUTES)
def backend(request) -> str:
    if request.param == "c" and native.load() is None:
        pytest.skip("no C routine")
    return request.param


def t(*rows) -> torch.Tensor:  # noqa: ANN002
    return torch.tensor(rows, dtype=DT)


def test_status_values_are_stable() -> None:
    assert [int(s) for s in (S.SOLVED, S.MAX_ITER, S.PRIMAL_INFEASIBLE, S.DUAL_INFEASIBLE)] == [0, 1, 2, 3]
    assert [int(s) for s in (S.NON_CONVEX, S.INVALID_INPUT, S.TOLERANCE_NOT_MET)] == [4, 5, 6]


def test_no_rows_and_singular_p_is_unbounded_not_a_crash(backend: str) -> None:
    assert solve_qp(torch.zeros(2, 2, dtype=DT), t(1.0, 0.0), backend=backend).status.tolist() == [S.DUAL_INFEASIBLE]
    v = t(1.0, 2.0)
    assert solve_qp(torch.outer(v, v), t(2.0, -1.0), backend=backend).status.tolist() == [S.DUAL_INFEASIBLE]
    assert solve_qp(torch.zeros(1, 1, dtype=DT), t(1.0), backend=backend).status.tolist() == [S.DUAL_INFEASIBLE]
    # An unconstrained batch [I, 0]: the first instance is solved, the second unbounded.
    P = torch.stack([torch.eye(2, dtype=DT), torch.zeros(2, 2, dtype=DT)])
    sol = solve_qp(P, t([1.0, -1.0], [1.0, 0.0]), backend=backend)
    assert sol.status.tolist() == [S.SOLVED, S.DUAL_INFEASIBLE]
    assert torch.allclose(sol.x[0], t(-1.0, 1.0)) and (sol.x[1] == 0).all()


def test_one_large_bound_does_not_loosen_the_other_rows(backend: str) -> None:
    for big in (1e10, 1e19, 1e20, float("inf")):
        sol = solve_qp(2 * torch.eye(2, dtype=DT), t(-4.0, 0.0), G=t([1.0, 0.0]), h=t(1.0), ub=t(float("inf"), big),
                       backend=backend)
        assert sol.status.tolist() == [S.SOLVED] and torch.allclose(sol.x, t([1.0, 0.0]), atol=1e-9), (big, sol.x)
    # ±1e20 (and beyond) on the "no bound" side means none, also as a row's right-hand side.
    sol = solve_qp(torch.eye(2, dtype=DT), t(-3.0, 0.0), G=t([1.0, 0.0], [0.0, 1.0]), h=t(1.0, 1e20), backend=backend)
    assert sol.status.tolist() == [S.SOLVED] and torch.allclose(sol.x, t([1.0, 0.0]), atol=1e-9)


def test_lp_with_an_unbounded_optimal_face(backend: str) -> None:
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        C = torch.randn(5, 10, generator=g, dtype=DT)
        q = C.mT @ torch.randn(5, generator=g, dtype=DT)
        G, h = torch.cat([C, -C]), torch.ones(10, dtype=DT)
        sol = solve_qp(torch.zeros(10, 10, dtype=DT), q, G=G, h=h, backend=backend)
        assert sol.status.tolist() == [S.SOLVED]
        # LP duality: the optimum is −Σ|w_i| over the dual (q = Cᵀw on |Cx| ≤ 1) if that w is feasible.
        import cvxpy as cp

        x = cp.Variable(10)
        ref = cp.Problem(cp.Minimize(q.numpy() @ x), [cp.abs(C.numpy() @ x) <= 1]).solve(solver=cp.CLARABEL)
        assert abs(float(q @ sol.x[0]) - ref) <= 1e-6 * (1 + abs(ref))
        assert float((G @ sol.x[0] - h).max()) <= 1e-8


def test_non_convex_p_is_flagged(backend: str) -> None:
    box = dict(lb=-torch.ones(2, dtype=DT), ub=torch.ones(2, dtype=DT))
    assert solve_qp(-torch.eye(2, dtype=DT), t(0.1, 0.0), **box, backend=backend).status.tolist() == [S.NON_CONVEX]
    assert solve_qp(torch.diag(t(1.0, -1e-3)), t(0.0, 0.0), **box, backend=backend).status.tolist() == [S.NON_CONVEX]
    # Rounding of a PSD product is not non-convexity.
    v = t(5.4, -1.2, -1e-2, 1e4)
    assert solve_qp(torch.outer(v, v), v.clone(), backend=backend).status.tolist() == [S.SOLVED]


@pytest.mark.parametrize("case", ["lb=+inf", "ub=-inf", "h=-inf", "lb=1e20", "lb>ub"])
def test_wrong_sign_infinities_are_infeasible(case: str, backend: str) -> None:
    inf = float("inf")
    kw = {"lb=+inf": dict(lb=t(inf, 0.0)), "ub=-inf": dict(ub=t(-inf, 0.0)), "h=-inf": dict(G=t([1.0, 1.0]), h=t(-inf)),
          "lb=1e20": dict(lb=t(1e20, 0.0)), "lb>ub": dict(lb=t(1.0, 0.0), ub=t(0.0, 1.0))}[case]
    assert solve_qp(torch.eye(2, dtype=DT), t(0.0, 0.0), **kw, backend=backend).status.tolist() == [S.PRIMAL_INFEASIBLE]


def test_invalid_input_per_instance_leaves_the_rest_of_the_batch_alone(backend: str) -> None:
    qp = random_qp_batch(8, n=4, m=6, p=1, bounds=True, spread=0.3, seed=21)
    ref = solve_qp(*qp.args(), backend=backend)
    assert bool(ref.solved.all())
    P, q, A, b, G, h, lb, ub = (x.clone() for x in qp.args())
    nan, inf = float("nan"), float("inf")
    G[0, 1, 2] = nan
    h[1, 0] = nan
    P[2, 0, 0] = inf
    q[3, 1] = nan
    A[4, 0, 0] = inf
    lb[5, 3] = nan
    ub[6, 0] = nan
    sol = solve_qp(P, q, A, b, G, h, lb, ub, backend=backend)
    assert sol.status.tolist() == [S.INVALID_INPUT] * 7 + [S.SOLVED]
    # (the C route is exact per instance; batched torch ops may round a neighbour differently)
    assert (sol.x[7] - ref.x[7]).abs().max() <= (0.0 if backend == "c" else 1e-9)
    assert (sol.x[:7] == 0).all() and torch.isfinite(sol.z).all()


def test_infeasible_and_unbounded_instances_beside_solved_ones(backend: str) -> None:
    qp = random_qp_batch(6, n=3, m=4, spread=0.2, seed=5)
    P, q, G, h = (x.clone() for x in (qp.P, qp.q, qp.G, qp.h))
    G[1, 0], G[1, 1], h[1, :2] = t(1.0, 0.0, 0.0), t(-1.0, 0.0, 0.0), -1.0  # x0 ≤ −1 and x0 ≥ 1
    P[2] = torch.diag(t(1.0, 1.0, 0.0))  # unbounded along x2: every row ignores it
    G[2, :, 2], q[2, 2] = 0.0, -1.0
    sol = solve_qp(P, q, G=G, h=h, backend=backend)
    assert sol.status.tolist() == [S.SOLVED, S.PRIMAL_INFEASIBLE, S.DUAL_INFEASIBLE, S.SOLVED, S.SOLVED, S.SOLVED]
    alone = solve_qp(qp.P[3:], qp.q[3:], G=qp.G[3:], h=qp.h[3:], backend=backend)
    assert (sol.x[3:] - alone.x).abs().max() <= (0.0 if backend == "c" else 1e-9)


def test_float32_meets_its_tolerance_or_says_so(backend: str) -> None:
    # An infeasible problem is flagged in float32 as in float64.
    kw = dict(G=t([1.0, 1.0, 1.0]), h=t(-1.0), lb=torch.zeros(3, dtype=DT))
    for dtype in (DT, torch.float32):
        args = [torch.eye(3, dtype=dtype), torch.zeros(3, dtype=dtype)]
        sol = solve_qp(*args, **{k: v.to(dtype) for k, v in kw.items()}, backend=backend)
        assert sol.status.tolist() == [S.PRIMAL_INFEASIBLE]
    # Least squares with condition ~1e6: SOLVED means the rounded answer meets the KKT tolerance on the
    # rounded data; otherwise TOLERANCE_NOT_MET.
    g = torch.Generator().manual_seed(3)
    for k in range(5):
        W = torch.randn(12, 6, generator=g, dtype=DT) @ torch.diag(torch.logspace(0, 3, 6, dtype=DT))
        P, q = (W.mT @ W).float(), (-W.mT @ torch.randn(12, generator=g, dtype=DT)).float()
        lb, ub = -torch.ones(6), torch.ones(6)
        sol = solve_qp(P, q, lb=lb, ub=ub, backend=backend)
        assert sol.x.dtype == torch.float32 and sol.status.item() in (S.SOLVED, S.TOLERANCE_NOT_MET)
        ref = solve_qp(P.double(), q.double(), lb=lb.double(), ub=ub.double(), backend=backend)
        assert ref.status.item() == S.SOLVED
        # the float32 answer is the float64 answer of the same (rounded) data, rounded
        assert (sol.x.double() - ref.x).abs().max() <= 1e-6 * (1 + ref.x.abs().max())


def test_numpy_inputs_are_converted_and_bad_types_refused(backend: str) -> None:
    qp = random_qp_batch(3, seed=2)
    ref = solve_qp(*qp.args(), backend=backend)
    sol = solve_qp(*(None if a is None else a.numpy() for a in qp.args()), backend=backend)
    assert isinstance(sol.x, torch.Tensor) and torch.equal(sol.x, ref.x)
    sol = solve_qp(qp.P, qp.q.numpy(), G=qp.G.numpy(), h=qp.h, backend=backend)
    assert torch.equal(sol.x, ref.x)
    with pytest.raises(QPShapeError, match="torch.Tensor or a numpy array"):
        solve_qp("P", qp.q)
    with pytest.raises(QPShapeError, match="dtype"):
        solve_qp(qp.P.numpy().astype(np.float32), qp.q.numpy())


def test_backend_argument() -> None:
    qp = random_qp_batch(2, seed=3)
    with pytest.raises(QPBackendError, match="must be one of"):
        solve_qp(qp.P, qp.q, backend="gpu")
    with pytest.raises(QPBackendError, match="numpy"):
        solve_qp(qp.P, qp.q, backend="numpy")
    x_ref, _ = clarabel_reference(qp)
    for b in (["auto", "torch"] + (["c"] if native.load() is not None else [])):
        assert (solve_qp(qp.P, qp.q, G=qp.G, h=qp.h, backend=b).x - x_ref).abs().max() <= 1e-8


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_c_backend_on_cuda_is_refused_and_auto_takes_torch() -> None:
    qp = random_qp_batch(4, seed=4)
    args = [a.cuda() for a in (qp.P, qp.q, qp.G, qp.h)]
    with pytest.raises(QPBackendError, match="CPU"):
        solve_qp(args[0], args[1], G=args[2], h=args[3], backend="c")
    sol = solve_qp(args[0], args[1], G=args[2], h=args[3])
    assert sol.x.is_cuda and bool(sol.solved.all())
    assert (sol.x.cpu() - solve_qp(qp.P, qp.q, G=qp.G, h=qp.h).x).abs().max() <= 1e-8
