"""Tests of the small-batch CPU path of solve_qp (numpy dual active set): same answers, statuses and gradients as the batched path."""

from __future__ import annotations

import pytest
import torch

import a3cqp_rl.qp.solver as solver
from a3cqp_rl.qp import QPStatus, solve_qp
from a3cqp_rl.qp.random_qp import RandomQP, clarabel_reference, random_qp_batch

DT = torch.float64


@pytest.fixture
def batched_only(monkeypatch):
    """Context in which every batch takes the batched torch path (the reference for the small path)."""

    limits = (solver.SMALL_BATCH_MAX, solver.SMALL_BATCH_MAX_WARM)

    def use(flag: bool) -> None:
        monkeypatch.setattr(solver, "SMALL_BATCH_MAX", -1 if flag else limits[0])
        monkeypatch.setattr(solver, "SMALL_BATCH_MAX_WARM", -1 if flag else limits[1])

    return use


def test_dispatch_is_by_batch_size_and_device() -> None:
    q = torch.zeros(solver.SMALL_BATCH_MAX, 3, dtype=DT)
    assert solver._use_small_path(q) and solver._use_small_path(q[:1])
    assert not solver._use_small_path(torch.zeros(solver.SMALL_BATCH_MAX + 1, 3, dtype=DT))
    assert not solver._use_small_path(q, solver.SMALL_BATCH_MAX_WARM) and solver.SMALL_BATCH_MAX_WARM < solver.SMALL_BATCH_MAX


# Easy (default spread) and heavily constrained families, with equalities and bounds.
FAMILIES = [
    dict(m=30),
    dict(m=30, p=3, bounds=True),
    dict(m=30, spread=0.35),
    dict(m=40, p=3, bounds=True, spread=0.35),
    dict(n=20, m=50, p=4, spread=0.5),
]


@pytest.mark.parametrize("family", range(len(FAMILIES)))
def test_small_batches_match_clarabel_and_the_batched_path(family: int, batched_only) -> None:
    qp = random_qp_batch(16, seed=200 + family, **FAMILIES[family])
    sol = solve_qp(*qp.args())
    x_ref, statuses = clarabel_reference(qp)
    assert set(statuses) == {"optimal"}
    assert bool(sol.solved.all())
    assert (sol.x - x_ref).abs().max().item() <= 1e-6
    # Dual feasibility and complementarity of the returned multipliers.
    assert (sol.z >= 0).all() and (sol.z_lb >= 0).all() and (sol.z_ub >= 0).all()
    slack = qp.h - (qp.G @ sol.x.unsqueeze(-1)).squeeze(-1)
    assert (sol.z * slack).abs().max() < 1e-8 and slack.min() > -1e-8
    batched_only(True)
    ref = solve_qp(*qp.args())
    assert (sol.x - ref.x).abs().max() < 1e-8 and (sol.z - ref.z).abs().max() < 1e-7


