"""Actor-critic MLPs stored in ONE flat parameter vector, with a hand-derived backward pass.

Why flat and hand-derived: at the paper's settings (4 envs, n = 4) A2C does 62,500 tiny updates per
1e6 steps, so per-op overhead dominates. With every weight a view into one float32 vector, the
gradient is one vector too: clipping and RMSProp (eq. 32) become three fused element-wise ops, and
the whole update (forward, eq. 31 loss gradients, backward, clip, step) compiles into a handful of
kernels. `ActorCritic` is also an ordinary `nn.Module` (autograd works through the views), which the
tests use to check the hand-derived gradients.

Layouts (tanh hidden layers, like SB3's MlpPolicy):
  - ``separate`` (SB3): policy MLP obs → hidden → mean (4); value MLP obs → hidden → V (1).
  - ``shared`` (the paper's "partially shared" network): one trunk obs → hidden, two linear heads.
The policy is a diagonal Gaussian with a state-independent log-std (SB3's default).
With ``critic_obs_dim`` (separate layout only) the value MLP reads a wider input than the policy
(asymmetric actor-critic): inputs are [B, critic_obs_dim], the policy reads the first obs_dim columns.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = ["ParamLayout", "ActorCritic", "forward", "policy_forward", "policy_mean", "backward"]

LOG_2PI = math.log(2.0 * math.pi)


class ParamLayout:
    """Names, shapes and offsets of every tensor inside the flat parameter vector."""

    def __init__(
        self, obs_dim: int, act_dim: int, hidden: Sequence[int], network: str, critic_obs_dim: int | None = None
    ) -> None:
        """Build the layout for `network` in {'separate', 'shared'} with tanh `hidden` sizes.

        `critic_obs_dim` (>= obs_dim, separate only): the value MLP's input width; None = obs_dim.
        """
        if network not in ("separate", "shared"):
            raise ValueError(f"network must be 'separate' or 'shared', got {network!r}")
        critic_obs_dim = obs_dim if critic_obs_dim is None else critic_obs_dim
        if critic_obs_dim < obs_dim:
            raise ValueError(f"critic_obs_dim ({critic_obs_dim}) must be >= obs_dim ({obs_dim})")
        if network == "shared" and critic_obs_dim != obs_dim:
            raise ValueError("a wider critic input needs network 'separate' (a shared trunk would feed it to the policy)")
        self.obs_dim, self.act_dim, self.hidden, self.network = obs_dim, act_dim, tuple(hidden), network
        self.critic_obs_dim = critic_obs_dim
        self.in_dims = {"pi": obs_dim, "vf": critic_obs_dim, "trunk": obs_dim}
        self.stacks = ("pi", "vf") if network == "separate" else ("trunk",)
        shapes: list[tuple[str, tuple[int, ...]]] = []
        for stack in self.stacks:
            fan_in = self.in_dims[stack]
            for i, h in enumerate(self.hidden):
                shapes += [(f"{stack}.{i}.w", (h, fan_in)), (f"{stack}.{i}.b", (h,))]
                fan_in = h
        last = self.hidden[-1]
        shapes += [("pi.out.w", (act_dim, last)), ("pi.out.b", (act_dim,)), ("vf.out.w", (1, last)),
                   ("vf.out.b", (1,)), ("log_std", (act_dim,))]
        self.shapes = dict(shapes)
        self.offsets: dict[str, tuple[int, int]] = {}
        o = 0
        for name, shape in shapes:
            n = math.prod(shape)
            self.offsets[name] = (o, o + n)
            o += n
        self.size = o

    def views(self, flat: Tensor) -> dict[str, Tensor]:
        """Named views (no copies) into `flat` [size]."""
        return {k: flat[a:b].view(self.shapes[k]) for k, (a, b) in self.offsets.items()}

    def init(self, generator: torch.Generator | None = None, log_std_init: float = 0.0) -> Tensor:
        """SB3-style init: orthogonal weights (gain √2 hidden, 0.01 policy head, 1 value head), zero biases."""
        flat = torch.zeros(self.size, dtype=torch.float32)
        v = self.views(flat)
        for name, t in v.items():
            if name.endswith(".w"):
                gain = 0.01 if name == "pi.out.w" else 1.0 if name == "vf.out.w" else math.sqrt(2.0)
                w = torch.empty(t.shape, dtype=torch.float32)
                _orthogonal_(w, gain, generator)
                t.copy_(w)
        v["log_std"].fill_(log_std_init)
        return flat


def _orthogonal_(w: Tensor, gain: float, generator: torch.Generator | None) -> None:
    # torch.nn.init.orthogonal_ has no generator argument; same QR recipe, seeded.
    rows, cols = w.shape
    a = torch.randn(max(rows, cols), min(rows, cols), generator=generator, dtype=torch.float64)
    q, r = torch.linalg.qr(a)
    q = q * torch.sign(torch.diagonal(r)).unsqueeze(0)
    w.copy_((q if rows >= cols else q.T)[:rows, :cols].to(w.dtype) * gain)


def _stack_forward(p: dict[str, Tensor], stack: str, depth: int, x: Tensor) -> list[Tensor]:
    acts = [x]
    for i in range(depth):
        x = torch.tanh(torch.addmm(p[f"{stack}.{i}.b"], x, p[f"{stack}.{i}.w"].T))
        acts.append(x)
    return acts


def forward(
    layout: ParamLayout, flat: Tensor, obs: Tensor, next_obs: Tensor | None = None, policy_acts: list[Tensor] | None = None
) -> tuple[Tensor, Tensor, Tensor, dict[str, list[Tensor]]]:
    """Policy mean [B, act], log-std [act], values [B (+ B')] at `obs` (then `next_obs`), and the cache at `obs` for `backward`.

    `obs` [B, critic_obs_dim], `next_obs` [B', critic_obs_dim]: each stack reads its first
    `layout.in_dims[stack]` columns. At `next_obs` only V is computed (what bootstrapping needs).
    `policy_acts`: the policy stack's activations at `obs` from `policy_forward` while acting; the
    parameters have not changed since, so they are reused instead of computed again.
    """
    p, d, B = layout.views(flat), len(layout.hidden), obs.shape[0]
    pol = "pi" if layout.network == "separate" else "trunk"
    if policy_acts is None:
        policy_acts = _stack_forward(p, pol, d, obs[:, : layout.obs_dim])
    mu = torch.addmm(p["pi.out.b"], policy_acts[-1], p["pi.out.w"].T)
    if layout.network == "separate":
        x = obs if next_obs is None else torch.cat([obs, next_obs])
        vf = _stack_forward(p, "vf", d, x[:, : layout.critic_obs_dim])
        cache = {"pi": policy_acts, "vf": [a[:B] for a in vf]}
        h_vf = vf[-1]
    else:  # the trunk at obs is the policy's; only next_obs needs a pass
        cache = {"trunk": policy_acts}
        h_vf = policy_acts[-1]
        if next_obs is not None:
            h_vf = torch.cat([h_vf, _stack_forward(p, "trunk", d, next_obs[:, : layout.obs_dim])[-1]])
    values = torch.addmm(p["vf.out.b"], h_vf, p["vf.out.w"].T).squeeze(-1)
    return mu, p["log_std"], values, cache


def policy_forward(layout: ParamLayout, flat: Tensor, obs: Tensor,
                   params: dict[str, Tensor] | None = None) -> tuple[Tensor, list[Tensor]]:
    """Policy mean [B, act] and the policy stack's activations (for `forward`); reads the first obs_dim columns of `obs`.

    `params`: `layout.views(flat)`, where the caller keeps them (building the views costs more than a small forward)."""
    p = layout.views(flat) if params is None else params
    stack = "pi" if layout.network == "separate" else "trunk"
    acts = _stack_forward(p, stack, len(layout.hidden), obs[:, : layout.obs_dim])
    return torch.addmm(p["pi.out.b"], acts[-1], p["pi.out.w"].T), acts


def policy_mean(layout: ParamLayout, flat: Tensor, obs: Tensor) -> Tensor:
    """Policy mean [B, act] only (no value head): what acting needs; reads the first obs_dim columns of `obs`."""
    return policy_forward(layout, flat, obs)[0]


def backward(
    layout: ParamLayout, flat: Tensor, cache: dict[str, list[Tensor]], g_mu: Tensor, g_log_std: Tensor, g_value: Tensor
) -> Tensor:
    """Flat gradient [size] given ∂L/∂mean [B, act], ∂L/∂log-std [act] and ∂L/∂value [B] (hand-derived)."""
    p, d = layout.views(flat), len(layout.hidden)
    grads: dict[str, Tensor] = {"log_std": g_log_std}
    sep = layout.network == "separate"
    g_v = g_value.unsqueeze(-1)  # [B, 1]
    h_pi, h_vf = cache["pi" if sep else "trunk"][-1], cache["vf" if sep else "trunk"][-1]
    grads["pi.out.w"], grads["pi.out.b"] = g_mu.T @ h_pi, g_mu.sum(0)
    grads["vf.out.w"], grads["vf.out.b"] = g_v.T @ h_vf, g_v.sum(0)
    g_top = {"pi": g_mu @ p["pi.out.w"], "vf": g_v @ p["vf.out.w"]}
    if not sep:
        g_top = {"trunk": g_top["pi"] + g_top["vf"]}
    for stack, g in g_top.items():
        acts = cache[stack]
        for i in reversed(range(d)):
            g = g * (1.0 - acts[i + 1] * acts[i + 1])  # tanh' = 1 − tanh²
            grads[f"{stack}.{i}.w"], grads[f"{stack}.{i}.b"] = g.T @ acts[i], g.sum(0)
            if i > 0:
                g = g @ p[f"{stack}.{i}.w"]
    return torch.cat([grads[k].reshape(-1) for k in layout.offsets])


class ActorCritic(nn.Module):
    """nn.Module view of the flat-parameter actor-critic (autograd-capable; used by tests and TorchRL)."""

    def __init__(self, layout: ParamLayout, flat: Tensor | None = None) -> None:
        """Wrap `flat` (or a fresh SB3-style init) as the module's only parameter."""
        super().__init__()
        self.layout = layout
        self.flat = nn.Parameter(layout.init() if flat is None else flat.detach().clone())

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(mean [B, act], log-std [act], value [B]) for observations [B, obs]."""
        mu, log_std, value, _ = forward(self.layout, self.flat, obs)
        return mu, log_std, value

    def log_prob(self, mu: Tensor, log_std: Tensor, action: Tensor) -> Tensor:
        """Diagonal-Gaussian log-density of `action` [B, act], summed over action dims."""
        z = (action - mu) * torch.exp(-log_std)
        return (-0.5 * z * z - log_std - 0.5 * LOG_2PI).sum(-1)
