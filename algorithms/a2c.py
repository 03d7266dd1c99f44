"""Synchronous n-step advantage actor-critic (A2C), paper 000 eq. 31-32, hand-written.

Reads top to bottom: n-step returns → `a2c_update` (eq. 31 loss, hand-derived gradients, λζ
clipping, eq. 32 RMSProp) → two rollout sources → `train` (loop, logging, atomic checkpoints, resume).

Conventions (those of Stable-Baselines3's A2C, the paper's library; defaults = Table IV):
  * Gaussian policy on the raw action; the env receives it clipped to [-1, 1] and the update
    uses the log-probability of the unclipped sample.
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
(b) any TorchRL EnvBase through a TorchRL `Collector` (ParallelEnv/SerialEnv, MuJoCo Panda).
"""

from __future__ import annotations

import csv
import math
import time
import types
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from a3cqp_rl.checkpoint import load_checkpoint, save_atomic
from a3cqp_rl.config import A2CConfig, ExperimentConfig, config_to_dict
from a3cqp_rl.exceptions import CheckpointError
from a3cqp_rl.regions import REGION_COLUMNS, region_row
from algorithms.networks import LOG_2PI, ParamLayout, backward, forward, policy_forward, policy_mean
from algorithms.rmsprop import clip_grad_norm_, rmsprop_step_

__all__ = ["Batch", "HeldNoise", "ParameterAverage", "nstep_returns", "gae_advantages", "a2c_update", "train", "TrainResult",
           "load_policy", "METRICS"]

METRICS = ("policy_loss", "value_loss", "entropy", "grad_norm", "explained_variance")
CSV_COLUMNS = ("step", "update", *METRICS, "episode_reward", "episodes", "steps_per_second", *REGION_COLUMNS)
"""metrics.csv columns. The region columns check the policy policy.pt would hold at that row (with `a2c.average_last`,
the running average once it has begun); NaN on rows without a Fig. 5 check (`a2c.region_checks`)."""


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


def a2c_update(layout: ParamLayout, flat: Tensor, square_avg: Tensor, batch: Batch, hp: A2CConfig) -> Tensor:
    """One A2C step in place on `flat` and the RMSProp accumulator; returns METRICS as a tensor [5]."""
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
    rmsprop_step_([flat], [grad], [square_avg], hp.learning_rate, hp.rms_alpha, hp.rms_eps)  # eq. 32
    explained_var = 1.0 - (returns - values).var() / (returns.var() + 1e-8)
    return torch.stack([policy_loss, value_loss, entropy, grad_norm, explained_var]).detach()


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


def _sample_action(layout: ParamLayout, flat: Tensor, obs: Tensor, noise: Tensor) -> tuple[Tensor, list[Tensor]]:
    """Unclipped Gaussian action mean + σ·noise [B, act], and the policy's activations at `obs`."""
    mu, acts = policy_forward(layout, flat, obs)
    return mu + torch.exp(layout.views(flat)["log_std"]) * noise, acts


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

        self._native = _native_iteration(env, layout, hp)
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
        if any_done:
            _count_episodes(self, rewards, dones)
            self.env.refill(dones.any(0))
        else:
            self.ep_return += rewards.sum(0)
            self.ep_length += rewards.shape[0]
        return metrics

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


def _native_iteration(env, layout: ParamLayout, hp: A2CConfig):
    """The C iteration (algorithms/native) for this trainer per `hp.backend`, or None for the torch path."""
    if hp.backend == "torch":
        return None
    from algorithms import native

    why = native.unsupported(env, layout)
    if why is None and hp.backend == "auto" and hp.n_steps * env.num_envs > native.AUTO_MAX_BATCH:
        return None  # large batches are GEMM-bound: MKL through torch is faster there
    lib = native.load() if why is None else None
    if lib is None:
        if hp.backend == "native":
            reason = why or "no C compiler, a failed build or A3CQP_NATIVE_A2C=0 (see the warning above)"
            raise ValueError(f"a2c.backend: native is not available here: {reason}")
        return None
    return native.NativeIteration(lib, env, layout, hp)


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


