"""QP limits of the A3CQP controller: each returns inequality rows G x ≤ h on x = (q̈, f) (section III-B).

Rows are numpy arrays or torch tensors, the kind of the context (see arrays.py).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from a3cqp_rl.control.arrays import Array, cat, const, mm, mv
from a3cqp_rl.control.context import N_QDD, N_VARS, ControlContext
from a3cqp_rl.control.exceptions import InvalidGainError
from a3cqp_rl.control.piece import QPPiece

__all__ = ["Inequality", "Limit", "JointLimitsViability", "WrenchBox", "FrictionPyramid", "TorqueLimits",
           "joint_acceleration_bounds"]

_BIG = 1e10

_CONSTANTS: dict[tuple, torch.Tensor] = {}


def _cached(key: tuple, make) -> torch.Tensor:  # noqa: ANN001
    """Constant tensors (identities, zero blocks, fixed rows) made once per shape/dtype/device: read-only."""
    t = _CONSTANTS.get(key)
    if t is None:
        t = _CONSTANTS[key] = make()
    return t


def _key(like: Array) -> tuple:
    return ("numpy",) if isinstance(like, np.ndarray) else (like.dtype, like.device)


def _eye(n: int, like: Array) -> Array:
    return _cached(("eye", n, *_key(like)), lambda: const(torch.eye(n, dtype=torch.float64), like))


def _zeros(b: int, m: int, k: int, like: Array) -> Array:
    return _cached(("zeros", b, m, k, *_key(like)), lambda: const(torch.zeros(b, m, k, dtype=torch.float64), like))


def _ones(b: int, m: int, like: Array) -> Array:
    return _cached(("ones", b, m, *_key(like)), lambda: const(torch.ones(b, m, dtype=torch.float64), like))


@dataclass(frozen=True)
class Inequality:
    """Rows G x ≤ h for a batch."""

    G: Array
    """[B, m, 13]."""
    h: Array
    """[B, m]."""


class Limit(QPPiece, ABC):
    """A QP limit: inequality rows from the step's context."""

    name: str = "limit"

    @abstractmethod
    def rows(self, ctx: ControlContext) -> Inequality:
        """Rows (G, h) of this limit for the batch in `ctx`."""


def _acc_bounds_from_position(q, dq, q_min, q_max, dt, xp):  # noqa: ANN001, ANN202
    """Del Prete 2017: q̈ bounds keeping q_{k+1} = q + Δt q̇ + Δt²/2 q̈ in [q_min, q_max], braking if needed."""
    two_dt_sq = 2.0 / dt**2
    ub_q3 = two_dt_sq * (q_max - q - dt * dq)
    lb_q3 = two_dt_sq * (q_min - q - dt * dq)
    stop = -dq / dt  # q̈ that stops the joint in one step
    # moving down (q̇ ≤ 0): the lower bound either keeps q ≥ q_min in one step or brakes to stop exactly at q_min
    dq2 = dq * dq
    lb_brake = xp.maximum(dq2 / (2.0 * xp.where(q != q_min, q - q_min, 1.0)), stop)
    lb_down = xp.where(lb_q3 < stop, lb_q3, xp.where(q != q_min, lb_brake, stop))
    ub_brake = xp.minimum(-dq2 / (2.0 * xp.where(q != q_max, q_max - q, 1.0)), stop)
    ub_up = xp.where(ub_q3 > stop, ub_q3, xp.where(q != q_max, ub_brake, stop))
    down = dq <= 0.0
    return xp.where(down, lb_down, lb_q3), xp.where(down, ub_q3, ub_up)


