"""RMSProp exactly as paper 000 eq. 32, with ε inside the square root, and global-norm clipping.

    g ← λα g + (1 − λα) Δθ²;   θ ← θ − λη Δθ / √(g + λε)                          (eq. 32)

This is TensorFlow's RMSProp (which Stable-Baselines 2/3's `RMSpropTFLike` reproduces), not
`torch.optim.RMSprop`, which computes θ ← θ − λη Δθ / (√g + ε). The accumulator's start value is
an option: TF and SB3's `RMSpropTFLike` start it at 1, torch's RMSprop (SB3's A2C default) at 0.
The difference matters at the paper's tiny λη: with g₀ = 1 the first hundreds of updates are
scaled down by up to 1/√(1 + λε) ≈ 1 instead of 1/√λε ≈ 160.

The functional forms (`rmsprop_step_`, `clip_grad_norm_`) are what the fused A2C update calls;
`RMSpropEq32` wraps them as a `torch.optim.Optimizer` for everything else.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import Tensor

__all__ = ["RMSpropEq32", "rmsprop_step_", "clip_grad_norm_"]


def clip_grad_norm_(grads: Sequence[Tensor], max_norm: float) -> Tensor:
    """Scale `grads` in place so their global L2 norm is at most `max_norm`; returns the norm before clipping."""
    total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
    # Same rule as torch.nn.utils.clip_grad_norm_ (and SB3): scale = min(1, max_norm / (norm + 1e-6)).
    scale = (max_norm / (total + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(scale)
    return total


@torch.no_grad()
def rmsprop_step_(
    params: Sequence[Tensor],
    grads: Sequence[Tensor],
    square_avg: Sequence[Tensor],
    lr: float | Tensor,
    alpha: float = 0.99,
    eps: float = 1e-5,
) -> None:
    """Eq. 32 in place: square_avg ← α·square_avg + (1−α)·grad²; param ← param − lr·grad/√(square_avg + eps).

    `lr` a 0-d tensor: a learning rate that changes between calls of one compiled graph (a schedule).
    """
    for p, g, s in zip(params, grads, square_avg):
        s.mul_(alpha).addcmul_(g, g, value=1.0 - alpha)
        if isinstance(lr, Tensor):
            p.sub_(lr * g / (s + eps).sqrt())
        else:
            p.addcdiv_(g, (s + eps).sqrt(), value=-lr)


class RMSpropEq32(torch.optim.Optimizer):
    """Eq. 32 RMSProp (ε inside the root) with optional global-norm clipping at `max_grad_norm` (λζ)."""

    def __init__(
        self,
        params: Iterable[Tensor],
        lr: float = 4.25339846e-6,
        alpha: float = 0.99,
        eps: float = 3.938214948e-5,
        init_square_avg: float = 0.0,
        max_grad_norm: float | None = None,
    ) -> None:
        """λη = lr, λα = alpha, λε = eps, g₀ = init_square_avg (0 torch-like, 1 TF-like), λζ = max_grad_norm."""
        if lr <= 0:
            raise ValueError(f"lr must be > 0, got {lr}")
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"alpha must be in [0, 1), got {alpha}")
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        if init_square_avg < 0:
            raise ValueError(f"init_square_avg must be >= 0, got {init_square_avg}")
        if max_grad_norm is not None and max_grad_norm <= 0:
            raise ValueError(f"max_grad_norm must be > 0 or None, got {max_grad_norm}")
        defaults = dict(lr=lr, alpha=alpha, eps=eps, init_square_avg=init_square_avg, max_grad_norm=max_grad_norm)
        super().__init__(params, defaults)

    @torch.no_grad()
    def step(self, closure=None):  # type: ignore[override]
        """Clip all gradients to the global norm λζ (if set), then apply eq. 32 to every parameter."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            ps = [p for p in group["params"] if p.grad is not None]
            if not ps:
                continue
            grads = [p.grad for p in ps]
            if group["max_grad_norm"] is not None:
                clip_grad_norm_(grads, group["max_grad_norm"])
            avgs = []
            for p in ps:
                state = self.state[p]
                if "square_avg" not in state:
                    state["square_avg"] = torch.full_like(p, group["init_square_avg"])
                avgs.append(state["square_avg"])
            rmsprop_step_(ps, grads, avgs, group["lr"], group["alpha"], group["eps"])
        return loss
