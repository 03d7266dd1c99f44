"""Per-step quantities shared by the tasks and limits of the A3CQP QP (built once per control step).

The arrays are torch tensors, or numpy arrays on the controller's CPU path (see arrays.py); the field docs say
"tensor" for either.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from a3cqp_rl.robot.kinematics import Kinematics

__all__ = ["ControlContext", "N_QDD", "N_WRENCH", "N_VARS"]

N_QDD = 7
"""Joint accelerations q̈ occupy x[:, :7] (rad/s²)."""
N_WRENCH = 6
"""The end-effector wrench f occupies x[:, 7:13] (N, N m), world frame, force first."""
N_VARS = N_QDD + N_WRENCH
"""QP variable x = (q̈, f) (eq. 1)."""


@dataclass(frozen=True)
class ControlContext:
    """Batch [B] of robot states, references and derived matrices for one control step; world frame, SI units."""

    q: torch.Tensor
    """Joint positions [B, 7] (rad)."""
    qd: torch.Tensor
    """Joint velocities [B, 7] (rad/s)."""
    kin: Kinematics
    """Control-site pose, Jacobian J [B, 6, 7], J̇q̇ and twist ẋ = J q̇."""
    mass: torch.Tensor
    """Joint-space inertia B(q) [B, 7, 7] (kg m²)."""
    mass_inv_jt: torch.Tensor
    """B⁻¹ Jᵀ [B, 7, 6]: joint acceleration per unit end-effector wrench."""
    cart_inertia: torch.Tensor
    """Λ = (J B⁻¹ Jᵀ)⁻¹ [B, 6, 6] (kg, kg m²), eq. 12."""
    cart_inertia_inv: torch.Tensor
    """Λ⁻¹ = J B⁻¹ Jᵀ [B, 6, 6]: site acceleration per unit wrench applied through Jᵀ."""
    D: torch.Tensor
    """blockdiag(R, R) [B, 6, 6] with R the rotation of the local frame 𝓛 (eq. 3)."""
    weights_local: torch.Tensor
    """Per-axis local weights w^𝓛 [B, 6, 3] (columns IK, AC, FC)."""
    W1: torch.Tensor
    """IK weight in world [B, 6, 6] (eq. 8)."""
    W2: torch.Tensor
    """AC weight in world [B, 6, 6] (eq. 8)."""
    W3: torch.Tensor
    """FC weight in world [B, 6, 6] (eq. 8)."""
    pose_error: torch.Tensor
    """e_x = x_d ⊖ x [B, 6] (m, rad), world frame (eq. 10)."""
    f_ext: torch.Tensor
    """Measured external wrench at the control site [B, 6] (N, N m), world frame."""
    f_d_local: torch.Tensor
    """Desired contact wrench in 𝓛 [B, 6] (N, N m), already clipped to [0, f̄_d] (eq. 21)."""
    in_contact: torch.Tensor
    """Bool [B]: the tool touches the environment (activates the friction pyramid, eq. 9)."""
    qdd_pd0: torch.Tensor
    """q̈_pd of eq. 5 evaluated with q̈* = 0 [B, 7] (rad/s²)."""
    pd_qdd_gain: torch.Tensor
    """∂q̈_pd/∂q̈* = (c_v Δt + c_p Δt²/2) P W1 J [B, 7, 7] (eq. 5-7 are linear in q̈*)."""
    nullspace: torch.Tensor
    """N = I − J⁺J [B, 7, 7], damped pseudo-inverse: the joint motions that leave the site still."""
    pd_matrix: torch.Tensor
    """P W1 J [B, 7, 7] of eq. 5 (P = Jᵀ as printed, or J⁺; see ControllerOptions.pd_projection)."""
    dt: float
    """Control period Δt [s]."""
    bias: torch.Tensor | None = None
    """h + g [B, 7] (N m), for the torque limits (None when the caller did not provide it)."""
    qdd_map: torch.Tensor | None = None
    """I + ∂q̈_pd/∂q̈* [B, 7, 7]: the commanded joint acceleration per unit q̈* (None: limits compute it)."""
    jpinv: torch.Tensor | None = None
    """J⁺ [B, 7, 6], the damped pseudo-inverse of N (for the per-axis relaxation of q*, q̇*)."""
    jt_w1_j: torch.Tensor | None = None
    """Jᵀ W1 J [B, 7, 7] (the IK weight pulled back to joint space; None: tasks compute it)."""
    wrench_feedforward: torch.Tensor | None = None
    """Wrench the AC/FC tasks are expected to command [B, 6] (N, N m) (set by the controller; None = 0): the IK task
    can subtract its acceleration Λ⁻¹ f so that AC/FC on some axes do not drag the IK axes (Λ⁻¹ couples them)."""
    f_ext_limits: torch.Tensor | None = None
    """Bool [B]: the robots whose joint-limit rows count f_ext (A3CQPController.step), or None: none."""
    cache: dict = field(default_factory=dict, compare=False, repr=False)
    """Per-step values shared between limits (e.g. the viable joint acceleration bounds, used by JointLimitsViability,
    TorqueLimits and the fallback); shared by `dataclasses.replace` copies of this context."""

    @property
    def batch(self) -> int:
        """Batch size B."""
        return self.q.shape[0]

    @property
    def xp(self):  # noqa: ANN201
        """The array module of this context's arrays: numpy or torch."""
        return np if isinstance(self.q, np.ndarray) else torch