def _acc_bounds_from_viability(q, dq, q_min, q_max, ddq_stop, dt, xp):  # noqa: ANN001, ANN202
    """Del Prete 2017: q̈ bounds keeping the next state able to stop before the position limits with |q̈| ≤ ddq_stop."""
    dt2 = dt * dt
    two_a = 2.0 * dt2
    stop = -dq / dt
    dq2 = dq * dq
    b = 2.0 * dt * dq + ddq_stop * dt2
    c = dq2 - 2.0 * ddq_stop * (q_max - q - dt * dq)
    delta = b * b - 2.0 * two_a * c
    ub = xp.where(delta >= 0.0, (-b + xp.sqrt(xp.maximum(delta, 0.0))) / two_a, stop)
    b = 2.0 * dt * dq - ddq_stop * dt2
    c = dq2 - 2.0 * ddq_stop * (q + dt * dq - q_min)
    delta = b * b - 2.0 * two_a * c
    lb = xp.where(delta >= 0.0, (-b - xp.sqrt(xp.maximum(delta, 0.0))) / two_a, stop)
    return xp.minimum(lb, stop), xp.maximum(ub, stop)


def _acc_bounds(q, dq, q_min, q_max, dq_max, ddq_max, dt, xp, ddq_stop=None):  # noqa: ANN001, ANN202
    lb_p, ub_p = _acc_bounds_from_position(q, dq, q_min, q_max, dt, xp)
    lb_v, ub_v = (-dq_max - dq) / dt, (dq_max - dq) / dt
    lb_s, ub_s = _acc_bounds_from_viability(q, dq, q_min, q_max, ddq_max if ddq_stop is None else ddq_stop, dt, xp)
    lb_pv, ub_pv = xp.maximum(lb_p, lb_v), xp.minimum(ub_p, ub_v)
    lb, ub = xp.maximum(lb_pv, lb_s), xp.minimum(ub_pv, ub_s)
    # conflicts among position, velocity and viability (a state outside the viable set): drop viability, then
    # velocity, keeping the position bounds
    c2 = ub < lb
    lb, ub = xp.where(c2, lb_pv, lb), xp.where(c2, ub_pv, ub)
    c3 = ub < lb
    lb, ub = xp.where(c3, lb_p, lb), xp.where(c3, ub_p, ub)
    # the acceleration limits always hold: a demand beyond them is saturated (monotone clip, so lb ≤ ub stays).
    # Inside the viable set Del Prete's bounds never ask for more than ddq_max; they do only after the state has
    # left it (model mismatch, torque saturation), e.g. 0.1 mm past q_max with the 2Δt horizon the position bound
    # asks for ~20 rad/s² back, which with gravity needs more than τ_max: braking/returning at ddq_max instead keeps
    # the joint within the q_margin band while staying torque-feasible (see TorqueLimits and the fallback).
    neg = -ddq_max
    return xp.minimum(xp.maximum(lb, neg), ddq_max), xp.minimum(xp.maximum(ub, neg), ddq_max)


