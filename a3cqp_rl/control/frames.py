"""Frame helpers for the A3CQP controller: eq. 3 (D), eq. 8 (weights to world), eq. 10 pose error; batched float64.

Each takes numpy arrays or torch tensors (see arrays.py) and returns the same kind.
"""

from __future__ import annotations

import numpy as np
import torch

from a3cqp_rl.control.arrays import Array, cat, mm, xp_of

__all__ = ["block_rotation", "weights_to_world", "pose_error", "rotation_log"]


_BLOCK_MASK = torch.kron(torch.eye(2, dtype=torch.float64), torch.ones(3, 3, dtype=torch.float64))  # (6, 6)


def block_rotation(rot: Array) -> Array:
    """D = blockdiag(R, R) [B, 6, 6] from R [B, 3, 3] (eq. 3): maps local-frame twists/wrenches to world."""
    if isinstance(rot, np.ndarray):
        D = np.zeros(rot.shape[:-2] + (6, 6))
        D[..., :3, :3] = rot
        D[..., 3:, 3:] = rot
        return D
    # tile R 2 x 2 and zero the off-diagonal blocks: 2 ops instead of zeros + 2 slice writes
    return rot.repeat(*([1] * (rot.dim() - 2)), 2, 2) * _BLOCK_MASK.to(rot)


def weights_to_world(D: Array, w_local: Array) -> Array:
    """W = D diag(w^L) Dᵀ [B, 6, 6] (eq. 8) from D [B, 6, 6] and per-axis local weights w^L [B, 6].

    Also [B, K, 6, 6] for K weights at once from D [B, 1, 6, 6] (or [B, K, 6, 6]) and w^L [B, K, 6].
    """
    Dw = D * w_local[..., None, :]
    if Dw.ndim == 4 and D.shape[1] == 1:  # K weights, one D per robot: one product on the stacked rows [B, 6K, 6]
        B, K = Dw.shape[:2]
        return mm(Dw.reshape(B, K * 6, 6), D[:, 0].mT).reshape(B, K, 6, 6)
    return Dw @ D.mT


_VEE = [7, 2, 3]  # flat indices of (R − Rᵀ)[2,1], [0,2], [1,0]: the vee of the skew part
_VEE_T = torch.tensor(_VEE)


def rotation_log(rot: Array) -> Array:
    """Rotation vector θ·axis [B, 3] (rad) of rotation matrices [B, 3, 3] (exact for θ < π, any θ near 0)."""
    xp = xp_of(rot)
    skew = (rot - rot.mT).reshape(*rot.shape[:-2], 9)
    v = 0.5 * skew[..., _VEE if xp is np else _VEE_T]  # sin θ · axis
    s = xp.sqrt((v * v).sum(-1))[..., None]
    c = 0.5 * (rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2] - 1.0)[..., None]
    theta = xp.arctan2(s, c)
    scale = xp.where(s > 1e-9, theta / s.clip(1e-12), 1.0 + theta * theta / 6.0)  # θ / sin θ
    return scale * v


def pose_error(pos_d: Array, rot_d: Array, pos: Array, rot: Array) -> Array:
    """e_x = x_d ⊖ x [B, 6] in the world frame (eq. 10): position error (m), then axis-angle of R_d Rᵀ (rad)."""
    R_err = mm(rot_d, rot.mT) if rot.ndim == 3 else rot_d @ rot.mT
    return cat([pos_d - pos, rotation_log(R_err)], -1)
