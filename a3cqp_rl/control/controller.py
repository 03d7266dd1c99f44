"""The A3CQP controller (paper 000, section III): batched QP over (q̈, f) from four tasks + limits, then eq. 4-7."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import operator
from dataclasses import dataclass, field
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Literal

import numpy as np
import torch

from a3cqp_rl.config import ControllerConfig
from a3cqp_rl.control import native
from a3cqp_rl.control.arrays import Array, cat, const, inv, mm, mv, solve_spd, zeros
from a3cqp_rl.control.context import N_QDD, N_VARS, ControlContext
from a3cqp_rl.control.exceptions import ControlShapeError, InvalidGainError
from a3cqp_rl.control.frames import block_rotation, pose_error, weights_to_world
from a3cqp_rl.control.hierarchy import Hierarchy, solve_cascade
from a3cqp_rl.control.limits import (FrictionPyramid, Inequality, JointLimitsViability, Limit, TorqueLimits,
                                     WrenchBox)
from a3cqp_rl.control.tasks import (Admittance, CartesianAccelerationRegularizer, CartesianIK, ForceControl,
                                    JointCentering, Residual, Task)
from a3cqp_rl.qp import QPSolution, QPStatus, solve_qp
from a3cqp_rl.robot.kinematics import Kinematics, PandaModel
from a3cqp_rl.robot.sense import wrench as _native_wrench
from a3cqp_rl.robot.specs import PANDA_HOME, PANDA_LIMITS, PandaLimits

__all__ = ["ControllerOptions", "ControlOutput", "A3CQPController", "wrench_from_joint_torques", "INVALID_INPUT",
           "SOLVER_ERROR"]

logger = logging.getLogger(__name__)
FALLBACK_LOG_FIRST = 10
"""Steps with a fallback that are logged one by one; after them, every FALLBACK_LOG_EVERY-th."""
FALLBACK_LOG_EVERY = 1000

INVALID_INPUT = -1
"""`ControlOutput.status` code of a robot whose inputs (state, B(q), references) were not finite."""
SOLVER_ERROR = -2
"""`ControlOutput.status` code when solve_qp raised instead of returning (every robot of the batch falls back)."""


@contextlib.contextmanager
def fallback_log_quiet() -> Iterator[None]:
    """Within it, no per-step fallback log line: for callers that count fallbacks per trial or genome instead."""
    level = logger.level
    logger.setLevel(max(level, logging.ERROR))
    try:
        yield
    finally:
        logger.setLevel(level)


def _status_names(status: torch.Tensor) -> list[str]:
    """QP statuses by name (NON_CONVEX, not 4; −1: the controller's own input check), for the fallback's log line."""
    names = {int(s): s.name for s in QPStatus} | {-1: "INVALID_INPUT"}
    return [names.get(int(s), str(int(s))) for s in status.tolist()]


@dataclass
class ControllerOptions:
    """Choices the paper leaves open (documented deviations are marked); Table I gains live in ControllerConfig."""

    admittance_form: Literal["consistent", "paper"] = "consistent"
    """"consistent": AC damping Λ Λd⁻¹ Cd ẋ so the closed loop is exactly eq. 17; "paper": eq. 18 as printed."""
    ik_wrench_feedforward: bool = True
    """Out of contact, IK subtracts the acceleration Λ⁻¹ f_ff of the wrench that AC/FC will command (f_ff = the
    unconstrained optimum of eq. 24b), so that AC/FC axes do not drag the IK axes through the off-diagonal terms of
    Λ⁻¹ (not in the paper; False = eq. 1). In contact the environment cancels that acceleration, so it is off."""
    pd_projection: Literal["transpose", "pinv"] = "pinv"
    """q̈_pd = P W1 J (c_v Δq̇ + c_p Δq) with P = Jᵀ (eq. 5 as printed) or J⁺ ("pinv", default): with J⁺ the
    feedback acceleration J q̈_pd = W1 J(...) stays on the IK axes instead of leaking into the FC axis through JJᵀ."""
    cartesian_regularization: float = 1e-2
    """γ of CartesianAccelerationRegularizer: keeps q̈* out of the axes IK does not weight (0 = eq. 1)."""
    jc_nullspace_weight: float = 1e-3
    """ε_N: extra null-space weight of the JC task (0 = eq. 1 exactly; see tasks.JointCentering)."""
    regularization: float = 1e-6
    """Tikhonov term added to the QP Hessian ("the resulting QP Hessians are regularized", section III-A)."""
    pinv_damping: float = 1e-6
    """λ² added to J B⁻¹ Jᵀ (for Λ and f_ext) near singularities."""
    nullspace_damping: float = 1e-9
    """λ² added to J Jᵀ in J⁺ for the null-space projector N = I − J⁺J (small: N leaks λ/σ² into the row space)."""
    desired_state_leak: float = 10.0
    """[1/s] rate at which q*, q̇* relax toward the measured q, q̇ where IK does not lead (not in the paper: without
    it q* drifts away from q while IK is off and q̈_pd would yank the arm back when IK returns); see `leak_axes`."""
    leak_axes: Literal["min_w1", "per_axis"] = "min_w1"
    """How the leak is shared out. "min_w1" (default): every joint at rate × (1 − min_i w1_i): as soon as one axis
    leaves IK, the integral action of eq. 5-7 is gone from the axes IK still tracks too. "per_axis": along each axis
    of the local frame L at rate × (w2 + w3 · min(1, f_d / 1 N)), the null-space part of q* − q at the full rate, so
    an axis IK leads (or where force control does not push) keeps its integral action. On the simulated
    peg-in-hole the scripted IK + FC trigger succeeds in 26/26 trials with "per_axis" and 3/26 with "min_w1"
    (friction holds the peg on the rim); on a flat table "per_axis" presses 10.8 N for f_d = 10 N (the IK axes'
    integral terms push through Λ's coupling) where "min_w1" presses 10.0 N. With "per_axis" a caller can add its
    own rate per axis of L (`A3CQPController.step(leak_extra=...)`, 1/s), relaxed together with this one."""
    wrench_blend: Literal["normalized", "weighted_sum"] = "normalized"
    """How the wrench sub-problem (eq. 24b) shares f* out on each axis of L. "normalized" (default, eq. 24b):
    f* = (w2 f_adm + w3 f_ctc) / (w2 + w3), so an axis IK leads still commands the AC/FC mix at full size (on the
    Panda, ½ f_adm on the rotational axes where w2 and w3 both sit at eq. 29's floor). "weighted_sum": IK's weight
    counts in that sub-problem as a zero-wrench reference (‖f‖² weighted by W1), so with w1 + w2 + w3 = 1
    f* = w2 f_adm + w3 f_ctc: the weighted sum of the point-mass surrogate the adaptation is trained on (eq. 35),
    and "the optimization variable not associated with any active task is set to null" (section III-A) also when
    the weights of the idle tasks are small but not zero."""
    joint_limit_target: Literal["total", "qdd"] = "total"
    """What the viable joint bounds constrain: the commanded total acceleration (default) or q̈* only (eq. 24a)."""
    joint_limits_include_f_ext: bool = False
    """Count the measured f_ext in the bounded total acceleration (can make the QP infeasible; see limits.py)."""
    q_margin: float = 0.01
    """[rad] position limits are tightened by this much."""
    dq_margin: float = 0.02
    """[rad/s] velocity limits are tightened by this much."""
    limit_horizon_steps: float = 2.0
    """Horizon of the viability bounds in control periods (TSID uses 2)."""
    viability_stop_share: float = 0.9
    """Share of the acceleration limit ddq_max the viability bound counts on to stop before a position limit (the
    bounds still allow all of it): headroom for torque the model lacks, e.g. MuJoCo's joint damping
    (JointLimitsViability.stopping_deceleration). 1.0: Del Prete's bound as published."""
    torque_limits: bool = True
    """Add |τ| ≤ 0.98 τ_max rows (TorqueLimits; not in the paper) so the QP never asks for unrealisable torques."""
    contact_force_threshold: float = 1.0
    """[N] measured contact force above which the friction pyramid is active."""
    brake_gain: float = 20.0
    """[1/s] fallback joint deceleration q̈ = −k q̇ (within the viable bounds) when a QP fails."""
    qp_failure: Literal["brake", "least_violation"] = "brake"
    """What a robot whose QP fails gets. "brake" (default): the fallback brake (`brake_gain`, f = 0, gravity
    compensation). "least_violation": the same QP once more with the joint-limit rows that bound the arm's actual
    acceleration soft (`JointLimitsViability.soft_rows`; a slack per row, s ≥ 0, penalised by `RELAX_L1` Σs +
    `RELAX_L2`/2 Σs², far above every task), so that the torque, wrench and friction rows still hold, those joint
    rows give way as little as they can, and the tasks go on in what is left; `ControlOutput.relaxed` says so, and
    the brake follows only where that QP fails too. Those rows are the ones that conflict: with the measured f_ext
    counted in them (`joint_limits_include_f_ext`, `step(f_ext_limits=)`) an operator's pull can ask for more torque
    than the limits give. q*, q̇* forget a relaxed step as they forget a braked one (`_forget_relaxed`). On the peg
    its numbers match the brake's, each failed period costing a Python period (docs/panda.md, "A least-violation
    step for a failed QP"). Strict hierarchies (`set_levels`) always brake."""
    qp_max_iter: int = 50
    """Interior-point iteration budget of the QP solver."""
    qp_hand_on: bool = False
    """Whether a QP the solver's C route cannot decide goes on to its torch route (solve_qp's hand_on). Off (default):
    the robot falls back at once, as a 1 kHz loop must: the torch route takes ~20 ms an instance. The C route decided
    every QP of peg-in-hole (8 trials, every controller) with the external wrench off the joint-limit rows; with it
    on, the undecided ones were ill-conditioned infeasible QPs (all of ~6,000). True: the exact optimum where the C
    route cannot give it (offline analysis; random states near the limits: 7 of 1,920 solved there, not braked)."""
    q_center: tuple[float, ...] = field(default=PANDA_HOME)
    """q_d of the JC task (eq. 23) [rad]; default the Franka "ready" pose."""
    backend: Literal["auto", "python", "native"] = "auto"
    """Who evaluates the default tasks, limits and torque law on CPU: "python" the objects of tasks.py/limits.py;
    "native" their C translation (control/native: same numbers to rounding, ~20x faster per step; an error if the
    composition is not the default one or the library cannot be built); "auto" (default) native when possible."""


@dataclass(frozen=True)
class ControlOutput:
    """Result of one control step for N robots (world frame, SI units)."""

    tau: torch.Tensor
    """Joint torques [N, 7] (N m), clipped to the datasheet limits (eq. 4)."""
    qdd: torch.Tensor
    """Optimal joint accelerations q̈* [N, 7] (rad/s²)."""
    wrench: torch.Tensor
    """Optimal end-effector wrench f* [N, 6] (N, N m)."""
    qdd_pd: torch.Tensor
    """Feedback acceleration q̈_pd [N, 7] (eq. 5)."""
    pose_error: torch.Tensor
    """e_x [N, 6] (m, rad) (eq. 10)."""
    f_adm: torch.Tensor
    """Admittance wrench reference [N, 6] (eq. 18)."""
    f_ctc: torch.Tensor
    """Contact wrench reference [N, 6] (eq. 20)."""
    status: torch.Tensor
    """QP status per robot [N] (0 solved; see a3cqp_rl.qp.QPStatus; −1 invalid input)."""
    fallback: torch.Tensor
    """Bool [N]: the QP failed and the safe fallback torque (brake + gravity compensation) was applied."""
    saturated: torch.Tensor
    """Bool [N]: some joint torque hit its limit."""
    iterations: torch.Tensor
    """QP solver iterations per robot [N]."""
    relaxed: torch.Tensor
    """Bool [N]: the QP failed and the least-violation QP (`ControllerOptions.qp_failure`) gave the step instead."""


def wrench_from_joint_torques(tau_ext: torch.Tensor, jac: torch.Tensor, mass: torch.Tensor,
                              damping: float = 1e-6) -> torch.Tensor:
    """f_ext = J^{T†} τ_ext = Λ J B⁻¹ τ_ext [B, 6] (N, N m) from external joint torques [B, 7] (section V-A)."""
    if all(t.device.type == "cpu" and t.dtype == torch.float64 and not t.requires_grad for t in (tau_ext, jac, mass)):
        # the 1 kHz loop's case: two numpy solves (~15 µs) instead of four torch.linalg calls (~100 µs), and none
        # for the robots nothing pushes (τ_ext = 0 exactly, f_ext = 0: an arm in free motion)
        tau = tau_ext.numpy()
        native = _native_wrench(tau, jac.numpy(), mass.numpy(), damping)  # the same in C (a3cqp_rl/robot/sense.py)
        if native is not None:
            return torch.from_numpy(native)
        out = np.zeros(tau.shape[:-1] + (6,))
        live = tau.any(-1)  # NaN counts as pushing: it propagates as before
        if live.any():
            J = jac.numpy()[live]
            X = np.linalg.solve(mass.numpy()[live], np.concatenate([J.transpose(0, 2, 1), tau[live][..., None]], -1))
            lam_inv = J @ X[..., :6] + damping * np.eye(6)
            out[live] = np.linalg.solve(lam_inv, J @ X[..., 6:])[..., 0]
        return torch.from_numpy(out)
    L = torch.linalg.cholesky(mass)
    binv_jt = torch.cholesky_solve(jac.transpose(-1, -2), L)  # (B, 7, 6)
    lam_inv = jac @ binv_jt + damping * torch.eye(6, dtype=jac.dtype, device=jac.device)
    binv_tau = torch.cholesky_solve(tau_ext.unsqueeze(-1), L)
    return torch.linalg.solve(lam_inv, jac @ binv_tau).squeeze(-1)


@dataclass
class _StepInputs:
    """One step's inputs after the checks of `A3CQPController._prepare`: float64, numpy views on the CPU path."""

    q: Array
    qd: Array
    mass: Array
    bias: Array
    weights: Array
    f_d: Array
    pos_d: Array
    rot_d: Array
    f_ext: Array
    in_contact: Array
    kin: Kinematics | None
    valid: Array
    """Bool [N]: every input of the robot is finite."""
    all_valid: bool
    xp: Any
    """numpy or torch: the kind of the arrays above."""
    leak_extra: Array | None = None
    """Extra per-axis relaxation rate of q*, q̇* [N, 6] (1/s), or None (`A3CQPController.step`)."""
    f_ext_limits: Array | None = None
    """Bool [N]: the robots whose joint-limit rows count the measured f_ext, or None (`A3CQPController.step`)."""


_INPUT_NAMES = ("q", "qd", "mass", "bias", "weights", "f_d", "pos_d", "rot_d", "f_ext")
"""`A3CQPController.step`'s array inputs checked by `_prepare`, in `_StepInputs`' field order."""
_INPUT_SHAPES = ((7,), (7,), (7, 7), (7,), (6, 3), (6,), (3,), (3, 3), (6,))
"""Their per-robot shapes."""
_WEIGHTS = _INPUT_NAMES.index("weights")
_ROT_D = _INPUT_NAMES.index("rot_d")
W_MAX = 1e6
"""The largest task weight `step` takes. Up to 1e6 the C and Python routes agree to 5e-7 N m on random inputs; at 1e9
the QP runs out of iterations (a fallback, said so); at 1e12 it reported SOLVED with torques 40 N m apart and
accelerations of 1e8 rad/s² (2026-12-01). The A3CQP weights lie in [0, 1] (eq. 28)."""
ROT_TOL = 1e-5
"""Largest |R_dᵀ R_d − I| entry a reference rotation may have (a float32 rotation's round-off is ~1e-7)."""


RELAX_L1 = 1e4
"""Linear penalty of the least-violation QP's joint-row slacks (ControllerOptions.qp_failure), per rad/s²: an exact
penalty, so the rows give way only where no x meets them, as long as no task's multiplier on them exceeds it."""
RELAX_L2 = 1.0
"""Its quadratic penalty on the slacks, per (rad/s²)²: keeps the slacks' block of the Hessian positive definite; small
beside RELAX_L1, so that the sum of the violations is the least an LP finds (at 1e2 it was 7 % above it under a
300-N pull; tests/test_control_least_violation.py)."""


def _f_ext_limits(mask: Array | None, n: int) -> np.ndarray:
    """The C input `f_ext_limits` [N] (1.0 where the robot's joint-limit rows count f_ext) from step's mask."""
    return np.zeros(n) if mask is None else np.asarray(mask, dtype=np.float64)


SUBSET_MIN_IDLE = 12
"""`A3CQPController.step`'s `active`: from this many inactive robots on, the C route computes only the active ones."""


def _spread(n: int, rows: np.ndarray, a: np.ndarray) -> np.ndarray:
    """[n, ...] zeros with `a` in `rows`."""
    out = np.zeros((n, *a.shape[1:]), dtype=a.dtype)
    out[rows] = a
    return out


def _np(t: torch.Tensor) -> np.ndarray:
    """numpy view of a CPU tensor (no copy)."""
    return (t.detach() if t.requires_grad else t).numpy()


def _torque_law(x, q, qd, mass, bias, jac, pd, q_des, qd_des, dt: float, cv: float, cp: float):  # noqa: ANN001, ANN202
    """Eq. 4-7 for a batch of numpy arrays or torch tensors (operators only: the same code runs on both).

    From x = (q̈*, f) [N, 13]: q̇* ← q̇* + Δt q̈* (eq. 6), q* ← q* + Δt q̇* + Δt²/2 q̈* (eq. 7),
    q̈_pd = P W1 J (c_v (q̇* − q̇) + c_p (q* − q)) (eq. 5, P W1 J = `pd`), τ = B (q̈* + q̈_pd) + Jᵀ f + h + g (eq. 4).
    Returns (τ, q̈*, f, q̈_pd, q*, q̇*), τ [N m] not yet clipped.
    """
    qdd, f = x[:, :N_QDD], x[:, N_QDD:]
    qd_new = qd_des + dt * qdd
    q_new = q_des + dt * qd_des + (0.5 * dt * dt) * qdd
    qdd_pd = (pd @ (cv * (qd_new - qd) + cp * (q_new - q))[..., None])[..., 0]
    tau = (mass @ (qdd + qdd_pd)[..., None])[..., 0] + (jac.mT @ f[..., None])[..., 0] + bias
    return tau, qdd, f, qdd_pd, q_new, qd_new


def _finish(xp, tau, qdd, f, qdd_pd, q_des, qd_des, saturated_limit):  # noqa: ANN001, ANN202
    """Clip τ to ±τ_max (NaN → 0). xp = numpy or torch. Returns (τ clipped, q̈*, f, q̈_pd, q*, q̇*, saturated [N])."""
    saturated = (xp.abs(tau) > saturated_limit).any(-1)
    tau = tau.clip(-saturated_limit, saturated_limit)  # (the .clip methods: np.clip costs ~3 µs more)
    tau[tau != tau] = 0.0  # NaN -> 0 (cheaper than nan_to_num in numpy)
    return tau, qdd, f, qdd_pd, q_des, qd_des, saturated


def _relax_min_w1(xp, q_des, qd_des, q, qd, weights, leak: float):  # noqa: ANN001, ANN202
    """q*, q̇* toward (q, q̇) at rate leak × (1 − min_i w1_i) for every joint (ControllerOptions.leak_axes "min_w1")."""
    w1_min = xp.amin(weights[..., 0], -1).clip(0.0, 1.0)
    rate = (leak * (1.0 - w1_min)).clip(0.0, 1.0)[:, None]
    return q_des - rate * (q_des - q), qd_des - rate * (qd_des - qd)


def _relax_per_axis(q_des, qd_des, q, qd, weights, f_d_local, J, jpinv, D, leak: float,  # noqa: ANN001, ANN202
                    dt: float, extra):  # noqa: ANN001
    """q*, q̇* toward (q, q̇) per local axis (ControllerOptions.leak_axes "per_axis"): the task-space part of q* − q
    at rate leak × (w2 + w3 · min(1, f_d / 1 N)) + Δt × extra along each axis of L (clipped to [0, 1] per control
    period; leak = Δt × desired_state_leak, extra [N, 6] in 1/s or None), the null-space part at rate leak."""
    r = leak * (weights[..., 1] + weights[..., 2] * f_d_local.clip(0.0, 1.0))  # [N, 6]
    if extra is not None:  # one relaxation at the summed rate (the caller's extra rate, e.g. an idle share's)
        r = r + dt * extra
    r = r.clip(0.0, 1.0)
    full = min(leak, 1.0)
    out = []
    for des, meas in ((q_des, q), (qd_des, qd)):
        d = des - meas
        dx = mv(J, d)  # the task-space part, world frame [N, 6]
        back = mv(D, r * mv(D.mT, dx))  # scaled per axis of L (eq. 3), back to the world
        task = mv(jpinv, dx)
        out.append(des - mv(jpinv, back) - full * (d - task))
    return out[0], out[1]


def _kin_numpy(kin: Kinematics) -> Kinematics:
    """The same kinematics as numpy views (the controller's CPU path)."""
    return Kinematics(pos=_np(kin.pos), rot=_np(kin.rot), jac=_np(kin.jac), jdot_qdot=_np(kin.jdot_qdot),
                      twist=_np(kin.twist))


def _model_kinematics(model: PandaModel, q: Array, qd: Array) -> Kinematics:
    """One pass of `model.kinematics` at (q, q̇), returned in the kind of q (numpy arrays or tensors)."""
    if isinstance(q, np.ndarray):
        return _kin_numpy(model.kinematics(torch.from_numpy(q), torch.from_numpy(qd)))
    return model.kinematics(q, qd)


class A3CQPController:
    """Batched A3CQP QP controller for N Panda arms (paper 000, eq. 1-24), float64, one step per call.

    Per robot and step the inputs are the measured state (q, q̇), MuJoCo's B(q) and h + g, the per-axis local task
    weights w^𝓛 [6, 3] (columns IK, AC, FC), the local desired contact wrench f_d^𝓛 [6], the Cartesian reference
    (position, rotation) and the measured external wrench f_ext at the control site.

    On CPU the default composition (these tasks and limits, float64, one level) runs as a C translation of the
    objects (control/native, `ControllerOptions.backend`); any other composition runs the objects themselves.

    Strict priorities (paper 002, eq. 2-3): `levels` puts each task in level 1..3 (1 highest) or off (None); soft
    weights act inside a level, and each level is solved in the optimal set of the levels above (hierarchy.py).

    Args:
        n: number of robots N.
        model: kinematics (default PandaModel() with the peg tool).
        config: Table I gains and the wrench box (a3cqp_rl.config.ControllerConfig).
        options: the choices the paper leaves open (ControllerOptions).
        limits: joint limits (datasheet).
        tasks, extra_limits: replace the default tasks / append limits (mink-style composition).
        levels: strict priority of each task: {task name: 1..3 or None (off)} naming every task (default names
            "ik", "ac", "fc", "jc", "cartesian_regularizer"), or a list in the order of `tasks`; default None, every
            task in level 1 (the single weighted QP of eq. 1). See `Hierarchy`, `hierarchy.level_from_selector`.
    """

    def __init__(self, n: int = 1, model: PandaModel | None = None, config: ControllerConfig | None = None,
                 options: ControllerOptions | None = None, limits: PandaLimits = PANDA_LIMITS,
                 tasks: list[Task] | None = None, extra_limits: list[Limit] | None = None,
                 levels: Mapping[str, int | None] | Sequence[int | None] | None = None) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ControlShapeError(f"n (the number of robots) must be an integer >= 1, got {n!r}")
        self.n = int(n)
        self.model = model or PandaModel()
        self.config = config or ControllerConfig()
        self.options = options or ControllerOptions()
        cfg, opt = self.config, self.options
        self.dt = 1.0 / cfg.rate_hz
        if not (cfg.cp >= 0 and cfg.cv >= 0 and opt.brake_gain >= 0 and opt.regularization > 0):
            raise InvalidGainError(f"need cp, cv, brake_gain >= 0 and regularization > 0; got {cfg.cp}, {cfg.cv}, "
                                   f"{opt.brake_gain}, {opt.regularization}")
        self.tasks: list[Task] = tasks if tasks is not None else [
            CartesianIK(cfg.kp, cfg.k_theta),
            Admittance(cfg.lambda_d, cfg.c_d, form=opt.admittance_form),
            ForceControl(),
            JointCentering(torch.tensor(opt.q_center, dtype=torch.float64), cfg.kq, cfg.epsilon,
                           opt.jc_nullspace_weight),
        ]
        if tasks is None and opt.cartesian_regularization > 0:
            self.tasks.append(CartesianAccelerationRegularizer(opt.cartesian_regularization))
        names = [t.name for t in self.tasks]
        twice = sorted({x for x in names if names.count(x) > 1})
        if twice:  # residuals are kept by name: a second task of a name would silently replace or drop the first
            raise ValueError(f"task names must differ, got {twice} more than once in {names}; give each task its own "
                             "`name` attribute")
        lim = limits.tensors()
        self.tau_max = lim["tau_max"]
        self._tau_max_np = self.tau_max.to(torch.float64).numpy()
        self.joint_limits = JointLimitsViability(lim["q_min"], lim["q_max"], lim["dq_max"], lim["ddq_max"], self.dt,
                                                 q_margin=opt.q_margin, dq_margin=opt.dq_margin,
                                                 horizon_steps=opt.limit_horizon_steps, target=opt.joint_limit_target,
                                                 include_f_ext=opt.joint_limits_include_f_ext,
                                                 brake_gain=opt.brake_gain, tau_max=lim["tau_max"],
                                                 stop_share=opt.viability_stop_share)
        self.limits: list[Limit] = [self.joint_limits, WrenchBox(cfg.force_limit, cfg.torque_limit),
                                    FrictionPyramid(cfg.mu)]
        if opt.torque_limits:
            # anchored to the viable brake: torque limits give way before joint-limit safety (always feasible QP)
            self.limits.append(TorqueLimits(lim["tau_max"], safe=self.joint_limits))
        self.limits += list(extra_limits or [])
        self.f_d_max = getattr(cfg, "f_d_max", 20.0)
        self._q_center = torch.tensor(opt.q_center, dtype=torch.float64)  # stand-in for a non-finite first state
        self.q_des: torch.Tensor | None = None  # q*, eq. 7 [N, 7]
        self.qd_des: torch.Tensor | None = None  # q̇*, eq. 6 [N, 7]
        self._warm: QPSolution | None = None
        self._warm_levels: tuple[QPSolution, ...] = ()  # each level's solution of the last step (strict hierarchy)
        self._const: dict[tuple, dict[str, Array]] = {}
        # numpy steps need every task and limit to accept numpy contexts (a user's torch-only one keeps torch)
        self._numpy_ok = all(getattr(p, "numpy_capable", False) for p in [*self.tasks, *self.limits])
        self._input_shapes = tuple((n, *shape) for shape in _INPUT_SHAPES)
        self.residuals: dict[str, Residual] = {}
        """Task residuals of the last step, by task name (their b are the references f_adm, f_ctc, ...); numpy arrays
        when the step ran on the CPU path (see arrays.py); empty after a native step (ControlOutput has f_adm, f_ctc)."""
        self.fallback_count = 0
        """Number of (robot, step) pairs that used the fallback since construction."""
        self.relaxed_count = 0
        """Number of (robot, step) pairs that used the least-violation QP since construction."""
        self._fallback_steps = 0  # steps with a fallback: the log shows the first ones, then every FALLBACK_LOG_EVERY
        self._native: native.NativeStep | None = None
        if opt.leak_axes not in ("per_axis", "min_w1"):
            raise InvalidGainError(f"leak_axes must be 'per_axis' or 'min_w1', got {opt.leak_axes!r}")
        if opt.wrench_blend not in ("normalized", "weighted_sum"):
            raise InvalidGainError(f"wrench_blend must be 'normalized' or 'weighted_sum', got {opt.wrench_blend!r}")
        if opt.qp_failure not in ("least_violation", "brake"):
            raise InvalidGainError(f"qp_failure must be 'least_violation' or 'brake', got {opt.qp_failure!r}")
        if opt.backend not in ("auto", "python", "native"):
            raise InvalidGainError(f"backend must be 'auto', 'python' or 'native', got {opt.backend!r}")
        if opt.backend != "python":
            self._native, why = self._make_native_step()
            if self._native is None and opt.backend == "native":
                raise InvalidGainError(f"backend='native' is not available: {why}")
        # the composition the native step was made for (a task or limit swapped in later turns it off)
        self._native_for = (tuple(map(id, self.tasks)), tuple(map(id, self.limits)))
        self.hierarchy = Hierarchy(levels=((),))
        self.set_levels(levels)

    def set_levels(self, levels: Mapping[str, int | None] | Sequence[int | None] | None) -> None:
        """Put each task in a strict level 1..3 or off (None); None: every task in level 1 (see `__init__`)."""
        hierarchy = Hierarchy.of([t.name for t in self.tasks], levels)
        if not hierarchy.is_flat and self.options.wrench_blend == "weighted_sum":
            raise InvalidGainError("wrench_blend='weighted_sum' weighs IK against AC and FC in one level; "
                                   f"it has no meaning with strict levels ({hierarchy})")
        if not hierarchy.is_flat and self.options.backend == "native":
            raise InvalidGainError(f"backend='native' translates one level with every task active, not {hierarchy}")
        self.hierarchy = hierarchy
        self._warm, self._warm_levels = None, ()

    def _make_native_step(self) -> tuple[native.NativeStep | None, str]:
        """The C step for this composition, or (None, why)."""
        fields, why = self._native_fields()
        if fields is None:
            return None, why
        lib = native.load()
        if lib is None:
            return None, "the C library is not available (see the warning above)"
        return native.NativeStep(lib, fields), ""

    def _native_fields(self, tasks: list[Task] | None = None) -> tuple[dict | None, str]:
        """The C step's parameters: each task (of `tasks`, default this controller's) and limit hands its own, the
        step-level ones come from here."""
        cfg, opt = self.config, self.options
        step_fields = {"dt": self.dt, "cv": cfg.cv, "cp": cfg.cp, "f_d_max": self.f_d_max,
                       "wrench_ff": float(opt.ik_wrench_feedforward), "pd_pinv": float(opt.pd_projection == "pinv"),
                       "reg": opt.regularization, "pinv_damping": opt.pinv_damping,
                       "nullspace_damping": opt.nullspace_damping, "tau_clip": self.tau_max.numpy(),
                       "leak": self.dt * opt.desired_state_leak, "leak_per_axis": float(opt.leak_axes == "per_axis"),
                       "wrench_sum": float(opt.wrench_blend == "weighted_sum")}
        return native.compose_params([(type(t).__name__, t.c_params()) for t in (self.tasks if tasks is None else tasks)],
                                     [(type(x).__name__, x.c_params()) for x in self.limits], step_fields)

    # ------------------------------------------------------------------ state
    def reset(self, q: torch.Tensor, qd: torch.Tensor | None = None, idx: torch.Tensor | list[int] | None = None) -> None:
        """Set the integrated references q*, q̇* to the measured state (all robots, or rows `idx`)."""
        q = torch.as_tensor(q, dtype=torch.float64)
        qd = torch.zeros_like(q) if qd is None else torch.as_tensor(qd, dtype=torch.float64)
        rows = self.n if self.q_des is None or idx is None else len(torch.as_tensor(idx).reshape(-1))
        for name, v in (("q", q), ("qd", qd)):
            if tuple(v.shape) != (rows, N_QDD) and not (rows == 1 and tuple(v.shape) == (N_QDD,)):
                raise ControlShapeError(f"reset: {name} must have shape ({rows}, {N_QDD}) (rad{'' if name == 'q' else '/s'}),"
                                        f" got {tuple(v.shape)}")
        if self.q_des is None or idx is None:
            self.q_des, self.qd_des = q.clone().reshape(self.n, N_QDD), qd.clone().reshape(self.n, N_QDD)
            self._warm, self._warm_levels = None, ()
        else:
            self.q_des[idx], self.qd_des[idx] = q, qd

    # ------------------------------------------------------------------ pieces
    def _check(self, name: str, t: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
        if not isinstance(t, torch.Tensor):
            t = torch.as_tensor(t)
        if t.shape != shape:
            raise ControlShapeError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
        return t if t.dtype == torch.float64 else t.to(dtype=torch.float64)

    def build_context(self, q: Array, qd: Array, mass: Array, weights: Array, f_d: Array, pos_d: Array,
                      rot_d: Array, f_ext: Array, in_contact: Array, bias: Array | None = None,
                      kin: Kinematics | None = None, f_ext_limits: Array | None = None) -> ControlContext:
        """All per-step matrices the tasks and limits need (one kinematics pass, one factorisation of B).

        Takes torch tensors, or numpy arrays (the CPU path of `step`); the context holds the same kind.
        `kin`: the control site's kinematics when the caller already has them (e.g. PandaSim's `SimState.kin`,
        from MuJoCo's own step); default one pass of `self.model.kinematics(q, qd)`.
        """
        opt, cfg, dt = self.options, self.config, self.dt
        if kin is None:
            kin = _model_kinematics(self.model, q, qd)
        c = self._constants(q)
        J = kin.jac
        Jt = J.mT
        binv_jt = solve_spd(mass, Jt)  # B⁻¹Jᵀ (B, 7, 6)
        lam_inv = mm(J, binv_jt) + c["pinv_damping"]  # J B⁻¹ Jᵀ + λ² I
        lam = inv(lam_inv)  # Λ, eq. 12
        lam = 0.5 * (lam + lam.mT)
        D = block_rotation(kin.rot)  # eq. 3
        # eq. 8 for the three weights at once: W_i = D diag(w_i) Dᵀ, (B, 3, 6, 6)
        W = weights_to_world(D[:, None], weights.mT)
        W1 = W[:, 0]
        jpinv = mm(Jt, inv(mm(J, Jt) + c["nullspace_damping"]))  # J⁺ (B, 7, 6)
        W1J = mm(W1, J)
        pd = mm(jpinv if opt.pd_projection == "pinv" else Jt, W1J)  # Jᵀ W1 J (eq. 5) or J⁺ W1 J
        # q̈_pd with q̈* = 0 (eq. 5-7): q* − q = q*_prev + Δt q̇*_prev − q, q̇* − q̇ = q̇*_prev − q̇
        q_des, qd_des = const(self.q_des, q), const(self.qd_des, q)
        err = cfg.cv * (qd_des - qd) + cfg.cp * (q_des + dt * qd_des - q)
        pd_qdd_gain = (cfg.cv * dt + cfg.cp * dt * dt / 2) * pd
        return ControlContext(
            q=q, qd=qd, kin=kin, mass=mass, mass_inv_jt=binv_jt, cart_inertia=lam, cart_inertia_inv=lam_inv,
            D=D, weights_local=weights, W1=W1, W2=W[:, 1], W3=W[:, 2],
            pose_error=pose_error(pos_d, rot_d, kin.pos, kin.rot), f_ext=f_ext,
            f_d_local=f_d.clip(0.0, self.f_d_max), in_contact=in_contact,
            qdd_pd0=mv(pd, err), pd_qdd_gain=pd_qdd_gain, nullspace=c["eye7"] - mm(jpinv, J),
            pd_matrix=pd, dt=dt, bias=bias, qdd_map=c["eye7"] + pd_qdd_gain, jt_w1_j=mm(Jt, W1J), jpinv=jpinv,
            f_ext_limits=f_ext_limits)

    def _constants(self, like: Array) -> dict[str, Array]:
        """Per-step constants (identities, damping terms, zero blocks), made once per array kind: read-only."""
        key = ("numpy",) if isinstance(like, np.ndarray) else (like.dtype, like.device)
        if key not in self._const:
            opt, f64 = self.options, torch.float64
            eye6 = torch.eye(6, dtype=f64)
            made = {"eye7": torch.eye(N_QDD, dtype=f64), "pinv_damping": opt.pinv_damping * eye6,
                    "nullspace_damping": opt.nullspace_damping * eye6,
                    "P0": opt.regularization * torch.eye(N_VARS, dtype=f64), "tau_max": self.tau_max.to(f64),
                    "zeros_qf": torch.zeros(self.n, N_QDD, N_VARS - N_QDD, dtype=f64),
                    "zeros_fq": torch.zeros(self.n, N_VARS - N_QDD, N_QDD, dtype=f64)}
            self._const[key] = {k: const(v, like) for k, v in made.items()}
        return self._const[key]

    def wrench_feedforward(self, ctx: ControlContext, residuals: dict[str, Residual] | None = None) -> Array:
        """Unconstrained optimum of the wrench sub-problem (eq. 24b): (W2 + W3 + r I)⁻¹(W2 f_adm + W3 f_ctc) [B, 6].

        With W_i = D diag(w_i) Dᵀ (eq. 8) the inverse is D diag(1 / (w2 + w3 + r)) Dᵀ, computed per local axis;
        wrench_blend "weighted_sum" adds W1 (IK's zero-wrench reference) to the inverted sum.
        """
        if residuals is None:
            residuals = {t.name: t.residual(ctx) for t in self.tasks if isinstance(t, (Admittance, ForceControl))}
        refs = [(res.b, k) for task_type, k in ((Admittance, 1), (ForceControl, 2)) for t in self.tasks
                if isinstance(t, task_type) and (res := residuals.get(t.name)) is not None]
        if not refs:
            return zeros((ctx.batch, 6), ctx.q)
        # local frame: f^𝓛 = Dᵀ f, all references in one product
        local = mm(cat([b[:, None] for b, _ in refs], 1), ctx.D).mT  # (B, 6, R)
        cols = [k for _, k in refs]
        w = ctx.weights_local[..., 1:3] if cols == [1, 2] else ctx.weights_local[..., cols]  # (B, 6, R)
        num = (w * local).sum(-1)
        den = w.sum(-1) + self.options.regularization
        if self.options.wrench_blend == "weighted_sum":  # IK's zero-wrench reference (ControllerOptions)
            den = den + ctx.weights_local[..., 0]
        return mv(ctx.D, num / den)

    def _ik_wrench(self, ctx: ControlContext) -> Residual:
        """‖f‖² weighted by W1 (ControllerOptions.wrench_blend "weighted_sum"): along the axes IK leads, no wrench."""
        return Residual(A=None, b=zeros((ctx.batch, 6), ctx.q), W=ctx.W1, col=N_QDD)

    def task_residuals(self, ctx: ControlContext) -> dict[str, Residual]:
        """Residuals of the active tasks by name (kept in `self.residuals`; their b are the references f_adm, ...).

        The wrench tasks are evaluated first so that IK can feed their wrench forward (ik_wrench_feedforward)."""
        active = self.tasks if self.hierarchy.is_flat else [t for t in self.tasks if t.name in self.hierarchy.active]
        residuals = {t.name: t.residual(ctx) for t in active if isinstance(t, (Admittance, ForceControl))}
        if self.options.ik_wrench_feedforward and residuals:
            f_ff = self.wrench_feedforward(ctx, residuals) * (~ctx.in_contact)[:, None]
            ctx = dataclasses.replace(ctx, wrench_feedforward=f_ff)
        for task in active:
            if task.name not in residuals:
                residuals[task.name] = task.residual(ctx)
        if self.options.wrench_blend == "weighted_sum" and any(isinstance(t, (Admittance, ForceControl))
                                                                for t in active):
            residuals["ik_wrench"] = self._ik_wrench(ctx)
        self.residuals = residuals
        return residuals

    def task_cost(self, ctx: ControlContext, residuals: list[Residual]) -> tuple[Array, Array]:
        """(P [B, 13, 13], c [B, 13]) of Σ ‖A_i x − b_i‖²_{W_i} + r‖x‖² over `residuals` (halved, eq. 1, 24)."""
        # residuals sharing the same rows A (e.g. IK and the Cartesian regularizer on J) are merged first:
        # Σ Aᵀ W_i (A x − b_i) = Aᵀ (Σ W_i) A x − Aᵀ Σ W_i b_i, one pair of products per distinct A
        groups: dict[tuple[int, int], list[Residual]] = {}
        for res in residuals:
            groups.setdefault((id(res.A), res.col), []).append(res)
        # blocks of P on the diagonal, summed per block (col, size); assembled once below
        blocks: dict[tuple[int, int], list[Array]] = {}
        for members in groups.values():
            first = members[0]
            W = functools.reduce(operator.add, [r.W for r in members])
            Wb = functools.reduce(operator.add, [mv(r.W, r.b) for r in members])
            if first.A is None:
                H, g = W, -Wb
            else:
                At = first.A.mT
                H, g = mm(At, mm(W, first.A)), -mv(At, Wb)
            blk = blocks.setdefault((first.col, first.size), [H, g])
            if blk[0] is not H:
                blk[0], blk[1] = blk[0] + H, blk[1] + g
        return self._assemble(ctx, blocks)

    def limit_rows(self, ctx: ControlContext) -> tuple[Array, Array]:
        """The limits stacked: (G [B, m, 13], h [B, m])."""
        rows: list[Inequality] = [lim.rows(ctx) for lim in self.limits]
        return cat([r.G for r in rows], 1), cat([r.h for r in rows], 1)

    def build_qp(self, ctx: ControlContext) -> tuple[Array, Array, Array, Array]:
        """Stack the active task costs and limit rows: (P [B, 13, 13], c [B, 13], G [B, m, 13], h [B, m]) (eq. 1, 24).

        This is the QP of one level: with a strict hierarchy it merges the levels (soft priorities only); the
        cascade uses `build_levels`."""
        residuals = self.task_residuals(ctx)
        P, c = self.task_cost(ctx, list(residuals.values()))
        return P, c, *self.limit_rows(ctx)

    def build_levels(self, ctx: ControlContext) -> tuple[list[tuple[Array, Array]], Array, Array]:
        """Each level's cost (P_k, c_k), highest priority first, and the limit rows (G, h) (paper 002, eq. 2)."""
        residuals = self.task_residuals(ctx)
        costs = [self.task_cost(ctx, [residuals[name] for name in level]) for level in self.hierarchy.levels]
        return costs, *self.limit_rows(ctx)

    def _assemble(self, ctx: ControlContext, blocks: dict[tuple[int, int], list[Array]]) -> tuple[Array, Array]:
        """P = r I + Σ blocks (symmetrised), c = Σ blocks, on x = (q̈, f)."""
        B, like = ctx.batch, ctx.q
        k = self._constants(like)
        qq, ff = blocks.get((0, N_QDD)), blocks.get((N_QDD, N_VARS - N_QDD))
        if qq is not None and ff is not None and len(blocks) == 2 and B == self.n:
            # the usual case (the default tasks): block-diagonal, built with cats instead of zeros + slice adds
            H = cat([cat([qq[0], k["zeros_qf"]], 2), cat([k["zeros_fq"], ff[0]], 2)], 1)
            P, c = H + k["P0"], cat([qq[1], ff[1]], 1)
        else:
            P, c = k["P0"] + zeros((B, N_VARS, N_VARS), like), zeros((B, N_VARS), like)
            for (col, size), (H, g) in blocks.items():
                P[:, col:col + size, col:col + size] += H
                c[:, col:col + size] += g
        return 0.5 * (P + P.mT), c

    def _solve(self, P: torch.Tensor, c: torch.Tensor, G: torch.Tensor, h: torch.Tensor,
               rows: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """solve_qp warm-started from the last step: (x [N, 13], status [N], iterations [N]); never raises. `rows`:
        the QPs are those of these robots only (the others' warm starts are kept)."""
        n = self.n
        warm = self._warm if self._warm is not None and self._warm.z_shape == (n, G.shape[1]) else None
        try:
            sol = solve_qp(P, c, G=G, h=h, warm_start=warm if rows is None or warm is None else warm.take(rows),
                           max_iter=self.options.qp_max_iter, hand_on=self.options.qp_hand_on)
            if rows is None:
                self._warm = sol
            else:  # the other robots' warm starts stay (cold where none was kept)
                self._warm = (warm if warm is not None else QPSolution.zeros_like(sol, n)).put(rows, sol)
            return sol.x, sol.status, sol.iterations
        except Exception:  # a solver bug must not take the arms down: brake every robot and say so loudly
            return self._solver_raised(P)

    def _solve_levels(self, costs: list[tuple[torch.Tensor, torch.Tensor]], G: torch.Tensor,
                      h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The cascade of `solve_cascade`, each level warm-started from the last step; as `_solve`, never raises.

        A robot whose QP fails at any level gets that status (and the fallback brake in `_apply`)."""
        try:
            sol = solve_cascade(costs, G, h, self.options.regularization, warm=self._warm_levels,
                                max_iter=self.options.qp_max_iter, hand_on=self.options.qp_hand_on)
            self._warm_levels = sol.solutions
            return sol.x, sol.status, sol.iterations
        except Exception:
            return self._solver_raised(G)

    def _solver_raised(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What `_solve` returns when solve_qp raised: status SOLVER_ERROR for every robot (all fall back)."""
        n = self.n
        logger.exception("A3CQP: solve_qp raised; every robot of the batch falls back")
        self._warm, self._warm_levels = None, ()
        return (like.new_zeros(n, N_VARS), torch.full((n,), SOLVER_ERROR, dtype=torch.long),
                torch.zeros(n, dtype=torch.long))

    def _relax_failed(self, P: torch.Tensor, c: torch.Tensor, G: torch.Tensor, h: torch.Tensor, x: torch.Tensor,
                      solved: np.ndarray, valid: np.ndarray) -> tuple[torch.Tensor, np.ndarray | None]:
        """x [B, 13] with the least-violation QP's answer where the QP failed on valid inputs, and which robots got
        it (bool [B], None where none did); `ControllerOptions.qp_failure`."""
        failed = np.flatnonzero(valid & ~(solved & torch.isfinite(x).all(-1).cpu().numpy()))
        if (len(failed) == 0 or self.options.qp_failure != "least_violation"
                or self.limits[0] is not self.joint_limits):  # (the joint rows must be G's first)
            return x, None
        xr, ok = self.least_violation(P[failed], c[failed], G[failed], h[failed])
        if not ok.any():
            return x, None
        x = x.clone()
        x[failed[ok]] = xr[ok].to(x.device)
        relaxed = np.zeros(len(x), dtype=bool)
        relaxed[failed[ok]] = True
        self.relaxed_count += int(ok.sum())
        return x, relaxed

    @staticmethod
    def _forget_relaxed(q_des: np.ndarray, qd_des: np.ndarray, relaxed: np.ndarray, q: np.ndarray,
                        qd: np.ndarray) -> None:
        """q*, q̇* [B, 7] set in place to the measured q, q̇ where the step was relaxed, as the brake sets them.

        The relaxed q̈* gave the torque of this period only: integrated into q*, q̇* (eq. 6-7), an acceleration the
        joint rows did not bound would drive the arm after it through the PD in the next periods. On the peg it did:
        with the references kept, IK + FC's arms swung up to 1 rad in their null space onto a joint limit while the
        operator pulled, and the QP stayed infeasible for seconds (docs/panda.md, "A least-violation step ...")."""
        q_des[relaxed], qd_des[relaxed] = q[relaxed], qd[relaxed]

    def least_violation(self, P: torch.Tensor, c: torch.Tensor, G: torch.Tensor, h: torch.Tensor
                        ) -> tuple[torch.Tensor, np.ndarray]:
        """The QPs (P, c, G, h) of `build_qp` with the joint-limit rows soft: (x [B, 13], solved bool [B]).

        min ½xᵀPx + cᵀx + RELAX_L1 Σs + ½ RELAX_L2 Σs² s.t. G_soft x − s ≤ h_soft, G_rest x ≤ h_rest, s ≥ 0, with
        the soft rows `JointLimitsViability.soft_rows`. The other rows are met by x = (the viable brake, f = 0)
        (TorqueLimits is anchored to it), so this QP always has a solution; solved cold (its size differs from the
        step's)."""
        B, nv = c.shape
        soft = self.joint_limits.soft_rows
        mj = soft.stop - soft.start
        eye = torch.eye(mj, dtype=P.dtype, device=P.device).expand(B, mj, mj)
        Pz = P.new_zeros(B, nv + mj, nv + mj)
        Pz[:, :nv, :nv] = P
        Pz[:, nv:, nv:] = RELAX_L2 * eye
        Gz = P.new_zeros(B, G.shape[1], nv + mj)
        Gz[:, :, :nv] = G
        Gz[:, soft, nv:] = -eye
        cz = torch.cat([c, c.new_full((B, mj), RELAX_L1)], 1)
        lb = torch.cat([c.new_full((nv,), -torch.inf), c.new_zeros(mj)])
        try:
            sol = solve_qp(Pz, cz, G=Gz, h=h, lb=lb, max_iter=self.options.qp_max_iter,
                           hand_on=self.options.qp_hand_on)
        except Exception:  # as `_solve`: a solver bug brakes these robots instead of taking the batch down
            logger.exception("A3CQP: the least-violation QP raised; its robots fall back to the brake")
            return c.new_zeros(B, nv), np.zeros(B, dtype=bool)
        xr = sol.x[:, :nv]
        return xr, ((sol.status == 0) & torch.isfinite(xr).all(-1)).cpu().numpy()

    def _report_fallback(self, ok: Array, qp_status: torch.Tensor, valid: Array) -> None:
        """Count and log the robots that fell back this step (and start their next QP cold)."""
        bad = [i for i in range(self.n) if not bool(ok[i])]
        self.fallback_count += len(bad)
        self._fallback_steps += 1
        k = self._fallback_steps
        if k <= FALLBACK_LOG_FIRST or k % FALLBACK_LOG_EVERY == 0:  # a scene that falls back often fills no log
            names = _status_names(qp_status[bad])
            why = (" (no command meets the joint-limit, torque and wrench rows together this period: the arm brakes "
                   "instead, safely; docs/panda.md, \"Joints in contact\")") if "PRIMAL_INFEASIBLE" in names else ""
            logger.warning("A3CQP fallback (brake + gravity compensation) for robots %s: QP status %s%s, valid input %s"
                           " (step %d with a fallback, %d robot-steps in all%s)", bad, names, why,
                           [bool(valid[i]) for i in bad], k, self.fallback_count,
                           f"; now logged every {FALLBACK_LOG_EVERY}th" if k == FALLBACK_LOG_FIRST else "")
        # a failed instance's multipliers are no working set to start from; the others' still are
        for sol in (self._warm, *self._warm_levels):
            if sol is not None:
                sol.forget(bad)

    # ------------------------------------------------------------------ step
    @torch.no_grad()
    def step(self, q: torch.Tensor, qd: torch.Tensor, mass: torch.Tensor, bias: torch.Tensor, weights: torch.Tensor,
             f_d: torch.Tensor, pos_d: torch.Tensor, rot_d: torch.Tensor, f_ext: torch.Tensor | None = None,
             in_contact: torch.Tensor | None = None, f_env: torch.Tensor | None = None,
             kin: Kinematics | None = None, leak_extra: torch.Tensor | None = None,
             f_ext_limits: torch.Tensor | None = None, active: torch.Tensor | None = None) -> ControlOutput:
        """One 1 kHz control step for N robots: QP (eq. 24) then computed torque (eq. 4-7).

        Args:
            q, qd: measured joint positions/velocities [N, 7] (rad, rad/s).
            mass: B(q) [N, 7, 7]; bias: h + g [N, 7] (N m) (MuJoCo qM, qfrc_bias).
            weights: local per-axis task weights w^𝓛 [N, 6, 3], columns (w1 IK, w2 AC, w3 FC) (eq. 8, 28), in
                [0, W_MAX]; a robot with one outside (or NaN) gets the fallback, status INVALID_INPUT.
            f_d: local desired contact wrench f_d^𝓛 [N, 6] (N, N m), clipped to [0, f̄_d] (eq. 21).
            pos_d, rot_d: Cartesian reference of the control site [N, 3] (m), [N, 3, 3]; a robot whose rot_d is no
                rotation (|R_dᵀR_d − I| > ROT_TOL, or det < 0) gets the fallback, status INVALID_INPUT.
            f_ext: measured external wrench at the control site [N, 6], world frame (default 0).
            in_contact: bool [N] activating the friction pyramid; default |f_env force| > threshold, else False.
            f_env: measured environment (F/T) wrench [N, 6], world frame, only used to infer `in_contact` (a
                non-finite row makes that robot's input invalid: the fallback).
            kin: kinematics of the control site at (q, q̇) if the caller has them (PandaSim's `SimState.kin`, from
                MuJoCo's step: same values as `self.model.kinematics` to ~1e-8); default computed by `self.model`.
            leak_extra: an extra relaxation rate of q*, q̇* [N, 6] (1/s, ≥ 0) along each axis of the local frame L,
                added to the per-axis leak's own desired_state_leak × (w2 + w3 · min(1, f_d / 1 N)) in one relaxation
                (`leak_axes` "per_axis" only); default None, none.
            f_ext_limits: bool [N], the robots whose joint-limit rows count the measured f_ext, as
                `ControllerOptions.joint_limits_include_f_ext` does for every robot; default None, none.
            active: bool [N], the robots controlled this step; default None, all. An inactive robot gets
                τ = h + g (gravity and Coriolis compensation, clipped), status 0, no fallback, zeros for the other
                outputs, and keeps q*, q̇* as they were. From `SUBSET_MIN_IDLE` inactive robots on, the C route
                computes only the active ones (a batch whose finished arms wait for the others); the active
                robots' numbers are those of a step of all either way.

        A robot whose inputs are not finite (or whose QP fails) gets the safe fallback: a viable brake with gravity
        compensation, `fallback` True and status INVALID_INPUT (or the QP's status).
        """
        inp = self._prepare(q, qd, mass, bias, weights, f_d, pos_d, rot_d, f_ext, in_contact, f_env, kin)
        if leak_extra is not None:
            inp.leak_extra = self._check_leak_extra(leak_extra, inp.q)
        if f_ext_limits is not None:
            m = torch.as_tensor(f_ext_limits)
            if tuple(m.shape) != (self.n,) or m.dtype != torch.bool:
                raise ControlShapeError(f"f_ext_limits must be a bool tensor of shape ({self.n},), got "
                                        f"{m.dtype} {tuple(m.shape)}")
            inp.f_ext_limits = _np(m) if inp.xp is np else m.to(inp.q.device)
        split = self._active_rows(active)
        native_route = inp.all_valid and inp.xp is np and self._native is not None and self._native_fits() and (
            self._native_for == (tuple(map(id, self.tasks)), tuple(map(id, self.limits))))
        if native_route:
            return self._step_native(inp) if split is None else self._step_native(inp, *split)
        refs = None if split is None else (self.q_des.clone(), self.qd_des.clone())  # the other routes hold after
        if not inp.all_valid:
            inp = self._stand_ins(inp)
        ctx = self.build_context(inp.q, inp.qd, inp.mass, inp.weights, inp.f_d, inp.pos_d, inp.rot_d, inp.f_ext,
                                 inp.in_contact, inp.bias, kin=inp.kin, f_ext_limits=inp.f_ext_limits)
        relaxed = None
        if self.hierarchy.strict:  # paper 002 eq. 2: one QP per level
            costs, G, h = self.build_levels(ctx)
            t = torch.as_tensor
            x, qp_status, iterations = self._solve_levels([(t(P), t(c)) for P, c in costs], t(G), t(h))
        else:
            P, c, G, h = (torch.as_tensor(a) for a in self.build_qp(ctx))
            x, qp_status, iterations = self._solve(P, c, G, h)
            x, relaxed = self._relax_failed(P, c, G, h, x, qp_status.cpu().numpy() == 0,
                                            torch.as_tensor(inp.valid).cpu().numpy())
        out = self._apply(inp, ctx, x, qp_status, iterations, relaxed)
        return out if split is None else self._hold(out, split[1], inp.bias, refs)

    def _active_rows(self, active: torch.Tensor | np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """The indices of `step`'s active and inactive robots, or None where every robot is active (or `active` is
        None)."""
        if active is None:
            return None
        a = active.detach().cpu().numpy() if isinstance(active, torch.Tensor) else np.asarray(active)
        if a.shape != (self.n,) or a.dtype != np.bool_:
            raise ControlShapeError(f"active must be a bool tensor of shape ({self.n},), got {a.dtype} {a.shape}")
        return None if a.all() else (np.flatnonzero(a), np.flatnonzero(~a))

    def _hold(self, out: ControlOutput, idle: np.ndarray, bias: Array, refs: tuple[torch.Tensor, ...]) -> ControlOutput:
        """`out` with the robots `idle` given `step`'s inactive output (τ = h + g clipped, q*, q̇* from `refs`)."""
        fields = {}
        for name in ("tau", "qdd", "wrench", "qdd_pd", "pose_error", "f_adm", "f_ctc", "status", "fallback",
                     "saturated", "iterations", "relaxed"):
            v = getattr(out, name).clone()
            v[idle] = 0
            fields[name] = v
        dev = fields["tau"].device
        tau_max = self.tau_max.to(device=dev, dtype=torch.float64)
        h = torch.as_tensor(bias, dtype=torch.float64, device=dev)[idle].clip(-tau_max, tau_max)
        fields["tau"][idle] = h.nan_to_num(nan=0.0)  # (as `_finish` does: a non-finite reading gives no torque)
        self.q_des[idle], self.qd_des[idle] = refs[0][idle], refs[1][idle]
        return ControlOutput(**fields)

    def _prepare(self, q, qd, mass, bias, weights, f_d, pos_d, rot_d, f_ext, in_contact, f_env,  # noqa: ANN001
                 kin) -> _StepInputs:  # noqa: ANN001
        """Stage 1: shapes, float64, contact flag, per-robot finiteness, first-call references, numpy views on CPU."""
        n = self.n
        if not isinstance(q, torch.Tensor):  # numpy arrays as tensors (the other inputs: `_check`)
            q = torch.as_tensor(q)
        t = [self._check(name, v, shape) for name, v, shape in zip(_INPUT_NAMES, (
            q, qd, mass, bias, weights, f_d, pos_d, rot_d, q.new_zeros(n, 6) if f_ext is None else f_ext),
            self._input_shapes)]
        on_cpu = all(v.is_cpu for v in t)
        if on_cpu:  # (numpy for the finiteness check in any case: ~1 µs per op instead of ~5)
            arrays = [_np(v) for v in t]
            valid = np.isfinite(np.concatenate([a.reshape(n, -1) for a in arrays], axis=1)).all(axis=1)
        else:
            valid = torch.isfinite(torch.cat([v.reshape(n, -1) for v in t], dim=1)).all(-1)
        # a negative weight makes the QP non-convex, and one above W_MAX ill-conditioned: that robot's input is
        # invalid (the fallback), as a NaN's
        w = arrays[_WEIGHTS] if on_cpu else t[_WEIGHTS]
        valid = valid & ((w >= 0.0) & (w <= W_MAX)).reshape(n, -1).all(-1)
        # a rot_d that is no rotation (scaled, sheared, a reflection) makes eq. 3's orientation error meaningless
        r = arrays[_ROT_D] if on_cpu else t[_ROT_D]
        xp = np if on_cpu else torch
        eye = np.eye(3) if on_cpu else torch.eye(3, dtype=r.dtype, device=r.device)
        off = xp.abs(xp.einsum("nji,njk->nik", r, r) - eye)
        valid = valid & (off <= ROT_TOL).reshape(n, -1).all(-1) & (xp.linalg.det(r) > 0.0)
        if in_contact is not None:
            c = in_contact if isinstance(in_contact, (torch.Tensor, np.ndarray)) else np.asarray(in_contact)
            if tuple(c.shape) != (n,) or c.dtype not in (torch.bool, np.bool_):
                raise ControlShapeError(f"in_contact must be a bool tensor of shape ({n},), got {c.dtype} "
                                        f"{tuple(c.shape)}")
        if f_env is not None:
            if tuple(f_env.shape) != (n, 6):
                raise ControlShapeError(f"f_env must have shape ({n}, 6) (N, N m, world), got {tuple(f_env.shape)}")
            # a non-finite F/T reading would read as "no contact": that robot's input is invalid instead
            valid = valid & (np.isfinite(_np(f_env.cpu())).all(1) if on_cpu else torch.isfinite(f_env).all(-1))
        if self.q_des is None:  # first call: q*, q̇* from the measured state, a harmless stand-in where not finite
            ok = torch.as_tensor(valid)[:, None]
            self.reset(torch.where(ok, t[0], self._q_center.to(t[0])), torch.where(ok, t[1], 0.0))
        if kin is not None and tuple(kin.jac.shape) != (n, 6, 7):
            raise ControlShapeError(f"kin must hold the kinematics of {n} robots (jac [{n}, 6, 7]), got jac "
                                    f"{tuple(kin.jac.shape)}")
        if on_cpu and self._numpy_ok:  # the objects on numpy views: ~3x less overhead per op (arrays.py)
            if in_contact is None:
                in_contact = self._contact_np(f_env)
            elif isinstance(in_contact, torch.Tensor):
                in_contact = _np(in_contact)
            return _StepInputs(*arrays, in_contact=in_contact, kin=None if kin is None else _kin_numpy(kin),
                               valid=valid, all_valid=bool(valid.all()), xp=np)
        if in_contact is None:
            in_contact = self.contact_from(f_env)
        return _StepInputs(*t, in_contact=in_contact, kin=kin, valid=torch.as_tensor(valid),
                           all_valid=bool(valid.all()), xp=torch)

    def _check_leak_extra(self, leak_extra: torch.Tensor, like: Array) -> Array:
        """`step`'s leak_extra as float64 [N, 6] of the kind of `like` (numpy, or a tensor on its device), or a
        one-line error."""
        if self.options.leak_axes != "per_axis":
            raise InvalidGainError(f"leak_extra needs ControllerOptions.leak_axes 'per_axis', got "
                                   f"{self.options.leak_axes!r}")
        t = self._check("leak_extra", torch.as_tensor(leak_extra), (self.n, 6))
        a = _np(t) if t.device.type == "cpu" else t  # (numpy on CPU: the checks cost ~1 µs each instead of ~5)
        xp = np if isinstance(a, np.ndarray) else torch
        if not bool(xp.isfinite(a).all()):
            raise InvalidGainError("leak_extra must be finite (1/s), got a non-finite value")
        if not bool((a >= 0.0).all()):
            raise InvalidGainError(f"leak_extra must be ≥ 0 (1/s) on every axis, got {float(a.min()):.6g}")
        return _np(t.cpu()) if isinstance(like, np.ndarray) else t.to(like.device)

    def contact_from(self, f_env: torch.Tensor | None) -> torch.Tensor:
        """in_contact [N] from the F/T wrench f_env [N, 6]: |force| > ControllerOptions.contact_force_threshold."""
        if f_env is None or f_env.device.type == "cpu":
            return torch.from_numpy(self._contact_np(f_env))
        return f_env[:, :3].norm(dim=-1) > self.options.contact_force_threshold

    def _contact_np(self, f_env: torch.Tensor | None) -> np.ndarray:
        """`contact_from` of a CPU wrench as a numpy bool array [N]."""
        if f_env is None:
            return np.zeros(self.n, dtype=bool)
        thr = self.options.contact_force_threshold  # |f| > thr as a squared norm in numpy (two µs instead of ~20)
        return np.square(_np(f_env)[:, :3]).sum(axis=1) > thr * thr

    def _stand_ins(self, inp: _StepInputs) -> _StepInputs:
        """Stage 2: robots with non-finite inputs computed on a harmless stand-in (replaced by the fallback later).

        A caller's kin is not checked: non-finite kinematics make x non-finite, which falls back too; it is
        recomputed here from the stand-in q, q̇."""
        xp, n = inp.xp, self.n

        def keep(t: Array, default: Array | float) -> Array:
            ok = xp.isfinite(t.reshape(n, -1)).all(-1).reshape(-1, *([1] * (t.ndim - 1)))
            return xp.where(ok, t, default)

        eye7 = self._constants(inp.q)["eye7"]
        return dataclasses.replace(
            inp, q=keep(inp.q, const(self.q_des, inp.q)), qd=keep(inp.qd, 0.0), mass=keep(inp.mass, eye7),
            bias=keep(inp.bias, 0.0), weights=keep(inp.weights, 1.0 / 3.0), f_d=keep(inp.f_d, 0.0),
            f_ext=keep(inp.f_ext, 0.0), pos_d=keep(inp.pos_d, 0.0), rot_d=keep(inp.rot_d, eye7[:3, :3]), kin=None)

    def _apply(self, inp: _StepInputs, ctx: ControlContext, x: torch.Tensor, qp_status: torch.Tensor,
               iterations: torch.Tensor, relaxed: np.ndarray | None = None) -> ControlOutput:
        """Stage 4: computed torque (eq. 4-7) where the QP (or the least-violation QP, `relaxed`) succeeded, the safe
        brake elsewhere, then the clip."""
        xp = inp.xp
        solved = qp_status.cpu().numpy() == 0
        if relaxed is not None:
            solved = solved | relaxed
        if xp is np:
            x = _np(x)
            ok = solved & inp.valid & np.isfinite(x).all(axis=1)
        else:
            ok = torch.as_tensor(solved, device=x.device) & inp.valid & torch.isfinite(x).all(-1)
        cfg, dt = self.config, self.dt
        q_des, qd_des = const(self.q_des, inp.q), const(self.qd_des, inp.q)
        tau, qdd, f, qdd_pd, q_des, qd_des = _torque_law(x, inp.q, inp.qd, inp.mass, inp.bias, ctx.kin.jac,
                                                         ctx.pd_matrix, q_des, qd_des, dt, cfg.cv, cfg.cp)
        if not bool(ok.all()):
            # a damped joint-space brake inside the viable bounds, which always respect the acceleration limits
            # (Del Prete 2017; limits._acc_bounds), so that with gravity compensation it is torque-realisable
            qdd_fb = self.joint_limits.safe_acceleration(ctx)
            o1 = ok[:, None]
            tau = xp.where(o1, tau, mv(inp.mass, qdd_fb) + inp.bias)
            qdd, f, qdd_pd = xp.where(o1, qdd, qdd_fb), xp.where(o1, f, 0.0), xp.where(o1, qdd_pd, 0.0)
            q_des, qd_des = xp.where(o1, q_des, inp.q), xp.where(o1, qd_des, inp.qd)
            self._report_fallback(ok, qp_status, inp.valid)
        if relaxed is not None:  # the references forget a relaxed step (`_forget_relaxed`)
            r1 = torch.as_tensor(relaxed, device=inp.q.device)[:, None] if xp is torch else relaxed[:, None]
            q_des, qd_des = xp.where(r1, inp.q, q_des), xp.where(r1, inp.qd, qd_des)
        leak = dt * self.options.desired_state_leak
        if self.options.leak_axes == "per_axis":
            q_des, qd_des = _relax_per_axis(q_des, qd_des, inp.q, inp.qd, inp.weights, ctx.f_d_local, ctx.kin.jac,
                                            ctx.jpinv, ctx.D, leak, dt, inp.leak_extra)
        else:
            q_des, qd_des = _relax_min_w1(xp, q_des, qd_des, inp.q, inp.qd, inp.weights, leak)
        out = _finish(xp, tau, qdd, f, qdd_pd, q_des, qd_des, self._constants(inp.q)["tau_max"])
        f_adm = self.residuals["ac"].b if "ac" in self.residuals else xp.zeros_like(out[2])
        f_ctc = self.residuals["fc"].b if "fc" in self.residuals else xp.zeros_like(out[2])
        out = [torch.as_tensor(np.ascontiguousarray(a) if xp is np else a)
               for a in (*out, ctx.pose_error, f_adm, f_ctc, ok)]
        tau, qdd, f, qdd_pd, self.q_des, self.qd_des, saturated, pose_err, f_adm, f_ctc, ok = out
        status = qp_status if inp.all_valid else torch.where(
            torch.as_tensor(inp.valid), qp_status, torch.full_like(qp_status, INVALID_INPUT))
        relaxed = torch.zeros(self.n, dtype=torch.bool) if relaxed is None else torch.from_numpy(relaxed)
        return ControlOutput(tau=tau, qdd=qdd, wrench=f, qdd_pd=qdd_pd, pose_error=pose_err, f_adm=f_adm,
                             f_ctc=f_ctc, status=status, fallback=~ok, saturated=saturated, iterations=iterations,
                             relaxed=relaxed.to(ok.device))

    def assemble_native(self, q: np.ndarray, qd: np.ndarray, mass: np.ndarray, bias: np.ndarray,
                        weights: np.ndarray, f_d: np.ndarray, pos_d: np.ndarray, rot_d: np.ndarray,
                        f_ext: np.ndarray, in_contact: np.ndarray, kin: Kinematics | None = None,
                        f_ext_limits: np.ndarray | None = None, rows: np.ndarray | None = None) -> native.Assembled:
        """`build_context` + `build_qp` by the C step (numpy arrays, shapes as `step`; the default composition only);
        `rows`: of those robots only (in that order)."""
        if self._native is None:
            raise RuntimeError("this controller has no native step (backend='python' or not the default composition)")
        kin = kin if kin is not None else _model_kinematics(self.model, q, qd)
        packed = self._native.pack(
            q=q, qd=qd, mass=mass, bias=bias, jac=kin.jac, jdot_qdot=kin.jdot_qdot, twist=kin.twist, pos=kin.pos,
            rot=kin.rot, weights=weights, f_d=f_d, pos_d=pos_d, rot_d=rot_d, f_ext=f_ext, in_contact=in_contact,
            q_des=_np(self.q_des), qd_des=_np(self.qd_des), f_ext_limits=_f_ext_limits(f_ext_limits, self.n))
        return self._native.assemble(packed=packed if rows is None else packed[rows])

    def _native_fits(self) -> bool:
        """Whether the C step translates this controller's stack (one level with every task active)."""
        return self.hierarchy.is_flat

    def _native_qp(self, inp: _StepInputs, rows: np.ndarray | None = None
                   ) -> tuple[native.Assembled, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The C assembly and the QP's (x, status, iterations) of a native step (of the robots `rows` only)."""
        asm = self.assemble_native(inp.q, inp.qd, inp.mass, inp.bias, inp.weights, inp.f_d, inp.pos_d, inp.rot_d,
                                   inp.f_ext, inp.in_contact, inp.kin, inp.f_ext_limits, rows)
        return asm, *self._solve(*(torch.from_numpy(a) for a in (asm.P, asm.c, asm.G, asm.h)), rows=rows)

    def _step_native(self, inp: _StepInputs, rows: np.ndarray | None = None,
                     idle: np.ndarray | None = None) -> ControlOutput:
        """Stages 3-4 by the C translation of the default tasks, limits and torque law (finite numpy inputs); `rows`,
        `idle`: the active and the inactive robots (`step`'s `active`), None: all active."""
        # a few idle robots are computed with the others and held after: gathering and scattering the arrays costs
        # ~50 µs, ~13 robots' C step at 65
        sub = (rows is not None and self.n - len(rows) >= SUBSET_MIN_IDLE
               and type(self)._native_qp is A3CQPController._native_qp)  # (a population assembles its own way)
        asm, x, qp_status, iterations = self._native_qp(inp, rows) if sub else self._native_qp(inp)
        xn = _np(x)
        ok = (_np(qp_status) == 0) & np.isfinite(xn).all(axis=1)
        relaxed = np.zeros(len(ok), dtype=bool)
        if not ok.all() and not self.hierarchy.strict:  # (a cascade's failure brakes: ControllerOptions.qp_failure)
            t = torch.from_numpy
            x, done = self._relax_failed(t(asm.P), t(asm.c), t(asm.G), t(asm.h), x, ok, np.ones(len(ok), dtype=bool))
            if done is not None:
                xn, relaxed, ok = _np(x), done, ok | done
        extra = inp.leak_extra if not sub or inp.leak_extra is None else inp.leak_extra[rows]
        out = [*self._native.torque(xn, ok, asm, extra), asm.pose_error, asm.f_adm, asm.f_ctc, ok, relaxed]
        if relaxed.any():
            q, qd = (inp.q, inp.qd) if not sub else (inp.q[rows], inp.qd[rows])
            self._forget_relaxed(out[4], out[5], relaxed, q, qd)
        if rows is not None:  # the inactive robots: h + g, their q*, q̇* kept, no fallback, zeros elsewhere
            counts = [_np(qp_status), _np(iterations)]
            if sub:  # (spread: zeros in the idle rows already)
                out, counts = ([_spread(self.n, rows, a) for a in arrays] for arrays in (out, counts))
            else:  # every robot computed: the fresh outputs zeroed in place; status and iterations are views of the
                counts = [a.copy() for a in counts]  # solver's buffer, which the warm start keeps
                for a in out + counts:
                    a[idle] = 0
            out[0][idle] = np.clip(inp.bias[idle], -self._tau_max_np, self._tau_max_np)
            out[4][idle], out[5][idle], out[10][idle] = _np(self.q_des)[idle], _np(self.qd_des)[idle], True
            qp_status, iterations = (torch.from_numpy(a) for a in counts)
        tau, qdd, f, qdd_pd, q_des, qd_des, saturated, pose_error, f_adm, f_ctc, ok, relaxed = out
        if not ok.all():
            self._report_fallback(ok, qp_status, np.ones(self.n, dtype=bool))
        self.q_des, self.qd_des = torch.from_numpy(q_des), torch.from_numpy(qd_des)
        self.residuals = {}
        t = torch.from_numpy
        return ControlOutput(tau=t(tau), qdd=t(qdd), wrench=t(f), qdd_pd=t(qdd_pd), pose_error=t(pose_error),
                             f_adm=t(f_adm), f_ctc=t(f_ctc), status=qp_status, fallback=t(~ok),
                             saturated=t(saturated), iterations=iterations, relaxed=t(relaxed))