def joint_acceleration_bounds(q: torch.Tensor, dq: torch.Tensor, q_min: torch.Tensor, q_max: torch.Tensor,
                              dq_max: torch.Tensor, ddq_max: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Viable joint acceleration bounds (lb, ub) [B, 7] (rad/s²) from position, velocity and acceleration limits.

    Del Prete, "Joint position and velocity bounds in discrete-time acceleration/torque control of robot
    manipulators", RA-L 2018 (as in OpenSoT JointLimitsViability / TSID TaskJointPosVelAccBounds): the most
    conservative of the position, velocity, viability and acceleration bounds. On conflict (a state outside the
    viable set) viability is dropped first, then the velocity bounds, and what remains is saturated into the
    acceleration limits, which always hold (so the bounds stay realisable with the motors' torque; dropping them
    instead made the QP infeasible together with TorqueLimits).
    CPU tensors without gradients are evaluated with numpy (≈40 elementwise ops, ~5x less overhead than torch).
    """
    args = (q, dq, q_min, q_max, dq_max, ddq_max)
    if q.device.type == "cpu" and not any(t.requires_grad for t in args):
        return _numpy_bounds(q, dq, *(t.numpy() for t in args[2:]), dt)
    return _acc_bounds(q, dq, *(t.expand_as(q) for t in args[2:]), dt, _TorchOps)


def _numpy_bounds(q: torch.Tensor, dq: torch.Tensor, q_min: np.ndarray, q_max: np.ndarray, dq_max: np.ndarray,
                  ddq_max: np.ndarray, dt: float, ddq_stop: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """`_acc_bounds` in numpy for CPU tensors without gradients; the [7] limits broadcast over the batch."""
    with np.errstate(divide="ignore", invalid="ignore"):
        lb, ub = _acc_bounds(q.numpy(), dq.numpy(), q_min, q_max, dq_max, ddq_max, dt, np, ddq_stop)
    lb, ub = torch.from_numpy(np.asarray(lb)), torch.from_numpy(np.asarray(ub))
    return (lb, ub) if lb.dtype == q.dtype else (lb.to(q.dtype), ub.to(q.dtype))


class _TorchOps:
    """The few numpy functions `_acc_bounds` uses, on torch tensors (scalars allowed)."""

    where = staticmethod(torch.where)
    sqrt = staticmethod(torch.sqrt)

    @staticmethod
    def maximum(a: torch.Tensor, b: torch.Tensor | float) -> torch.Tensor:
        return torch.maximum(a, torch.as_tensor(b, dtype=a.dtype, device=a.device))

    @staticmethod
    def minimum(a: torch.Tensor, b: torch.Tensor | float) -> torch.Tensor:
        return torch.minimum(a, torch.as_tensor(b, dtype=a.dtype, device=a.device))


class JointLimitsViability(Limit):
    """Joint position/velocity/acceleration limits made viable at acceleration level (Del Prete 2017).

    Args:
        q_min, q_max: position limits [7] (rad), shrunk by `q_margin`.
        dq_max: velocity limits [7] (rad/s), shrunk by `dq_margin`.
        ddq_max: acceleration limits [7] (rad/s²).
        dt: control period [s]; the bounds use a horizon `horizon_steps` Δt (TSID uses 2) so that the one-step
            delay and the simulator's semi-implicit Euler (q += Δt² q̈ instead of Δt²/2 q̈) stay inside.
        target: "qdd" bounds q̈* + q̈_pd (eq. 24a and the remark after eq. 7); "total" (default) bounds, in
            addition, the whole commanded joint acceleration q̈* + q̈_pd + B⁻¹Jᵀf (eq. 4: f enters the
            torque through Jᵀf), so that AC/FC wrenches cannot drive the arm through its limits either.
        include_f_ext: also count the measured external wrench in the total (q̈ = ... + B⁻¹Jᵀ(f + f_ext)). Off by
            default: then x = (q̈ inside the bounds, f = 0) satisfies every row, so the QP is always feasible;
            with it, an external wrench larger than the wrench box can make the QP infeasible (-> fallback).
        brake_gain: k [1/s] of `safe_acceleration` (the fallback brake q̈ = −k q̇ inside the bounds).
        tau_max, torque_share, min_stop_fraction, stop_share: torque-consistent stopping deceleration of the
            viability bound (`stopping_deceleration`; tau_max None = Del Prete's ddq_max).
    """

    name = "joint_limits"
    numpy_capable = True

    def __init__(self, q_min: torch.Tensor, q_max: torch.Tensor, dq_max: torch.Tensor, ddq_max: torch.Tensor,
                 dt: float, q_margin: float = 0.01, dq_margin: float = 0.02, horizon_steps: float = 2.0,
                 target: Literal["total", "qdd"] = "total", include_f_ext: bool = False,
                 brake_gain: float = 20.0, tau_max: torch.Tensor | None = None, torque_share: float = 0.5,
                 min_stop_fraction: float = 0.2, stop_share: float = 0.9) -> None:
        if target not in ("total", "qdd"):
            raise InvalidGainError(f"target must be 'total' or 'qdd', got {target!r}")
        if not (dt > 0 and horizon_steps >= 1 and q_margin >= 0 and dq_margin >= 0 and brake_gain >= 0):
            raise InvalidGainError(f"need dt > 0, horizon_steps >= 1, margins >= 0; got {dt}, {horizon_steps}, "
                                   f"{q_margin}, {dq_margin}")
        if not min_stop_fraction <= stop_share <= 1.0:
            raise InvalidGainError(f"stop_share must be in [min_stop_fraction, 1] = [{min_stop_fraction}, 1], got "
                                   f"{stop_share!r}")
        f64 = torch.float64
        self.q_min = torch.as_tensor(q_min, dtype=f64) + q_margin
        self.q_max = torch.as_tensor(q_max, dtype=f64) - q_margin
        self.dq_max = torch.as_tensor(dq_max, dtype=f64) - dq_margin
        self.ddq_max = torch.as_tensor(ddq_max, dtype=f64)
        self.dt, self.horizon, self.target, self.include_f_ext = dt, horizon_steps * dt, target, include_f_ext
        self.brake_gain = brake_gain
        self.tau_max = None if tau_max is None else torch.as_tensor(tau_max, dtype=f64)
        self.torque_share, self.min_stop_fraction, self.stop_share = torque_share, min_stop_fraction, stop_share
        self._np_limits = tuple(t.numpy() for t in (self.q_min, self.q_max, self.dq_max, self.ddq_max))

    def _c_params(self) -> tuple[str, dict]:
        q_min, q_max, dq_max, ddq_max = self._np_limits
        return "joint_limits", {
            "q_min": q_min, "q_max": q_max, "dq_max": dq_max, "ddq_max": ddq_max, "horizon": self.horizon,
            "target_total": float(self.target == "total"), "include_f_ext": float(self.include_f_ext),
            "brake_gain": self.brake_gain, "has_tau_stop": float(self.tau_max is not None),
            "tau_stop_max": np.zeros(7) if self.tau_max is None else self.tau_max.numpy(),
            "torque_share": self.torque_share, "min_stop_fraction": self.min_stop_fraction,
            "stop_share": self.stop_share}

    def bounds(self, q: Array, qd: Array, ddq_stop: Array | None = None) -> tuple[Array, Array]:
        """Viable acceleration bounds (lb, ub) [B, 7] (rad/s²) at state (q, q̇), arrays of q's kind.

        `ddq_stop` [B, 7]: the deceleration the viability bound may count on to stop before a position limit
        (default ddq_max); see `stopping_deceleration`.
        """
        if isinstance(q, np.ndarray):
            with np.errstate(divide="ignore", invalid="ignore"):
                return _acc_bounds(q, qd, *self._np_limits, self.horizon, np, ddq_stop)
        if q.device.type == "cpu" and q.dtype == torch.float64 and not (q.requires_grad or qd.requires_grad):
            stop = None if ddq_stop is None else ddq_stop.numpy()
            return _numpy_bounds(q, qd.to(q.dtype), *self._np_limits, self.horizon, stop)  # the 1 kHz loop's path
        lb, ub = (joint_acceleration_bounds(q, qd, self.q_min.to(q), self.q_max.to(q), self.dq_max.to(q),
                                            self.ddq_max.to(q), self.horizon) if ddq_stop is None else
                  _acc_bounds(q, qd, *(t.to(q).expand_as(q) for t in (self.q_min, self.q_max, self.dq_max,
                                                                      self.ddq_max)), self.horizon, _TorchOps,
                              ddq_stop))
        return lb, ub

    def stopping_deceleration(self, ctx: ControlContext) -> Array | None:
        """Torque-consistent stopping deceleration [B, 7] for the viability bound (None: ddq_max, no torque model).

        Del Prete's viability assumes a joint can always brake at ddq_max; with gravity and the other joints'
        inertial coupling the Panda's shoulder cannot (random switching: joint 2 braking with τ saturated at
        −87 N m under −44 N m of gravity reached −3 rad/s², not −7.5, and overshot q_max). As in OpenSoT, where the
        acceleration limits are chosen consistent with the torque limits, the deceleration counted on is
        min(`stop_share` ddq_max, `torque_share` (τ_max − |h + g|) / B_ii), at least `min_stop_fraction` ddq_max.

        `stop_share` < 1 keeps headroom between the deceleration the bound counts on and the one the acceleration
        bounds allow, for torque the model does not have. In MuJoCo the joints' viscous damping (0.1 N m s/rad, not in
        h + g), coupled through B⁻¹, cut joint 2's realised braking from the commanded 7.5 to 7.2 rad/s² at 2.1 rad/s:
        the stop then needs v²/2 (1/7.2 − 1/7.5) ≈ 13 mrad more than the bound planned, more than the 10 mrad
        q_margin, and the joint reached its datasheet limit. With 0.9 the bound starts braking at 90 % of ddq_max,
        and the QP may brake up to all of it.
        """
        if ctx.bias is None or self.tau_max is None:
            return None
        xp, n = ctx.xp, ctx.mass.shape[-1]
        diag = ctx.mass.reshape(-1, n * n)[:, ::n + 1]  # B_ii (a strided view; diagonal() is spelled differently)
        room = (const(self.tau_max, ctx.q) - xp.abs(ctx.bias)).clip(0.0)
        ddq_max = const(self.ddq_max, ctx.q)
        # (the lower bound min_stop_fraction · ddq_max > 0 also clips negative values)
        return xp.maximum(xp.minimum(self.torque_share * room / diag, self.stop_share * ddq_max),
                          self.min_stop_fraction * ddq_max)

    def bounds_for(self, ctx: ControlContext) -> tuple[Array, Array]:
        """`bounds(ctx.q, ctx.qd)`, computed once per context (shared with TorqueLimits and the fallback)."""
        key = ("viable_bounds", id(self))
        out = ctx.cache.get(key)
        if out is None:
            out = ctx.cache[key] = self.bounds(ctx.q, ctx.qd, self.stopping_deceleration(ctx))
        return out

    def safe_acceleration(self, ctx: ControlContext) -> Array:
        """The damped brake q̈ = clamp(−k q̇, lb, ub) [B, 7] (rad/s²), k = `brake_gain`: inside the viable bounds, so
        inside the position, velocity and acceleration limits (Del Prete 2017). It is the controller's fallback
        acceleration and the point (q̈ total = this, f = 0) that TorqueLimits keeps feasible, so the QP always is."""
        key = ("safe_acceleration", id(self))
        out = ctx.cache.get(key)
        if out is None:
            lb, ub = self.bounds_for(ctx)
            out = ctx.cache[key] = ctx.xp.minimum(ctx.xp.maximum(-self.brake_gain * ctx.qd, lb), ub)
        return out

    @property
    def row_count(self) -> int:
        """Rows of `rows`: ± the motion part, and ± the total where `target` is "total"."""
        return 4 * N_QDD if self.target == "total" else 2 * N_QDD

    @property
    def soft_rows(self) -> slice:
        """The rows of `rows` a least-violation QP may relax: the ones that bound the acceleration the arm will have
        (the total, with f_ext where counted; the motion part where `target` is "qdd"). The motion rows of the
        "total" target only keep f from faking IK success, and the brake meets them and every other row."""
        return slice(2 * N_QDD, 4 * N_QDD) if self.target == "total" else slice(0, 2 * N_QDD)

    def rows(self, ctx: ControlContext) -> Inequality:
        lb, ub = self.bounds_for(ctx)
        B = ctx.batch
        # motion part: q̈* + q̈_pd = (I + ∂q̈_pd/∂q̈*) q̈* + q̈_pd0 ∈ [lb, ub] (eq. 5-7 are linear in q̈*)
        gain = ctx.qdd_map if ctx.qdd_map is not None else _eye(N_QDD, ctx.q) + ctx.pd_qdd_gain
        motion = cat([gain, _zeros(B, N_QDD, N_VARS - N_QDD, ctx.q)], 2)
        if self.target == "qdd":
            return Inequality(G=cat([motion, -motion], 1), h=cat([ub - ctx.qdd_pd0, ctx.qdd_pd0 - lb], 1))
        # total commanded acceleration, adding the wrench's B⁻¹Jᵀ(f + f_ext). Both row sets are kept: with the
        # total alone, an unweighted f could cancel an over-limit q̈* inside the sum and fake IK success.
        total = cat([gain, ctx.mass_inv_jt], 2)
        offset = ctx.qdd_pd0
        if self.include_f_ext or ctx.f_ext_limits is not None:  # every robot, or those named by step(f_ext_limits=)
            ext = mv(ctx.mass_inv_jt, ctx.f_ext)
            offset = offset + (ext if self.include_f_ext else ctx.xp.where(ctx.f_ext_limits[:, None], ext, 0.0 * ext))
        return Inequality(G=cat([motion, -motion, total, -total], 1),
                          h=cat([ub - ctx.qdd_pd0, ctx.qdd_pd0 - lb, ub - offset, offset - lb], 1))


class WrenchBox(Limit):
    """Wrench limits |f_i| ≤ f_max (forces, N) and ≤ tau_max (torques, N m), world frame (section V-B: 20 N, 5 N m)."""

    name = "wrench_box"
    numpy_capable = True

    def __init__(self, force_limit: float = 20.0, torque_limit: float = 5.0) -> None:
        if not (force_limit > 0 and torque_limit > 0 and math.isfinite(force_limit + torque_limit)):
            raise InvalidGainError(f"wrench limits must be finite and > 0, got {force_limit}, {torque_limit}")
        self.limit = torch.tensor([force_limit] * 3 + [torque_limit] * 3, dtype=torch.float64)
        self._rows: dict[tuple, tuple[Array, Array]] = {}

    def _c_params(self) -> tuple[str, dict]:
        return "wrench_box", {"wrench_max": self.limit.numpy()}

    def rows(self, ctx: ControlContext) -> Inequality:
        B, like = ctx.batch, ctx.q

        def make() -> tuple[Array, Array]:  # constant rows: built once per batch size
            S = torch.zeros(B, 6, N_VARS, dtype=torch.float64)
            S[:, :, N_QDD:] = torch.eye(6, dtype=torch.float64)
            lim = self.limit.expand(B, 6)
            return const(torch.cat([S, -S], dim=1), like), const(torch.cat([lim, lim], dim=1), like)

        key = ("wrench_box", id(self), B, *_key(like))
        if key not in self._rows:
            self._rows = {key: make()}
        G, h = self._rows[key]
        return Inequality(G=G, h=h)


class FrictionPyramid(Limit):
    """Linearised friction cone U(μ) f^𝓛 ≤ 0 (eq. 9) on the force part of f in 𝓛, normal = local z (tool axis).

    Rows: ±f_x − μ f_z ≤ 0, ±f_y − μ f_z ≤ 0 with f^𝓛 = Dᵀ f. Active only for robots in contact (`ctx.in_contact`):
    in free space the wrench must be free to follow the operator (AC) in any direction; inactive rows are 0 ≤ 1.
    """

    name = "friction"
    numpy_capable = True

    def __init__(self, mu: float = 0.4) -> None:
        if not (mu > 0 and math.isfinite(mu)):
            raise InvalidGainError(f"mu must be finite and > 0, got {mu!r}")
        self.mu = mu
        self.U = torch.tensor([[1.0, 0.0, -mu], [-1.0, 0.0, -mu], [0.0, 1.0, -mu], [0.0, -1.0, -mu]],
                              dtype=torch.float64)  # (4, 3) on the local force

    def _c_params(self) -> tuple[str, dict]:
        return "friction", {"mu": self.mu}

    def rows(self, ctx: ControlContext) -> Inequality:
        B, like = ctx.batch, ctx.q
        if not bool(ctx.in_contact.any()):  # nobody in contact (free motion): the constant rows 0 ≤ 1
            return Inequality(G=_zeros(B, 4, N_VARS, like), h=_ones(B, 4, like))
        R = ctx.D[:, :3, :3]  # world <- local
        contact = ctx.in_contact
        active = (contact.astype(like.dtype) if isinstance(contact, np.ndarray) else contact.to(like.dtype))
        URt = active.reshape(B, 1, 1) * (const(self.U, like) @ R.mT)  # U Rᵀ f_world
        G = cat([_zeros(B, 4, N_QDD, like), URt, _zeros(B, 4, N_VARS - N_QDD - 3, like)], 2)
        h = _ones(B, 4, like) - active.reshape(B, 1)
        return Inequality(G=G, h=h)


class TorqueLimits(Limit):
    """|τ| ≤ τ_max for the torque law τ = B(q̈* + q̈_pd) + Jᵀf + h + g (eq. 4), linear in x = (q̈*, f).

    Not in the paper's QP: without it, fast random weight switching can command accelerations the motors cannot
    deliver (87 / 12 N m); the clipped torque then brakes too little and a joint overshoots its velocity limit.
    Rows: ±(B(I + ∂q̈_pd/∂q̈*) q̈* + Jᵀ f) ≤ τ̄ ∓ (B q̈_pd0 + h + g).

    Safety first (`safe`): joint-limit viability must hold, torque limits may give. Near a limit the viable
    acceleration with gravity can need more than τ_max, and the two row sets are then jointly infeasible (seen with
    random weight switching: joint 2 resting on q_max − margin under −51 N m of gravity). With `safe` given, the
    limit per joint is τ̄ = max(scale τ_max, |τ_safe|), τ_safe = B q̈_safe + h + g the torque of the viable brake
    q̈_safe = `safe.safe_acceleration(ctx)` (with f = 0, inside the wrench box and the friction pyramid): that point
    always satisfies every row, so the QP is always feasible, and τ_max gives way only as much as the brake needs
    (the applied torque is still clipped to the motors' ±τ_max afterwards).
    """

    name = "torque_limits"
    numpy_capable = True

    def __init__(self, tau_max: torch.Tensor, scale: float = 0.98, safe: "JointLimitsViability | None" = None) -> None:
        if not 0.0 < scale <= 1.0:
            raise InvalidGainError(f"scale must be in (0, 1], got {scale!r}")
        self.tau_max = scale * torch.as_tensor(tau_max, dtype=torch.float64)
        self.safe = safe

    def _c_params(self) -> tuple[str, dict] | None:
        # C anchors the rows to the brake of the step's own joint limits: "anchor" lets it check that they are these
        anchor = None if self.safe is None else self.safe.c_params()
        return "torque_limits", {"torque_max": self.tau_max.numpy(), "torque_safe": float(self.safe is not None),
                                 "anchor": anchor}

    def rows(self, ctx: ControlContext) -> Inequality:
        xp = ctx.xp
        gain = ctx.qdd_map if ctx.qdd_map is not None else _eye(N_QDD, ctx.q) + ctx.pd_qdd_gain
        M = cat([mm(ctx.mass, gain), ctx.kin.jac.mT], 2)
        offset = mv(ctx.mass, ctx.qdd_pd0)
        if ctx.bias is not None:
            offset = offset + ctx.bias
        lim = const(self.tau_max, ctx.q)  # [7], broadcast over the batch
        if self.safe is not None:
            tau_safe = mv(ctx.mass, self.safe.safe_acceleration(ctx))
            if ctx.bias is not None:
                tau_safe = tau_safe + ctx.bias
            lim = xp.maximum(lim, xp.abs(tau_safe))
        return Inequality(G=cat([M, -M], 1), h=cat([lim - offset, lim + offset], 1))