class TorchRLRollout:
    """n-step rollouts of any TorchRL EnvBase (batched, ParallelEnv, SerialEnv) through a `Collector`."""

    def __init__(self, env, layout: ParamLayout, generator: torch.Generator, hp: A2CConfig) -> None:
        """`env` must expose `observation` [*, obs] and accept `action` [*, act]; batch size [N]."""
        from tensordict.nn import TensorDictModule
        from torchrl.collectors import Collector

        self.layout, self.gen, self.flat, self.hp, self.n = layout, generator, layout.init(), hp, hp.n_steps
        self._update = _compile(a2c_update) if hp.compile else a2c_update
        self.compiles = hp.compile
        self.num_envs = int(env.batch_size.numel())
        held = HeldNoise(generator, self.num_envs, layout.act_dim, hp.noise_hold)

        def policy(obs: Tensor) -> tuple[Tensor, Tensor]:
            noise = held.draw(1)[0].reshape(obs.shape[:-1] + (layout.act_dim,))
            raw, _ = _sample_action(layout, self.flat, obs.reshape(-1, layout.obs_dim), noise.reshape(-1, layout.act_dim))
            raw = raw.reshape(noise.shape)
            return raw.clamp(-1.0, 1.0).to(env.action_spec.dtype), raw

        module = TensorDictModule(policy, in_keys=["observation"], out_keys=["action", "action_raw"])
        # The policy is feed-forward and needs no env transforms; torchrl 0.14 still flags a missing InitTracker
        # with a FutureWarning (0.15 would append it to the user's env). False keeps the env as given, silently.
        self.collector = Collector(env, module, frames_per_batch=self.n * self.num_envs, total_frames=-1,
                                   auto_register_policy_transforms=False)
        self._iter = iter(self.collector)
        self.ep_return = torch.zeros(self.num_envs)
        self.ep_length = torch.zeros(self.num_envs, dtype=torch.int64)
        self.finished: list[tuple[float, int]] = []

    def iterate(self, flat: Tensor, square_avg: Tensor) -> Tensor:
        """Next batch from the collector (time-major [n, N]), then one `a2c_update`; returns METRICS [5]."""
        n = self.n
        with torch.no_grad():
            self.flat.copy_(flat)
            td = next(self._iter).reshape(self.num_envs, n).transpose(0, 1)  # [T, N]
        r = td["next", "reward"].reshape(n, self.num_envs).float()
        term = td["next", "terminated"].reshape(n, self.num_envs)
        trunc = td["next", "truncated"].reshape(n, self.num_envs) if ("next", "truncated") in td.keys(True) else torch.zeros_like(term)
        _count_episodes(self, r, term | trunc)
        key = "critic_observation" if self.hp.critic == "privileged" else "observation"  # [obs; privileged]
        obs = td[key].reshape(n, self.num_envs, -1).float()
        batch = Batch(obs, td["action_raw"].reshape(n, self.num_envs, -1).float(), r, term, trunc,
                      td["next", key].reshape(n, self.num_envs, -1).float())
        return self._update(self.layout, flat, square_avg, batch, self.hp)

    def state_dict(self) -> dict:
        """Collector-driven envs cannot be snapshotted in general; resume restarts their episodes."""
        return {}

    def load_state_dict(self, d: dict) -> None:
        """Nothing to restore (see `state_dict`)."""

    def close(self) -> None:
        """Shut the collector (and its env workers) down."""
        self.collector.shutdown()


# ------------------------------------------------------------------------------ training loop


