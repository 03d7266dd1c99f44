"""QP tasks of the A3CQP controller (eq. 1, 10-11, 18-23): each returns a weighted residual ‖A x − b‖²_W.

The variable is x = (q̈ [7], f [6]) (see context.py). A task only builds its residual (A, b) and its weight W;
`Residual.objective` turns it into the quadratic cost ½ xᵀ H x + cᵀ x with H = AᵀWA, c = −AᵀWb, and the controller
sums the costs (mink-style). Residuals are numpy arrays or torch tensors, the kind of the context (see arrays.py).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

import torch

from a3cqp_rl.control.arrays import Array, const, mm, mv, zeros
from a3cqp_rl.control.context import N_QDD, N_VARS, ControlContext
from a3cqp_rl.control.exceptions import InvalidGainError
from a3cqp_rl.control.frames import weights_to_world
from a3cqp_rl.control.piece import QPPiece

__all__ = ["Residual", "Task", "CartesianIK", "Admittance", "ForceControl", "JointCentering",
           "CartesianAccelerationRegularizer"]


@dataclass(frozen=True)
class Residual:
    """Weighted residual of one task for a batch: cost ‖A x_blk − b‖²_W on the block x_blk = x[col:col + m]."""

    A: Array | None
    """[B, k, m] rows on the block (None: the identity, k = m)."""
    b: Array
    """[B, k] target."""
    W: Array
    """[B, k, k] symmetric positive semi-definite weight."""
    col: int = 0
    """First variable of the block: 0 for q̈ (m = 7), 7 for f (m = 6)."""

    @property
    def size(self) -> int:
        """Block width m."""
        return self.b.shape[-1] if self.A is None else self.A.shape[-1]

    def block_objective(self) -> tuple[Array, Array]:
        """(H [B, m, m], c [B, m]) of the block cost ½ x_blkᵀ H x_blk + cᵀ x_blk (= ½‖A x_blk − b‖²_W + const)."""
        Wb = mv(self.W, self.b)
        if self.A is None:
            return self.W, -Wb
        At = self.A.mT
        return mm(At, mm(self.W, self.A)), -mv(At, Wb)

    def objective(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(H [B, 13, 13], c [B, 13]) on the whole x = (q̈, f) (torch residuals)."""
        Hb, cb = self.block_objective()
        H = Hb.new_zeros(Hb.shape[0], N_VARS, N_VARS)
        c = cb.new_zeros(cb.shape[0], N_VARS)
        sl = slice(self.col, self.col + self.size)
        H[:, sl, sl] = Hb
        c[:, sl] = cb
        return H, c

    def rows(self) -> torch.Tensor:
        """A as [B, k, 13] rows on the whole x (torch residuals)."""
        B, k = self.b.shape
        A = self.b.new_zeros(B, k, N_VARS)
        A[:, :, self.col:self.col + self.size] = (torch.eye(k, dtype=self.b.dtype, device=self.b.device)
                                                  if self.A is None else self.A)
        return A


def _check_positive(**values: float) -> None:
    for name, value in values.items():
        if not (value >= 0.0 and math.isfinite(value)):
            raise InvalidGainError(f"{name} must be finite and >= 0, got {value!r}")


class Task(QPPiece, ABC):
    """A QP task: its residual and weight from the step's context."""

    name: str = "task"

    @abstractmethod
    def residual(self, ctx: ControlContext) -> Residual:
        """Residual (A, b) and weight W of this task for the batch in `ctx`."""


class CartesianIK(Task):
    """IK task (eq. 1, 10-11): J q̈ + J̇q̇ = ẍ_d with ẍ_d = K_p e_x − K_v ẋ, weight W1.

    Args:
        kp: translational stiffness k_p [1/s²] (Table I: 150).
        k_theta: rotational stiffness k_θ [1/s²] (Table I: 20). K_v = 2√K_p (critical damping, eq. 11).
    """

    name = "ik"
    numpy_capable = True

    def __init__(self, kp: float = 150.0, k_theta: float = 20.0) -> None:
        _check_positive(kp=kp, k_theta=k_theta)
        self.kp, self.k_theta = kp, k_theta
        kp_diag = torch.tensor([kp] * 3 + [k_theta] * 3, dtype=torch.float64)
        self._gains = (kp_diag, 2.0 * kp_diag.sqrt())  # made once: building them costs as much as using them

    def gains(self, like: Array) -> tuple[Array, Array]:
        """Diagonals of K_p and K_v [6] (eq. 11)."""
        kp, kv = self._gains
        return const(kp, like), const(kv, like)

    def _c_params(self) -> tuple[str, dict]:
        return "ik", {"kp": self._gains[0].numpy(), "kv": self._gains[1].numpy()}

    def desired_acceleration(self, ctx: ControlContext) -> Array:
        """ẍ_d = K_p e_x − K_v ẋ [B, 6] (eq. 10), world frame (m/s², rad/s²)."""
        kp, kv = self.gains(ctx.q)
        return kp * ctx.pose_error - kv * ctx.kin.twist

    def residual(self, ctx: ControlContext) -> Residual:
        b = self.desired_acceleration(ctx) - ctx.kin.jdot_qdot
        if ctx.wrench_feedforward is not None:  # J q̈ + Λ⁻¹ f_ff + J̇q̇ = ẍ_d on the IK axes
            b = b - mv(ctx.cart_inertia_inv, ctx.wrench_feedforward)
        return Residual(A=ctx.kin.jac, b=b, W=ctx.W1, col=0)


