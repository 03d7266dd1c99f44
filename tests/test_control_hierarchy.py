"""Strict priority levels (paper 002, eq. 2-4): the QP cascade against references, in the controller, in closed loop."""

from __future__ import annotations

import logging
import math

import cvxpy as cp
import numpy as np
import pytest
import torch

import a3cqp_rl.control.hierarchy as hierarchy_module
from a3cqp_rl.config import ControllerConfig
from a3cqp_rl.control import (A3CQPController, ControllerOptions, Hierarchy, Inequality, Limit, level_from_selector,
                              levels_from_selectors, solve_cascade)
from a3cqp_rl.control.context import ControlContext
from a3cqp_rl.control.controller import SOLVER_ERROR
from a3cqp_rl.control.exceptions import InvalidGainError, InvalidLevelError
from a3cqp_rl.control.tasks import Residual
from a3cqp_rl.robot import PANDA_HOME, PandaSim
from test_control_native import random_inputs

F64 = torch.float64
TASKS = ["ik", "ac", "fc", "jc", "cartesian_regularizer"]
STACKS = {  # eq. 3 stacks over the default tasks (None: off)
    "ik/jc": dict(ik=1, jc=2, ac=None, fc=None, cartesian_regularizer=None),
    "ik/wrench+jc": dict(ik=1, cartesian_regularizer=1, ac=2, fc=2, jc=2),
    "ik/wrench/jc": dict(ik=1, cartesian_regularizer=1, ac=2, fc=2, jc=3),
    "wrench/ik/jc": dict(ac=1, fc=1, ik=2, cartesian_regularizer=2, jc=3),
    "jc/ik": dict(jc=1, ik=2, ac=None, fc=None, cartesian_regularizer=2),
}


def step_x(levels, inputs: dict, n: int, **kw) -> tuple[np.ndarray, A3CQPController, object]:  # noqa: ANN001
    """x = (q̈*, f*) [n, 13] of one step of a fresh controller (q* = q) at `inputs`, the controller and its output."""
    ctrl = A3CQPController(n, model=inputs.get("model"), levels=levels, **kw)
    out = ctrl.step(**{k: v for k, v in inputs.items() if k != "model"})
    return torch.cat([out.qdd, out.wrench], 1).numpy(), ctrl, out


def residual_cost(res: Residual, x: np.ndarray) -> np.ndarray:
    """‖A x_blk − b‖²_W per robot [B]."""
    blk = x[:, res.col:res.col + res.size]
    r = (blk if res.A is None else np.einsum("bkm,bm->bk", np.asarray(res.A), blk)) - np.asarray(res.b)
    return np.einsum("bk,bkl,bl->b", r, np.asarray(res.W), r)


def level_cost(ctrl: A3CQPController, names: tuple[str, ...], x: np.ndarray) -> np.ndarray:
    return sum(residual_cost(ctrl.residuals[name], x) for name in names)


@pytest.fixture(scope="module")
def states() -> dict:
    """48 random controller inputs, a third of them at the joint limits (limit rows bind)."""
    inputs, model = random_inputs(48, seed=11, near_limits=True)
    return dict(inputs, model=model)


# ---------------------------------------------------------------------------------------------- the guarantees
def level_problems(levels, inputs: dict, n: int,  # noqa: ANN001
                   **kw) -> tuple[A3CQPController, list, torch.Tensor, torch.Tensor]:
    """A controller's per-level QPs (P_k, c_k) and limit rows at `inputs` (q* = q), as tensors."""
    ctrl = A3CQPController(n, model=inputs["model"], levels=levels, **kw)
    ctrl.reset(inputs["q"], inputs["qd"])
    ctx = ctrl.build_context(**{k: v for k, v in inputs.items() if k not in ("kin", "bias", "model")},
                             bias=inputs["bias"], kin=inputs["kin"])
    costs, G, h = ctrl.build_levels(ctx)
    t = torch.as_tensor
    return ctrl, [(t(P), t(c)) for P, c in costs], t(G), t(h)


