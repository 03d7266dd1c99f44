"""A trained A2C policy as torch / TorchRL modules, loaded from OUT/policy.pt (or checkpoint.pt).

  * `load_policy(path)` -> `A2CPolicy`: an nn.Module, observation tensor [..., obs] -> mean action [..., act] in the
    env's units, clipped to the action bounds; `.to()`, `.parameters()`. Plots and the Fig. 5 checks call it.
  * `load_actor(path, sample=False)` -> a TorchRL `ProbabilisticActor` reading "observation" and writing "action":
    `env.rollout(max_steps, policy=load_actor(path))`. The mean by default; `sample=True` (or TorchRL's
    `set_exploration_type(ExplorationType.RANDOM)`) draws from the Gaussian the policy was trained with,
    projected onto the action bounds as the trainer clips it.

Both evaluate the flat parameter vector with `networks.policy_mean`, the trainer's own fast path.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from a3cqp_rl.checkpoint import load_checkpoint
from a3cqp_rl.exceptions import CheckpointError
from a3cqp_rl.run_folder import policy_file
from algorithms.networks import ParamLayout, policy_mean

if TYPE_CHECKING:  # annotations only: torchrl is imported where an actor is built
    from torchrl.envs import EnvBase
    from torchrl.modules import ProbabilisticActor

__all__ = ["A2CPolicy", "load_policy", "load_actor", "layout_key", "first_episode_returns", "fingerprint"]


def layout_key(key: list) -> list:
    """[obs, act, hidden, network, critic input]; files written before the critic option have 4 entries."""
    key = list(key)
    return key if len(key) == 5 else [*key, key[0]]


class A2CPolicy(nn.Module):
    """Observation [..., obs_dim] -> mean action [..., act_dim] in the env's units (clipped to its bounds).

    The network acts in normalised units: a raw action a ∈ [-1, 1] maps to mid + half·a with mid = (high + low)/2,
    half = (high − low)/2 (identity for [-1, 1]; unbounded actions: mid 0, half 1, no clipping).
    """

    def __init__(self, layout: ParamLayout, flat: Tensor, low: list[float] | None = None,
                 high: list[float] | None = None) -> None:
        """Wrap the flat parameters `flat` [layout.size] of `layout`; `low`/`high` the action bounds (None: unbounded)."""
        super().__init__()
        if flat.shape != (layout.size,):
            raise ValueError(f"parameter vector has {flat.shape[0]} entries, layout needs {layout.size}")
        if not bool(torch.isfinite(flat).all()):  # (a diverged run's parameters: every action would be NaN)
            raise ValueError(f"{int((~torch.isfinite(flat)).sum())} of its {layout.size} parameters are not finite")
        self.layout, self.bounded = layout, low is not None
        self.flat = nn.Parameter(flat.detach().clone().float(), requires_grad=False)
        lo = torch.tensor(low if low is not None else [-1.0] * layout.act_dim, dtype=torch.float32)
        hi = torch.tensor(high if high is not None else [1.0] * layout.act_dim, dtype=torch.float32)
        self.register_buffer("action_mid", (hi + lo) / 2 if self.bounded else torch.zeros(layout.act_dim))
        self.register_buffer("action_half", (hi - lo) / 2 if self.bounded else torch.ones(layout.act_dim))

    def _mean(self, obs: Tensor) -> Tensor:
        d = self.layout.obs_dim
        if obs.shape[-1] != d:
            raise ValueError(f"observations need a last dim of {d}, got shape {tuple(obs.shape)}")
        if not bool(torch.isfinite(obs).all()):
            raise ValueError("observations contain NaN or inf")
        mu = policy_mean(self.layout, self.flat, obs.reshape(-1, d).to(self.flat.dtype))
        return mu.reshape(*obs.shape[:-1], self.layout.act_dim)

    def forward(self, obs: Tensor) -> Tensor:
        """Mean action in the env's units [..., act_dim]."""
        mu = self._mean(obs)
        return self.action_mid + self.action_half * (mu.clamp(-1.0, 1.0) if self.bounded else mu)

    def loc_scale(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """(loc, scale) [..., act_dim] of the training Gaussian in the env's units, before clipping."""
        mu = self._mean(obs)
        std = torch.exp(self.layout.views(self.flat)["log_std"])
        return self.action_mid + self.action_half * mu, (self.action_half * std).expand_as(mu)


def fingerprint(policy: A2CPolicy) -> str:
    """The first 16 hex digits of a SHA-256 over what the policy computes with: its layout, action bounds and float32
    parameters (the file's other entries, e.g. the run folder in its config, do not count)."""
    lay = policy.layout
    h = hashlib.sha256(repr((lay.obs_dim, lay.act_dim, lay.hidden, lay.network, lay.critic_obs_dim,
                             policy.bounded)).encode())
    for t in (policy.action_mid, policy.action_half, policy.flat.detach()):
        h.update(t.to(torch.float32).contiguous().numpy().astype("<f4").tobytes())
    return h.hexdigest()[:16]


class _LocScale(nn.Module):
    """`A2CPolicy.loc_scale` as a module's forward, for TensorDictModule."""

    def __init__(self, policy: A2CPolicy) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        return self.policy.loc_scale(obs)


def load_policy(path: str | Path) -> A2CPolicy:
    """OUT/policy.pt (or a checkpoint.pt: the raw, never averaged parameters; a run folder: its policy.pt) as an
    `A2CPolicy`."""
    path = policy_file(path)
    data = load_checkpoint(path, ("flat", "layout"))
    obs_dim, act_dim, hidden, network, critic_dim = layout_key(data["layout"])
    layout = ParamLayout(obs_dim, act_dim, hidden, network, critic_dim)
    # files from before the action bounds were recorded: the point mass, clipped to [-1, 1]
    low, high = data.get("action_low", [-1.0] * act_dim), data.get("action_high", [1.0] * act_dim)
    try:
        return A2CPolicy(layout, data["flat"], low, high)
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from None


def load_agent_policy(path: str | Path, agents: str) -> A2CPolicy:
    """`load_policy`, refused (naming the file) unless it maps the per-axis observation [3] to the four actions
    (ẇ1, ẇ2, ẇ3, ḟd) of an A3CQP agent (eq. 26-27); `agents` names who needs it in the message."""
    policy = load_policy(path)
    dims = (policy.layout.obs_dim, policy.layout.act_dim)
    if dims != (3, 4):
        raise ValueError(f"{path}: a policy of {dims[0]} observations and {dims[1]} actions; {agents} 3 -> 4 "
                         "(|e|, |f_env|, |f_ope| -> ẇ1, ẇ2, ẇ3, ḟd), a point-mass or Panda policy")
    return policy


def init_from_policy(path: str | Path, layout: ParamLayout, flat: Tensor, low: tuple | None = None,
                     high: tuple | None = None) -> list[str]:
    """Copy into `flat` (in place) the tensors of a saved policy whose name and shape match `layout`; their names.

    A2CConfig.init_policy (fine-tuning). CheckpointError when nothing of the actor fits or the action bounds differ
    (the network's outputs are in normalised units of the bounds it was trained with)."""
    path = policy_file(path)
    data = load_checkpoint(path, ("flat", "layout"))
    obs_dim, act_dim, hidden, network, critic_dim = layout_key(data["layout"])
    src = ParamLayout(obs_dim, act_dim, hidden, network, critic_dim).views(data["flat"].to(flat.dtype))
    if low is not None and "action_low" in data:
        if [float(v) for v in data["action_low"]] != list(low) or [float(v) for v in data["action_high"]] != list(high):
            raise CheckpointError(f"{path}: action bounds {data['action_low']}..{data['action_high']} differ from the "
                                  f"env's {list(low)}..{list(high)}")
    dst = layout.views(flat)
    copied = [k for k, t in dst.items() if k in src and src[k].shape == t.shape]
    actor = [k for k in dst if k.startswith("pi.") or k == "log_std" or k.startswith("trunk.")]
    if not set(actor) <= set(copied):
        raise CheckpointError(f"{path}: its actor (obs {obs_dim}, act {act_dim}, hidden {list(hidden)}, {network}) "
                              f"does not fit this run's (obs {layout.obs_dim}, act {layout.act_dim}, hidden "
                              f"{list(layout.hidden)}, {layout.network})")
    for k in copied:
        dst[k].copy_(src[k])
    return copied


def load_actor(path: str | Path, sample: bool = False) -> ProbabilisticActor:
    """OUT/policy.pt as a TorchRL ProbabilisticActor ("observation" -> "action"); the mean unless `sample`."""
    from tensordict.nn import InteractionType, TensorDictModule
    from torchrl.data import Bounded, Unbounded
    from torchrl.modules import IndependentNormal, ProbabilisticActor

    policy = load_policy(path)
    act = policy.layout.act_dim
    spec = (Bounded(policy.action_mid - policy.action_half, policy.action_mid + policy.action_half, shape=(act,)) if policy.bounded
            else Unbounded(shape=(act,)))
    module = TensorDictModule(_LocScale(policy), in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(module, in_keys=["loc", "scale"], out_keys=["action"], spec=spec, safe=policy.bounded,
                              distribution_class=IndependentNormal,
                              default_interaction_type=InteractionType.RANDOM if sample else InteractionType.DETERMINISTIC)


@torch.no_grad()
def first_episode_returns(policy_path: str | Path, env: EnvBase, max_steps: int, sample: bool = False) -> Tensor:
    """Return of each env's first episode [num_envs] under the policy of `policy_path` (its mean action unless
    `sample`), from `env`'s reset; ValueError if an env's episode outlasts `max_steps`."""
    td = env.rollout(max_steps, policy=load_actor(policy_path, sample), break_when_any_done=False)
    reward = td["next", "reward"].reshape(*env.batch_size, max_steps, -1).sum(-1)  # [N, T]
    done = td["next", "done"].reshape(*env.batch_size, max_steps, -1).any(-1)
    if not bool(done.any(-1).all()):
        raise ValueError(f"an episode lasted more than max_steps={max_steps}")
    first = done.int().argmax(-1, keepdim=True)  # index of each env's first done
    steps = torch.arange(max_steps).expand_as(reward)
    return (reward * (steps <= first)).sum(-1).reshape(-1)


def main(argv: list[str] | None = None) -> int:
    """`python -m algorithms.policy A.pt [B.pt ...]`: each policy's fingerprint; exit 1 when they are not all equal."""
    import sys

    paths = list(sys.argv[1:] if argv is None else argv)
    if not paths:
        print("usage: python -m algorithms.policy POLICY.pt [POLICY.pt ...]", file=sys.stderr)
        return 2
    try:
        prints = [fingerprint(load_policy(p)) for p in paths]
    except (CheckpointError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for p, f in zip(paths, prints):
        print(f"{f}  {p}")
    if len(paths) > 1:
        same = len(set(prints)) == 1
        print("the same parameters" if same else "the parameters differ: the training's numbers on this machine or in "
              "this version are not those of the other file")
        return 0 if same else 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