class Admittance(Task):
    """AC task (eq. 16-18): f = f_adm so that the closed loop follows Λd ẍ + Cd ẋ = f_ext (eq. 17), weight W2.

    Args:
        lambda_d: desired apparent mass Λd [kg] (Table I: 5), the same for all six axes.
        c_d: desired damping Cd [N s/m] (Table I: 5).
        form: "consistent" (default) uses f_adm = (ΛΛd⁻¹ − I) f_ext − (ΛΛd⁻¹ Cd J + Λ J̇) q̇, which is what
            eq. 16 + 17 give and makes the steady velocity f_ext / Cd; "paper" uses eq. 18 as printed,
            −(Cd J + Λ J̇) q̇, whose steady velocity is Λ Λd⁻¹ f_ext / Cd.
    """

    name = "ac"
    numpy_capable = True

    def __init__(self, lambda_d: float = 5.0, c_d: float = 5.0,
                 form: Literal["consistent", "paper"] = "consistent") -> None:
        _check_positive(c_d=c_d)
        if not lambda_d > 0.0:
            raise InvalidGainError(f"lambda_d must be > 0, got {lambda_d!r}")
        if form not in ("consistent", "paper"):
            raise InvalidGainError(f"form must be 'consistent' or 'paper', got {form!r}")
        self.lambda_d, self.c_d, self.form = lambda_d, c_d, form

    def _c_params(self) -> tuple[str, dict]:
        return "ac", {"lambda_d": self.lambda_d, "c_d": self.c_d, "ac_paper": float(self.form == "paper")}

    def admittance_wrench(self, ctx: ControlContext) -> Array:
        """f_adm [B, 6] (N, N m), world frame (eq. 18)."""
        lam = ctx.cart_inertia  # Λ (B, 6, 6)
        twist, jdq = ctx.kin.twist, ctx.kin.jdot_qdot
        if self.form == "consistent":
            # Λ Λd⁻¹ (f_ext − Cd ẋ) − f_ext − Λ J̇q̇ = Λ (Λd⁻¹ (f_ext − Cd ẋ) − J̇q̇) − f_ext: one product with Λ
            v = (ctx.f_ext - self.c_d * twist) / self.lambda_d - jdq
            return mv(lam, v) - ctx.f_ext
        # eq. 18 as printed: Λ (Λd⁻¹ f_ext − J̇q̇) − f_ext − Cd J q̇
        v = ctx.f_ext / self.lambda_d - jdq
        return mv(lam, v) - ctx.f_ext - self.c_d * twist

    def residual(self, ctx: ControlContext) -> Residual:
        return Residual(A=None, b=self.admittance_wrench(ctx), W=ctx.W2, col=N_QDD)


class ForceControl(Task):
    """FC task (eq. 20-21): f = D f_d^𝓛 with 0 ≤ f_d^𝓛 ≤ f̄_d (clipped when the context is built), weight W3."""

    name = "fc"
    numpy_capable = True

    def _c_params(self) -> tuple[str, dict]:
        return "fc", {}

    def contact_wrench(self, ctx: ControlContext) -> Array:
        """f_ctc = D f_d^𝓛 [B, 6] (N, N m), world frame (eq. 20)."""
        return mv(ctx.D, ctx.f_d_local)

    def residual(self, ctx: ControlContext) -> Residual:
        return Residual(A=None, b=self.contact_wrench(ctx), W=ctx.W3, col=N_QDD)