def test_warm_start_solves_the_next_control_step_in_about_one_kkt_solve() -> None:
    qp = random_qp_batch(solver.SMALL_BATCH_MAX_WARM, spread=0.3, seed=3)
    first = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    assert (first.z > 0).any(-1).all()  # every instance has active rows, so warm-starting matters
    q2 = qp.q + 1e-4 * torch.randn(qp.q.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    warm = solve_qp(qp.P, q2, G=qp.G, h=qp.h, warm_start=first)
    cold = solve_qp(qp.P, q2, G=qp.G, h=qp.h)
    assert bool(warm.solved.all())
    # Mostly one solve; an instance whose active set changes pays one more per changed row.
    assert warm.iterations.float().mean() <= 1.25 and (warm.iterations <= cold.iterations).all()
    assert (warm.x - cold.x).abs().max() < 1e-9


def test_gradients_match_the_batched_path(batched_only) -> None:
    qp = random_qp_batch(6, n=8, m=12, p=1, bounds=True, spread=0.1, seed=21)
    w = torch.randn(6, 8, generator=torch.Generator().manual_seed(3), dtype=DT)

    def grads():
        leaves = [t.clone().requires_grad_() for t in qp.args()]
        sol = solve_qp(*leaves)
        (sol.x * w).sum().backward()
        return sol, [t.grad for t in leaves]

    sol, g_small = grads()
    assert ((sol.z > 0).any(-1) | (sol.z_lb > 0).any(-1) | (sol.z_ub > 0).any(-1)).any()
    batched_only(True)
    _, g_ref = grads()
    for a, b in zip(g_small, g_ref):
        assert (a - b).abs().max() < 1e-7


def test_degenerate_instances_fall_back_and_stay_exact(batched_only) -> None:
    # Duplicated rows (dependent active constraints): the dual active set never works with both
    # copies; the warm start from the batched solution's multipliers (both copies positive) is
    # singular and must restart cold.
    qp = random_qp_batch(8, n=6, m=10, p=1, spread=0.2, seed=11)
    G = torch.cat([qp.G, qp.G, torch.zeros_like(qp.G[:, :1])], 1)
    h = torch.cat([qp.h, qp.h, torch.ones_like(qp.h[:, :1])], 1)
    base = solve_qp(qp.P, qp.q, qp.A, qp.b, qp.G, qp.h)
    dup = solve_qp(qp.P, qp.q, qp.A, qp.b, G, h)
    assert bool(dup.solved.all()) and (dup.x - base.x).abs().max() < 1e-8
    batched_only(True)
    dup_ref = solve_qp(qp.P, qp.q, qp.A, qp.b, G, h)
    batched_only(False)
    warm = solve_qp(qp.P, qp.q, qp.A, qp.b, G, h, warm_start=dup_ref)
    assert bool(warm.solved.all()) and (warm.x - base.x).abs().max() < 1e-8
    # Linear program (P = 0: no Cholesky, handed to the batched path) and float32.
    lp = solve_qp(torch.zeros(2, 3, 3, dtype=DT), torch.tensor([[1.0, -2.0, 0.5]] * 2, dtype=DT), lb=-torch.ones(2, 3, dtype=DT), ub=torch.ones(2, 3, dtype=DT))
    assert bool(lp.solved.all()) and torch.allclose(lp.x, torch.tensor([[-1.0, 1.0, -1.0]] * 2, dtype=DT), atol=1e-8)
    qp32 = random_qp_batch(8, p=2, bounds=True, spread=0.35, seed=9)
    sol32 = solve_qp(*[t.float() for t in qp32.args()])
    sol64 = solve_qp(*qp32.args())
    assert sol32.x.dtype == torch.float32 and sol32.z.dtype == torch.float32 and bool(sol32.solved.all())
    assert (sol32.x.double() - sol64.x).abs().max() < 1e-3


def test_infeasible_unbounded_and_nan_instances_get_their_status() -> None:
    qp = random_qp_batch(4, n=5, m=8, spread=0.2, seed=4)
    G, h, q = qp.G.clone(), qp.h.clone(), qp.q.clone()
    G[1, 0], h[1, 0] = torch.eye(5, dtype=DT)[0], -1.0  # x0 ≤ −1 and x0 ≥ 1
    G[1, 1], h[1, 1] = -torch.eye(5, dtype=DT)[0], -1.0
    q[2, 0] = torch.nan
    sol = solve_qp(qp.P, q, G=G, h=h)
    ref = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    assert sol.status[1] == QPStatus.PRIMAL_INFEASIBLE and sol.status[2] != QPStatus.SOLVED
    assert (sol.status[[0, 3]] == QPStatus.SOLVED).all() and (sol.x[[0, 3]] - ref.x[[0, 3]]).abs().max() < 1e-10
    assert torch.isfinite(sol.x).all() and torch.isfinite(sol.z).all()
    # Unbounded: P = diag(1, 0), x1 free with cost −x1 and only bounded below.
    P = torch.diag(torch.tensor([1.0, 0.0], dtype=DT)).expand(2, 2, 2)
    unb = solve_qp(P, torch.tensor([[1.0, 1.0], [1.0, -1.0]], dtype=DT), G=torch.tensor([[0.0, -1.0]], dtype=DT).expand(2, 1, 2), h=torch.zeros(2, 1, dtype=DT))
    assert unb.status.tolist() == [QPStatus.SOLVED, QPStatus.DUAL_INFEASIBLE]


@pytest.mark.parametrize("family", range(len(FAMILIES)))
def test_cold_solves_with_definite_p_stay_on_the_range_space_path(family: int, monkeypatch) -> None:
    # The LU method is only the fallback of the range-space path (P ≻ 0): these families must not need it.
    import a3cqp_rl.qp.small_batch as small

    def fail(*args, **kwargs):
        raise AssertionError("fell back to the LU method")

    monkeypatch.setattr(small, "_dual_active_set", fail)
    qp = random_qp_batch(16, seed=300 + family, **FAMILIES[family])
    sol = solve_qp(*qp.args())
    x_ref, _ = clarabel_reference(qp)
    assert bool(sol.solved.all()) and (sol.x - x_ref).abs().max().item() <= 1e-6
    sol32 = solve_qp(*(t.float() if t is not None else None for t in qp.args()))
    assert bool(sol32.solved.all()) and (sol32.x.double() - x_ref).abs().max().item() <= 1e-4


@pytest.mark.parametrize("spread", [0.015, 0.35])
def test_single_controller_qp_cold_and_warm_take_the_fast_paths_and_match_clarabel(spread: float, monkeypatch) -> None:
    # B = 1 as the controller solves it: cold on the range-space path, warm certified by the
    # one-solve check on the previous working set; neither falls back to the LU method.
    import a3cqp_rl.qp.small_batch as small

    qp = random_qp_batch(1, spread=spread, seed=1001)  # the instance bench/qp.py times at B = 1
    x_ref, _ = clarabel_reference(qp)

    def fail(*args, **kwargs):
        raise AssertionError("fell back to the LU method")

    monkeypatch.setattr(small, "_dual_active_set", fail)
    cold = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    assert bool(cold.solved.all()) and (cold.x - x_ref).abs().max().item() <= 1e-9
    warm = solve_qp(qp.P, qp.q + 1e-6, G=qp.G, h=qp.h, warm_start=cold)
    assert bool(warm.solved.all()) and warm.iterations.tolist() == [1]
    x_ref2, _ = clarabel_reference(RandomQP(qp.P, qp.q + 1e-6, None, None, qp.G, qp.h, None, None, qp.x_feasible))
    assert (warm.x - x_ref2).abs().max().item() <= 1e-9
    # Same answer and multipliers as the batched path; gradients too.
    monkeypatch.undo()
    ref_limits = (solver.SMALL_BATCH_MAX, solver.SMALL_BATCH_MAX_WARM)
    monkeypatch.setattr(solver, "SMALL_BATCH_MAX", -1)
    monkeypatch.setattr(solver, "SMALL_BATCH_MAX_WARM", -1)
    ref = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    assert (cold.x - ref.x).abs().max() < 1e-9 and (cold.z - ref.z).abs().max() < 1e-8
    w = torch.linspace(-1.0, 1.0, qp.q.shape[1], dtype=DT)

    def grads():
        leaves = [t.clone().requires_grad_() for t in (qp.P, qp.q, qp.G, qp.h)]
        (solve_qp(leaves[0], leaves[1], G=leaves[2], h=leaves[3]).x * w).sum().backward()
        return [t.grad for t in leaves]

    g_ref = grads()
    monkeypatch.setattr(solver, "SMALL_BATCH_MAX", ref_limits[0])
    monkeypatch.setattr(solver, "SMALL_BATCH_MAX_WARM", ref_limits[1])
    for a, b in zip(grads(), g_ref):
        assert (a - b).abs().max() < 1e-8


def test_warm_start_whose_working_set_changed_falls_back_and_counts_the_failed_check() -> None:
    qp = random_qp_batch(1, spread=0.35, seed=1001)
    cold = solve_qp(qp.P, qp.q, G=qp.G, h=qp.h)
    q2 = qp.q + 0.3 * torch.randn(qp.q.shape, generator=torch.Generator().manual_seed(1), dtype=DT)
    warm = solve_qp(qp.P, q2, G=qp.G, h=qp.h, warm_start=cold)
    ref = solve_qp(qp.P, q2, G=qp.G, h=qp.h)
    assert bool(warm.solved.all()) and (warm.x - ref.x).abs().max() < 1e-9 and warm.iterations.item() >= 2


def test_infinite_right_hand_sides_on_the_small_path_become_inert_rows() -> None:
    qp = random_qp_batch(1, spread=0.35, seed=5)
    h = qp.h.clone()
    h[0, :10] = torch.inf
    sol = solve_qp(qp.P, qp.q, G=qp.G, h=h)
    sub = solve_qp(qp.P, qp.q, G=qp.G[:, 10:], h=qp.h[:, 10:])
    assert bool(sol.solved.all()) and (sol.x - sub.x).abs().max() < 1e-10 and (sol.z[:, :10] == 0).all()
