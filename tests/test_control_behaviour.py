"""A3CQP controller in closed loop with MuJoCo: IK, AC, FC, JC behaviours, random switching, safe fallback."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import pytest
import torch

from a3cqp_rl.config import ControllerConfig
from a3cqp_rl.control import A3CQPController, ControllerOptions, Inequality, Limit, wrench_from_joint_torques
from a3cqp_rl.control.context import ControlContext
from a3cqp_rl.control.controller import FALLBACK_LOG_EVERY, FALLBACK_LOG_FIRST
from a3cqp_rl.control.exceptions import ControlShapeError
from a3cqp_rl.robot import PANDA_HOME, PANDA_LIMITS, PandaSim, table_xml

F64 = torch.float64
IK, AC, FC = 0, 1, 2


def task_weights(n: int, per_axis: list[int]) -> torch.Tensor:
    """One-hot local weights [n, 6, 3]: per_axis[i] ∈ {IK, AC, FC} selects the task of local axis i."""
    w = torch.zeros(n, 6, 3, dtype=F64)
    w[:, torch.arange(6), torch.tensor(per_axis)] = 1.0
    return w


@dataclass
class Log:
    """Per-step records of a closed-loop run (numpy arrays after `finish`)."""

    pos: list = field(default_factory=list)
    vel: list = field(default_factory=list)
    q: list = field(default_factory=list)
    qd: list = field(default_factory=list)
    err: list = field(default_factory=list)
    tau: list = field(default_factory=list)
    fallback: list = field(default_factory=list)
    contact: list = field(default_factory=list)

    def finish(self) -> "Log":
        for k, v in vars(self).items():
            setattr(self, k, np.array(v))
        return self


def run(sim: PandaSim, ctrl: A3CQPController, steps: int, weights, f_d, pos_d, rot_d,  # noqa: ANN001
        push=None, contact_geom: str | None = None, sim_kin: bool = False) -> Log:  # noqa: ANN001
    """Closed loop: observe -> controller (f_ext from the joint-torque estimate, section V-A) -> push -> step.

    sim_kin: feed the controller MuJoCo's site kinematics (`SimState.kin`) instead of PandaModel's."""
    log = Log()
    s = sim.observe()
    for k in range(steps):
        w = weights(k) if callable(weights) else weights
        fd = f_d(k) if callable(f_d) else f_d
        kin = s.kin if sim_kin else ctrl.model.kinematics(s.q, s.qd)
        f_ext = wrench_from_joint_torques(s.tau_ext, kin.jac, s.mass)  # J^{T†} τ_ext
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, fd, pos_d, rot_d, f_ext=f_ext, f_env=s.f_env,
                        kin=kin if sim_kin else None)
        if push is not None:
            sim.push(push(k))
        sim.step(out.tau)
        log.pos.append(kin.pos.numpy().copy())
        log.vel.append(kin.twist.numpy().copy())
        log.q.append(s.q.numpy().copy())
        log.qd.append(s.qd.numpy().copy())
        log.err.append(out.pose_error.numpy().copy())
        log.tau.append(out.tau.numpy().copy())
        log.fallback.append(out.fallback.numpy().copy())
        if contact_geom is not None:
            log.contact.append(sim.contact_force(contact_geom))
        s = sim.observe()
    return log.finish()


def home_reference(ctrl: A3CQPController, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    q = torch.tensor([PANDA_HOME] * n, dtype=F64)
    return ctrl.model.fk(q)


# ---------------------------------------------------------------------------------------------- IK
def rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)


@pytest.mark.parametrize("n", [2])
def test_ik_weights_track_a_cartesian_target(n: int) -> None:
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    pos_d = pos0 + torch.tensor([[0.08, -0.05, 0.06], [-0.05, 0.1, -0.08]], dtype=F64)
    rot_d = rot_z(0.2) @ rot0
    log = run(sim, ctrl, 1500, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64), pos_d, rot_d)
    pos_err = np.linalg.norm(log.err[:, :, :3], axis=-1)  # (T, n) m
    rot_err = np.linalg.norm(log.err[:, :, 3:], axis=-1)
    assert pos_err[0].min() > 0.09  # a real move
    assert pos_err[-200:].max() < 1e-3  # sub-millimetre after settling (last 0.2 s of 1.5 s)
    assert rot_err[-200:].max() < 5e-3
    assert not log.fallback.any()


# ---------------------------------------------------------------------------------------------- AC
@pytest.mark.parametrize("c_d, duration, t_check", [(50.0, 700, (0.5, 0.7)), (5.0, 250, (0.2, 0.25))])
def test_ac_weights_follow_a_constant_push_at_the_handle(c_d: float, duration: int, t_check: tuple) -> None:
    """Λd ẍ + Cd ẋ = f (eq. 17): v(t) = f/Cd (1 − exp(−Cd t/Λd)). With Cd = 50 the steady velocity 0.2 m/s is
    reached within the workspace; Table I's Cd = 5 has a 1 s time constant and a 2 m/s steady state, so only the
    transient is checked there."""
    sim = PandaSim(1)
    ctrl = A3CQPController(1, config=ControllerConfig(c_d=c_d, lambda_d=5.0))
    pos0, rot0 = home_reference(ctrl, 1)
    push = np.array([[10.0, 0.0, 0.0]])
    log = run(sim, ctrl, duration, task_weights(1, [AC] * 6), torch.zeros(1, 6, dtype=F64), pos0, rot0,
              push=lambda k: push)
    t = (np.arange(duration) + 1) * sim.dt
    expected = 10.0 / c_d * (1.0 - np.exp(-c_d * t / 5.0))
    window = (t >= t_check[0]) & (t <= t_check[1])
    vx = log.vel[window, 0, 0]
    assert np.abs(vx / expected[window] - 1.0).max() < 0.10
    assert np.abs(log.vel[window, 0, 1:3]).max() < 0.1 * expected[window].max()  # moves along the push
    assert not log.fallback.any()


# ---------------------------------------------------------------------------------------------- FC
def test_fc_weights_press_on_a_rigid_table_with_the_desired_force() -> None:
    """IK holds x, y and the orientation; FC pushes along the tool axis (local z, pointing down) with f_d = 10 N."""
    ctrl = A3CQPController(1)
    pos0, rot0 = home_reference(ctrl, 1)
    table_top = float(pos0[0, 2]) - 0.01  # 1 cm below the peg tip
    sim = PandaSim(1, scene=table_xml(height=table_top, center=(float(pos0[0, 0]), float(pos0[0, 1]))))
    f_d = torch.tensor([[0.0, 0.0, 10.0, 0.0, 0.0, 0.0]], dtype=F64)
    log = run(sim, ctrl, 2000, task_weights(1, [IK, IK, FC, IK, IK, IK]), f_d, pos0, rot0, contact_geom="peg")
    fz = log.contact[:, 0, 2]  # world z force the table exerts on the peg (up = positive)
    tail = fz[-500:]
    assert fz[:50].max() == 0.0 and tail.min() > 0.0  # starts in the air, ends (and stays) in contact
    assert abs(tail.mean() - 10.0) < 0.5  # within 5 % of f_d
    assert tail.std() < 0.2 and np.abs(np.diff(tail)).max() < 0.1  # no chatter
    assert np.abs(log.err[-500:, 0, :2]).max() < 2e-3  # x, y held by IK while pressing
    assert not log.fallback.any()


# ---------------------------------------------------------------------------------------------- JC
def swivel_start(ctrl: A3CQPController, min_gap: float = 0.35) -> torch.Tensor:
    """Move from the ready pose along the null space (same site pose) until a joint is within `min_gap` of a limit."""
    lim = PANDA_LIMITS.tensors()
    q = torch.tensor([PANDA_HOME], dtype=F64)
    direction = None
    for _ in range(2000):
        J = ctrl.model.jacobian(q)
        N = torch.eye(7, dtype=F64) - torch.linalg.pinv(J) @ J
        v = torch.linalg.eigh(N[0]).eigenvectors[:, -1]  # the 1-D null space
        if direction is None:
            direction = v if v[0] > 0 else -v  # swivel so that joint 1 increases
        v = v if torch.dot(v, direction) > 0 else -v
        direction = v
        q = q + 0.005 * v
        gap = torch.minimum(q - lim["q_min"], lim["q_max"] - q).min()
        if gap < min_gap:
            return q
    raise AssertionError("no joint came close to a limit along the null space")


def min_limit_gap(q: np.ndarray) -> np.ndarray:
    lim = PANDA_LIMITS
    return np.minimum(q - np.array(lim.q_min), np.array(lim.q_max) - q).min(-1)


@pytest.mark.parametrize("nullspace_weight, moves", [(1e-3, True), (0.0, False)])
def test_jc_keeps_the_arm_away_from_joint_limits_in_the_null_space(nullspace_weight: float, moves: bool) -> None:
    ctrl = A3CQPController(1, options=ControllerOptions(jc_nullspace_weight=nullspace_weight))
    q0 = swivel_start(ctrl)
    pos0, rot0 = ctrl.model.fk(q0)
    sim = PandaSim(1, q0=tuple(q0[0].tolist()))
    log = run(sim, ctrl, 2000, task_weights(1, [IK] * 6), torch.zeros(1, 6, dtype=F64), pos0, rot0)
    gap = min_limit_gap(log.q[:, 0])
    pos_err = np.linalg.norm(log.err[:, 0, :3], axis=-1)
    assert pos_err.max() < 2e-3  # the end effector (nearly) does not move while the elbow swivels
    if moves:
        # JC swivelled the elbow away from the limit, to the ready pose's gap (0.716 rad, joint 4)
        assert gap[0] < 0.36 and gap[-1] > 0.7
        assert np.linalg.norm(log.q[-1, 0] - np.array(PANDA_HOME)) < 0.5 * np.linalg.norm(log.q[0, 0] - PANDA_HOME)
    else:
        assert abs(gap[-1] - gap[0]) < 0.05  # eq. 1's ε JᵀW1J alone does not act in the null space


# ---------------------------------------------------------------------------------------------- switching
def random_switching(n: int, steps: int, seed: int, sim_kin: bool = False) -> Log:
    """Random, rapidly switching (every 5-50 ms) weights, desired forces up to 20 N and targets; no contact."""
    gen = torch.Generator().manual_seed(seed)
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    state = {"w": None, "f": None, "next": torch.zeros(n, dtype=torch.long)}

    def weights(k: int) -> torch.Tensor:
        if state["w"] is None:
            state["w"] = torch.full((n, 6, 3), 1.0 / 3.0, dtype=F64)
            state["f"] = torch.zeros(n, 6, dtype=F64)
        switch = state["next"] <= k
        if bool(switch.any()):
            m = int(switch.sum())
            logits = 6.0 * (torch.rand(m, 6, 3, generator=gen, dtype=F64) - 0.5)  # ± σw/2 (eq. 29)
            state["w"][switch] = torch.softmax(logits, dim=-1)
            state["f"][switch] = 20.0 * torch.rand(m, 6, generator=gen, dtype=F64)
            state["next"][switch] = k + torch.randint(5, 50, (m,), generator=gen)
        return state["w"]

    pos_d = pos0 + 0.3 * (torch.rand(n, 3, generator=gen, dtype=F64) - 0.5)
    return run(sim, ctrl, steps, weights, lambda k: state["f"], pos_d, rot0, sim_kin=sim_kin)


def assert_within_limits(log: Log) -> None:
    lim = PANDA_LIMITS
    assert np.isfinite(log.tau).all() and np.isfinite(log.q).all() and np.isfinite(log.qd).all()
    q_excess = np.maximum(np.array(lim.q_min) - log.q, log.q - np.array(lim.q_max)).max()
    qd_excess = (np.abs(log.qd) - np.array(lim.dq_max)).max()
    fallbacks = int(log.fallback.sum())
    print(f"max position excess {q_excess:.2e} rad, velocity excess {qd_excess:.2e} rad/s, {fallbacks} fallbacks")
    assert q_excess <= 0.0 and qd_excess <= 0.0
    assert fallbacks == 0  # the QP is feasible by construction (TorqueLimits anchored to the viable brake)


def test_random_switching_weights_respect_joint_limits_fast() -> None:
    log = random_switching(n=3, steps=1500, seed=0)
    assert_within_limits(log)
    assert np.abs(log.qd).max() > 0.5  # the arms really moved


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_switching_several_seeds_with_mujoco_kinematics(seed: int) -> None:
    """Same with SimState.kin (MuJoCo's site kinematics), whose chaotically different trajectories once reached
    states where the joint-limit and torque-limit rows were jointly infeasible; 8 arms x 1500 steps per seed."""
    log = random_switching(n=8, steps=1500, seed=seed, sim_kin=True)
    assert_within_limits(log)


@pytest.mark.slow
@pytest.mark.parametrize("sim_kin", [False, True])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_switching_weights_respect_joint_limits_10000_steps(seed: int, sim_kin: bool) -> None:
    log = random_switching(n=8, steps=10_000, seed=seed, sim_kin=sim_kin)
    assert_within_limits(log)


# ---------------------------------------------------------------------------------------------- fallback
class Contradiction(Limit):
    """x_0 ≤ −1 and −x_0 ≤ −1 (i.e. x_0 ≥ 1) for the robots in `mask`: an infeasible QP."""

    name = "contradiction"

    def __init__(self, mask: torch.Tensor) -> None:
        self.mask = mask

    def rows(self, ctx: ControlContext) -> Inequality:
        G = ctx.q.new_zeros(ctx.batch, 2, 13)
        G[:, 0, 0], G[:, 1, 0] = 1.0, -1.0
        h = torch.where(self.mask.view(-1, 1), -1.0, 100.0).to(ctx.q).expand(ctx.batch, 2).clone()
        return Inequality(G=G, h=h)


def test_infeasible_qp_falls_back_safely_and_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    n = 3
    mask = torch.tensor([False, True, False])
    sim = PandaSim(n)
    ctrl = A3CQPController(n, extra_limits=[Contradiction(mask)])
    pos0, rot0 = home_reference(ctrl, n)
    s = sim.observe()
    sim.reset(np.tile(PANDA_HOME, (n, 1)), qd=np.tile([0.5, -0.3, 0.2, 0.4, -0.5, 0.3, 0.2], (n, 1)))
    s = sim.observe()
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.control.controller"):
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64),
                        pos0 + 0.05, rot0)
    assert out.status.tolist()[1] != 0 and out.status[0] == 0 and out.status[2] == 0
    assert out.fallback.tolist() == [False, True, False]
    assert "robots [1]" in caplog.text and ctrl.fallback_count == 1
    assert "QP status ['PRIMAL_INFEASIBLE']" in caplog.text  # by name, not its number
    # the fallback brakes (q̈ opposes q̇) with zero wrench and gravity compensation
    assert torch.all(out.qdd[1] * s.qd[1] < 0) and out.wrench[1].abs().max() == 0.0
    # keep running infeasible: robot 1 comes to rest without NaN, the others keep tracking
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="a3cqp_rl.control.controller"):
        log = run(sim, ctrl, 400, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64), pos0 + 0.05, rot0)
    assert np.isfinite(log.tau).all() and log.fallback[:, 1].all() and not log.fallback[:, [0, 2]].any()
    # 401 steps with a fallback: the log has the first FALLBACK_LOG_FIRST, then one per FALLBACK_LOG_EVERY
    lines = [r.getMessage() for r in caplog.records if "A3CQP fallback" in r.getMessage()]
    assert len(lines) == FALLBACK_LOG_FIRST - 1 and ctrl.fallback_count == 401
    assert f"now logged every {FALLBACK_LOG_EVERY}th" in lines[-1] and "step 10 with a fallback" in lines[-1]
    assert np.abs(log.qd[-1, 1]).max() < 1e-2
    assert np.linalg.norm(log.err[-1, 0, :3]) < 5e-3


def test_non_finite_inputs_fall_back_without_nan() -> None:
    n = 2
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    s = sim.observe()
    f_d = torch.zeros(n, 6, dtype=F64)
    f_d[0, 2] = float("nan")
    out = ctrl.step(s.q, s.qd, s.mass, s.bias, task_weights(n, [IK] * 6), f_d, pos0, rot0)
    assert out.status.tolist() == [-1, 0] and out.fallback.tolist() == [True, False]
    assert torch.isfinite(out.tau).all()
    assert torch.allclose(out.tau[0], s.bias[0], atol=1e-9)  # at rest: brake = 0, pure gravity compensation
    # a NaN F/T reading would read as "no contact" (the friction pyramid off): that robot's input is invalid instead
    f_env = torch.zeros(n, 6, dtype=F64)
    f_env[1, 4] = float("nan")
    out = A3CQPController(n).step(s.q, s.qd, s.mass, s.bias, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64),
                                  pos0, rot0, f_env=f_env)
    assert out.status.tolist() == [0, -1] and out.fallback.tolist() == [False, True]
    # kinematics of another number of robots: named, not a reshape error from inside
    kin3 = A3CQPController(3).model.kinematics(torch.cat([s.q, s.q[:1]]), torch.cat([s.qd, s.qd[:1]]))
    with pytest.raises(ControlShapeError, match=r"kin must hold the kinematics of 2 robots"):
        A3CQPController(n).step(s.q, s.qd, s.mass, s.bias, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64),
                                pos0, rot0, kin=kin3)


def test_solver_exception_falls_back_for_all_robots(monkeypatch: pytest.MonkeyPatch,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    import a3cqp_rl.control.controller as controller_module

    def broken(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise IndexError("solver bug")

    n = 2
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    s = sim.observe()
    monkeypatch.setattr(controller_module, "solve_qp", broken)
    with caplog.at_level(logging.ERROR, logger="a3cqp_rl.control.controller"):
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64), pos0, rot0)
    assert out.status.tolist() == [controller_module.SOLVER_ERROR] * n and bool(out.fallback.all())
    assert "solve_qp raised" in caplog.text and torch.isfinite(out.tau).all()


def test_per_axis_leak_keeps_the_integral_action_of_the_axes_ik_still_tracks() -> None:
    """Admittance on local z, IK elsewhere, a constant 5 N sideways push at the handle: with the per-axis leak the IK
    axes keep eq. 5-7's integral action and hold the reference; with the min-w1 leak (one axis off IK) they lose it."""
    err = {}
    for mode in ("min_w1", "per_axis"):
        ctrl = A3CQPController(1, options=ControllerOptions(leak_axes=mode))
        pos0, rot0 = home_reference(ctrl, 1)
        push = np.array([[0.0, 5.0, 0.0]])
        log = run(PandaSim(1), ctrl, 2000, task_weights(1, [IK, IK, AC, IK, IK, IK]), torch.zeros(1, 6, dtype=F64),
                  pos0, rot0, push=lambda k: push if k >= 300 else np.zeros((1, 3)))
        err[mode] = np.abs(log.err[-200:, 0, :2]).max()
        assert not log.fallback.any()
    assert err["per_axis"] < 1.5e-3 and err["min_w1"] > 4e-3, err  # measured 0.5 mm vs 7.2 mm


def test_a_negative_weight_is_that_robots_invalid_input() -> None:
    """w < 0 makes the QP non-convex: that robot falls back (INVALID_INPUT), the other computes as before."""
    n = 2
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    s = sim.observe()
    w = task_weights(n, [IK] * 6)
    ref = A3CQPController(n).step(s.q, s.qd, s.mass, s.bias, w, torch.zeros(n, 6, dtype=F64), pos0, rot0)
    w[0, 1, 0] = -0.5
    out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, torch.zeros(n, 6, dtype=F64), pos0, rot0)
    assert out.status.tolist() == [-1, 0] and out.fallback.tolist() == [True, False]
    torch.testing.assert_close(out.tau[1], ref.tau[1], rtol=0, atol=1e-12)
    # a weight so large that the QP is ill-conditioned likewise (1e12 was reported SOLVED with absurd torques)
    from a3cqp_rl.control.controller import W_MAX

    w[0, 1, 0] = 1e12
    w[1, 2, 1] = W_MAX  # the largest taken
    out = A3CQPController(n).step(s.q, s.qd, s.mass, s.bias, w, torch.zeros(n, 6, dtype=F64), pos0, rot0)
    assert out.status.tolist() == [-1, 0] and out.fallback.tolist() == [True, False]


