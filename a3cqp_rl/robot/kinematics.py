"""Batched Panda kinematics on pytorch-kinematics: FK, world-frame site Jacobian and J̇q̇ (float64)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import pytorch_kinematics as pk
import pytorch_kinematics.mjcf as pk_mjcf
import torch

from a3cqp_rl.robot.exceptions import MjcfError
from a3cqp_rl.robot.mjcf import DEFAULT_TOOL, compose_mjcf, mjcf_file

__all__ = ["Kinematics", "PandaModel", "build_chain_from_mjcf", "JOINT_NAMES", "LINK_NAMES"]

JOINT_NAMES = tuple(f"joint{i}" for i in range(1, 8))
LINK_NAMES = tuple(f"link{i}" for i in range(1, 8))
"""Bodies carrying joints 1..7; each joint is a hinge about its body's local z axis at the body origin."""


def build_chain_from_mjcf(xml: str) -> pk.Chain:
    """pytorch-kinematics `build_chain_from_mjcf` that works with current MuJoCo (float32 chain).

    Upstream problem (pytorch-kinematics 0.10 with mujoco >= 3): `pytorch_kinematics.mjcf.JOINT_TYPE_MAP` is keyed
    by `mujoco.mjtJoint` enum members, but the loader looks it up with `m.joint(i).type[0]`, a numpy integer, which
    no longer hashes equal to the enum -> KeyError. We look the map up with int keys for the duration of the call.
    """
    original = pk_mjcf.JOINT_TYPE_MAP
    # A fresh dict: adding int keys to the enum-keyed dict would only overwrite values (3 == enum, same hash).
    patched = {int(k): v for k, v in original.items()}
    pk_mjcf.JOINT_TYPE_MAP = patched
    try:
        return pk_mjcf.build_chain_from_mjcf(xml)
    finally:
        pk_mjcf.JOINT_TYPE_MAP = original


@dataclass(frozen=True)
class Kinematics:
    """Kinematic quantities of the control site for a batch [B], world frame, SI units."""

    pos: torch.Tensor
    """Site position [B, 3] (m)."""
    rot: torch.Tensor
    """Site orientation [B, 3, 3] (columns = site axes in world)."""
    jac: torch.Tensor
    """Geometric Jacobian [B, 6, 7]: rows 0-2 linear velocity (m/s per rad/s), rows 3-5 angular velocity."""
    jdot_qdot: torch.Tensor
    """J̇(q, q̇) q̇ [B, 6] (m/s², rad/s²): the site acceleration when q̈ = 0."""
    twist: torch.Tensor
    """Site twist J q̇ [B, 6] (linear m/s, angular rad/s)."""