class ParameterAverage:
    """`a2c.average_last` (stochastic weight averaging): the running uniform mean of the parameters over the last
    `fraction` of `num_updates` updates, which policy.pt holds instead of the last parameters."""

    def __init__(self, num_updates: int, fraction: float) -> None:
        """Average the parameters after updates num_updates − ⌈fraction·num_updates⌉ + 1 … num_updates."""
        self.num_updates, self.first = num_updates, num_updates - math.ceil(fraction * num_updates) + 1
        self.mean: Tensor | None = None
        self.count = 0

    def update(self, done_updates: int, flat: Tensor) -> None:
        """Fold in the parameters after update `done_updates` (1-based) if it is inside the window."""
        if done_updates >= self.first:
            self.count += 1
            self.mean = flat.clone() if self.mean is None else self.mean.lerp_(flat, 1.0 / self.count)

    def policy(self, flat: Tensor) -> Tensor:
        """The parameters a saved policy gets now: the average once it has begun, else `flat`."""
        return self.mean if self.count else flat

    def state_dict(self) -> dict:
        """Checkpoint entry (empty before the window)."""
        return {"first": self.first, "count": self.count, "mean": self.mean} if self.count else {}

    def load_state_dict(self, d: dict, start: int) -> None:
        """Restore at checkpoint update `start`; a window moved by another --steps restarts (with a warning if its
        start has passed)."""
        if d and d["first"] == self.first:
            self.count, self.mean = int(d["count"]), d["mean"].clone()
        elif start >= self.first:
            warnings.warn(f"a2c.average_last: the average over updates {self.first}-{self.num_updates} cannot be "
                          f"rebuilt from a checkpoint at update {start}; policy.pt averages {start + 1}-{self.num_updates}")


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


CKPT_KEYS = ("format", "update", "flat", "square_avg", "gen", "rollout", "config", "layout", "metric_sum", "metric_count")


