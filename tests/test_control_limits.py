"""Limits (Del Prete viability bounds, wrench box, friction pyramid) and the stacked QP against cvxpy + Clarabel."""

from __future__ import annotations

import dataclasses
import math
import types

import cvxpy as cp
import numpy as np
import pytest
import torch

from a3cqp_rl.control import FrictionPyramid, JointLimitsViability, TorqueLimits, WrenchBox, joint_acceleration_bounds
from a3cqp_rl.control.controller import ControllerOptions
from a3cqp_rl.control.exceptions import InvalidGainError
from a3cqp_rl.qp import solve_qp
from a3cqp_rl.robot import PANDA_LIMITS
from test_control_tasks import B, make_context, mv


def reference_bounds(q, dq, q_min, q_max, dq_max, ddq_max, dt):  # noqa: ANN001, ANN201
    """Scalar Del Prete (2017) acceleration bounds, written branch by branch from the paper's algorithm."""
    def from_pos():
        ub_q3 = 2.0 / dt**2 * (q_max - q - dt * dq)
        lb_q3 = 2.0 / dt**2 * (q_min - q - dt * dq)
        stop = -dq / dt
        if dq <= 0.0:
            ub = ub_q3
            if lb_q3 < stop:
                lb = lb_q3
            elif q != q_min:
                lb = max(dq**2 / (2.0 * (q - q_min)), stop)
            else:
                lb = stop
        else:
            lb = lb_q3
            if ub_q3 > stop:
                ub = ub_q3
            elif q != q_max:
                ub = min(-dq**2 / (2.0 * (q_max - q)), stop)
            else:
                ub = stop
        return lb, ub

    def from_viability():
        a, stop = 2.0 * dt**2, -dq / dt
        b = 2 * dt * dq + ddq_max * dt**2
        c = dq**2 - 2 * ddq_max * (q_max - q - dt * dq)
        d = b**2 - 2 * a * c
        ub = (-b + math.sqrt(d)) / a if d >= 0 else stop
        b = 2 * dt * dq - ddq_max * dt**2
        c = dq**2 - 2 * ddq_max * (q + dt * dq - q_min)
        d = b**2 - 2 * a * c
        lb = (-b - math.sqrt(d)) / a if d >= 0 else stop
        return min(lb, stop), max(ub, stop)

    bounds = [from_pos(), ((-dq_max - dq) / dt, (dq_max - dq) / dt), from_viability()]
    for keep in (3, 2, 1):  # on conflict drop viability, then velocity bounds
        lb, ub = max(b[0] for b in bounds[:keep]), min(b[1] for b in bounds[:keep])
        if ub >= lb:
            break
    # then saturate into the acceleration limits, which always hold
    return min(max(lb, -ddq_max), ddq_max), min(max(ub, -ddq_max), ddq_max)


def test_viability_bounds_match_scalar_reference() -> None:
    gen = torch.Generator().manual_seed(10)
    n = 2000
    q = -1.2 + 2.4 * torch.rand(n, generator=gen, dtype=torch.float64)  # some states outside [-1, 1]
    dq = 3.0 * torch.randn(n, generator=gen, dtype=torch.float64)
    q_min, q_max, dq_max, ddq_max, dt = -1.0, 1.0, 2.0, 10.0, 0.002
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    lb, ub = joint_acceleration_bounds(q, dq, t(q_min), t(q_max), t(dq_max), t(ddq_max), dt)
    ref = torch.tensor([reference_bounds(a, b, q_min, q_max, dq_max, ddq_max, dt) for a, b in zip(q.tolist(),
                                                                                              dq.tolist())], dtype=torch.float64)
    assert torch.allclose(lb, ref[:, 0].double(), rtol=1e-9, atol=1e-6)
    assert torch.allclose(ub, ref[:, 1].double(), rtol=1e-9, atol=1e-6)
    assert bool((ub >= lb).all())


def test_viable_accelerations_keep_joints_inside_limits() -> None:
    """Any acceleration inside the bounds, applied for 3 s, keeps position and velocity within limits."""
    gen = torch.Generator().manual_seed(11)
    n, dt = 4096, 0.001
    q_min, q_max = torch.tensor(-1.0, dtype=torch.float64), torch.tensor(0.5, dtype=torch.float64)
    dq_max, ddq_max = torch.tensor(2.0, dtype=torch.float64), torch.tensor(8.0, dtype=torch.float64)
    q = q_min + (q_max - q_min) * torch.rand(n, generator=gen, dtype=torch.float64)
    dq = torch.zeros(n, dtype=torch.float64)
    worst_q, worst_dq = 0.0, 0.0
    for k in range(3000):
        lb, ub = joint_acceleration_bounds(q, dq, q_min, q_max, dq_max, ddq_max, dt)
        pick = torch.rand(n, generator=gen, dtype=torch.float64)
        pick = torch.where(torch.rand(n, generator=gen) < 0.5, pick.round(), pick)  # often bang-bang
        ddq = lb + (ub - lb) * pick
        q, dq = q + dt * dq + 0.5 * dt * dt * ddq, dq + dt * ddq
        worst_q = max(worst_q, float((q - q_max).max()), float((q_min - q).max()))
        worst_dq = max(worst_dq, float((dq.abs() - dq_max).max()))
    assert worst_q <= 1e-9 and worst_dq <= 1e-9
    assert float(dq.abs().max()) > 0.5  # the joints really moved


