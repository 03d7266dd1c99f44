"""Frame helpers for the A3CQP controller: eq. 3 (D), eq. 8 (weights to world), eq. 10 pose error; batched float64."""

from __future__ import annotations

import torch

__all__ = ["block_rotation", "weights_to_world", "pose_error", "rotation_log"]


def block_rotation(rot: torch.Tensor) -> torch.Tensor:
    """D = blockdiag(R, R) [B, 6, 6] from R [B, 3, 3] (eq. 3): maps local-frame twists/wrenches to world."""
    D = rot.new_zeros(*rot.shape[:-2], 6, 6)
    D[..., :3, :3] = rot
    D[..., 3:, 3:] = rot
    return D


def weights_to_world(D: torch.Tensor, w_local: torch.Tensor) -> torch.Tensor:
    """W = D diag(w^L) Dᵀ [B, 6, 6] (eq. 8) from D [B, 6, 6] and per-axis local weights w^L [B, 6]."""
    return (D * w_local.unsqueeze(-2)) @ D.transpose(-1, -2)


def rotation_log(rot: torch.Tensor) -> torch.Tensor:
    """Rotation vector θ·axis [B, 3] (rad) of rotation matrices [B, 3, 3] (exact for θ < π, any θ near 0)."""
    v = 0.5 * torch.stack([rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0],
                           rot[..., 1, 0] - rot[..., 0, 1]], dim=-1)  # sin θ · axis
    s = v.norm(dim=-1, keepdim=True)
    c = 0.5 * (rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2] - 1.0).unsqueeze(-1)
    theta = torch.atan2(s, c)
    scale = torch.where(s > 1e-9, theta / s.clamp_min(1e-12), 1.0 + theta.square() / 6.0)  # θ / sin θ
    return scale * v


def pose_error(pos_d: torch.Tensor, rot_d: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """e_x = x_d ⊖ x [B, 6] in the world frame (eq. 10): position error (m), then axis-angle of R_d Rᵀ (rad)."""
    return torch.cat([pos_d - pos, rotation_log(rot_d @ rot.transpose(-1, -2))], dim=-1)
