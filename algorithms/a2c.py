"""Synchronous n-step advantage actor-critic (A2C), paper 000 eq. 31-32, hand-written.

Reads top to bottom: n-step returns → `a2c_update` (eq. 31 loss, hand-derived gradients, λζ
clipping, eq. 32 RMSProp) → what the env's specs say (`EnvLayout`) → two rollout sources → `train` (the loop;
checkpoints, resume, logs and region checks are small objects in algorithms/a2c_run.py and run_log.py).

Conventions (those of Stable-Baselines3's A2C, the paper's library; defaults = Table IV):
  * Gaussian policy on a normalised action; the env receives it clipped to [-1, 1] and mapped onto the action
    spec's bounds [low, high] (the identity for the point mass), and the update uses the log-probability of the
    unclipped sample. Observation and action sizes come from the env's specs; dims between the env's batch dims
    and the features (e.g. [N, 6, 3]: six agents sharing the policy) are more samples of the same policy.
  * Loss L = −mean(A·log π(a|s)) + λv·mean((R − V)²) − λβ·H(π). Paper eq. 31d prints "+λβ H"; as in
    A3C (Mnih et al. 2016) and SB3 the entropy is a bonus, so it enters with a minus sign.
  * n-step returns bootstrap from V(s') at the end of a rollout and at truncation (time limit),
    and not at termination.
  * Options beyond the paper (all off by default): GAE(λ) advantages, a privileged (asymmetric)
    critic, held exploration noise (`HeldNoise`), and a bound loss on the policy mean outside
    [-1, 1] (rl_games' `bounds_loss_coef`): with weak per-sample signal, RMSProp's ~lr-sized steps
    random-walk weakly-rewarded action means far past the clip, where every clipped sample is the
    same action and the policy gradient can no longer pull them back. And `average_last`: the saved
    policy is the mean of the parameters over the run's final fraction (stochastic weight averaging).
Data comes from either (a) the env's fused API (`fused_functions`: a pure step with auto-reset, PointMassEnv), rollout
and update compiled together into one graph (or, for small batches, the same iteration in C: algorithms/native), or
(b) any TorchRL EnvBase through a TorchRL `Collector` (gymnasium tasks via GymWrapper, ParallelEnv/SerialEnv).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from a3cqp_rl.config import A2CConfig, ExperimentConfig, project_path
from a3cqp_rl.exceptions import TrainingDiverged
from a3cqp_rl.timing import Timer, process_age
from algorithms.a2c_run import (Checkpoints, ParameterAverage, RegionChecks, StopCheckpoint, TransferSelection,
                               open_run_folder)
from algorithms.networks import LOG_2PI, ParamLayout, backward, forward, policy_forward
from algorithms.policy import init_from_policy, load_actor, load_policy
from algorithms.rmsprop import clip_grad_norm_, rmsprop_step_
from a3cqp_rl.regions import REGION_COLUMNS
from algorithms.run_log import CSV_COLUMNS, METRICS, TRANSFER_COLUMNS, RunLog, truncate_csv

if TYPE_CHECKING:  # annotations only: torchrl is imported where an env is read
    from torchrl.envs import EnvBase

__all__ = ["Batch", "HeldNoise", "ParameterAverage", "EnvLayout", "read_env_layout", "nstep_returns", "gae_advantages",
           "a2c_update", "train", "TrainResult", "load_policy", "load_actor", "METRICS", "CSV_COLUMNS"]

_truncate_csv = truncate_csv  # the name tests and older callers use

UNBOUNDED = 1e30
"""An action bound at or beyond this magnitude is no bound (TorchRL's Unbounded spec reports ±3.4e38)."""


@dataclass
class Batch:
    """One rollout, time-major: obs/next_obs [T, N, obs], actions [T, N, act] (unclipped), rest [T, N]."""

    obs: Tensor
    actions: Tensor
    rewards: Tensor
    terminated: Tensor
    truncated: Tensor
    next_obs: Tensor  # observation after each step, before any reset
    policy_acts: tuple[Tensor, ...] | None = None  # policy hidden layers at obs while acting, [T, N, h] each


def nstep_returns(rewards: Tensor, terminated: Tensor, truncated: Tensor, next_values: Tensor, gamma: float) -> Tensor:
    """n-step returns [T, N]: R_t = r_t + γ·R_{t+1}, cut at episode ends; bootstrap V(s') at truncation and at t = T−1."""
    T = rewards.shape[0]
    bootstrap = gamma * next_values * (~terminated)
    end = terminated | truncated
    out = []
    ret = bootstrap[T - 1] + rewards[T - 1]
    out.append(ret)
    for t in range(T - 2, -1, -1):
        ret = rewards[t] + torch.where(end[t], bootstrap[t], gamma * ret)
        out.append(ret)
    return torch.stack(out[::-1])


def gae_advantages(rewards: Tensor, terminated: Tensor, truncated: Tensor, values: Tensor, next_values: Tensor,
                   gamma: float, lam: float) -> Tensor:
    """GAE(λ) advantages [T, N] (Schulman et al. 2016), cut at episode ends, bootstrapping V(s') unless terminated.

    λ = 1 gives the n-step advantage R_t − V(s_t) of `nstep_returns`; λ = 0 the one-step TD error.
    """
    delta = rewards + gamma * next_values * (~terminated) - values
    cont = gamma * lam * (~(terminated | truncated))
    out = [delta[-1]]
    for t in range(rewards.shape[0] - 2, -1, -1):
        out.append(delta[t] + cont[t] * out[-1])
    return torch.stack(out[::-1])


def a2c_update(layout: ParamLayout, flat: Tensor, square_avg: Tensor, batch: Batch, hp: A2CConfig,
               lr: Tensor | None = None) -> Tensor:
    """One A2C step in place on `flat` and the RMSProp accumulator; returns METRICS as a tensor [5].

    `lr`: a 0-d tensor overriding hp.learning_rate (a2c.lr_schedule), else the constant λη."""
    T, N = batch.rewards.shape
    B = T * N
    obs, actions = batch.obs.reshape(B, -1), batch.actions.reshape(B, -1)
    acts = None  # the parameters have not moved since acting: reuse the policy's activations at obs
    if batch.policy_acts is not None:
        acts = [obs[:, : layout.obs_dim], *(a.reshape(B, -1) for a in batch.policy_acts)]
    # V at [obs; next_obs]: the second half only feeds the bootstrap values V(s')
    mu, log_std, values, cache = forward(layout, flat, obs, batch.next_obs.reshape(B, -1), acts)
    values, next_values = values[:B], values[B:].reshape(T, N)
    if hp.gae_lambda == 1.0:  # the paper's n-step returns (eq. 31)
        returns = nstep_returns(batch.rewards, batch.terminated, batch.truncated, next_values, hp.gamma).reshape(B)
        adv = returns - values
    else:
        adv = gae_advantages(batch.rewards, batch.terminated, batch.truncated, values.detach().reshape(T, N),
                             next_values, hp.gamma, hp.gae_lambda).reshape(B)
        returns = adv + values
    if hp.normalize_advantage:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    inv_std = torch.exp(-log_std)
    z = (actions - mu) * inv_std  # standardised action
    log_prob = (-0.5 * z * z - log_std - 0.5 * LOG_2PI).sum(-1)
    entropy = (log_std + 0.5 * (1.0 + LOG_2PI)).sum()  # state-independent std
    policy_loss = -(adv * log_prob).mean()  # eq. 31b
    value_loss = (returns - values).pow(2).mean()  # eq. 31c (without λv)
    # ∂L/∂(mean, log-std, value) of L = policy_loss + λv·value_loss − λβ·entropy (+ bound loss), by hand:
    w = (adv / B).unsqueeze(-1)
    g_mu = -w * z * inv_std
    if hp.bound_coef > 0:  # λb·mean(Σ relu(|μ| − 1)²): keeps the mean where clipped actions still differ
        g_mu = g_mu + (2.0 * hp.bound_coef / B) * (mu.abs() - 1.0).clamp(min=0.0) * torch.sign(mu)
    g_log_std = -(w * (z * z - 1.0)).sum(0) - hp.ent_coef
    g_value = (2.0 * hp.vf_coef / B) * (values - returns)
    grad = backward(layout, flat, cache, g_mu, g_log_std, g_value)
    grad_norm = clip_grad_norm_([grad], hp.max_grad_norm)  # λζ
    rmsprop_step_([flat], [grad], [square_avg], hp.learning_rate if lr is None else lr, hp.rms_alpha, hp.rms_eps)  # eq. 32
    explained_var = 1.0 - (returns - values).var() / (returns.var() + 1e-8)
    return torch.stack([policy_loss, value_loss, entropy, grad_norm, explained_var]).detach()


# ------------------------------------------------------------------------------ what the env's specs say


@dataclass(frozen=True)
class EnvLayout:
    """Sizes and bounds read from a TorchRL env's specs.

    Observation [*batch, *agents, obs_dim], action [*batch, *agents, act_dim]; `agents` (possibly empty) are dims
    whose entries all run the same policy. `low`/`high`: the action bounds per action dim (None: unbounded).
    """

    obs_dim: int
    act_dim: int
    num_envs: int
    agents: tuple[int, ...] = ()
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None
    _bounds: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def samples(self) -> int:
        """Policy evaluations per env step: num_envs × prod(agents)."""
        return self.num_envs * math.prod(self.agents)

    def to_env(self, raw: Tensor) -> Tensor:
        """Normalised raw actions [..., act] -> the env's units: clipped to [-1, 1], then mid + half·a (bounded)."""
        if self.low is None:
            return raw
        mid, half = self._mid_half(raw.dtype)
        return mid + half * raw.clamp(-1.0, 1.0)

    def _mid_half(self, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """(hi + lo) / 2 and (hi - lo) / 2 in `dtype` (made once per dtype: `to_env` runs every env step)."""
        if dtype not in self._bounds:
            lo, hi = torch.tensor(self.low, dtype=dtype), torch.tensor(self.high, dtype=dtype)
            self._bounds[dtype] = ((hi + lo) / 2, (hi - lo) / 2)
        return self._bounds[dtype]

    def unit_bounds(self) -> bool:
        """Whether the action bounds are [-1, 1] in every dim (the fused path's, and the point mass's)."""
        return self.low is not None and all(v == -1.0 for v in self.low) and all(v == 1.0 for v in self.high)


def read_env_layout(env: EnvBase) -> EnvLayout:
    """`EnvLayout` of a TorchRL env; ValueError naming what is missing or unsupported."""
    batch = tuple(env.batch_size)
    keys = list(env.observation_spec.keys())
    if "observation" not in keys:
        raise ValueError(f"the env's observation_spec has no 'observation' entry (it has {keys}); the policy reads "
                         "'observation' [*batch, obs] (wrap the env with a TorchRL transform that writes it)")
    obs_shape = tuple(env.observation_spec["observation"].shape)
    act_spec = env.action_spec
    act_shape = tuple(act_spec.shape)
    if len(obs_shape) <= len(batch) or obs_shape[: len(batch)] != batch:
        raise ValueError(f"observation shape {list(obs_shape)} does not start with the env's batch size {list(batch)}")
    agents = obs_shape[len(batch):-1]
    if act_shape[: len(batch)] != batch or tuple(act_shape[len(batch):-1]) != agents or len(act_shape) < len(batch) + 1:
        raise ValueError(f"action shape {list(act_shape)} does not match the observation's {list(obs_shape)} "
                         f"([*batch, *agents, act] with batch {list(batch)}, agents {list(agents)})")
    if getattr(act_spec, "domain", "continuous") != "continuous":
        raise ValueError(f"A2C here has a Gaussian policy: it needs a continuous action spec, got {type(act_spec).__name__}")
    act_dim = act_shape[-1]
    low = high = None
    space = getattr(act_spec, "space", None)
    if hasattr(space, "low") and hasattr(space, "high"):
        lo, hi = space.low.reshape(-1, act_dim).double(), space.high.reshape(-1, act_dim).double()
        if not (bool((lo == lo[0]).all()) and bool((hi == hi[0]).all())):
            raise ValueError("action bounds differ between envs/agents; the shared policy needs the same bounds")
        # TorchRL's Unbounded spec reports ±float32 max (and a float32 range from it overflows): no bound there
        if bool((lo[0].abs() < UNBOUNDED).all() and (hi[0].abs() < UNBOUNDED).all()):
            low, high = tuple(lo[0].tolist()), tuple(hi[0].tolist())
        elif bool((lo[0].abs() < UNBOUNDED).any() or (hi[0].abs() < UNBOUNDED).any()):
            logging.getLogger(__name__).warning(
                "the action spec bounds some components and not others: actions go to the env as sampled, unclipped")
    return EnvLayout(obs_shape[-1], act_dim, math.prod(batch), tuple(agents), low, high)


# ------------------------------------------------------------------------------ rollout sources


class HeldNoise:
    """Standard-normal policy noise [n, N, act], redrawn every `hold` agent steps and held in between.

    hold = 1 is the usual white Gaussian exploration (SB3's default, the paper). A rate action moves a
    task weight by only σw·Δt = 0.06 per step, so a single step's noise barely changes the return
    (measured corr(z, return) ≈ 0.005); holding it for k steps, as gSDE does with its
    `sde_sample_freq` (Raffin et al. 2022), makes its effect k times larger. The log-probability stays
    the per-step Gaussian one, as in gSDE.
    """

    def __init__(self, generator: torch.Generator, num_envs: int, act_dim: int, hold: int) -> None:
        """Draw from `generator`; `hold` >= 1 agent steps per draw."""
        self.gen, self.shape, self.hold = generator, (num_envs, act_dim), hold
        self.t = 0
        self.current = torch.zeros(self.shape)

    def draw(self, n: int) -> Tensor:
        """Noise for the next `n` agent steps, [n, N, act]."""
        fresh = torch.randn(n, *self.shape, generator=self.gen)
        if self.hold == 1:
            self.t += n
            return fresh
        out = []
        for i in range(n):
            if (self.t + i) % self.hold == 0:
                self.current = fresh[i]
            out.append(self.current)
        self.t += n
        return torch.stack(out)

    def state_dict(self) -> dict:
        """Step counter and the held draw, for exact resume."""
        return {"t": self.t, "current": self.current.clone()}

    def load_state_dict(self, d: dict) -> None:
        """Restore `state_dict()`."""
        self.t, self.current = int(d["t"]), d["current"].clone()


def _sample_action(layout: ParamLayout, flat: Tensor, obs: Tensor, noise: Tensor,
                   params: dict[str, Tensor] | None = None) -> tuple[Tensor, list[Tensor]]:
    """Unclipped Gaussian action mean + σ·noise [B, act], and the policy's activations at `obs` (`params`: as in
    `policy_forward`)."""
    p = layout.views(flat) if params is None else params
    mu, acts = policy_forward(layout, flat, obs, p)
    return mu + torch.exp(p["log_std"]) * noise, acts


def rollout_step(layout: ParamLayout, env_step, flat: Tensor, state: dict, pending: dict, schedule: Tensor,
                 obs: Tensor, noise: Tensor):
    """Act and step once: (state, batch row (obs, action, r, term, trunc, final_obs, policy hidden acts), next obs)."""
    action, acts = _sample_action(layout, flat, obs, noise)
    state, final_obs, next_obs, r, term, trunc = env_step(state, pending, schedule, action.clamp(-1.0, 1.0))
    return state, (obs, action, r, term, trunc, final_obs, tuple(acts[1:])), next_obs


def fused_iteration(layout: ParamLayout, hp: A2CConfig, env_step, env_observe, flat: Tensor, square_avg: Tensor,
                    state: dict, pending: dict, schedule: Tensor, noise: Tensor):
    """n env steps (pure `env_step` with auto-reset) + one `a2c_update`, as ONE function to compile."""
    state, batch = collect(lambda s, o, z: rollout_step(layout, env_step, flat, s, pending, schedule, o, z),
                           state, env_observe(state), noise)
    metrics = a2c_update(layout, flat, square_avg, batch, hp)
    return state, metrics, batch.rewards, batch.terminated | batch.truncated


def collect(step: Callable, state: dict, obs: Tensor, noise: Tensor) -> tuple[dict, Batch]:
    """Run `step(state, obs, noise_t) -> (state, row, next_obs)` for each of noise's n rows; (state, Batch [n, N])."""
    rows = []
    for t in range(noise.shape[0]):
        state, row, obs = step(state, obs, noise[t])
        rows.append(row)
    *fields, acts = zip(*rows)
    return state, Batch(*(torch.stack(c) for c in fields), tuple(torch.stack(a) for a in zip(*acts)))


class FusedRollout:
    """Rollout + update fused into one (compiled) call, for envs with the fused API (PointMassEnv).

    With `a2c.backend` auto/native the whole iteration is one C call instead (algorithms/native).
    Per iteration Python does: draw the policy noise, call the compiled graph, and — only when an
    episode ended — record its return and draw a new pending episode (`env.refill`).
    Compile time grows faster than the graph (n steps × env sub-steps, unrolled), so for n_steps >
    FUSE_MAX_STEPS the step and the update are compiled as two graphs and Python loops over n:
    same numbers, a few more calls per iteration.
    """

    FUSE_MAX_STEPS = 8

    def __init__(self, env, layout: ParamLayout, generator: torch.Generator, hp: A2CConfig,
                 fuse: bool | None = None) -> None:
        """Drive `env` with actions sampled from `layout` params; noise from `generator`."""
        self.env, self.layout, self.gen, self.hp = env, layout, generator, hp
        self.num_envs = env.num_envs
        self.noise = HeldNoise(generator, self.num_envs, layout.act_dim, hp.noise_hold)
        step_fn, self._observe = env.fused_functions(privileged=hp.critic == "privileged")
        self.fuse = hp.n_steps <= self.FUSE_MAX_STEPS if fuse is None else fuse
        maybe_compile = _compile if hp.compile else (lambda f: f)

        def iteration(flat, square_avg, state, pending, schedule, noise):
            return fused_iteration(layout, hp, step_fn, self._observe, flat, square_avg, state, pending, schedule, noise)

        def step(flat, state, pending, schedule, obs, noise):
            return rollout_step(layout, step_fn, flat, state, pending, schedule, obs, noise)

        def update(flat, square_avg, batch):
            return a2c_update(layout, flat, square_avg, batch, hp)

        self._native, self.route = _native_iteration(env, layout, hp)
        """`route`: which code runs the iteration, said after training (the C copy of the step ignores Python edits
        of it)."""
        self.compiles = hp.compile and self._native is None
        """Whether the first `iterate` pays for torch.compile."""
        if self._native is None:  # the torch graphs (the C iteration needs none)
            if self.fuse:
                self._iteration = maybe_compile(iteration)
            else:
                self._step, self._update = maybe_compile(step), maybe_compile(update)
        self.ep_return = torch.zeros(self.num_envs)
        self.ep_length = torch.zeros(self.num_envs, dtype=torch.int64)
        self.finished: list[tuple[float, int]] = []
        # Many C iterations per call must add the rollouts' rewards as `rewards.sum(0)` does (checked for this shape);
        # a noise draw for many iterations is one torch.randn where that gives the same numbers as one per iteration.
        self._many = self._native is not None and self._native.sums_like_torch()
        self._noise_splits = _randn_splits(hp.n_steps, (self.num_envs, layout.act_dim))

    def set_progress(self, fraction: float) -> None:
        """The fused iteration's learning rate is constant (a2c.lr_schedule is refused before it is built)."""

    def iterate(self, flat: Tensor, square_avg: Tensor) -> Tensor:
        """Collect n steps in every env and update `flat`/`square_avg` in place; returns METRICS [5]."""
        noise = self.noise.draw(self.hp.n_steps)
        state, pending, schedule = self.env.fused_inputs()
        if self._native is not None:  # updates the env's state in place; counts the episode ends itself
            _, metrics, rewards, dones = self._native(flat, square_avg, state, pending, schedule, noise)
            any_done = self._native.done_count > 0
        else:
            if self.fuse:
                state, metrics, rewards, dones = self._iteration(flat, square_avg, state, pending, schedule, noise)
            else:
                state, batch = collect(lambda s, o, z: self._step(flat, s, pending, schedule, o, z),
                                       state, self._observe(state), noise)
                metrics = self._update(flat, square_avg, batch)
                rewards, dones = batch.rewards, batch.terminated | batch.truncated
            self.env.fused_commit(state)
            any_done = bool(dones.any())
        self._book_episodes(rewards, dones, any_done)
        return metrics

    def _book_episodes(self, rewards: Tensor, dones: Tensor, any_done: bool) -> None:
        """Add a rollout's rewards [n, N] to the running episodes; record those that ended and draw their successors."""
        if any_done:
            _count_episodes(self, rewards, dones)
            self.env.refill(dones.any(0))
        else:
            self.ep_return += rewards.sum(0)
            self.ep_length += rewards.shape[0]

    def max_updates(self) -> int:
        """How many iterations one `iterate_many` call may run now: up to the one in which the next episode ends on
        the C iteration (new episodes are drawn in Python between calls), else 1."""
        if not self._many:
            return 1
        left = self.env.cfg.episode_steps - int(self.env.fused_inputs()[0]["t"].max())
        return max(1, -(-left // self.hp.n_steps))

    def iterate_many(self, count: int, flat: Tensor, square_avg: Tensor, metric_sum: Tensor) -> None:
        """`count` (<= `max_updates()`) iterations, as `count` calls of `iterate` whose METRICS are added to
        `metric_sum` [5], bit for bit; on the C iteration in one call."""
        if count == 1:
            metric_sum += self.iterate(flat, square_avg)
            return
        if count > self.max_updates():
            raise ValueError(f"{count} iterations cross an episode end ({self.max_updates()} may run in one call)")
        n = self.hp.n_steps
        noise = self.noise.draw(count * n) if self._noise_splits else torch.cat([self.noise.draw(n) for _ in range(count)])
        state, pending, schedule = self.env.fused_inputs()
        ran = self._native.run(count, flat, square_avg, state, pending, schedule, noise, metric_sum, self.ep_return,
                               self.ep_length)
        if ran != count:  # the bound above comes from the same step counters: a broken invariant, not a user error
            raise RuntimeError(f"an episode ended in iteration {ran} of {count}, before the env's step counters said")
        self._book_episodes(self._native.rewards, self._native.dones, self._native.done_count > 0)

    def state_dict(self) -> dict:
        """Everything needed to resume bit-identically."""
        return {"env": self.env.get_state(), "ep_return": self.ep_return, "ep_length": self.ep_length,
                "noise": self.noise.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        """Restore `state_dict()`."""
        self.env.set_state(d["env"])
        if "noise" in d:
            self.noise.load_state_dict(d["noise"])
        self.ep_return, self.ep_length = d["ep_return"], d["ep_length"]


def _native_iteration(env, layout: ParamLayout, hp: A2CConfig):  # noqa: ANN201
    """(the C iteration (algorithms/native) for this trainer per `hp.backend`, or None for the torch path; that route
    in words, with why the C iteration does not run where it could)."""
    torch_route = "the torch step" + (", compiled" if hp.compile else "")
    if hp.backend == "torch":
        return None, torch_route + " (a2c.backend: torch)"
    from algorithms import native

    why = native.unsupported(env, layout)
    if why is None and hp.backend == "auto" and hp.n_steps * env.num_envs > native.AUTO_MAX_BATCH:
        return None, torch_route  # large batches are GEMM-bound: MKL through torch is faster there
    lib = native.load() if why is None else None
    if lib is None:
        if hp.backend == "native":
            reason = why or "no C compiler, a failed build or A3CQP_NATIVE_A2C=0 (see the warning above)"
            raise ValueError(f"a2c.backend: native is not available here: {reason}")
        return None, torch_route + (f" ({why})" if why else " (the C library is not built)")
    return (native.NativeIteration(lib, env, layout, hp),
            "the C iteration (algorithms/native: its own copy of the eq. 35 step and eq. 30 reward)")


def _randn_splits(n: int, shape: tuple[int, ...]) -> bool:
    """Whether one torch.randn of [k·n, *shape] equals k draws of [n, *shape] from the same generator (torch's CPU
    normal fills blocks of 16 independently: true when n·prod(shape) is a multiple of 16)."""
    one, many = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    joint = torch.randn(3 * n, *shape, generator=one)
    split = torch.cat([torch.randn(n, *shape, generator=many) for _ in range(3)])
    return torch.equal(joint, split) and torch.equal(one.get_state(), many.get_state())


def _count_episodes(runner, rewards: Tensor, dones: Tensor) -> None:
    """Accumulate per-env returns over a [T, N] rollout; record (return, length) of episodes that end."""
    for t in range(rewards.shape[0]):  # n is small; only runs on rollouts where an episode ended
        runner.ep_return += rewards[t]
        runner.ep_length += 1
        done = dones[t]
        if bool(done.any()):
            runner.finished += list(zip(runner.ep_return[done].tolist(), runner.ep_length[done].tolist()))
            runner.ep_return[done] = 0.0
            runner.ep_length[done] = 0


@functools.cache
def _sampling_policy_class() -> type:
    """`SamplingPolicy`, made on first use (tensordict is imported only by the TorchRL rollout)."""
    from tensordict.nn import TensorDictModuleBase

    class SamplingPolicy(TensorDictModuleBase):
        """The collector's policy: "observation" -> "action" (env units) and "action_raw" (the unclipped sample).

        It writes its two entries itself: tensordict 0.14's `TensorDictModule` passes each output through
        `TensorDict.from_any`, which calls `importlib.util.find_spec("pandas")` on every plain tensor (~1 ms per step
        here, a third of a Pendulum-v1 step with 16 envs).
        """

        def __init__(self, layout: ParamLayout, flat: Tensor, spec: EnvLayout, noise: HeldNoise, dtype: torch.dtype):
            super().__init__()
            self.in_keys, self.out_keys = ["observation"], ["action", "action_raw"]
            self.layout, self.flat, self.env_layout, self.noise, self.dtype = layout, flat, spec, noise, dtype
            self.params = layout.views(flat)  # views into `flat`, which the rollout updates in place

        def forward(self, td):
            obs = td.get("observation")
            noise = self.noise.draw(1)[0].reshape(obs.shape[:-1] + (self.layout.act_dim,))
            raw, _ = _sample_action(self.layout, self.flat, obs.reshape(-1, obs.shape[-1]).float(),
                                    noise.reshape(-1, self.layout.act_dim), self.params)
            raw = raw.reshape(noise.shape)
            td.set("action", self.env_layout.to_env(raw).to(self.dtype))
            td.set("action_raw", raw)
            return td

    return SamplingPolicy


class TorchRLRollout:
    """n-step rollouts of any TorchRL EnvBase (GymWrapper, batched envs, ParallelEnv, SerialEnv) through a `Collector`.

    Every (env, agent) entry is one sample stream of the shared policy: rewards and done flags without the agent
    dims apply to all of an env's agents.
    """

    def __init__(self, env, layout: ParamLayout, spec: EnvLayout, generator: torch.Generator, hp: A2CConfig) -> None:
        """Drive `env` (read into `spec`) with actions sampled from `layout` params; noise from `generator`."""
        from torchrl.collectors import Collector

        self.layout, self.spec, self.gen, self.flat, self.hp, self.n = layout, spec, generator, layout.init(), hp, hp.n_steps
        self._update = _compile(a2c_update) if hp.compile else a2c_update
        self.compiles = hp.compile
        self.num_envs = spec.num_envs
        self.streams = spec.samples
        module = _sampling_policy_class()(layout, self.flat, spec, HeldNoise(generator, self.streams, layout.act_dim, hp.noise_hold),
                                 env.action_spec.dtype)
        # The policy is feed-forward and needs no env transforms; torchrl 0.14 still flags a missing InitTracker
        # with a FutureWarning (0.15 would append it to the user's env). False keeps the env as given, silently.
        self.collector = Collector(env, module, frames_per_batch=self.n * self.num_envs, total_frames=-1,
                                   auto_register_policy_transforms=False)
        self._iter = iter(self.collector)
        self.ep_return = torch.zeros(self.streams)
        self.ep_length = torch.zeros(self.streams, dtype=torch.int64)
        self.finished: list[tuple[float, int]] = []
        self.lr = torch.tensor(hp.learning_rate) if hp.lr_schedule == "linear" else None
        """The scheduled learning rate (a2c.lr_schedule: linear), set by `set_progress`; None = constant."""

    def set_progress(self, fraction: float) -> None:
        """Tell the rollout which fraction of the run's updates is done (the learning-rate schedule reads it)."""
        if self.lr is not None:
            self.lr.fill_(self.hp.learning_rate * (1.0 - fraction))

    def _per_stream(self, x: Tensor) -> Tensor:
        """[n, N, (*agents), (1)] -> [n, N·A]: values without the agent dims hold for all of an env's agents."""
        n, N, A = self.n, self.num_envs, self.streams // self.num_envs
        if x.numel() == n * N * A:
            return x.reshape(n, N * A)
        return x.reshape(n, N, 1).expand(n, N, A).reshape(n, N * A)

    def iterate(self, flat: Tensor, square_avg: Tensor) -> Tensor:
        """Next batch from the collector (time-major [n, N·A]), then one `a2c_update`; returns METRICS [5]."""
        n, S = self.n, self.streams
        with torch.no_grad():
            self.flat.copy_(flat)
            td = next(self._iter).reshape(self.num_envs, n).transpose(0, 1)  # [T, N]
        r = self._per_stream(td["next", "reward"]).float()
        term = self._per_stream(td["next", "terminated"])
        trunc = self._per_stream(td["next", "truncated"]) if ("next", "truncated") in td.keys(True) else torch.zeros_like(term)
        _count_episodes(self, r, term | trunc)
        key = "critic_observation" if self.hp.critic == "privileged" else "observation"  # [obs; privileged]
        obs = td[key].reshape(n, S, -1).float()
        if self.hp.reward_scale != 1.0:
            r = r * self.hp.reward_scale
        batch = Batch(obs, td["action_raw"].reshape(n, S, -1).float(), r, term, trunc, td["next", key].reshape(n, S, -1).float())
        if self.lr is None:
            return self._update(self.layout, flat, square_avg, batch, self.hp)
        return self._update(self.layout, flat, square_avg, batch, self.hp, self.lr)

    def max_updates(self) -> int:
        """One update per `iterate_many` call (the collector yields one batch at a time)."""
        return 1

    def iterate_many(self, count: int, flat: Tensor, square_avg: Tensor, metric_sum: Tensor) -> None:
        """`iterate` once (count must be 1), its METRICS added to `metric_sum`."""
        if count != 1:
            raise ValueError(f"the TorchRL rollout runs one update per call, not {count}")
        metric_sum += self.iterate(flat, square_avg)

    def state_dict(self) -> dict:
        """Collector-driven envs cannot be snapshotted in general; resume restarts their episodes."""
        return {}

    def load_state_dict(self, d: dict) -> None:
        """Nothing to restore (see `state_dict`)."""

    def close(self) -> None:
        """Shut the collector (and its env workers) down."""
        self.collector.shutdown()


# ------------------------------------------------------------------------------ training loop


@dataclass
class TrainResult:
    """What `train` did: steps, timings and where files went."""

    steps: int
    updates: int
    seconds: float
    compile_seconds: float
    steps_per_second: float
    out_dir: Path | None
    policy_path: Path | None
    final_metrics: dict[str, float] = field(default_factory=dict)
    episode_returns: list[float] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    """Totals of the loop's named blocks [s]: iterate (rollout + update), log, regions, transfer, checkpoint; and
    select, the Panda trials of `a2c.select_policy: panda` after the loop."""
    startup_seconds: float = float("nan")
    """Process start to the end of this run's first update [s] (the first update's compile included)."""
    fig5_applies: bool = False
    """Whether the env is the point mass, whose eq. 26 observation the Fig. 5 regions and policy maps are drawn in."""
    selected_update: int | None = None
    """With `a2c.select_policy: transfer`, the update whose parameters policy.pt holds."""
    transfer_margin: float = float("nan")
    """With `a2c.select_policy: transfer`, their transfer margin (a3cqp_rl.transfer; > 0: both Panda checks pass)."""
    panda_selection: list[dict] = field(default_factory=list)
    """With `a2c.select_policy: panda`, each candidate's row (algorithms.panda_select), in the margins' order."""
    resumed_steps: int = 0
    """Steps the run had trained before this call (a resume); equal to `steps`: nothing was left to train."""
    route: str = ""
    """Which code ran the iteration (the C iteration, the torch step, a TorchRL collector)."""


def train(
    cfg: ExperimentConfig,
    out_dir: str | Path | None = None,
    *,
    total_steps: int | None = None,
    resume: bool = False,
    force: bool = False,
    override: bool = False,
    progress: bool = False,
    env: EnvBase | None = None,
    callback: Callable[[int, dict], None] | None = None,
) -> TrainResult:
    """Train a Gaussian policy with A2C on `env` (default: the env `cfg.env` names, a2c.num_envs copies, seeded);
    write config.yaml, metrics.csv, checkpoint.pt and policy.pt under `out_dir` (see a3cqp_rl.run_folder's rules:
    `force` starts over in a folder holding a run, `override` lets `resume` change the config)."""
    if not isinstance(cfg, ExperimentConfig):
        raise TypeError(f"train needs an ExperimentConfig (a3cqp_rl.config.load_config(path)), got "
                        f"{type(cfg).__name__}" + (f" {cfg!r}" if isinstance(cfg, (str, Path)) else ""))
    hp = cfg.a2c
    total = int(total_steps if total_steps is not None else hp.total_steps)
    if total <= 0:
        raise ValueError(f"total_steps must be > 0, got {total}")
    if total != hp.total_steps:  # the run's config.yaml records the length it runs to: a plain --resume continues it
        cfg = dataclasses.replace(cfg, a2c=dataclasses.replace(hp, total_steps=total))
        hp = cfg.a2c
    if hp.select_policy == "panda":  # before training: the selection after it needs both
        from algorithms.panda_select import select_config_path

        if out_dir is None:
            raise ValueError("a2c.select_policy: panda writes its candidates into the run folder: give out_dir")
        select_config_path(hp)
    folder = open_run_folder(out_dir, resume=resume, force=force)
    failed = True
    try:
        result = _train(cfg, folder, total, resume, override, progress, env, callback)
        failed = False
        return result
    finally:
        if folder is not None:
            folder.close(failed=failed)


def _train(cfg, folder, total, resume, override, progress, env, callback) -> TrainResult:
    """`train` in its run folder (locked)."""
    hp = cfg.a2c
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    env = _prepare_env(env, cfg)
    spec = read_env_layout(env)
    # look on the class: batched TorchRL envs forward unknown attributes to their workers
    fused = getattr(type(env), "fused_functions", None) is not None and hp.rollout == "auto" and spec.unit_bounds()
    layout = ParamLayout(spec.obs_dim, spec.act_dim, hp.hidden, hp.network, _critic_input_dim(env, hp, fused, spec.obs_dim))
    flat = layout.init(gen, hp.log_std_init)
    if hp.init_policy is not None and not resume:  # a shipped policy is found from any working directory
        copied = init_from_policy(project_path(hp.init_policy), layout, flat, spec.low, spec.high)
        fresh = [k for k in layout.offsets if k not in copied]
        print(f"a2c: starting from {hp.init_policy} ({len(copied)} of {len(layout.offsets)} tensors"
              + (f"; initialised afresh: {', '.join(fresh)}" if fresh else "") + ")")
    square_avg = torch.full_like(flat, hp.rms_init)
    if fused and (hp.lr_schedule != "constant" or hp.reward_scale != 1.0):
        raise ValueError("a2c.lr_schedule and a2c.reward_scale apply to the TorchRL rollout (a2c.rollout: torchrl); "
                         "the fused point-mass iteration has a constant learning rate and unscaled rewards")
    runner = FusedRollout(env, layout, gen, hp) if fused else TorchRLRollout(env, layout, spec, gen, hp)
    per_update = hp.n_steps * runner.num_envs
    num_updates = math.ceil(total / per_update)

    average = ParameterAverage(num_updates, hp.average_last)
    selection = TransferSelection(layout, spec, num_updates, hp)
    ckpt = Checkpoints(folder, cfg, layout, spec, flat, square_avg, gen, runner, average, selection)
    start = ckpt.begin(resume, override, num_updates, total)
    if start and not runner.state_dict():  # a collector-driven env: its episodes start again, not bit for bit
        logging.getLogger(__name__).warning(
            "resumed at update %d with the parameters and optimiser state; the env (%s) is not snapshotted, so its "
            "episodes start again from the seed: the run will not be bit for bit an uninterrupted one", start, cfg.env)
    log = RunLog(folder.path if folder else None, start, per_update, hp.log_every, finished=start == num_updates)
    regions = RegionChecks(layout, flat, average, num_updates, hp) if _fig5_applies(env) else None
    bar = _ProgressBar(num_updates * per_update, start * per_update, progress, runner.compiles and start < num_updates)
    timer, compile_s, startup_s, last = Timer(), 0.0, float("nan"), {}
    t_start = time.perf_counter()
    u = start
    with StopCheckpoint(enabled=folder is not None) as stop:
        while u < num_updates:
            t0 = time.perf_counter()
            runner.set_progress(u / num_updates)  # the learning-rate schedule's clock
            k = _updates_before_python(u, start, num_updates, hp, average, runner)
            with timer("iterate"):
                runner.iterate_many(k, flat, square_avg, ckpt.metric_sum)
            ckpt.metric_count += k
            u = done = u + k
            if not bool(torch.isfinite(flat).all()):  # at once: every check after this would only fail on the NaNs
                raise _diverged(done, per_update, hp, "non-finite parameters")
            average.update(done, flat)
            if done - k == start:  # the first iteration pays for torch.compile
                startup_s = process_age()
                compile_s = time.perf_counter() - t0 if runner.compiles else 0.0
                bar.compiled()
            if done % hp.log_every == 0 or done == num_updates:
                with timer("regions"):
                    row_checks = regions(done) if regions else {}
                with timer("transfer"):
                    row_checks.update(selection(done, flat))
                with timer("log"):
                    last = _log_row(log, ckpt, done, per_update, runner, t_start, compile_s, start, row_checks)
                if not all(math.isfinite(last[k]) for k in ("policy_loss", "value_loss")):
                    raise _diverged(done, per_update, hp, f"policy loss {last['policy_loss']}, value loss "
                                                          f"{last['value_loss']}")
                if callback:
                    callback(done * per_update, last)
                bar.set_postfix(ep_reward=f"{last['episode_reward']:.2f}", refresh=False)
            bar.update(per_update * k)
            if folder and (done % hp.checkpoint_every == 0 or done == num_updates or stop.requested is not None):
                with timer("checkpoint"):
                    ckpt.save(done)
            stop.stop_if_requested(done * per_update, folder)
    bar.close()
    log.close()
    if isinstance(runner, TorchRLRollout):
        runner.close()
    elapsed = time.perf_counter() - t_start
    panda_rows: list[dict] = []
    if hp.select_policy == "panda" and selection.candidates:
        from algorithms.panda_select import PANDA_SELECTION_KEYS, select_on_panda

        print(f"a2c.select_policy: panda: {len(selection.candidates)} candidates on {hp.select_trials} peg-in-hole "
              f"trials each (seed {hp.select_seed})")
        with timer("select"):
            chosen, panda_rows = select_on_panda(selection.candidates, ckpt.meta(), folder.path, hp)
        selection.choose(chosen, {k: panda_rows[chosen][k] for k in PANDA_SELECTION_KEYS})
    policy_path = ckpt.save_policy() if folder else None
    return TrainResult(
        steps=num_updates * per_update, updates=num_updates, seconds=elapsed, compile_seconds=compile_s,
        steps_per_second=(num_updates - start) * per_update / max(elapsed - compile_s, 1e-9),
        out_dir=folder.path if folder else None, policy_path=policy_path, final_metrics=last,
        episode_returns=[r for r, _ in runner.finished], timings=dict(timer.totals), startup_seconds=startup_s,
        fig5_applies=regions is not None,
        selected_update=selection.update if selection.best is not None else None,
        transfer_margin=selection.margin if selection.best is not None else float("nan"),
        panda_selection=panda_rows, resumed_steps=start * per_update,
        route=getattr(runner, "route", "a TorchRL rollout of the env's own step"),
    )


# ------------------------------------------------------------------------------ helpers


def _diverged(update: int, per_update: int, hp: A2CConfig, what: str) -> TrainingDiverged:
    """The error of a run that diverged in `update`: where, what, and the settings that bound the step size."""
    return TrainingDiverged(f"training diverged at step {update * per_update:,} (update {update:,}): {what}; lower "
                            f"a2c.learning_rate (now {hp.learning_rate:g}) or a2c.max_grad_norm (now "
                            f"{hp.max_grad_norm:g})")


def _updates_before_python(u: int, start: int, num_updates: int, hp: A2CConfig, average: ParameterAverage,
                           runner) -> int:
    """How many updates the loop may run, after `u` done, before Python must look again: the next log row,
    checkpoint or end of the run, each update of the parameter-averaging window, the first update (its time is the
    start-up's) and what the rollout allows (`max_updates`: its next episode end)."""
    if u == start or u + 1 >= average.first:
        return 1
    stops = (num_updates, (u // hp.log_every + 1) * hp.log_every, (u // hp.checkpoint_every + 1) * hp.checkpoint_every,
             average.first - 1)
    return max(1, min(min(stops) - u, runner.max_updates()))


def _prepare_env(env, cfg: ExperimentConfig):
    """The env to train on: `cfg.env` built and seeded, or the caller's, seeded and checked against a2c.num_envs."""
    if env is None:
        from a3cqp_rl.config import check_memory
        from algorithms.make_env import make_env

        check_memory(cfg)
        return make_env(cfg)
    n = int(env.batch_size.numel())
    if n != cfg.a2c.num_envs:
        raise ValueError(f"a2c.num_envs is {cfg.a2c.num_envs} but the env passed has {n} (batch_size "
                         f"{list(env.batch_size)}); set a2c.num_envs: {n}")
    env.set_seed(cfg.seed)
    return env


def _fig5_applies(env) -> bool:
    """The Fig. 5 regions are boxes in the point mass's eq. 26 observation: checked on PointMassEnv only, and only
    while its observation is eq. 26's three values (an extended one has no Fig. 5 to be checked against)."""
    from envs.point_mass import PointMassEnv

    return isinstance(env, PointMassEnv) and env.observation_spec["observation"].shape[-1] == 3


def _log_row(log: RunLog, ckpt, updates, per_update, runner, t_start, compile_s, start, checks) -> dict[str, float]:
    """The metric row after `updates` updates (means since the last row), written to `log`; `checks` holds the row's
    Fig. 5 region and transfer columns (missing ones: NaN)."""
    recent = [r for r, _ in runner.finished[-100:]]
    row = {"step": updates * per_update, "update": updates,
           **{k: float(v) for k, v in zip(METRICS, ckpt.metric_means(updates))},
           "episode_reward": float(sum(recent) / len(recent)) if recent else float("nan"),
           "episodes": ckpt.episodes_before + len(runner.finished),
           "steps_per_second": (updates - start) * per_update / max(time.perf_counter() - t_start - compile_s, 1e-9),
           **{k: checks.get(k, float("nan")) for k in (*REGION_COLUMNS, *TRANSFER_COLUMNS)}}
    log.write(row)
    return row


def _critic_input_dim(env, hp: A2CConfig, fused: bool, obs_dim: int) -> int:
    """Width of the value network's input: obs_dim, or that of the env's privileged observation."""
    if hp.critic != "privileged":
        return obs_dim
    if fused:
        return int(env.fused_functions(privileged=True)[1](env.fused_inputs()[0]).shape[-1])
    spec = env.observation_spec
    if "critic_observation" not in spec.keys():
        raise ValueError("a2c.critic: privileged needs an env with a 'critic_observation' entry "
                         "([obs; privileged state]); this env has none")
    return int(spec["critic_observation"].shape[-1])


def _compile(fn: Callable) -> Callable:
    """torch.compile for the per-iteration graphs: C++ wrapper, and no guards.

    The graphs are dozens of tiny kernels, so fixed per-call costs dominate: the default Python
    wrapper was ~1.5x slower per iteration, and guard checks cost ~100 µs per call. Guards can be
    skipped safely because each compiled function is private to one trainer (its own copy of the
    code object, below) and always receives tensors of the same shapes and dtypes (its configs are
    captured constants).
    """
    import torch._inductor.config as inductor_config

    # Dynamo keeps compiled graphs on the function's *code object*, which every function made by the same `def`
    # shares (each FusedRollout's `iteration` closure; `a2c_update` itself). With the guards skipped, a second
    # trainer in the same process (another config: a sweep, a GA, the slow tests) would silently run the first
    # one's graph with the first one's hyper-parameters baked in. A private copy of the code object gives each
    # compiled function its own cache (tests/test_a2c.py::test_compiled_functions_do_not_share_graphs).
    private = types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    private.__kwdefaults__ = fn.__kwdefaults__
    fn = private
    compiled = torch.compile(fn, dynamic=False, options={"guard_filter_fn": torch.compiler.skip_all_guards_unsafe})
    first = [True]

    def run(*args):
        if first[0]:  # compilation happens on the first call: only it needs the patched config
            first[0] = False
            with inductor_config.patch(cpp_wrapper=True):
                return compiled(*args)
        return compiled(*args)

    return run


class _ProgressBar:
    """tqdm over agent steps; says when the first update compiles, and restarts its rate estimate after it."""

    def __init__(self, total: int, initial: int, enabled: bool, compiling: bool) -> None:
        from tqdm.auto import tqdm

        self.initial, self.compiling = initial, compiling
        self.bar = tqdm(total=total, initial=initial, disable=not enabled, unit="step", unit_scale=True,
                        dynamic_ncols=True, desc="A2C (compiling the step, one-time)" if compiling else "A2C")
        self.update, self.set_postfix, self.close = self.bar.update, self.bar.set_postfix, self.bar.close

    def compiled(self) -> None:
        """The first update is done."""
        if self.compiling:
            self.bar.set_description("A2C")
            self.bar.reset(total=self.bar.total)
            self.bar.update(self.initial)