def _brake_toward_q_min(stop_share: float, realised: float) -> float:
    """Every joint from its speed limit toward q_min, 0.6 rad away, each 1 ms step at the bound's lb (the hardest a
    task may push toward the limit) of which only `realised` is delivered where lb brakes; the lowest q − q_min [rad]
    (q_min tightened by q_margin) over 1.5 s, integrated as MuJoCo does (semi-implicit Euler)."""
    lim = PANDA_LIMITS.tensors()
    viability = JointLimitsViability(lim["q_min"], lim["q_max"], lim["dq_max"], lim["ddq_max"], 1e-3,
                                     tau_max=lim["tau_max"], stop_share=stop_share)
    q_min, dq_max = viability.q_min.numpy(), viability.dq_max.numpy()  # (tightened by the margins)
    q, qd, dt, low = (q_min + 0.6)[None], -dq_max[None], 1e-3, np.inf
    mass, bias = 0.5 * np.eye(7)[None], np.zeros((1, 7))  # (light links: the torque never limits the brake here)
    for _ in range(1500):
        ctx = types.SimpleNamespace(q=q, qd=qd, mass=mass, bias=bias, xp=np, cache={})
        lb, _ = viability.bounds_for(ctx)
        qd = qd + dt * np.where(lb > 0.0, realised * lb, lb)
        q = q + dt * qd
        low = min(low, float((q - q_min).min()))
    return low


def test_the_viability_bound_keeps_headroom_for_a_brake_the_joint_does_not_fully_deliver() -> None:
    """MuJoCo's joint damping, absent from h + g, cut joint 2's braking by 4 % at 2.1 rad/s. Counting on all of
    ddq_max to stop (stop_share 1), that shortfall overruns the tightened limit by more than the 10 mrad q_margin;
    with the default 0.9 a shortfall of 4 % or 10 % stays inside it."""
    assert _brake_toward_q_min(1.0, 1.0) > -1e-12  # a brake delivered in full stops in time either way
    assert _brake_toward_q_min(1.0, 0.96) < -0.010
    assert _brake_toward_q_min(0.9, 0.96) > -1e-12 and _brake_toward_q_min(0.9, 0.90) > -1e-12
    assert ControllerOptions().viability_stop_share == 0.9
    lim = PANDA_LIMITS.tensors()
    with pytest.raises(InvalidGainError, match="stop_share"):
        JointLimitsViability(lim["q_min"], lim["q_max"], lim["dq_max"], lim["ddq_max"], 1e-3, stop_share=1.2)


def test_joint_limit_rows_total_and_qdd() -> None:
    ctrl, ctx = make_context(seed=12)
    lim = ctrl.joint_limits
    lb, ub = lim.bounds(ctx.q, ctx.qd)
    rows = lim.rows(ctx)
    assert rows.G.shape == (B, 28, 13) and rows.h.shape == (B, 28)
    gen = torch.Generator().manual_seed(13)
    x = torch.randn(B, 13, generator=gen, dtype=torch.float64)
    qdd, f = x[:, :7], x[:, 7:]
    motion = qdd + mv(ctx.pd_qdd_gain, qdd) + ctx.qdd_pd0
    total = motion + mv(ctx.mass_inv_jt, f)  # the external wrench is not counted by default
    expected = torch.cat([motion - ub, lb - motion, total - ub, lb - total], dim=1)
    assert torch.allclose(mv(rows.G, x) - rows.h, expected, atol=1e-8)
    only = JointLimitsViability(lim.q_min, lim.q_max, lim.dq_max, lim.ddq_max, 1e-3, 0.0, 0.0, 2.0, target="qdd")
    assert only.rows(ctx).G.shape == (B, 14, 13)
    with_ext = JointLimitsViability(lim.q_min, lim.q_max, lim.dq_max, lim.ddq_max, 1e-3, 0.0, 0.0, 2.0,
                                    include_f_ext=True).rows(ctx)
    shift = mv(ctx.mass_inv_jt, ctx.f_ext)
    assert torch.allclose(with_ext.h[:, 14:21], only.rows(ctx).h[:, :7] - shift, atol=1e-9)
    with pytest.raises(InvalidGainError):
        JointLimitsViability(lim.q_min, lim.q_max, lim.dq_max, lim.ddq_max, 1e-3, target="torque")  # type: ignore


