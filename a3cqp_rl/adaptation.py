"""The adaptation module of A3CQP (paper 000, section IV): observation, eq. 29 integration, eq. 30 reward.

All functions are pure torch, batched over any leading shape, and reject NaN/inf inputs with a
ValueError naming the argument. Quantities are per Cartesian axis of the local frame L:
position error e [m], environment force f_env [N], operator force f_ope [N], desired force f_d [N].
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["observe", "integrate_weights", "integrate_force", "reward", "check_finite"]


def check_finite(**tensors: Tensor) -> None:
    """Raise ValueError naming the first argument that holds NaN or inf."""
    for name, t in tensors.items():
        if not torch.is_tensor(t):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name} contains NaN or inf (shape {tuple(t.shape)})")


def action_of(td, shape: tuple[int, ...]) -> Tensor:  # noqa: ANN001
    """An env step's "action" entry of `td`, checked (present, `shape`, finite; a ValueError naming the rows that are
    not) and detached: a policy's graph must not grow through the env's state."""
    action = td.get("action", None)
    if action is None:
        raise ValueError(f"the tensordict has no 'action' entry (keys: {sorted(map(str, td.keys()))})")
    if tuple(action.shape) != tuple(shape):
        raise ValueError(f"action must have shape {tuple(shape)}, got {tuple(action.shape)}")
    bad = ~torch.isfinite(action.reshape(shape[0], -1)).all(-1)
    if bool(bad.any()):
        rows = torch.nonzero(bad).flatten().tolist()
        raise ValueError(f"action contains NaN or inf in batch row(s) {rows[:10]}{' ...' if len(rows) > 10 else ''}")
    return action.detach()


def _normalised(x: Tensor, bound: float) -> Tensor:
    # eq. 26 and section V-B: each term divided by its bound and kept in [0, 1].
    return (x.abs() / bound).clamp(0.0, 1.0)


def observe(
    e: Tensor,
    f_env: Tensor,
    f_ope: Tensor,
    e_max: float = 1.0,
    f_env_max: float = 30.0,
    f_ope_max: float = 15.0,
    *,
    check: bool = True,
) -> Tensor:
    """Normalised agent state s = (|e|/ē, |f_env|/f̄_env, |f_ope|/f̄_ope) in [0, 1]^3 (eq. 26), shape [..., 3]."""
    if check:
        check_finite(e=e, f_env=f_env, f_ope=f_ope)
    return torch.stack(
        (_normalised(e, e_max), _normalised(f_env, f_env_max), _normalised(f_ope, f_ope_max)), dim=-1
    )


def integrate_weights(
    w_logits: Tensor, w_rate: Tensor, sigma_w: float = 6.0, dt: float = 0.01, *, check: bool = True
) -> tuple[Tensor, Tensor]:
    """Eq. 29a-c and 29e: integrate pre-softmax weights w̌ [..., 3] by rates ẇ in [-1, 1]; return (w̌, softmax w̌).

    `check=False` skips the NaN/shape checks (they synchronise; fused, compiled loops turn them off).
    """
    if check:
        check_finite(w_logits=w_logits, w_rate=w_rate)
        if w_logits.shape[-1] != 3 or w_rate.shape[-1] != 3:
            raise ValueError(
                f"w_logits and w_rate need a last dim of 3 tasks, got {tuple(w_logits.shape)} and {tuple(w_rate.shape)}"
            )
    half = 0.5 * sigma_w
    # eq. 29a-c: integrate, then keep w̌ in [-σw/2, σw/2] (the "if" in the paper is a saturation).
    w_logits = (w_logits + sigma_w * dt * w_rate.clamp(-1.0, 1.0)).clamp(-half, half)
    return w_logits, torch.softmax(w_logits, dim=-1)  # eq. 29e


def integrate_force(
    f_d: Tensor, f_rate: Tensor, sigma_f: float = 10.0, dt: float = 0.01, f_max: float = 20.0, *, check: bool = True
) -> Tensor:
    """Eq. 29d: desired contact force f_d ← clip(f_d + σf·Δt·ḟd, 0, f̄_d) [N], ḟd clipped to [-1, 1]."""
    if check:
        check_finite(f_d=f_d, f_rate=f_rate)
    return (f_d + sigma_f * dt * f_rate.clamp(-1.0, 1.0)).clamp(0.0, f_max)


def reward(
    e: Tensor,
    f_env: Tensor,
    f_ope: Tensor,
    f_d: Tensor,
    alpha: Sequence[float] = (0.5, 20.0, 2.0, 1.0),
    e_max: float = 1.0,
    f_env_max: float = 30.0,
    f_ope_max: float = 15.0,
    f_d_max: float = 20.0,
    *,
    check: bool = True,
) -> Tensor:
    """Eq. 30 reward r = −α1|e|/ē − α2|f_ope|/f̄_ope + α3|f_env|/f̄_env − α4 f_d/f̄_d, each ratio clipped to [0, 1].

    The clipping follows section IV-A ("all the variables have been normalized within [0, 1]") and
    bounds the reward to [−(α1+α2+α4), α3], so a large contact force cannot be farmed without limit.
    Training on the point mass runs a C copy of this reward and of the eq. 35 step by default
    (envs/native/point_mass.c, `a2c.backend: auto`): an edit here needs the same there, or `a2c.backend: torch`.
    """
    if check:
        check_finite(e=e, f_env=f_env, f_ope=f_ope, f_d=f_d)
    a1, a2, a3, a4 = (float(a) for a in alpha)
    return (
        -a1 * _normalised(e, e_max)  # eq. 30b
        - a2 * _normalised(f_ope, f_ope_max)  # eq. 30c
        + a3 * _normalised(f_env, f_env_max)  # eq. 30d
        - a4 * _normalised(f_d, f_d_max)  # eq. 30e
    )