@pytest.mark.parametrize("stack", list(STACKS))
def test_a_lower_level_never_degrades_a_higher_levels_optimum(states: dict, stack: str) -> None:
    """Each level's task cost at the optimum of the stack cut below it = after the lower levels were solved."""
    n = states["q"].shape[0]
    ctrl, costs, G, h = level_problems(STACKS[stack], states, n)
    reg = ctrl.options.regularization
    full = solve_cascade(costs, G, h, reg)
    assert (full.status == 0).all()
    stack_levels = ctrl.hierarchy.levels
    for depth in range(1, len(stack_levels)):
        cut = solve_cascade(costs[:depth], G, h, reg)
        for lvl in stack_levels[:depth]:
            alone, after = level_cost(ctrl, lvl, cut.x.numpy()), level_cost(ctrl, lvl, full.x.numpy())
            worse = (after - alone) / (1.0 + alone)
            assert worse.max() < 1e-7, f"{lvl} degraded by {worse.max():.2e} when {stack_levels[depth:]} were added"
    # the limits hold (to the solver's tolerance, which scales with P: ~5e-8 at the first level already)
    assert ((G @ full.x[..., None])[..., 0] - h).max() < 1e-6
    # the same QPs with soft priorities only (one level: the costs summed) trade the first level's cost away
    soft = solve_cascade([(sum(P for P, _ in costs) - (len(costs) - 1) * reg * torch.eye(13, dtype=F64),
                           sum(c for _, c in costs))], G, h, reg)
    first = stack_levels[0]
    assert (level_cost(ctrl, first, soft.x.numpy()) - level_cost(ctrl, first, full.x.numpy())).max() > 1e-3


def test_the_controller_step_keeps_the_first_levels_optimum(states: dict) -> None:
    """Through `step`: IK's cost with JC below it = IK alone (the wrench feed-forward off: it couples IK's
    reference to the active AC/FC tasks, so IK alone would be a different task)."""
    n = states["q"].shape[0]
    opts = ControllerOptions(ik_wrench_feedforward=False)
    levels = dict(ik=1, cartesian_regularizer=1, ac=2, fc=2, jc=3)
    x_full, ctrl, out = step_x(levels, states, n, options=opts)
    x_ik, ctrl_ik, _ = step_x(dict(levels, ac=None, fc=None, jc=None), states, n, options=opts)
    first = ("ik", "cartesian_regularizer")
    alone, after = level_cost(ctrl_ik, first, x_ik), level_cost(ctrl, first, x_full)
    assert not out.fallback.any() and ((after - alone) / (1.0 + alone)).max() < 1e-7
    assert np.abs(x_full - x_ik).max() > 1.0  # while the lower levels did change x


@pytest.mark.parametrize("stack", ["ik/wrench/jc", "wrench/ik/jc", "jc/ik"])
def test_each_level_is_optimal_given_the_levels_above_against_clarabel(states: dict, stack: str) -> None:
    """Reference: each level by Clarabel (cvxpy) in x, the levels above kept by equality rows H_j x = H_j x*_j."""
    n = 8
    inputs = {k: (v[:n] if isinstance(v, torch.Tensor) else v) for k, v in states.items()}
    inputs["kin"] = type(states["kin"])(**{f: getattr(states["kin"], f)[:n] for f in vars(states["kin"])})
    # the solver's full route: on one of these random states the C route cannot decide the first level, and a
    # controller by default (qp_hand_on=False) brakes there instead of waiting for the torch route
    x_mine, _, out = step_x(STACKS[stack], inputs, n, options=ControllerOptions(qp_hand_on=True))
    assert not out.fallback.any()
    ref, costs, G, h = level_problems(STACKS[stack], inputs, n)
    costs, G, h = [(P.numpy(), c.numpy()) for P, c in costs], G.numpy(), h.numpy()
    r_eye = ref.options.regularization * np.eye(13)
    for b in range(n):
        x = cp.Variable(13)
        constraints = [G[b] @ x <= h[b]]
        for P, c in costs:
            cp.Problem(cp.Minimize(0.5 * cp.quad_form(x, cp.psd_wrap(P[b])) + c[b] @ x), constraints).solve(
                solver="CLARABEL")
            x_ref = x.value.copy()
            H = P[b] - r_eye
            constraints = constraints + [H @ x == H @ x_ref]
        err = np.abs(x_mine[b] - x_ref).max() / (1.0 + np.abs(x_ref).max())
        assert err < 1e-6, f"robot {b}: {err:.2e}"


