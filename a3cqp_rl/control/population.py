"""A population of fixed controllers in one batch: every robot has its own gains and strict priority levels.

`A3CQPController` gives all N robots the same gains (Table I) and the same stack of priority levels; only the task
weights and f_d differ per robot. Tuning controllers the way paper 002 does (NSGA-II over soft weights, priority
levels and convergence gains) evaluates many different controllers on the same scene, and a batch of N robots is far
cheaper to simulate than N batches of one (the per-step cost of the env and the controller is mostly per call, not
per robot). `PopulationController` is that batch:

- gains per robot: k_p, k_θ (IK, eq. 11), Λd, Cd (AC, eq. 18), k_q (JC, eq. 23), and multipliers of the JC weight
  (ε, ε_N) and of the Cartesian regularizer's γ (`RobotGains`);
- levels per robot: each task in level 1..3 or off (0), as `A3CQPController(levels=...)` but per robot
  (`levels` [N, 5] in the order of `TASKS`). Robot b's QP is exactly the one `A3CQPController(levels=its levels)`
  builds: a task is added to level k's cost only for the robots that put it there, an off task for none of them,
  and the robots are solved in groups of equal level count (one `solve_cascade` call per group: 1 to 3 calls).

On the CPU the population runs the C step (control/native, `a3cqp_assemble_robots`): each arm its own gains and,
per level, which of its tasks count in that level's cost; one C call per level (1 to 3), then the same QP or cascade
as the Python objects, which stay the reference (`options.backend` "python"; tests: agreement to rounding).

A robot with Table I gains and every task in level 1 gets the same torques as `A3CQPController` (tested). The
weights of IK, AC and FC come in per step as for `A3CQPController` (columns of `weights`); for a robot with one of
them off, its column is zeroed here (so the feed-forward of the wrench tasks and the joint feedback of eq. 5, which
use the weights directly, see it off too).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from a3cqp_rl.config import ControllerConfig
from a3cqp_rl.control.arrays import Array, const, mv, zeros
from a3cqp_rl.control.context import ControlContext
from a3cqp_rl.control import native
from a3cqp_rl.control.controller import (A3CQPController, ControllerOptions, ControlOutput, _f_ext_limits,
                                         _model_kinematics, _np, _StepInputs)
from a3cqp_rl.control.exceptions import InvalidGainError, InvalidLevelError
from a3cqp_rl.control.hierarchy import MAX_LEVEL, Hierarchy, solve_cascade
from a3cqp_rl.control.tasks import (Admittance, CartesianAccelerationRegularizer, CartesianIK, ForceControl,
                                    JointCentering, Residual, regularizer_ik_weight)
from a3cqp_rl.robot.kinematics import PandaModel
from a3cqp_rl.robot.specs import PANDA_LIMITS, PandaLimits

__all__ = ["TASKS", "RobotGains", "PopulationController"]

TASKS = ("ik", "ac", "fc", "jc", "cartesian_regularizer")
"""The tasks of a population controller, in the order of the columns of `levels`."""
_WEIGHT_COLUMN = {"ik": 0, "ac": 1, "fc": 2}
"""Task -> its column in the per-axis weights w^L [N, 6, 3]."""


@dataclass(frozen=True)
class RobotGains:
    """Per-robot gains [N] each (SI units as ControllerConfig); `uniform` fills them from one ControllerConfig."""

    kp: np.ndarray
    """IK translational stiffness k_p [1/s²] (eq. 11)."""
    k_theta: np.ndarray
    """IK rotational stiffness k_θ [1/s²] (eq. 11)."""
    lambda_d: np.ndarray
    """AC desired apparent mass Λd [kg] (eq. 18)."""
    c_d: np.ndarray
    """AC desired damping Cd [N s/m] (eq. 18)."""
    kq: np.ndarray
    """JC gain k_q [1/s²] (eq. 23)."""
    jc_weight: np.ndarray
    """Multiplier of the JC weight (ε and ε_N of ControllerConfig / ControllerOptions; 1 = unchanged)."""
    cartesian_regularization: np.ndarray
    """γ of the Cartesian acceleration regularizer (ControllerOptions.cartesian_regularization)."""

    @classmethod
    def uniform(cls, n: int, config: ControllerConfig | None = None,
                options: ControllerOptions | None = None) -> "RobotGains":
        """Every robot with the gains of `config` (default Table I) and the regularizer of `options`."""
        c, o = config or ControllerConfig(), options or ControllerOptions()
        full = lambda v: np.full(n, float(v))  # noqa: E731
        return cls(kp=full(c.kp), k_theta=full(c.k_theta), lambda_d=full(c.lambda_d), c_d=full(c.c_d),
                   kq=full(c.kq), jc_weight=full(1.0), cartesian_regularization=full(o.cartesian_regularization))

    def check(self, n: int) -> "RobotGains":
        """Shapes [n] and values (finite, >= 0; Λd > 0): InvalidGainError naming the gain and the robot."""
        out = {}
        for f in dataclasses.fields(self):
            v = np.asarray(getattr(self, f.name), dtype=np.float64).reshape(-1)
            if v.shape != (n,):
                raise InvalidGainError(f"gain {f.name} needs one value per robot ({n}), got shape {v.shape}")
            low = 0.0 if f.name != "lambda_d" else math.nextafter(0.0, 1.0)
            bad = np.flatnonzero(~(np.isfinite(v) & (v >= low)))
            if len(bad):
                need = "> 0" if f.name == "lambda_d" else ">= 0"
                raise InvalidGainError(f"gain {f.name} of robot {bad[0]} must be finite and {need}, got {v[bad[0]]}")
            out[f.name] = v
        return RobotGains(**out)


def _column(v: np.ndarray, *trailing: int) -> torch.Tensor:
    """[N] values as a float64 tensor [N, 1, ...] that broadcasts against per-robot arrays."""
    return torch.from_numpy(np.ascontiguousarray(v, dtype=np.float64).reshape(-1, *([1] * len(trailing))))


class _RobotIK(CartesianIK):
    """CartesianIK with k_p, k_θ per robot (K_p = diag(k_p I3, k_θ I3), K_v = 2√K_p: eq. 11)."""

    def __init__(self, kp: np.ndarray, k_theta: np.ndarray) -> None:
        self.kp, self.k_theta = kp, k_theta
        kp_diag = torch.from_numpy(np.stack([kp] * 3 + [k_theta] * 3, axis=1))  # [N, 6]
        self._gains = (kp_diag, 2.0 * kp_diag.sqrt())


class _RobotAdmittance(Admittance):
    """Admittance with Λd, Cd per robot (eq. 16-18)."""

    def __init__(self, lambda_d: np.ndarray, c_d: np.ndarray, form: str) -> None:
        super().__init__(1.0, 1.0, form=form)  # validates `form`; the gains are replaced below
        self.lambda_d, self.c_d = _column(lambda_d, 1), _column(c_d, 1)

    def admittance_wrench(self, ctx: ControlContext) -> Array:
        lam, twist, jdq = ctx.cart_inertia, ctx.kin.twist, ctx.kin.jdot_qdot
        lambda_d, c_d = const(self.lambda_d, ctx.q), const(self.c_d, ctx.q)
        if self.form == "consistent":
            return mv(lam, (ctx.f_ext - c_d * twist) / lambda_d - jdq) - ctx.f_ext
        return mv(lam, ctx.f_ext / lambda_d - jdq) - ctx.f_ext - c_d * twist


class _RobotJointCentering(JointCentering):
    """JointCentering with k_q per robot and its weight ε JᵀW1J + ε_N N scaled per robot (eq. 23)."""

    def __init__(self, q_center: torch.Tensor, kq: np.ndarray, weight: np.ndarray, epsilon: float,
                 nullspace_weight: float) -> None:
        super().__init__(q_center, 1.0, epsilon, nullspace_weight)
        self.kq, self._kv = _column(kq, 1), _column(2.0 * np.sqrt(kq), 1)
        self.weight = _column(weight, 1, 1)

    def desired_acceleration(self, ctx: ControlContext) -> Array:
        e_q = const(self.q_center, ctx.q) - ctx.q
        return const(self.kq, ctx.q) * e_q - const(self._kv, ctx.q) * ctx.qd

    def residual(self, ctx: ControlContext) -> Residual:
        res = super().residual(ctx)
        return dataclasses.replace(res, W=const(self.weight, ctx.q) * res.W)


class _RobotCartesianRegularizer(CartesianAccelerationRegularizer):
    """CartesianAccelerationRegularizer with γ per robot: weight γ D(I − min(w1^L, 1))Dᵀ."""

    def __init__(self, gamma: np.ndarray) -> None:
        super().__init__(0.0)
        self.gamma = _column(gamma, 1, 1)
        self._eye6 = torch.eye(6, dtype=torch.float64)

    def residual(self, ctx: ControlContext) -> Residual:
        W = const(self.gamma, ctx.q) * (const(self._eye6, ctx.q) - regularizer_ik_weight(ctx))
        return Residual(A=ctx.kin.jac, b=zeros((ctx.batch, 6), ctx.q), W=W, col=0)


def _scaled(res: Residual, mask: Array) -> Residual:
    """The residual with its weight multiplied by a per-robot factor [N] (0: the task is not in this QP)."""
    return dataclasses.replace(res, W=res.W * mask[:, None, None])


_LEVEL_OF = {"ik_wrench": "ik"}
"""Residuals that are not tasks of their own -> the task whose level they share."""


class PopulationController(A3CQPController):
    """N fixed controllers in one batch: per-robot gains (`RobotGains`) and strict levels ([N, 5], `TASKS` order).

    Args:
        n: number of robots N.
        model, config, options, limits: as A3CQPController (config gives ε, the wrench box and the defaults of the
            gains; `options.backend`: "auto" the C step on the CPU when available, "python" the objects, "native"
            the C step or an error).
        gains: per-robot gains (default: `RobotGains.uniform(n, config, options)`).
        levels: per-robot levels [N, 5] (1..3, 0 = off) in the order of `TASKS` (default: all in level 1).
    """

    def __init__(self, n: int = 1, model: PandaModel | None = None, config: ControllerConfig | None = None,
                 options: ControllerOptions | None = None, limits: PandaLimits = PANDA_LIMITS,
                 gains: RobotGains | None = None, levels: np.ndarray | None = None) -> None:
        config, options = config or ControllerConfig(), options or ControllerOptions()
        g = (gains or RobotGains.uniform(n, config, options)).check(n)
        self.gains = g
        tasks = [_RobotIK(g.kp, g.k_theta), _RobotAdmittance(g.lambda_d, g.c_d, options.admittance_form),
                 ForceControl(),
                 _RobotJointCentering(torch.tensor(options.q_center, dtype=torch.float64), g.kq, g.jc_weight,
                                      config.epsilon, options.jc_nullspace_weight),
                 _RobotCartesianRegularizer(g.cartesian_regularization)]
        super().__init__(n, model=model, config=config, options=options, limits=limits, tasks=tasks)
        self.saturated_periods = np.zeros(n, dtype=np.int64)
        """Control periods in which some joint torque of the robot hit its limit (counted by `step`; zero it to
        start a new count)."""
        self.set_robot_levels(np.ones((n, len(TASKS)), dtype=np.int64) if levels is None else levels)

    # ------------------------------------------------------------------ levels
    def set_levels(self, levels) -> None:  # noqa: ANN001
        """The same stack for every robot ({task: 1..3 or None} or a list in `TASKS` order, as A3CQPController)."""
        if not hasattr(self, "robot_levels"):  # A3CQPController.__init__ calls this before the robot levels exist
            return super().set_levels(levels)
        h = Hierarchy.of(TASKS, levels)
        row = [next((k + 1 for k, lvl in enumerate(h.levels) if name in lvl), 0) for name in TASKS]
        self.set_robot_levels(np.tile(row, (self.n, 1)))

    def set_robot_levels(self, levels: np.ndarray) -> None:
        """Per-robot levels [N, 5] (ints 1..3, 0 = off; `TASKS` order). Empty levels are closed up per robot, as
        `Hierarchy.of` does (levels 1 and 3 act as 1 and 2)."""
        lv = np.asarray(levels)
        if lv.shape != (self.n, len(TASKS)):
            raise InvalidLevelError(f"levels must have shape ({self.n}, {len(TASKS)}) (robots × tasks {TASKS}), "
                                    f"got {lv.shape}")
        if not np.issubdtype(lv.dtype, np.integer):
            if not (np.isfinite(lv).all() and (lv == np.round(lv)).all()):
                raise InvalidLevelError(f"levels must be whole numbers 0..{MAX_LEVEL}, got {lv.tolist()}")
            lv = lv.astype(np.int64)
        bad = np.argwhere((lv < 0) | (lv > MAX_LEVEL))
        if len(bad):
            r, t = bad[0]
            raise InvalidLevelError(f"robot {r}, task {TASKS[t]!r}: level must be 1-{MAX_LEVEL} or 0 (off), "
                                    f"got {lv[r, t]}")
        # close up empty levels: level -> its rank among the robot's used levels
        used = np.stack([(lv == k).any(1) for k in range(1, MAX_LEVEL + 1)], axis=1)  # [N, 3]
        rank = np.concatenate([np.zeros((self.n, 1), np.int64), np.cumsum(used, axis=1)], axis=1)  # level -> rank
        compact = np.take_along_axis(rank, lv, axis=1) * (lv > 0)
        self.robot_levels = compact
        self.level_count = np.maximum(compact.max(1), 1)
        """Number of levels of each robot's stack [N] (a robot with every task off has one, empty)."""
        K = int(self.level_count.max())
        self._robot_rows = self._native_rows(compact, K) if self._native is not None else []
        self._masks = [{name: torch.from_numpy((compact[:, t] == k + 1).astype(np.float64))
                        for t, name in enumerate(TASKS)} for k in range(K)]
        self._on = {name: torch.from_numpy((compact[:, t] > 0).astype(np.float64)) for t, name in enumerate(TASKS)}
        self._weight_on = torch.from_numpy(np.stack([compact[:, _WEIGHT_COLUMN[n]] > 0 for n in ("ik", "ac", "fc")],
                                                    axis=1).astype(np.float64))[:, None, :]  # [N, 1, 3]
        self._groups = [(k, torch.from_numpy(np.flatnonzero(self.level_count == k)))
                        for k in range(1, K + 1) if (self.level_count == k).any()]
        # the union of the robots' stacks, for display and for A3CQPController.step's choice of path
        union = tuple(tuple(n for t, n in enumerate(TASKS) if (compact[:, t] == k + 1).any()) for k in range(K))
        self.hierarchy = Hierarchy(levels=union or ((),), off=tuple(n for t, n in enumerate(TASKS)
                                                                     if (compact[:, t] == 0).all()))
        self._warm, self._warm_levels, self._warm_groups = None, (), {}

    def _native_fields(self, tasks=None) -> tuple[dict | None, str]:  # noqa: ANN001
        """The C parameters of the default composition (the per-robot gains come in `_robot_rows`)."""
        if tasks is not None:
            return super()._native_fields(tasks)
        kinds = (_RobotIK, _RobotAdmittance, ForceControl, _RobotJointCentering, _RobotCartesianRegularizer)
        if len(self.tasks) != len(kinds) or not all(type(t) is k for t, k in zip(self.tasks, kinds)):
            return None, "the population's tasks were replaced"
        cfg, opt = self.config, self.options
        # stand-ins of the default classes (their gain fields are replaced per robot by the C call)
        return super()._native_fields([
            CartesianIK(cfg.kp, cfg.k_theta), Admittance(cfg.lambda_d, cfg.c_d, form=opt.admittance_form),
            ForceControl(), JointCentering(self.tasks[3].q_center, cfg.kq, cfg.epsilon, opt.jc_nullspace_weight),
            CartesianAccelerationRegularizer(1.0)])

    def _native_rows(self, compact: np.ndarray, K: int) -> list[np.ndarray]:
        """Per level k < K, the C step's per-robot rows [N, R]: the robot's gains and which of its tasks count in
        level k's cost (IK, AC, FC by cost shares; JC and the regularizer by their weights)."""
        g, jc = self.gains, self.tasks[3]
        kp = np.stack([g.kp] * 3 + [g.k_theta] * 3, axis=1)
        rows = []
        for k in range(1, K + 1):
            on = {name: (compact[:, t] == k).astype(np.float64) for t, name in enumerate(TASKS)}
            rows.append(self._native.robot_rows(
                kp=kp, kv=2.0 * np.sqrt(kp), lambda_d=g.lambda_d, c_d=g.c_d, kq=g.kq,
                jc_eps=jc.epsilon * g.jc_weight * on["jc"], jc_eps_n=jc.nullspace_weight * g.jc_weight * on["jc"],
                creg_gamma=g.cartesian_regularization * on["cartesian_regularizer"], cost_ik=on["ik"],
                cost_ac=on["ac"], cost_fc=on["fc"]))
        return rows

    def _native_fits(self) -> bool:
        """Any stack: the C step assembles each level's cost with the robots' own tasks (`_robot_rows`)."""
        return True

    def _native_qp(self, inp: _StepInputs) -> tuple[native.Assembled, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One C assembly per level, then the single QP (every robot one level) or the cascade per group."""
        kin = inp.kin if inp.kin is not None else _model_kinematics(self.model, inp.q, inp.qd)
        packed = self._native.pack(
            q=inp.q, qd=inp.qd, mass=inp.mass, bias=inp.bias, jac=kin.jac, jdot_qdot=kin.jdot_qdot, twist=kin.twist,
            pos=kin.pos, rot=kin.rot, weights=inp.weights, f_d=inp.f_d, pos_d=inp.pos_d, rot_d=inp.rot_d,
            f_ext=inp.f_ext, in_contact=inp.in_contact, q_des=_np(self.q_des), qd_des=_np(self.qd_des),
            f_ext_limits=_f_ext_limits(inp.f_ext_limits, self.n))
        levels = [self._native.assemble(robots=rows, packed=packed) for rows in self._robot_rows]
        t, asm = torch.from_numpy, levels[0]
        if len(levels) == 1:
            return asm, *self._solve(t(asm.P), t(asm.c), t(asm.G), t(asm.h))
        return asm, *self._solve_levels([(t(a.P), t(a.c)) for a in levels], t(asm.G), t(asm.h))

    def describe(self, b: int) -> str:
        """Robot b's stack in the notation of eq. 3, e.g. "(ik + cartesian_regularizer) / (ac + fc) / (jc)"."""
        lv = self.robot_levels[b]
        levels = {name: int(lv[t]) or None for t, name in enumerate(TASKS)}
        return str(Hierarchy.of(TASKS, levels))

    # ------------------------------------------------------------------ QP
    def step(self, q: torch.Tensor, qd: torch.Tensor, mass: torch.Tensor, bias: torch.Tensor,
             weights: torch.Tensor, *args, **kwargs) -> ControlOutput:
        """A3CQPController.step with the weights of robots' off tasks zeroed; counts torque saturation."""
        weights = torch.as_tensor(weights, dtype=torch.float64)
        if weights.shape == (self.n, 6, 3):
            weights = weights * self._weight_on
        out = super().step(q, qd, mass, bias, weights, *args, **kwargs)
        self.saturated_periods += out.saturated.numpy()
        return out

    def task_residuals(self, ctx: ControlContext) -> dict[str, Residual]:
        """Every task's residual, JC and the regularizer weighted 0 for the robots that turn them off (IK, AC and FC
        are off through their zeroed weights)."""
        res = super().task_residuals(ctx)
        for name in ("jc", "cartesian_regularizer"):
            if name in res:
                res[name] = _scaled(res[name], const(self._on[name], ctx.q))
        self.residuals = res
        return res

    def build_levels(self, ctx: ControlContext) -> tuple[list[tuple[Array, Array]], Array, Array]:
        """Level k's cost per robot: the tasks that robot puts in level k (paper 002 eq. 2); then the limit rows."""
        res = self.task_residuals(ctx)
        # wrench_blend "weighted_sum" adds IK's zero-wrench residual (weight W1): it belongs to IK's level
        costs = [self.task_cost(ctx, [_scaled(r, const(masks[_LEVEL_OF.get(name, name)], ctx.q))
                                      for name, r in res.items()])
                 for masks in self._masks]
        return costs, *self.limit_rows(ctx)

    def _solve_levels(self, costs: list[tuple[torch.Tensor, torch.Tensor]], G: torch.Tensor,
                      h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One cascade per group of robots with the same number of levels (a robot solves only its own levels)."""
        n = self.n
        try:
            if len(self._groups) == 1:
                k, _ = self._groups[0]
                sol = solve_cascade(costs[:k], G, h, self.options.regularization, warm=self._warm_groups.get(k),
                                    max_iter=self.options.qp_max_iter, hand_on=self.options.qp_hand_on)
                self._warm_groups[k] = sol.solutions
                return sol.x, sol.status, sol.iterations
            x = G.new_zeros(n, costs[0][0].shape[-1])
            status = torch.zeros(n, dtype=torch.long)
            iterations = torch.zeros(n, dtype=torch.long)
            for k, idx in self._groups:
                sol = solve_cascade([(P[idx], c[idx]) for P, c in costs[:k]], G[idx], h[idx],
                                    self.options.regularization, warm=self._warm_groups.get(k),
                                    max_iter=self.options.qp_max_iter, hand_on=self.options.qp_hand_on)
                self._warm_groups[k] = sol.solutions
                x[idx], status[idx], iterations[idx] = sol.x, sol.status, sol.iterations
            return x, status, iterations
        except Exception:
            self._warm_groups = {}
            return self._solver_raised(G)

    def reset(self, q: torch.Tensor, qd: torch.Tensor | None = None, idx=None) -> None:  # noqa: ANN001
        """A3CQPController.reset; a full reset also drops the groups' warm starts."""
        super().reset(q, qd, idx)
        if idx is None:
            self._warm_groups = {}

    def _report_fallback(self, ok, qp_status, valid) -> None:  # noqa: ANN001
        super()._report_fallback(ok, qp_status, valid)
        failed = ~np.asarray(ok, dtype=bool)
        for k, idx in self._groups:  # each group's solutions are indexed within the group
            rows = np.flatnonzero(failed[idx.numpy()])
            for sol in self._warm_groups.get(k, ()) if rows.size else ():
                sol.forget(rows)