def test_a_reference_that_is_no_rotation_is_that_robots_invalid_input() -> None:
    """A scaled, sheared or reflected rot_d would give eq. 3 a meaningless orientation error: that robot falls back
    (INVALID_INPUT); a float32 rotation's round-off is taken."""
    n = 4
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    s = sim.observe()
    w, f_d = task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64)
    ref = A3CQPController(n).step(s.q, s.qd, s.mass, s.bias, w, f_d, pos0, rot0)
    rot = rot0.clone()
    rot[0] *= 1.01  # scaled
    rot[1, :, 0] = -rot[1, :, 0]  # a reflection: orthonormal, det -1
    rot[3] = rot[3].to(torch.float32).to(F64)  # round-off only
    out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos0, rot)
    assert out.status.tolist() == [-1, -1, 0, 0] and out.fallback.tolist() == [True, True, False, False]
    torch.testing.assert_close(out.tau[2], ref.tau[2], rtol=0, atol=1e-12)


def test_step_and_reset_inputs_are_checked_with_named_shapes() -> None:
    from a3cqp_rl.control.exceptions import ControlShapeError

    n = 3
    sim, ctrl = PandaSim(n), A3CQPController(n)
    pos0, rot0 = home_reference(ctrl, n)
    s = sim.observe()
    q = torch.tensor(np.tile(PANDA_HOME, (n, 1)), dtype=F64)
    with pytest.raises(ControlShapeError, match=r"reset: q must have shape \(3, 7\)"):
        ctrl.reset(q.T)  # [7, 3]: was taken as [3, 7] by a reshape
    with pytest.raises(ControlShapeError, match=r"reset: q must have shape \(3, 7\)"):
        ctrl.reset(q[:2])
    ctrl.reset(q)
    with pytest.raises(ControlShapeError, match=r"reset: q must have shape \(2, 7\)"):
        ctrl.reset(q, idx=[0, 2])
    args = (s.qd, s.mass, s.bias, task_weights(n, [IK] * 6), torch.zeros(n, 6, dtype=F64), pos0, rot0)
    with pytest.raises(ControlShapeError, match="in_contact must be a bool"):
        ctrl.step(s.q, *args, in_contact=torch.zeros(n))
    with pytest.raises(ControlShapeError, match=r"f_env must have shape \(3, 6\)"):
        ctrl.step(s.q, *args, f_env=torch.zeros(n, 3, dtype=F64))
    out = ctrl.step(s.q.numpy(), *args)  # numpy inputs as tensors
    assert out.tau.shape == (n, 7)
    for bad in (0, -1, 2.5):
        with pytest.raises(ControlShapeError, match="number of robots"):
            A3CQPController(bad)