class JointCentering(Task):
    """JC task (eq. 23-24): q̈ = q̈_d = k_q (q_d − q) − 2√k_q q̇, weight ε JᵀW1J + ε_N N.

    Eq. 1 weights JC by ε JᵀW1J only; that weight is zero on the null space of J, so by itself it cannot move the
    arm in its null space (it only adds ε to the IK task). `nullspace_weight` ε_N adds ε_N N (N = I − J⁺J, the
    null-space projector): the null-space motion then follows q̈_d exactly as in a strict hierarchy (the two
    weights act on orthogonal subspaces, so IK is not disturbed). ε_N = 0 reproduces eq. 1 exactly.

    Args:
        q_center: q_d [7] (rad), a configuration far from joint limits and singularities.
        kq: joint centering gain k_q [1/s²] (Table I: 10).
        epsilon: ε (Table I: 1e-4).
        nullspace_weight: ε_N (default 1e-3).
    """

    name = "jc"
    numpy_capable = True

    def __init__(self, q_center: torch.Tensor, kq: float = 10.0, epsilon: float = 1e-4,
                 nullspace_weight: float = 1e-3) -> None:
        _check_positive(kq=kq, epsilon=epsilon, nullspace_weight=nullspace_weight)
        self.q_center = torch.as_tensor(q_center, dtype=torch.float64)
        self.kq, self.epsilon, self.nullspace_weight = kq, epsilon, nullspace_weight

    def _c_params(self) -> tuple[str, dict]:
        return "jc", {"q_center": self.q_center.numpy(), "kq": self.kq, "jc_eps": self.epsilon,
                      "jc_eps_n": self.nullspace_weight}

    def desired_acceleration(self, ctx: ControlContext) -> Array:
        """q̈_d [B, 7] (rad/s²), eq. 23."""
        e_q = const(self.q_center, ctx.q) - ctx.q
        return self.kq * e_q - (2.0 * math.sqrt(self.kq)) * ctx.qd

    def residual(self, ctx: ControlContext) -> Residual:
        J = ctx.kin.jac
        jt_w1_j = ctx.jt_w1_j if ctx.jt_w1_j is not None else mm(J.mT, mm(ctx.W1, J))
        W = self.epsilon * jt_w1_j + self.nullspace_weight * ctx.nullspace
        return Residual(A=None, b=self.desired_acceleration(ctx), W=W, col=0)


def regularizer_ik_weight(ctx: ControlContext) -> Array:
    """D min(w1^𝓛, 1) Dᵀ [B, 6, 6]: the IK weight the Cartesian regularizer leaves out, W1 wherever w1 ≤ 1.

    A fixed controller's IK weight plus the share of force control that does not push (PandaEnv's idle share) can
    pass 1 on an axis; γ(I − W1) would then be negative there, and a level holding the regularizer alone (a Pareto
    genome's stack) non-convex: the QP's NON_CONVEX status at every step."""
    w1 = ctx.weights_local[..., 0]
    over = (w1 > 1.0 + 1e-9).any(-1)  # (a softmax's rounding above 1 is no reason to change a robot's numbers)
    if not bool(over.any()):
        return ctx.W1
    clipped = weights_to_world(ctx.D, w1.clip(max=1.0))
    return ctx.xp.where(over[:, None, None], clipped, ctx.W1)


class CartesianAccelerationRegularizer(Task):
    """J q̈ ≈ 0 on the axes IK does not weight: ‖J q̈‖² with weight γ D(I − min(w1^𝓛, 1))Dᵀ (not in the paper).

    Eq. 1 leaves q̈ free on the axes where w1 = 0 and only the Tikhonov term picks it; the minimum-norm q̈ then
    accelerates those axes (and pushes, through B q̈, on the AC/FC axes: a 10 N FC force loses ~2 N). With this
    term the IK/JC acceleration stays out of the AC/FC axes. γ = 0 removes it. (`regularizer_ik_weight`: why w1 is
    clipped at 1.)
    """

    name = "cartesian_regularizer"
    numpy_capable = True

    def __init__(self, gamma: float = 1e-2) -> None:
        _check_positive(gamma=gamma)
        self.gamma = gamma
        self._gamma_eye = gamma * torch.eye(6, dtype=torch.float64)

    def _c_params(self) -> tuple[str, dict]:
        return "creg", {"creg_gamma": self.gamma}

    def residual(self, ctx: ControlContext) -> Residual:
        return Residual(A=ctx.kin.jac, b=zeros((ctx.batch, 6), ctx.q),
                        W=const(self._gamma_eye, ctx.q) - self.gamma * regularizer_ik_weight(ctx), col=0)
