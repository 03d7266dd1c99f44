"""Frame helpers for the A3CQP controller: eq. 3 (D), eq. 8 (weights to world), eq. 10 pose error; batched float64."""

from __future__ import annotations

import torch

__all__ = ["block_rotation", "weights_to_world", "pose_error", "rotation_log"]


_BLOCK_MASK = torch.kron(torch.eye(2, dtype=torch.float64), torch.ones(3, 3, dtype=torch.float64))  # (6, 6)


def block_rotation(rot: torch.Tensor) -> torch.Tensor:
    """D = blockdiag(R, R) [B, 6, 6] from R [B, 3, 3] (eq. 3): maps local-frame twists/wrenches to world."""
    # tile R 2 x 2 and zero the off-diagonal blocks: 2 ops instead of zeros + 2 slice writes
    return rot.repeat(*([1] * (rot.dim() - 2)), 2, 2) * _BLOCK_MASK.to(rot)


def weights_to_world(D: torch.Tensor, w_local: torch.Tensor) -> torch.Tensor:
    """W = D diag(w^L) Dᵀ [B, 6, 6] (eq. 8) from D [B, 6, 6] and per-axis local weights w^L [B, 6].

    Also [B, K, 6, 6] for K weights at once from D [B, 1, 6, 6] (or [B, K, 6, 6]) and w^L [B, K, 6].
    """
    Dw = D * w_local.unsqueeze(-2)
    if Dw.dim() == 4 and D.shape[1] == 1:  # K weights, one D per robot: one bmm on the stacked rows [B, 6K, 6]
        B, K = Dw.shape[:2]
        return torch.bmm(Dw.reshape(B, K * 6, 6), D[:, 0].transpose(-1, -2)).view(B, K, 6, 6)
    return Dw @ D.transpose(-1, -2)


_VEE = torch.tensor([7, 2, 3])  # flat indices of (R − Rᵀ)[2,1], [0,2], [1,0]: the vee of the skew part


def rotation_log(rot: torch.Tensor) -> torch.Tensor:
    """Rotation vector θ·axis [B, 3] (rad) of rotation matrices [B, 3, 3] (exact for θ < π, any θ near 0)."""
    v = 0.5 * (rot - rot.transpose(-1, -2)).flatten(-2)[..., _VEE]  # sin θ · axis
    s = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    c = 0.5 * (rot.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True) - 1.0)
    theta = torch.atan2(s, c)
    scale = torch.where(s > 1e-9, theta / s.clamp_min(1e-12), 1.0 + theta.square() / 6.0)  # θ / sin θ
    return scale * v


def pose_error(pos_d: torch.Tensor, rot_d: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """e_x = x_d ⊖ x [B, 6] in the world frame (eq. 10): position error (m), then axis-angle of R_d Rᵀ (rad)."""
    R_err = torch.bmm(rot_d, rot.transpose(-1, -2)) if rot.dim() == 3 else rot_d @ rot.transpose(-1, -2)
    return torch.cat([pos_d - pos, rotation_log(R_err)], dim=-1)