class PandaModel:
    """Batched Panda kinematics (pytorch-kinematics chain from our MJCF) at the control site, float64.

    Args:
        tool: tool mounted below the F/T sensor ("peg", "disc", "none"); changes the control site's position.
        site: MJCF site used as control frame (default "tcp", the tool tip, z along the tool axis).
        device: torch device of the chain and of the outputs.
    """

    def __init__(self, tool: str = DEFAULT_TOOL, site: str = "tcp", device: str | torch.device = "cpu") -> None:
        self.tool = tool
        self.site = site
        self.mjcf_path: Path = mjcf_file(tool)
        self.dtype = torch.float64
        self.device = torch.device(device)
        xml = compose_mjcf(tool)
        self.mj_model = mujoco.MjModel.from_xml_string(xml)
        # float32 build (the loader's dtype) then float64: constants carry float32 rounding (~1e-8 m).
        chain = build_chain_from_mjcf(xml)
        self.chain = pk.SerialChain(chain, site).to(dtype=self.dtype, device=self.device)
        names = self.chain.get_joint_parameter_names()
        if tuple(names) != JOINT_NAMES:
            raise MjcfError(f"expected joints {JOINT_NAMES} in {self.mjcf_path}, got {names}")
        self._site_idx = int(self.chain.frame_to_idx[site])
        self._link_idx = torch.tensor([self.chain.frame_to_idx[n] for n in LINK_NAMES], device=self.device)
        axes = self.chain.axes.to(dtype=self.dtype)
        if not torch.allclose(axes, axes.new_tensor([0.0, 0.0, 1.0]).expand_as(axes)):
            raise MjcfError(f"all Panda joints must rotate about their body z axis, got axes {axes.tolist()}")
        # Fixed offsets between consecutive joint frames, read from the pytorch-kinematics chain at q = 0 (where each
        # joint rotation is the identity): T_link_i(q) = T_link_{i-1}(q) @ C_{i-1} @ Rz(q_i), T_site = T_link7 @ C_7.
        # The whole 13-frame pytorch-kinematics FK costs ~0.5 ms per call at B = 1; this product of 8 transforms is
        # what runs in the 1 kHz loop (tests check both against MuJoCo).
        T0 = self._frames_pk(torch.zeros(1, 7, dtype=self.dtype, device=self.device))[:, 0]  # (F, 4, 4)
        chain_T = [torch.eye(4, dtype=self.dtype, device=self.device)] + [T0[int(i)] for i in self._link_idx]
        chain_T.append(T0[self._site_idx])
        self._offsets = torch.stack([torch.linalg.solve(a, b) for a, b in zip(chain_T[:-1], chain_T[1:])])  # (8,4,4)

    @property
    def n_joints(self) -> int:
        """Number of actuated joints (7)."""
        return 7

    def _frames_pk(self, q: torch.Tensor) -> torch.Tensor:
        """World transforms of all pytorch-kinematics chain frames [F, B, 4, 4] for q [B, 7] (rad)."""
        return self.chain.forward_kinematics_tensor(q.to(dtype=self.dtype, device=self.device), analytical_grad=False)

    def _frames(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World transforms of the 7 joint frames [B, 7, 4, 4] and of the site [B, 4, 4] for q [B, 7] (rad)."""
        if q.dim() != 2 or q.shape[-1] != 7:
            raise ValueError(f"q must have shape [B, 7], got {tuple(q.shape)}")
        q = q.to(dtype=self.dtype, device=self.device)
        c, s = torch.cos(q), torch.sin(q)  # (B, 7)
        o, z = torch.ones_like(c), torch.zeros_like(c)
        rz = torch.stack([c, -s, z, z, s, c, z, z, z, z, o, z, z, z, z, o], dim=-1).reshape(*q.shape, 4, 4)
        local = self._offsets[:7] @ rz  # (B, 7, 4, 4) = C_{i-1} Rz(q_i)
        frames = [local[:, 0]]
        for i in range(1, 7):
            frames.append(frames[-1] @ local[:, i])
        joints = torch.stack(frames, dim=1)
        return joints, frames[-1] @ self._offsets[7]

    def fk(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Site pose for q [B, 7] (rad): position [B, 3] (m) and rotation [B, 3, 3], world frame."""
        T = self._frames(q)[1]  # (B, 4, 4)
        return T[:, :3, 3], T[:, :3, :3]

    def jacobian(self, q: torch.Tensor) -> torch.Tensor:
        """World-frame geometric Jacobian of the site [B, 6, 7] (linear rows first) for q [B, 7] (rad)."""
        return self.kinematics(q).jac

    def kinematics(self, q: torch.Tensor, qd: torch.Tensor | None = None) -> Kinematics:
        """Pose, Jacobian, J̇q̇ and twist of the site from one FK pass; q, qd [B, 7] (rad, rad/s)."""
        T_j, T = self._frames(q)  # joint i rotates about z of link i, at its origin
        p = T[:, :3, 3]  # (B, 3)
        R = T[:, :3, :3]  # (B, 3, 3)
        z = T_j[:, :, :3, 2]  # (B, 7, 3) joint axes in world
        p_j = T_j[:, :, :3, 3]  # (B, 7, 3) joint origins in world
        dp = p.unsqueeze(1) - p_j  # (B, 7, 3)
        jac = torch.cat([torch.linalg.cross(z, dp, dim=-1), z], dim=-1).transpose(1, 2)  # (B, 6, 7)
        if qd is None:
            qd = torch.zeros_like(q, dtype=self.dtype)
        qd = qd.to(dtype=self.dtype, device=self.device)
        twist = (jac @ qd.unsqueeze(-1)).squeeze(-1)  # (B, 6)
        # J̇q̇ for a revolute chain, J_i = [z_i x (p - p_i); z_i]:
        #   ż_i = ω_{i-1} x z_i with ω_{i-1} = Σ_{j<i} q̇_j z_j,   d/dt (p - p_i) = v_site - v_i,
        #   v_i = Σ_{j<i} q̇_j z_j x (p_i - p_j) = ω_{i-1} x p_i - Σ_{j<i} q̇_j z_j x p_j.
        qz = qd.unsqueeze(-1) * z  # (B, 7, 3) per-joint angular velocity contributions
        w_prev = torch.cumsum(qz, dim=1) - qz  # (B, 7, 3) ω_{i-1}
        m_prev = torch.cumsum(torch.linalg.cross(qz, p_j, dim=-1), dim=1) - torch.linalg.cross(qz, p_j, dim=-1)
        v_j = torch.linalg.cross(w_prev, p_j, dim=-1) - m_prev  # (B, 7, 3)
        z_dot = torch.linalg.cross(w_prev, z, dim=-1)  # (B, 7, 3)
        v_site = twist[:, :3].unsqueeze(1)  # (B, 1, 3)
        lin = torch.linalg.cross(z_dot, dp, dim=-1) + torch.linalg.cross(z, v_site - v_j, dim=-1)  # (B, 7, 3)
        jdot_qdot = torch.cat([(qd.unsqueeze(-1) * lin).sum(1), (qd.unsqueeze(-1) * z_dot).sum(1)], dim=-1)
        return Kinematics(pos=p, rot=R, jac=jac, jdot_qdot=jdot_qdot, twist=twist)
