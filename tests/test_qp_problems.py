"""Other projects' QP test problems and the failure families (a3cqp_rl.qp.problems) on every route.

Each problem is solved alone (B = 1) and inside a batch [problem, well-posed companion, problem], on the
C route and the torch route, and checked against cvxpy + Clarabel: the same status, and where solved the
same optimal value with every constraint satisfied; the companion is solved as if alone.  Problems tagged
float32 are also solved in float32, where TOLERANCE_NOT_MET is an acceptable (honest) answer.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from a3cqp_rl.qp import QPStatus, native, solve_qp
from a3cqp_rl.qp.problems import (RANDOM_FAMILIES, QPProblem, companion, max_violation, objective, peer_problems,
                                  random_problem, reference)

PROBLEMS = {p.name: p for p in peer_problems()}
BACKENDS = ["c", "torch"]


@functools.lru_cache(maxsize=None)
def _reference(name: str):  # noqa: ANN202
    p = PROBLEMS[name] if name in PROBLEMS else companion(PROBLEMS[name.removeprefix("companion of ")])
    return reference(p)


def _tensors(args: tuple, dtype: torch.dtype) -> list[torch.Tensor | None]:
    return [None if a is None else torch.as_tensor(np.asarray(a), dtype=dtype) for a in args]


def _stack(ps: list[QPProblem]) -> list[np.ndarray | None]:
    out = []
    for k in range(8):
        vals = [p.args()[k] for p in ps]
        out.append(None if vals[0] is None else np.stack(vals))
    return out


def _check(p: QPProblem, ref_name: str, status: int, x: np.ndarray, low_precision: bool) -> None:
    st_ref, _, f_ref = _reference(ref_name)
    if low_precision and status == QPStatus.TOLERANCE_NOT_MET:
        return
    assert status == st_ref, f"{p.name}: {QPStatus(status).name}, expected {st_ref.name}"
    if status == QPStatus.SOLVED:
        f, viol = objective(p, x), max_violation(p, x)
        tol = 1e-4 if low_precision else 1e-6
        assert abs(f - f_ref) <= tol * (1.0 + abs(f_ref)), f"{p.name}: objective {f} vs {f_ref}"
        assert viol <= tol, f"{p.name}: violation {viol}"
    else:
        assert np.isfinite(x).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", list(PROBLEMS))
def test_peer_problem_alone_and_in_a_mixed_batch(name: str, backend: str) -> None:
    if backend == "c" and native.load() is None:
        pytest.skip("no C routine")
    p = PROBLEMS[name]
    for dtype in [torch.float64] + ([torch.float32] if "float32" in p.tags else []):
        low = dtype != torch.float64
        sol = solve_qp(*_tensors(p.args(), dtype), backend=backend)
        assert sol.x.dtype == dtype and sol.status.shape == (1,)
        _check(p, name, int(sol.status[0]), sol.x[0].double().numpy(), low)
        c = companion(p)
        batch = solve_qp(*_tensors(_stack([p, c, p]), dtype), backend=backend)
        st = batch.status.tolist()
        _check(p, name, st[0], batch.x[0].double().numpy(), low)
        _check(c, c.name, st[1], batch.x[1].double().numpy(), low)
        _check(p, name, st[2], batch.x[2].double().numpy(), low)  # (x itself may differ on an optimal face)
        assert st[0] == int(sol.status[0]) or low


def test_the_suite_covers_every_family_and_status() -> None:
    families = {p.family for p in PROBLEMS.values()}
    assert {"LP", "singular P", "degenerate", "equality-heavy", "infeasible", "unbounded", "ill-scaled",
            "non-convex", "invalid", "wrong-sign infinity", "published"} <= families
    statuses = {_reference(name)[0] for name in PROBLEMS}
    assert {QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE, QPStatus.DUAL_INFEASIBLE, QPStatus.NON_CONVEX,
            QPStatus.INVALID_INPUT} <= statuses
    assert len([p for p in PROBLEMS.values() if p.source]) >= 30  # published problems, rebuilt


@pytest.mark.parametrize("family", RANDOM_FAMILIES)
def test_random_members_of_each_family(family: str) -> None:
    # Seeds no other test or tuning used; `bench/qp.py --check --sweep 30` runs 30 per family.
    rng = np.random.default_rng(777)
    for _ in range(4):
        p = random_problem(family, rng)
        st_ref, _, f_ref = reference(p)
        for backend in BACKENDS:
            if backend == "c" and native.load() is None:
                continue
            sol = solve_qp(*_tensors(p.args(), torch.float64), backend=backend)
            status, x = int(sol.status[0]), sol.x[0].numpy()
            assert status != QPStatus.SOLVED or st_ref == QPStatus.SOLVED, f"{family} [{backend}]: SOLVED, reference {st_ref.name}"
            if status == QPStatus.SOLVED:
                assert abs(objective(p, x) - f_ref) <= 1e-6 * (1 + abs(f_ref)) and max_violation(p, x) <= 1e-6
            elif family == "infeasible":  # an LP can also have a recession direction: infeasible is the answer
                assert status == QPStatus.PRIMAL_INFEASIBLE
            else:
                assert status == st_ref or status == QPStatus.TOLERANCE_NOT_MET, f"{family} [{backend}]: {QPStatus(status).name}"