def test_wrench_box_and_friction_pyramid() -> None:
    ctrl, ctx = make_context(seed=14)
    box = WrenchBox(20.0, 5.0).rows(ctx)
    x = torch.zeros(B, 13, dtype=torch.float64)
    x[:, 7:] = torch.tensor([19.9, -19.9, 0.0, 4.9, -4.9, 0.0])
    assert bool((mv(box.G, x) <= box.h).all())
    x[:, 9] = 20.1
    assert bool(((mv(box.G, x) - box.h) > 0).any(-1).all())
    fric = FrictionPyramid(0.4).rows(ctx)
    R = ctx.D[:, :3, :3]
    inside = mv(R, torch.tensor([0.35, -0.35, 1.0], dtype=torch.float64).expand(B, 3))  # |f_t| ≤ μ f_n per axis
    outside = mv(R, torch.tensor([0.45, 0.0, 1.0], dtype=torch.float64).expand(B, 3))
    for f_world, ok_in_contact in ((inside, True), (outside, False)):
        x = torch.zeros(B, 13, dtype=torch.float64)
        x[:, 7:10] = 10.0 * f_world
        satisfied = (mv(fric.G, x) <= fric.h + 1e-12).all(-1)
        assert bool((satisfied[ctx.in_contact] == ok_in_contact).all())
        assert bool(satisfied[~ctx.in_contact].all())  # inactive without contact
    assert bool(ctx.in_contact.any() and (~ctx.in_contact).any())


def cvxpy_reference(P: np.ndarray, c: np.ndarray, G: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The same QP declared with cvxpy from the task residuals' (P, c) and the limits' rows, solved by Clarabel."""
    x = cp.Variable(P.shape[0])
    L = np.linalg.cholesky(0.5 * (P + P.T))
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(L.T @ x) + c @ x), [G @ x <= h])
    prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    assert prob.status == cp.OPTIMAL
    return x.value


def test_stacked_qp_matches_cvxpy_clarabel() -> None:
    """The controller's batched QP (tasks + limits) solved by a3cqp_rl.qp equals cvxpy + Clarabel per robot."""
    ctrl, ctx = make_context(n=12, seed=15)
    P, c, G, h = ctrl.build_qp(ctx)
    sol = solve_qp(P, c, G=G, h=h)
    assert bool((sol.status == 0).all())
    active = 0
    for i in range(12):
        ref = cvxpy_reference(P[i].numpy(), c[i].numpy(), G[i].numpy(), h[i].numpy())
        x = sol.x[i].numpy()
        obj = lambda v: 0.5 * v @ P[i].numpy() @ v + c[i].numpy() @ v  # noqa: E731
        assert obj(x) <= obj(ref) + 1e-6 * (1 + abs(obj(ref)))
        np.testing.assert_allclose(x, ref, atol=1e-4 * (1 + np.abs(ref).max()))
        active += int((G[i].numpy() @ ref - h[i].numpy() > -1e-7).sum())
    assert active > 0  # some limits bind in these random instances, so the inequality handling is exercised


def test_torque_limit_rows_match_the_torque_law_eq4() -> None:
    ctrl, ctx = make_context(seed=18)
    bias = torch.randn(B, 7, generator=torch.Generator().manual_seed(19), dtype=torch.float64)
    ctx = dataclasses.replace(ctx, bias=bias)
    rows = TorqueLimits(torch.tensor([87.0] * 4 + [12.0] * 3, dtype=torch.float64), scale=1.0).rows(ctx)
    x = torch.randn(B, 13, generator=torch.Generator().manual_seed(20), dtype=torch.float64)
    qdd, f = x[:, :7], x[:, 7:]
    qdd_pd = ctx.qdd_pd0 + mv(ctx.pd_qdd_gain, qdd)  # eq. 5 with q*, q̇* from eq. 6-7
    tau = mv(ctx.mass, qdd + qdd_pd) + mv(ctx.kin.jac.transpose(-1, -2), f) + bias  # eq. 4
    lim = torch.tensor([87.0] * 4 + [12.0] * 3, dtype=torch.float64)
    assert torch.allclose(mv(rows.G, x) - rows.h, torch.cat([tau - lim, -tau - lim], dim=1), atol=1e-8)