def train(
    cfg: ExperimentConfig,
    out_dir: str | Path | None = None,
    *,
    total_steps: int | None = None,
    resume: bool = False,
    progress: bool = False,
    env=None,
    callback: Callable[[int, dict], None] | None = None,
) -> TrainResult:
    """Train the A3CQP adaptation policy with A2C; write metrics.csv, checkpoint.pt and policy.pt under `out_dir`."""
    hp = cfg.a2c
    total = int(total_steps if total_steps is not None else hp.total_steps)
    if total <= 0:
        raise ValueError(f"total_steps must be > 0, got {total}")
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    if env is None and cfg.env == "panda":  # the six per-axis agents of num_envs simulated Pandas, one shared policy
        from envs.panda import PandaAxisAgents

        env = PandaAxisAgents(hp.num_envs, cfg, seed=cfg.seed)
        env.reset()
    if env is None:
        from envs.point_mass import PointMassEnv

        env = PointMassEnv(hp.num_envs, cfg, seed=cfg.seed)
        env.reset()
    # look on the class: batched TorchRL envs forward unknown attributes to their workers
    fused = getattr(type(env), "fused_functions", None) is not None and hp.rollout == "auto"
    obs_dim = 3
    act_dim = 4
    critic_dim = _critic_input_dim(env, hp, fused, obs_dim)
    layout = ParamLayout(obs_dim, act_dim, hp.hidden, hp.network, critic_dim)
    layout_key = [obs_dim, act_dim, list(hp.hidden), hp.network, critic_dim]
    flat = layout.init(gen, hp.log_std_init)
    square_avg = torch.full_like(flat, hp.rms_init)
    runner = FusedRollout(env, layout, gen, hp) if fused else TorchRLRollout(env, layout, gen, hp)
    n_envs = runner.num_envs
    per_update = hp.n_steps * n_envs
    num_updates = math.ceil(total / per_update)

    out = Path(out_dir) if out_dir is not None else None
    ckpt_path = out / "checkpoint.pt" if out else None
    start = 0
    metric_sum = torch.zeros(len(METRICS))  # running sums since the last logged row
    metric_count = 0
    average = ParameterAverage(num_updates, hp.average_last)
    if resume:
        if ckpt_path is None:
            raise CheckpointError("--resume needs an output directory holding checkpoint.pt")
        ck = load_checkpoint(ckpt_path, CKPT_KEYS)
        if _layout_key(ck["layout"]) != layout_key or ck["flat"].shape != flat.shape:
            raise CheckpointError(f"{ckpt_path} was written for network {ck['layout']}, config asks for {layout_key}")
        flat.copy_(ck["flat"])
        square_avg.copy_(ck["square_avg"])
        gen.set_state(ck["gen"])
        runner.load_state_dict(ck["rollout"])
        runner.finished = [tuple(x) for x in ck.get("finished", [])]
        start = int(ck["update"])
        metric_sum, metric_count = ck["metric_sum"].clone(), int(ck["metric_count"])
        average.load_state_dict(ck.get("average", {}), start)
    if out:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.yaml").write_text(_yaml_dump(config_to_dict(cfg)))
        _truncate_csv(out / "metrics.csv", keep_until_update=start, log_every=hp.log_every)
    tb = _tensorboard(out, start * per_update + 1) if out else None

    # Fig. 5 region checks on every `region_stride`-th log row and the last one (a2c.region_checks of them)
    region_stride = max(1, math.ceil(num_updates // hp.log_every / hp.region_checks)) if hp.region_checks else 0
    bar = _progress(num_updates * per_update, start * per_update, progress)
    compile_s = 0.0
    t_start = time.perf_counter()
    last: dict[str, float] = {}
    if runner.compiles and start < num_updates:
        bar.set_description("A2C (compiling the step, one-time)")
    for u in range(start, num_updates):
        t0 = time.perf_counter()
        metric_sum += runner.iterate(flat, square_avg)
        metric_count += 1
        done_updates = u + 1
        average.update(done_updates, flat)
        if u == start and runner.compiles:  # the first iteration pays for torch.compile
            compile_s = time.perf_counter() - t0
            bar.set_description("A2C")
            bar.reset(total=num_updates * per_update)  # restart the rate estimate after compiling
            bar.update(start * per_update)
        boundary = done_updates % hp.log_every == 0
        if boundary or done_updates == num_updates:
            check = region_stride and (done_updates == num_updates or (done_updates // hp.log_every) % region_stride == 0)
            # the policy that policy.pt would hold now
            regions = region_row(lambda o: policy_mean(layout, average.policy(flat), o).clamp(-1.0, 1.0)) if check else {}
            last = _log_row(out, done_updates, per_update, metric_sum / metric_count, runner, t_start, compile_s, start,
                            regions)
            if not math.isfinite(last["value_loss"]) or not bool(torch.isfinite(flat).all()):
                raise FloatingPointError(f"training diverged at update {done_updates}: {last}")
            if boundary:  # a final, partial window stays in the sums so a resumed run re-logs it whole
                metric_sum.zero_()
                metric_count = 0
            if tb is not None:
                for k, v in last.items():
                    if k not in ("step", "update") and math.isfinite(v):
                        tb.add_scalar(f"a2c/{k}", v, done_updates * per_update)
            if callback:
                callback(done_updates * per_update, last)
            bar.set_postfix(ep_reward=f"{last['episode_reward']:.2f}", refresh=False)
        bar.update(per_update)
        if ckpt_path and (done_updates % hp.checkpoint_every == 0 or done_updates == num_updates):
            save_atomic({"format": 1, "update": done_updates, "flat": flat, "square_avg": square_avg,
                         "gen": gen.get_state(), "rollout": runner.state_dict(), "config": config_to_dict(cfg),
                         "layout": layout_key,
                         "finished": [list(x) for x in runner.finished[-1000:]],
                         "metric_sum": metric_sum, "metric_count": metric_count, "average": average.state_dict()},
                        ckpt_path)
    bar.close()
    if tb is not None:
        tb.close()
    if isinstance(runner, TorchRLRollout):
        runner.close()
    elapsed = time.perf_counter() - t_start
    steps_done = (num_updates - start) * per_update
    policy_path = None
    if out:
        policy_path = save_atomic({"format": 1, "flat": average.policy(flat).clone(), "layout": layout_key,
                                   "config": config_to_dict(cfg), "averaged_updates": average.count}, out / "policy.pt")
    return TrainResult(
        steps=num_updates * per_update, updates=num_updates, seconds=elapsed, compile_seconds=compile_s,
        steps_per_second=steps_done / max(elapsed - compile_s, 1e-9), out_dir=out, policy_path=policy_path,
        final_metrics=last, episode_returns=[r for r, _ in runner.finished],
    )


def load_policy(path: str | Path) -> Callable[[Tensor], Tensor]:
    """Load OUT/policy.pt (or a checkpoint.pt: the raw, never averaged parameters); return f(obs [..., 3]) -> mean
    action [..., 4] clipped to [-1, 1]."""
    data = load_checkpoint(path, ("flat", "layout"))
    obs_dim, act_dim, hidden, network, critic_dim = _layout_key(data["layout"])
    layout = ParamLayout(obs_dim, act_dim, hidden, network, critic_dim)
    flat = data["flat"].float()
    if flat.shape != (layout.size,):
        raise CheckpointError(f"{path}: parameter vector has {flat.shape[0]} entries, layout needs {layout.size}")

    @torch.no_grad()
    def policy(obs: Tensor) -> Tensor:
        if obs.shape[-1] != obs_dim:
            raise ValueError(f"observations need a last dim of {obs_dim}, got shape {tuple(obs.shape)}")
        if not bool(torch.isfinite(obs).all()):
            raise ValueError("observations contain NaN or inf")
        lead = obs.shape[:-1]
        mu = policy_mean(layout, flat, obs.reshape(-1, obs_dim).float())
        return mu.clamp(-1.0, 1.0).reshape(*lead, act_dim)

    return policy


# ------------------------------------------------------------------------------ helpers


def _layout_key(key: list) -> list:
    """[obs, act, hidden, network, critic input]; files written before the critic option have 4 entries."""
    key = list(key)
    return key if len(key) == 5 else [*key, key[0]]


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



def _tensorboard(out: Path, purge_step: int):
    """A SummaryWriter on OUT/tb when TensorBoard is installed, else None. TensorBoard hides earlier events at steps
    >= `purge_step`: a resumed run passes its checkpoint's step + 1, dropping what a killed run logged after the
    checkpoint, as metrics.csv does."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # torch's writer needs the tensorboard package (the `tensorboard` extra)
        return None
    return SummaryWriter(str(out / "tb"), purge_step=purge_step if purge_step > 1 else None, flush_secs=10)


def _log_row(out, updates, per_update, means, runner, t_start, compile_s, start, regions) -> dict[str, float]:
    recent = [r for r, _ in runner.finished[-100:]]
    row = {"step": updates * per_update, "update": updates,
           **{k: float(v) for k, v in zip(METRICS, means)},
           "episode_reward": float(sum(recent) / len(recent)) if recent else float("nan"),
           "episodes": len(runner.finished),
           "steps_per_second": (updates - start) * per_update / max(time.perf_counter() - t_start - compile_s, 1e-9),
           **{k: regions.get(k, float("nan")) for k in REGION_COLUMNS}}
    if out:
        path = out / "metrics.csv"
        new = not path.exists()
        with path.open("a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
            if new:
                w.writeheader()
            w.writerow(row)
    return row


def _truncate_csv(path: Path, keep_until_update: int, log_every: int) -> None:
    """Drop metric rows past the checkpoint we resume from (and its partial final row): no step logged twice."""
    if not path.exists():
        return
    with path.open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    keep = [r for r in rows if int(r["update"]) <= keep_until_update and int(r["update"]) % log_every == 0]
    with path.open("w", newline="") as f:  # files from before a column existed get it, as NaN
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS, restval="nan", extrasaction="ignore")
        w.writeheader()
        w.writerows(keep)


def _progress(total: int, initial: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, disable=not enabled, unit="step", unit_scale=True,
                dynamic_ncols=True, desc="A2C")


def _yaml_dump(d: dict) -> str:
    import yaml

    return yaml.safe_dump(d, sort_keys=False)
