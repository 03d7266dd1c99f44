"""Whether a point-mass policy will drive the Panda: its actions in the two situations the surrogate leaves to chance.

A policy trained on the 1-DoF point mass meets the Panda's free motion (small tracking errors, no force) only once
it has reached a fixed target, where its weights cost nothing, and the operator's push mostly as the surrogate's
operator scenario shapes it. What it does there decides the transfer (docs/panda.md, "Which point-mass policies
transfer"): a policy that does not raise IK's weight at small force-free errors lets the Panda's reference go (no
measured one inserted more than 2 of 26 pegs), and one that does not raise admittance and lower f_d under the
operator's push resists the hand. Both are mean actions over a few eq. 26 observations, so they cost microseconds
and can be checked while training (`a2c.select_policy: transfer`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = ["FREE_MOTION_E", "GUIDED_OBS", "mean_action", "free_motion_rates", "guided_rates", "raises_ik", "yields",
           "transfer_margin"]

FREE_MOTION_E = (0.001, 0.003, 0.01, 0.02)
"""|e|/ē on the Panda in free motion (the approach of peg-in-hole: 0.001-0.018 with ē = 1 m, no force sensed)."""
GUIDED_OBS = tuple((e, 0.0, f) for e in (0.01, 0.05) for f in (0.1, 0.2, 0.3, 0.5))
"""Eq. 26 observations of an arm the operator guides: small error, |f_ope|/f̄_ope 0.1-0.5, no contact."""

Policy = Callable[[Tensor], Tensor]
"""Observations [B, 3] (eq. 26) -> mean actions [B, 4] (ẇ1, ẇ2, ẇ3, ḟd), clipped to [-1, 1]."""


def mean_action(policy: Policy, obs: Sequence[Sequence[float]]) -> np.ndarray:
    """A policy's mean action (ẇ1, ẇ2, ẇ3, ḟd) [4] over the eq. 26 observations `obs` [B, 3]."""
    with torch.no_grad():
        return policy(torch.tensor(obs, dtype=torch.float32)).mean(0).double().numpy()


def free_motion_rates(policy: Policy) -> np.ndarray:
    """A policy's mean action (ẇ1, ẇ2, ẇ3, ḟd) [4] over the Panda's free motion (|e|/ē in FREE_MOTION_E, no force)."""
    return mean_action(policy, [[e, 0.0, 0.0] for e in FREE_MOTION_E])


def guided_rates(policy: Policy) -> np.ndarray:
    """A policy's mean action (ẇ1, ẇ2, ẇ3, ḟd) [4] over GUIDED_OBS: what it does while the operator pushes."""
    return mean_action(policy, GUIDED_OBS)


def raises_ik(free: np.ndarray) -> bool:
    """Whether free-motion rates (ẇ1, ẇ2, ẇ3, ḟd) raise IK's weight over admittance's: ẇ1 > 0 > ẇ2."""
    # eq. 29: the logits saturate at ±σw/2, so two rising rates end at equal weights; with ẇ2 > 0 in free motion
    # admittance (a pure damper without force) takes half of what IK tracks
    return bool(free[0] > 0.0 > free[1])


def yields(guided: np.ndarray) -> bool:
    """Whether rates under the operator's push (ẇ1, ẇ2, ẇ3, ḟd) raise admittance and lower f_d: ẇ2 > 0 > ḟd."""
    return bool(guided[1] > 0.0 > guided[3])


def transfer_margin(policy: Policy) -> tuple[float, np.ndarray, np.ndarray]:
    """(margin, free-motion rates, guided rates): margin = min(free ẇ1, −free ẇ2, guided ẇ2, −guided ḟd), positive
    exactly when `raises_ik` and `yields` both hold."""
    free, guided = free_motion_rates(policy), guided_rates(policy)
    return float(min(free[0], -free[1], guided[1], -guided[3])), free, guided