def test_the_simulation_refuses_bad_torques_and_states_instead_of_touching_other_arms() -> None:
    """MuJoCo zeroes every arm's controls for one NaN torque and resets the whole model for a NaN qpos: PandaSim
    raises, naming the arm, and never auto-resets."""
    import mujoco

    n = 3
    sim = PandaSim(n)
    assert sim.model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
    sim.observe()
    tau = np.zeros((n, 7))
    tau[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"tau is not finite for arms \(rows\) \[1\]"):
        sim.step(tau)
    with pytest.raises(ValueError, match=r"tau must have shape \(3, 7\)"):
        sim.step(np.ones(7))
    q = np.tile(PANDA_HOME, (n, 1))
    with pytest.raises(ValueError, match=r"q must have shape \(3, 7\)"):
        sim.reset(q.T.copy())
    q[2, 0] = np.nan
    with pytest.raises(ValueError, match=r"q is not finite for arms \(rows\) \[2\]"):
        sim.reset(q)
    with pytest.raises(ValueError, match="number of arms"):
        PandaSim(0)


def test_two_tasks_of_one_name_are_refused_not_one_silently_dropped() -> None:
    from a3cqp_rl.control.tasks import JointCentering

    tasks = A3CQPController(1).tasks
    jc = next(t for t in tasks if t.name == "jc")
    again = JointCentering(jc.q_center.clone(), 1.0, 1.0) if hasattr(jc, "q_center") else None
    if again is None:
        pytest.skip("JointCentering keeps its centre under another name")
    with pytest.raises(ValueError, match=r"task names must differ, got \['jc'\]"):
        A3CQPController(1, tasks=[*tasks, again])
