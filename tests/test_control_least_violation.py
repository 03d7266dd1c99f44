"""A failed QP's least-violation step (ControllerOptions.qp_failure): the joint-limit rows give way as little as an LP
says they can, every other row holds, both routes agree, and "brake" keeps the brake."""
from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import torch

from a3cqp_rl.control import A3CQPController, ControllerOptions
from a3cqp_rl.control.exceptions import InvalidGainError
from a3cqp_rl.robot import PANDA_HOME, PANDA_LIMITS, PandaSim

F64 = torch.float64
N = 3


def pulled_arms() -> tuple:
    """Three moving arms at home; arms 1 and 2 count a 300-N external pull in their joint-limit rows (infeasible:
    the wrench box and the torque limits cannot hold it)."""
    sim = PandaSim(N)
    sim.reset(np.tile(PANDA_HOME, (N, 1)), qd=np.tile([0.5, -0.3, 0.2, 0.4, -0.5, 0.3, 0.2], (N, 1)))
    s = sim.observe()
    w = torch.zeros(N, 6, 3, dtype=F64)
    w[..., 0], w[..., 1], w[..., 2] = 0.4, 0.3, 0.3
    f_d = torch.zeros(N, 6, dtype=F64)
    f_d[:, 2] = 5.0
    f_ext = torch.zeros(N, 6, dtype=F64)
    f_ext[1:] = torch.tensor([150.0, -80.0, 300.0, 20.0, -25.0, 15.0], dtype=F64)
    args = dict(q=s.q, qd=s.qd, mass=s.mass, bias=s.bias, weights=w, f_d=f_d, pos_d=s.kin.pos + 0.02, rot_d=s.kin.rot,
                f_ext=f_ext, in_contact=torch.tensor([False, True, True]), kin=s.kin,
                f_ext_limits=torch.tensor([False, True, True]))
    return s, args


def step(backend: str, mode: str) -> tuple:
    s, args = pulled_arms()
    ctrl = A3CQPController(N, options=ControllerOptions(backend=backend, qp_failure=mode))
    ctrl.reset(s.q, s.qd)
    return ctrl, ctrl.step(**args)


def test_the_least_violation_qp_violates_the_joint_rows_as_little_as_an_lp_and_meets_the_others() -> None:
    s, args = pulled_arms()
    ctrl = A3CQPController(N, options=ControllerOptions(backend="python"))
    ctrl.reset(s.q, s.qd)
    ctx = ctrl.build_context(**{k: v for k, v in args.items()})
    P, c, G, h = (torch.as_tensor(a) for a in ctrl.build_qp(ctx))
    x, solved = ctrl.least_violation(P[1:], c[1:], G[1:], h[1:])
    assert solved.all()
    soft = np.zeros(G.shape[1], dtype=bool)
    soft[ctrl.joint_limits.soft_rows] = True
    assert soft.sum() == 14 and soft[14:28].all()  # the total's rows (target "total"), which count f_ext
    for k in range(2):
        Gk, hk, xk = G[1 + k].numpy(), h[1 + k].numpy(), x[k].numpy()
        assert (Gk[~soft] @ xk - hk[~soft]).max() < 1e-8  # the motion, torque, wrench and friction rows hold
        violation = np.maximum(Gk[soft] @ xk - hk[soft], 0.0).sum()
        X, S = cp.Variable(13), cp.Variable(14)
        lp = cp.Problem(cp.Minimize(cp.sum(S)), [Gk[soft] @ X - S <= hk[soft], Gk[~soft] @ X <= hk[~soft], S >= 0])
        lp.solve()
        assert lp.status == "optimal" and lp.value > 1.0  # the joint rows cannot all hold
        assert violation == pytest.approx(lp.value, rel=1e-6)


@pytest.mark.parametrize("backend", ["python", "native"])
def test_a_failed_qp_gets_the_least_violation_step_instead_of_the_brake(backend: str) -> None:
    _, brake = step(backend, "brake")
    ctrl, lv = step(backend, "least_violation")
    # the QP itself fails for the pulled arms in both modes (status kept), the other arm is untouched
    assert brake.status.tolist()[0] == 0 and (brake.status[1:] != 0).all()
    assert torch.equal(lv.status, brake.status)
    assert brake.fallback.tolist() == [False, True, True] and not brake.relaxed.any()
    assert lv.fallback.tolist() == [False, False, False] and lv.relaxed.tolist() == [False, True, True]
    assert ctrl.relaxed_count == 2 and ctrl.fallback_count == 0
    for name in ("tau", "qdd", "wrench", "qdd_pd"):
        assert torch.equal(getattr(lv, name)[0], getattr(brake, name)[0]), name
    # the brake drops the wrench; the least-violation step pushes back against the pull at the wrench box
    assert brake.wrench[1:].abs().max() == 0.0
    assert lv.wrench[1:, 2].max() < -19.9 and lv.wrench[1:, 0].max() < -10.0
    tau_max = torch.as_tensor(PANDA_LIMITS.tau_max, dtype=F64)
    assert (lv.tau.abs() <= tau_max + 1e-9).all() and torch.isfinite(lv.tau).all()
    # the references forget the relaxed step (q* = q, q̇* = q̇, as under the brake) and keep the solved arm's
    s, _ = pulled_arms()
    assert torch.equal(ctrl.q_des[1:], s.q[1:]) and torch.equal(ctrl.qd_des[1:], s.qd[1:])
    assert not torch.equal(ctrl.qd_des[0], s.qd[0])


def test_both_routes_give_the_same_least_violation_step() -> None:
    (c_py, py), (c_nat, nat) = step("python", "least_violation"), step("native", "least_violation")
    assert py.relaxed.tolist() == nat.relaxed.tolist() == [False, True, True]
    for name in ("tau", "qdd", "wrench"):
        torch.testing.assert_close(getattr(py, name), getattr(nat, name), rtol=0, atol=1e-6, msg=name)
    for name in ("q_des", "qd_des"):
        torch.testing.assert_close(getattr(c_py, name), getattr(c_nat, name), rtol=0, atol=1e-9, msg=name)


def test_an_unknown_qp_failure_mode_is_refused() -> None:
    with pytest.raises(InvalidGainError, match="qp_failure"):
        A3CQPController(1, options=ControllerOptions(qp_failure="slack"))  # type: ignore[arg-type]