def test_one_level_is_todays_weighted_qp_on_the_same_path(states: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    n = states["q"].shape[0]
    x_default, ctrl, out_default = step_x(None, states, n)
    assert ctrl.hierarchy.is_flat and str(ctrl.hierarchy) == "(ik + ac + fc + jc + cartesian_regularizer)"
    native_steps = []
    real = A3CQPController._step_native
    monkeypatch.setattr(A3CQPController, "_step_native", lambda self, inp: native_steps.append(1) or real(self, inp))
    for levels in ({name: 1 for name in TASKS}, {name: 3 for name in TASKS}, [2] * 5):
        x, ctrl, out = step_x(levels, states, n)
        assert ctrl.hierarchy.is_flat
        assert np.array_equal(x, x_default) and torch.equal(out.tau, out_default.tau)
    if ctrl._native is not None:  # the C step, as without levels
        assert len(native_steps) == 3
    x_py, _, _ = step_x(None, states, n, options=ControllerOptions(backend="python"))
    x_py1, _, _ = step_x([1] * 5, states, n, options=ControllerOptions(backend="python"))
    assert np.array_equal(x_py, x_py1)
    assert np.abs(x_py - x_default).max() < 1e-9 * (1.0 + np.abs(x_default).max())


def test_deactivated_tasks_have_no_effect(states: dict) -> None:
    n = states["q"].shape[0]
    for levels in (dict(ik=1, ac=1, fc=None, jc=1, cartesian_regularizer=1),  # one level, FC off
                   dict(ik=1, ac=2, fc=None, jc=3, cartesian_regularizer=1)):  # a strict stack, FC off
        x_off, ctrl, out = step_x(levels, states, n)
        assert not out.fallback.any() and "fc" not in ctrl.residuals
        # the controller built without FC at all (same task objects) gives the same x
        without = A3CQPController(n, model=states["model"], tasks=[t for t in ctrl.tasks if t.name != "fc"],
                                  levels={k: v for k, v in levels.items() if k != "fc"})
        out_without = without.step(**{k: v for k, v in states.items() if k != "model"})
        assert np.array_equal(x_off, torch.cat([out_without.qdd, out_without.wrench], 1).numpy())
        # and FC's reference (f_d) no longer matters, while with FC on it does
        other = dict(states, f_d=states["f_d"].flip(0))
        assert np.array_equal(step_x(levels, other, n)[0], x_off)
        assert not np.allclose(step_x({**levels, "fc": 2}, other, n)[0], step_x({**levels, "fc": 2}, states, n)[0])


def test_all_tasks_off_only_regularizes() -> None:
    inputs, model = random_inputs(4, seed=2)
    x, ctrl, out = step_x([None] * 5, dict(inputs, model=model), 4)
    assert ctrl.hierarchy.levels == ((),) and not out.fallback.any()
    assert np.abs(x).max() < 1e-6  # min ‖x‖² within the limits (x = 0 is feasible away from the joint limits)


# ---------------------------------------------------------------------------------------------- solve_cascade
def test_cascade_on_a_small_problem_with_a_known_answer() -> None:
    """x ∈ R²: level 1 x₁ + x₂ = 2 (given twice: dependent rows); level 2 x = (5, 5); limit x₁ ≤ 0 on robot 1."""
    r = 1e-9

    def cost(rows: list[tuple[list[float], float]]) -> tuple[torch.Tensor, torch.Tensor]:
        A = torch.tensor([a for a, _ in rows], dtype=F64)
        b = torch.tensor([v for _, v in rows], dtype=F64)
        P = A.T @ A + r * torch.eye(2, dtype=F64)
        return P.expand(2, 2, 2).clone(), (-A.T @ b).expand(2, 2).clone()

    level1 = cost([([1.0, 1.0], 2.0), ([1.0, 1.0], 2.0)])
    level2 = cost([([1.0, 0.0], 5.0), ([0.0, 1.0], 5.0)])
    G = torch.tensor([[[1.0, 0.0]], [[1.0, 0.0]]], dtype=F64)
    h = torch.tensor([[10.0], [0.0]], dtype=F64)
    sol = solve_cascade([level1, level2], G, h, r)
    assert sol.status.tolist() == [0, 0] and len(sol.solutions) == 2
    assert torch.allclose(sol.x, torch.tensor([[1.0, 1.0], [0.0, 2.0]], dtype=F64), atol=1e-6)
    # the reverse order: x = (5, 5) first, the sum then has nothing left to move
    rev = solve_cascade([level2, level1], G, h, r)
    assert torch.allclose(rev.x, torch.tensor([[5.0, 5.0], [0.0, 5.0]], dtype=F64), atol=1e-6)
    # one level is solve_qp itself
    from a3cqp_rl.qp import solve_qp
    assert torch.equal(solve_cascade([level1], G, h, r).x, solve_qp(*level1, G=G, h=h).x)


def test_a_lower_level_the_warm_solver_fails_on_is_solved_again_cold(states: dict,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """(The warm-started batched solver once hit MAX_ITER on a level-3 QP that it certifies cold in 5 iterations.)"""
    from a3cqp_rl.qp import QPStatus, solve_qp

    ctrl, costs, G, h = level_problems(STACKS["ik/wrench/jc"], states, 48)
    reg = ctrl.options.regularization
    first = solve_cascade(costs, G, h, reg)
    expected = solve_cascade(costs, G, h, reg, warm=first.solutions)
    calls = []

    def flaky(P, q, **kw):  # noqa: ANN001, ANN003, ANN202
        sol = solve_qp(P, q, **kw)
        calls.append(kw.get("warm_start") is not None)
        if kw.get("warm_start") is not None and len(calls) > 1:  # a warm lower level: instance 5 "fails"
            sol.status[5], sol.x[5] = QPStatus.MAX_ITER, 1e3
        return sol

    monkeypatch.setattr(hierarchy_module, "solve_qp", flaky)
    got = solve_cascade(costs, G, h, reg, warm=first.solutions)
    assert calls == [True, True, False, True, False]  # levels 2 and 3 each retried cold
    assert (got.status == 0).all()
    assert torch.allclose(got.x, expected.x, atol=1e-7 * (1 + expected.x.abs().max().item()))


def test_an_infeasible_first_level_falls_back_for_that_robot(caplog: pytest.LogCaptureFixture) -> None:
    class Contradiction(Limit):
        """x₀ ≤ −1 and x₀ ≥ 1 for robot 1: an infeasible QP."""

        name = "contradiction"

        def rows(self, ctx: ControlContext) -> Inequality:
            G = ctx.q.new_zeros(ctx.batch, 2, 13)
            G[:, 0, 0], G[:, 1, 0] = 1.0, -1.0
            h = ctx.q.new_full((ctx.batch, 2), 100.0)
            h[1] = -1.0
            return Inequality(G=G, h=h)

    inputs, model = random_inputs(3, seed=4)
    ctrl = A3CQPController(3, model=model, levels=STACKS["ik/wrench/jc"], extra_limits=[Contradiction()])
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.control.controller"):
        out = ctrl.step(**inputs)
    assert out.fallback.tolist() == [False, True, False] and out.status[1] != 0 and "robots [1]" in caplog.text
    assert torch.isfinite(out.tau).all() and out.wrench[1].abs().max() == 0.0


def test_a_raising_solver_in_the_cascade_falls_back_for_all(monkeypatch: pytest.MonkeyPatch,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    inputs, model = random_inputs(2, seed=4)
    ctrl = A3CQPController(2, model=model, levels=STACKS["ik/jc"])

    def broken(*a, **kw):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("solver bug")

    monkeypatch.setattr(hierarchy_module, "solve_qp", broken)
    with caplog.at_level(logging.ERROR, logger="a3cqp_rl.control.controller"):
        out = ctrl.step(**inputs)
    assert out.status.tolist() == [SOLVER_ERROR] * 2 and out.fallback.all() and "solve_qp raised" in caplog.text


# ---------------------------------------------------------------------------------------------- API
@pytest.mark.parametrize("selector, level", [(0.0, 1), (0.25, 1), (0.2500001, 2), (0.5, 2), (0.50001, 3),
                                             (0.75, 3), (0.7500001, None), (1.0, None), (np.float32(0.3), 2)])
def test_level_selector_is_eq_4(selector: float, level: int | None) -> None:
    assert level_from_selector(selector) == level


@pytest.mark.parametrize("bad", [-0.01, 1.01, math.nan, math.inf, "0.3", True, None])
def test_level_selector_outside_0_1_is_refused(bad: object) -> None:
    with pytest.raises(InvalidLevelError, match=r"level selector must be a number in \[0, 1\]"):
        level_from_selector(bad)  # type: ignore[arg-type]


def test_levels_from_selectors_feeds_the_controller() -> None:
    levels = levels_from_selectors(dict(ik=0.1, ac=0.4, fc=0.6, jc=0.9, cartesian_regularizer=0.2))
    assert levels == dict(ik=1, ac=2, fc=3, jc=None, cartesian_regularizer=1)
    assert str(Hierarchy.of(TASKS, levels)) == "(ik + cartesian_regularizer) / (ac) / (fc); off: jc"
    assert Hierarchy.of(TASKS, [np.int64(2), 1, None, 3, 1]).levels == (("ac", "cartesian_regularizer"), ("ik",),
                                                                         ("jc",))
    with pytest.raises(InvalidLevelError, match="task 'jc'"):
        levels_from_selectors(dict(ik=0.1, jc=1.5))


@pytest.mark.parametrize("levels, message", [
    (dict(ik=1, ac=1, fc=1, jc=1), r"missing \['cartesian_regularizer'\]"),
    (dict(ik=1, ac=1, fc=1, jc=1, cartesian_regularizer=1, posture=2), r"unknown \['posture'\]"),
    (dict(ik=0, ac=1, fc=1, jc=1, cartesian_regularizer=1), "task 'ik': level must be an integer 1-3 or None"),
    (dict(ik=1, ac=4, fc=1, jc=1, cartesian_regularizer=1), "task 'ac': level must be an integer 1-3"),
    (dict(ik=1, ac=1, fc=1.5, jc=1, cartesian_regularizer=1), "task 'fc': .* got 1.5"),
    (dict(ik=1, ac=1, fc=1, jc=True, cartesian_regularizer=1), "task 'jc': .* got True"),
    (dict(ik=1, ac=1, fc=1, jc="2", cartesian_regularizer=1), "task 'jc': .* got '2'"),
    ([1, 2, 3], "levels has 3 entries for 5 tasks"),
    ("ik", "levels must be a mapping"),
])
def test_bad_levels_are_refused_with_a_clear_message(levels: object, message: str) -> None:
    with pytest.raises(InvalidLevelError, match=message):
        A3CQPController(1, levels=levels)  # type: ignore[arg-type]


def test_native_backend_refuses_a_strict_stack_and_auto_never_takes_it(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(InvalidGainError, match="backend='native' translates one level"):
        A3CQPController(1, options=ControllerOptions(backend="native"), levels=STACKS["ik/jc"])
    inputs, model = random_inputs(2, seed=6)
    ctrl = A3CQPController(2, model=model, levels=STACKS["ik/wrench/jc"])
    taken = []
    monkeypatch.setattr(ctrl, "_step_native", lambda inp: taken.append(1))
    assert not ctrl.step(**inputs).fallback.any() and taken == []
    ctrl.set_levels(dict(ik=1, ac=1, fc=None, jc=1, cartesian_regularizer=1))  # one level, but not the default one
    ctrl.step(**inputs)
    assert taken == []
    ctrl.set_levels(None)
    ctrl.step(**inputs)
    assert taken == ([1] if ctrl._native is not None else [])


# ---------------------------------------------------------------------------------------------- closed loop
def swivelled(model, steps: int = 60, step: float = 0.01) -> torch.Tensor:  # noqa: ANN001
    """The ready pose moved 0.6 rad along the arm's null space (same site pose): an elbow for JC to bring back."""
    q = torch.tensor([PANDA_HOME], dtype=F64)
    direction = None
    for _ in range(steps):
        J = model.jacobian(q)[0]
        v = torch.linalg.eigh(torch.eye(7, dtype=F64) - torch.linalg.pinv(J) @ J).eigenvectors[:, -1]
        direction = v if direction is None else (v if torch.dot(v, direction) > 0 else -v)
        q = q + step * direction
    return q


def closed_loop(levels: dict, steps: int = 1000) -> tuple[np.ndarray, np.ndarray, int]:
    """IK weights on all six axes, the site target moved 10 cm along x in 0.5 s, JC as strong as IK (ε = 1)."""
    ctrl = A3CQPController(1, levels=levels, config=ControllerConfig(epsilon=1.0))
    q0 = swivelled(ctrl.model)
    pos0, rot0 = ctrl.model.fk(q0)
    sim = PandaSim(1, q0=tuple(q0[0].tolist()))
    weights = torch.zeros(1, 6, 3, dtype=F64)
    weights[..., 0] = 1.0
    s = sim.observe()
    err, q = [], []
    for k in range(steps):
        pos_d = pos0 + torch.tensor([[0.1 * min(1.0, k / 500), 0.0, 0.0]], dtype=F64)
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, weights, torch.zeros(1, 6, dtype=F64), pos_d, rot0, kin=s.kin)
        sim.step(out.tau)
        s = sim.observe()
        err.append(out.pose_error[0].numpy().copy())
        q.append(s.q[0].numpy().copy())
    return np.array(err), np.array(q), ctrl.fallback_count


def test_ik_above_jc_tracks_as_ik_alone_while_jc_acts_in_the_null_space() -> None:
    off = dict(ac=None, fc=None, cartesian_regularizer=None)
    err_ik, q_ik, fb_ik = closed_loop(dict(ik=1, jc=None, **off))
    err_h, q_h, fb_h = closed_loop(dict(ik=1, jc=2, **off))
    err_w, _, _ = closed_loop(dict(ik=1, jc=1, **off))  # the same two tasks with soft priorities
    assert fb_ik == fb_h == 0
    pos = {name: np.linalg.norm(e[:, :3], axis=1).max() for name, e in (("ik", err_ik), ("h", err_h), ("w", err_w))}
    rot = {name: np.linalg.norm(e[:, 3:], axis=1).max() for name, e in (("ik", err_ik), ("h", err_h), ("w", err_w))}
    print(f"max position error [m]: IK alone {pos['ik']:.2e}, IK / JC {pos['h']:.2e}, IK + JC {pos['w']:.2e}; "
          f"rotation [rad]: {rot['ik']:.2e}, {rot['h']:.2e}, {rot['w']:.2e}")
    assert pos["h"] < 1.02 * pos["ik"] and rot["h"] < 5e-3  # IK keeps its accuracy ...
    assert pos["w"] > 1.15 * pos["ik"] and rot["w"] > 2.0 * rot["h"]  # ... which the weighted QP gives away
    home = np.array(PANDA_HOME)
    dist_ik, dist_h = np.linalg.norm(q_ik[-1] - home), np.linalg.norm(q_h[-1] - home)
    assert dist_h < 0.7 * dist_ik  # JC brought the elbow back toward the ready pose in IK's null space


def test_a_three_level_stack_under_random_switching_weights_stays_within_the_limits() -> None:
    """4 arms, 1.5 s of weights and desired forces switching every 5-50 ms (as test_control_behaviour does for the
    weighted QP): the cascade never falls back and the joints stay inside their position and velocity limits."""
    from a3cqp_rl.robot import PANDA_LIMITS

    n, gen = 4, torch.Generator().manual_seed(7)
    sim = PandaSim(n)
    ctrl = A3CQPController(n, levels=STACKS["ik/wrench/jc"])
    pos0, rot0 = ctrl.model.fk(torch.tensor([PANDA_HOME] * n, dtype=F64))
    pos_d = pos0 + 0.3 * (torch.rand(n, 3, generator=gen, dtype=F64) - 0.5)
    w, f_d = torch.full((n, 6, 3), 1.0 / 3.0, dtype=F64), torch.zeros(n, 6, dtype=F64)
    switch_at = torch.zeros(n, dtype=torch.long)
    s = sim.observe()
    q_log, qd_log = [], []
    for k in range(1500):
        switch = switch_at <= k
        if bool(switch.any()):
            m = int(switch.sum())
            w[switch] = torch.softmax(6.0 * (torch.rand(m, 6, 3, generator=gen, dtype=F64) - 0.5), dim=-1)
            f_d[switch] = 20.0 * torch.rand(m, 6, generator=gen, dtype=F64)
            switch_at[switch] = k + torch.randint(5, 50, (m,), generator=gen)
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot0, f_env=s.f_env, kin=s.kin)
        assert torch.isfinite(out.tau).all()
        sim.step(out.tau)
        s = sim.observe()
        q_log.append(s.q.numpy().copy())
        qd_log.append(s.qd.numpy().copy())
    q, qd = np.array(q_log), np.array(qd_log)
    assert ctrl.fallback_count == 0
    assert (q >= np.array(PANDA_LIMITS.q_min)).all() and (q <= np.array(PANDA_LIMITS.q_max)).all()
    assert (np.abs(qd) <= np.array(PANDA_LIMITS.dq_max)).all() and np.abs(qd).max() > 0.3  # and the arms moved


def test_a_regularizer_in_a_level_of_its_own_stays_convex_with_ik_weights_above_one(states: dict) -> None:
    """A fixed controller's IK weight plus FC's idle share can pass 1 (PandaEnv.controller_weights); the regularizer's
    γ(I − W1) was then negative and a Pareto genome's stack (ik + ac + fc) / (regularizer) / (jc) NON_CONVEX at
    every step. It weighs the axes IK leaves, D(I − min(w1, 1))Dᵀ."""
    inputs = dict(states)
    w = inputs["weights"].clone()
    w[:, :, 0] = 1.0 + 0.4 * torch.rand(w.shape[:2], generator=torch.Generator().manual_seed(2), dtype=F64)
    inputs["weights"] = w
    stack = dict(ik=1, ac=1, fc=1, cartesian_regularizer=2, jc=3)
    ctrl, costs, G, h = level_problems(stack, inputs, 48)
    for k, (P, _) in enumerate(costs):
        assert torch.linalg.eigvalsh(0.5 * (P + P.mT)).min() > 0.0, f"level {k + 1} is not convex"
    _, ctrl, out = step_x(stack, {k: v for k, v in inputs.items() if k not in ("kin",)}, 48)
    assert (out.status == 0).all() and ctrl.fallback_count == 0
    # at w1 ≤ 1 nothing changed: the regularizer's weight is γ(I − W1) there
    ref = dict(states)
    _, costs_ref, _, _ = level_problems(stack, ref, 48)
    ctx = ctrl.build_context(**{k: v for k, v in ref.items() if k not in ("kin", "bias", "model")},
                             bias=ref["bias"], kin=ref["kin"])
    res = ctrl.task_residuals(ctx)["cartesian_regularizer"]
    gamma = ctrl.options.cartesian_regularization
    assert torch.equal(torch.as_tensor(res.W), gamma * torch.eye(6, dtype=F64) - gamma * ctx.W1)
