"""Franka Emika Panda datasheet limits (joint position, velocity, acceleration, torque)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["PandaLimits", "PANDA_LIMITS", "PANDA_HOME"]


@dataclass(frozen=True)
class PandaLimits:
    """Joint limits of the Panda from Franka's datasheet; radians, rad/s, rad/s^2, N m (7 joints)."""

    q_min: tuple[float, ...] = (-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973)
    """Lower joint position limit [rad] (same values as the MJCF joint ranges)."""
    q_max: tuple[float, ...] = (2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973)
    """Upper joint position limit [rad]."""
    dq_max: tuple[float, ...] = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)
    """Symmetric joint velocity limit [rad/s]."""
    ddq_max: tuple[float, ...] = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)
    """Symmetric joint acceleration limit [rad/s^2]."""
    tau_max: tuple[float, ...] = field(default=(87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0))
    """Symmetric joint torque limit [N m] (MJCF motor ctrlrange)."""

    def tensors(self, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """All limits as [7] tensors keyed by field name."""
        return {k: torch.tensor(getattr(self, k), dtype=dtype, device=device)
                for k in ("q_min", "q_max", "dq_max", "ddq_max", "tau_max")}


PANDA_LIMITS = PandaLimits()
"""The datasheet limits."""

PANDA_HOME: tuple[float, ...] = (0.0, -0.7853981633974483, 0.0, -2.356194490192345, 0.0, 1.5707963267948966,
                                 0.7853981633974483)
"""Franka "ready" configuration [rad] (MJCF keyframe "home"): flange pointing down."""
