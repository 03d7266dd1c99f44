"""Batched 1-DoF point-mass surrogate of the A3CQP controller (paper 000, eq. 35), as a TorchRL env.

One environment instance holds N independent point masses (``batch_size=[N]``) and steps all of
them in one torch call. The agent acts at 100 Hz with a = (ẇ1, ẇ2, ẇ3, ḟd) ∈ [-1, 1]^4; eq. 29
turns it into task weights w and desired force f_d, then eq. 35 is integrated at 1 kHz for
``substeps`` steps (semi-implicit Euler):

    Λẍ = f_ext + w1 Λ (Kp e − Kv ẋ + ẍ_pd) + w2 (Λ/Λd − 1) f_ext − w2 Cd ẋ + w3 f_d,  f_ext = f_env + f_ope

with e = x_target − x and ẍ_pd = 0 (fixed target). Scenarios (free motion, operator pushes, a stiff
wall in front of the target, both) are sampled per reset; see `a3cqp_rl.config.PointMassConfig`, whose
`operator_model` also offers an operator guiding the mass by hand through a spring-damper grip (used by
`envs.point_mass_eval`). Three options bring the surrogate closer to the Panda env (torch only): `target_speed_max`
makes the free scenario's target move at a constant speed (IK's damping then acts on ė = ẋ_d − ẋ),
`idle_force: damps` gives the share of force control that does not push, w3 (1 − min(1, f_d / 1 N)), to IK's
damping, as the Panda env's `panda.idle_force: damps` does; `disturbance_max` adds an unmeasured constant force to
the free scenario, which IK has to hold against.
All randomness is drawn at reset (targets, walls and the whole operator force schedule), so the
step is a pure function of (state, action): deterministic, and compilable by `torch.compile`.
Each env also holds a *pending* next episode, drawn in advance, so fused trainers can step through
episode ends inside one compiled graph (`fused_functions`) and draw the next pending episode afterwards.
The trainer's C iteration (`a2c.backend: auto`, algorithms/native) runs its own copy of this step and of the eq. 30
reward (envs/native/point_mass.c): an edit of the Python step needs the same there, or `a2c.backend: torch`. A config
field newer than the C file sends training to this torch step (`envs.native.C_FIELDS`), and `a3cqp train` says which
ran.

Physics runs in float64; observations and rewards are float32 for the networks.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from a3cqp_rl.adaptation import action_of, integrate_force, integrate_weights, observe, reward
from a3cqp_rl.config import AdaptationConfig, ExperimentConfig, PointMassConfig, RewardConfig

__all__ = ["PointMassEnv", "SCENARIOS", "INFO_KEYS"]

SCENARIOS = PointMassConfig.SCENARIOS
"""Scenario names; the ``scenario`` info entry holds the index into this tuple."""
INFO_KEYS = ("e", "x", "x_dot", "f_env", "f_ope", "w", "f_d", "target", "scenario")
"""Per-step info entries written next to ``observation`` (for plots and evaluation)."""



class PointMassEnv(EnvBase):
    """N point masses under eq. 35 with the A3CQP adaptation law; batch_size=[num_envs]."""

    _has_dynamic_specs = False

    def __init__(
        self,
        num_envs: int,
        config: ExperimentConfig | None = None,
        seed: int | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        """Create `num_envs` point masses with `config` (paper defaults if None) on `device`."""
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        cfg = config or ExperimentConfig()
        self.cfg: PointMassConfig = cfg.point_mass
        self.adapt: AdaptationConfig = cfg.adaptation
        self.rew: RewardConfig = cfg.reward
        self.num_envs = num_envs
        self.dtype = torch.float64
        probs = torch.tensor([self.cfg.scenario_probs.get(s, 0.0) for s in SCENARIOS], dtype=torch.float64)
        self._scenario_probs = probs / probs.sum()
        # Operator schedule: enough on/off phases to cover an episode with the shortest phases.
        T = self.cfg.episode_steps
        episode_s = T * self.cfg.substeps * self.cfg.physics_dt
        shortest = max(self.cfg.operator_on_min + self.cfg.operator_off_min, 1e-3)
        self._n_phases = int(math.ceil(episode_s / shortest)) + 2
        self._state: dict[str, Tensor] = {}
        self._pending: dict[str, Tensor] = {}
        # Operator force per agent step, double-buffered: [slot, env, step]; state["slot"] is the live one.
        self._schedule = torch.zeros(2, num_envs, T + 1, dtype=self.dtype, device=self.device)
        self._make_specs()
        self._rng = torch.Generator(device=self.device)
        self._set_seed(seed)
        self._init_state()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        N = self.batch_size
        f32, f64 = torch.float32, torch.float64
        info = {k: Unbounded(shape=(*N,), dtype=f64, device=self.device) for k in INFO_KEYS}
        info["w"] = Bounded(0.0, 1.0, shape=(*N, 3), dtype=f64, device=self.device)
        info["scenario"] = Unbounded(shape=(*N,), dtype=torch.int64, device=self.device)
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, shape=(*N, 3), dtype=f32, device=self.device),
            # [eq. 26 observation; privileged_state], for an asymmetric critic (a2c.critic: privileged)
            critic_observation=Unbounded(shape=(*N, 3 + PRIVILEGED_DIM), dtype=f32, device=self.device),
            **info,
            shape=N,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*N, 4), dtype=f32, device=self.device)
        self.reward_spec = Unbounded(shape=(*N, 1), dtype=f32, device=self.device)
        flag = Categorical(2, shape=(*N, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=N)

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self._rng.manual_seed(int(seed))

    # ------------------------------------------------------------------ reset
    def _init_state(self) -> None:
        N, dev, f64 = self.num_envs, self.device, self.dtype
        z = torch.zeros(N, dtype=f64, device=dev)
        self._state = {
            "x": z.clone(), "x_dot": z.clone(), "target": z.clone(), "w_logits": torch.zeros(N, 3, dtype=f64, device=dev),
            "f_d": z.clone(), "wall_pos": z.clone(), "has_wall": torch.zeros(N, dtype=torch.bool, device=dev),
            "t": torch.zeros(N, dtype=torch.int64, device=dev), "f_env": z.clone(), "f_ope": z.clone(),
            "scenario": torch.zeros(N, dtype=torch.int64, device=dev),
            "slot": torch.zeros(N, dtype=torch.int64, device=dev),
        }
        if self.cfg.operator_model == "hand":  # where and when the hand grasped (set by agent_step)
            self._state.update(hand_x0=z.clone(), hand_t0=torch.zeros(N, dtype=torch.int64, device=dev))
        if self.cfg.target_speed_max > 0.0:
            self._state["target_speed"] = z.clone()
        if self.cfg.disturbance_max > 0.0:
            self._state["disturbance"] = z.clone()
        self._pending = {k: self._state[k].clone() for k in _episode_keys(self._state)}

    def _uniform(self, n: int, lo: float, hi: float, *shape: int) -> Tensor:
        u = torch.rand((n, *shape), generator=self._rng, dtype=self.dtype, device=self.device)
        return lo + (hi - lo) * u

    def _sample_episodes(self, idx: Tensor, pending: bool = False) -> None:
        """Draw scenario, target, wall, initial weights and operator schedule for envs `idx`.

        pending=False starts the episode now (resets the dynamics); pending=True stores it as the
        episode that `auto_reset` will switch to when the current one ends.
        """
        c, n = self.cfg, int(idx.numel())
        if n == 0:
            return
        scen = torch.multinomial(self._scenario_probs.expand(n, -1), 1, generator=self._rng).squeeze(-1).to(self.device)
        has_wall = (scen == 2) | (scen == 3)
        has_op = (scen == 1) | (scen == 3)
        sign = torch.where(self._uniform(n, 0, 1) < 0.5, -1.0, 1.0).to(self.dtype)
        free_target = sign * self._uniform(n, c.target_min, c.target_max)
        op_target = self._uniform(n, -c.operator_target_range, c.operator_target_range)
        wall_pos = self._uniform(n, c.wall_min, c.wall_max)
        wall_target = wall_pos + self._uniform(n, c.depth_min, c.depth_max)
        target = torch.where(has_wall, wall_target, torch.where(has_op, op_target, free_target))
        half = 0.5 * self.adapt.sigma_w
        ik = torch.tensor([half, -half, -half], dtype=self.dtype, device=self.device).expand(n, 3)
        if c.random_initial_weights:
            w_logits = self._uniform(n, -half, half, 3)
            f_d = self._uniform(n, 0.0, self.adapt.f_d_max)
            if c.random_initial_fraction < 1.0:  # the rest start like a deployed robot: pure IK, f_d = 0
                from_ik = self._uniform(n, 0.0, 1.0) >= c.random_initial_fraction
                w_logits = torch.where(from_ik.unsqueeze(-1), ik, w_logits)
                f_d = torch.where(from_ik, torch.zeros_like(f_d), f_d)
        else:  # pure IK, no desired force
            w_logits = ik.clone()
            f_d = torch.zeros(n, dtype=self.dtype, device=self.device)
        dest = self._pending if pending else self._state
        for k, v in zip(EPISODE_KEYS, (target, wall_pos, has_wall, scen, w_logits, f_d)):
            dest[k][idx] = v
        if c.target_speed_max > 0.0:
            speed = self._uniform(n, -c.target_speed_max, c.target_speed_max)
            dest["target_speed"][idx] = torch.where(scen == 0, speed, torch.zeros_like(speed))
        if c.disturbance_max > 0.0:
            push = self._uniform(n, -c.disturbance_max, c.disturbance_max)
            dest["disturbance"][idx] = torch.where(scen == 0, push, torch.zeros_like(push))
        slot = self._state["slot"][idx]
        self._schedule[(1 - slot) if pending else slot, idx] = self._operator_schedule(n) * has_op.unsqueeze(-1)
        if not pending:
            for k in ("x", "x_dot", "t", "f_env", "f_ope"):
                self._state[k][idx] = 0

    def _operator_schedule(self, n: int) -> Tensor:
        """Piecewise-constant operator intent force [N] (hand operator: displacement [m]) per agent step, [n, T + 1]."""
        c, K = self.cfg, self._n_phases
        off = self._uniform(n, c.operator_off_min, c.operator_off_max, K)
        on = self._uniform(n, c.operator_on_min, c.operator_on_max, K)
        sign = torch.where(self._uniform(n, 0, 1, K) < 1.0 - c.operator_toward_wall, -1.0, 1.0).to(self.dtype)
        if c.operator_model == "hand":  # the hand's displacement [m] from where it grasps
            force = sign * self._uniform(n, c.operator_goal_min, c.operator_goal_max, K)
        else:
            force = sign * self._uniform(n, c.operator_force_min, self.adapt.f_ope_max, K)
        # Phase k is "off" during [start_k, start_k + off_k) then "on" until start_{k+1}.
        ends_off = torch.cumsum(off + on, dim=-1) - on  # [n, K]
        ends_on = torch.cumsum(off + on, dim=-1)
        boundaries = torch.stack((ends_off, ends_on), dim=-1).reshape(n, 2 * K)  # sorted
        agent_dt = c.substeps * c.physics_dt
        times = torch.arange(c.episode_steps + 1, dtype=self.dtype, device=self.device) * agent_dt
        seg = torch.searchsorted(boundaries, times.expand(n, -1).contiguous(), right=True)  # [n, T+1]
        phase = (seg // 2).clamp(max=K - 1)
        is_on = (seg % 2) == 1
        value = torch.gather(force, 1, phase)
        if c.operator_model == "drag":  # the hand's speed (so the force on a mass at rest) rises and falls: sin(π τ)
            start = torch.gather(ends_off, 1, phase)
            length = torch.gather(on, 1, phase)
            tau = ((times - start) / length).clamp(0.0, 1.0)
            value = value * torch.sin(math.pi * tau).clamp(min=1e-6)  # > 0 while holding: 0 means "not holding"
        return torch.where(is_on, value, torch.zeros((), dtype=self.dtype))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            idx = torch.arange(self.num_envs, device=self.device)
        else:
            idx = mask.reshape(self.num_envs).nonzero().squeeze(-1)
        self._sample_episodes(idx)
        self._sample_episodes(idx, pending=True)
        return self._observation_td(done=torch.zeros(self.num_envs, 1, dtype=torch.bool, device=self.device))

    # ------------------------------------------------------------------ step
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = action_of(tensordict, (self.num_envs, 4))
        self._state, reward = agent_step(self._state, action.to(self.dtype), self._schedule, self.cfg, self.adapt, self.rew)
        truncated = (self._state["t"] >= self.cfg.episode_steps).unsqueeze(-1)
        terminated = torch.zeros_like(truncated)  # eq. 35 has no terminal state; episodes end by time
        out = self._observation_td(done=truncated | terminated)
        out.set("reward", reward.to(torch.float32).unsqueeze(-1))
        out.set("terminated", terminated)
        out.set("truncated", truncated)
        return out

    def _observation_td(self, done: Tensor) -> TensorDictBase:
        s = self._state
        e = s["target"] - s["x"]
        critic_obs = observe_state(s, self.adapt, dtype=torch.float32, privileged=True)
        w = torch.softmax(s["w_logits"], dim=-1)
        return TensorDict(
            {
                "observation": critic_obs[:, :3].contiguous(),
                "critic_observation": critic_obs,
                "e": e, "x": s["x"].clone(), "x_dot": s["x_dot"].clone(), "f_env": s["f_env"].clone(),
                "f_ope": s["f_ope"].clone(), "w": w, "f_d": s["f_d"].clone(), "target": s["target"].clone(),
                "scenario": s["scenario"].clone(),
                "done": done, "terminated": torch.zeros_like(done), "truncated": done.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    # ------------------------------------------------------------------ fused-trainer access
    # The TorchRL step above costs ~1 ms of framework overhead per call; A2C at the paper's settings
    # needs 62,500 rollouts of 4 steps, so trainers that can drive the env directly use these:
    # (state, pending, schedule) go into a compiled graph with the `fused_functions`, the new state comes back
    # through `fused_commit`, and `refill` draws new pending episodes for the envs that reset.
    def functional(self) -> tuple[dict[str, Tensor], Tensor]:
        """The live (state dict, operator schedule [2, N, T+1]); read-only for callers."""
        return self._state, self._schedule

    def fused_inputs(self) -> tuple[dict[str, Tensor], dict[str, Tensor], Tensor]:
        """(state, pending episode, schedule) to pass to the `fused_functions`."""
        return self._state, self._pending, self._schedule

    def fused_functions(self, privileged: bool = False):
        """Pure functions (step_fn, observe_fn), free of this module so compiled graphs guard only on configs.

        step_fn(state, pending, schedule, action) -> (state, final_obs, next_obs, reward, terminated, truncated);
        observe_fn(state) -> obs [N, 3] float32, or [N, 3 + PRIVILEGED_DIM] with `privileged` (the
        eq. 26 observation first, then `privileged_state`, for an asymmetric critic).
        """
        obs_fn = functools.partial(observe_state, adapt=self.adapt, dtype=torch.float32, privileged=privileged)
        step_fn = functools.partial(fused_agent_step, cfg=self.cfg, adapt=self.adapt, rew=self.rew, observe_fn=obs_fn)
        return step_fn, obs_fn

    def fused_commit(self, state: dict[str, Tensor]) -> None:
        """Adopt the state returned by the fused step function."""
        self._state = state

    def refill(self, done: Tensor) -> None:
        """Draw new pending episodes for envs where `done` [N] (they just switched to their pending one)."""
        self._sample_episodes(done.nonzero().squeeze(-1), pending=True)

    def get_state(self) -> dict[str, Tensor]:
        """Everything needed to continue bit-identically: state, pending episodes, schedule, RNG."""
        return {**{k: v.clone() for k, v in self._state.items()},
                **{f"_pending.{k}": v.clone() for k, v in self._pending.items()},
                "_schedule": self._schedule.clone(), "_rng": self._rng.get_state()}

    def set_state(self, state: dict[str, Tensor]) -> None:
        """Restore a `get_state()` snapshot (shapes must match this env's num_envs)."""
        if state["x"].shape != (self.num_envs,):
            raise ValueError(f"state is for {state['x'].shape[0]} envs, this env has {self.num_envs}")
        self._state = {k: v.clone() for k, v in state.items() if not k.startswith("_")}
        self._pending = {k[len("_pending."):]: v.clone() for k, v in state.items() if k.startswith("_pending.")}
        self._schedule = state["_schedule"].clone()
        self._rng.set_state(state["_rng"])


EPISODE_KEYS = ("target", "wall_pos", "has_wall", "scenario", "w_logits", "f_d")
"""State entries drawn per episode (w_logits and f_d are their initial values)."""


def _episode_keys(state: dict[str, Tensor]) -> tuple[str, ...]:
    return EPISODE_KEYS + tuple(k for k in ("target_speed", "disturbance") if k in state)


def auto_reset(state: dict[str, Tensor], pending: dict[str, Tensor], done: Tensor) -> dict[str, Tensor]:
    """Switch envs where `done` [N] to their pending episode (dynamics zeroed, schedule slot flipped)."""
    out = dict(state)
    for k in _episode_keys(state):
        d = done.view(-1, *([1] * (state[k].dim() - 1)))
        out[k] = torch.where(d, pending[k], state[k])
    for k in ("x", "x_dot", "t", "f_env", "f_ope"):
        out[k] = torch.where(done, torch.zeros_like(state[k]), state[k])
    out["slot"] = torch.where(done, 1 - state["slot"], state["slot"])
    return out


def fused_agent_step(
    state: dict[str, Tensor],
    pending: dict[str, Tensor],
    schedule: Tensor,
    action: Tensor,
    cfg: PointMassConfig,
    adapt: AdaptationConfig,
    rew: RewardConfig,
    observe_fn: Callable[[dict[str, Tensor]], Tensor] | None = None,
) -> tuple[dict[str, Tensor], Tensor, Tensor, Tensor, Tensor, Tensor]:
    """`agent_step` + observation + auto-reset: (state, final_obs, next_obs, reward, terminated, truncated).

    Observations come from `observe_fn(state)` (default: the eq. 26 observation, float32).
    """
    if observe_fn is None:
        observe_fn = functools.partial(observe_state, adapt=adapt, dtype=torch.float32)
    state, r = agent_step(state, action.to(torch.float64), schedule, cfg, adapt, rew)
    final_obs = observe_fn(state)
    truncated = state["t"] >= cfg.episode_steps
    terminated = torch.zeros_like(truncated)  # eq. 35 has no terminal state
    state = auto_reset(state, pending, truncated | terminated)
    next_obs = observe_fn(state)
    return state, final_obs, next_obs, r.to(torch.float32), terminated, truncated


PRIVILEGED_DIM = 11
"""Entries `privileged_state` adds after the eq. 26 observation."""


def observe_state(
    state: dict[str, Tensor], adapt: AdaptationConfig, dtype: torch.dtype = torch.float64, privileged: bool = False
) -> Tensor:
    """Eq. 26 observation [N, 3] from a point-mass state dict; with `privileged`, [N, 3 + PRIVILEGED_DIM]."""
    e = state["target"] - state["x"]
    obs = observe(e, state["f_env"], state["f_ope"], adapt.e_max, adapt.f_env_max, adapt.f_ope_max, check=False)
    if privileged:
        obs = torch.cat([obs, privileged_state(state, adapt)], dim=-1)
    return obs.to(dtype)


def privileged_state(state: dict[str, Tensor], adapt: AdaptationConfig) -> Tensor:
    """What the agent cannot observe but its return depends on, normalised to about [-1, 1]: [N, PRIVILEGED_DIM].

    Task weights w (3, eq. 29e) and f_d/f̄_d (they are integrated, so the eq. 26 observation
    leaves them hidden), signed e/ē, signed forces f_env/f̄_env and f_ope/f̄_ope, tanh of the
    velocity [m/s], whether a wall / an operator is in this episode, and the gap to the wall /ē.
    Only a critic gets these (asymmetric actor-critic): the policy still maps eq. 26's s to a.
    """
    e = state["target"] - state["x"]
    has_wall = state["has_wall"].to(e.dtype)
    has_op = ((state["scenario"] == 1) | (state["scenario"] == 3)).to(e.dtype)
    gap = has_wall * ((state["wall_pos"] - state["x"]) / adapt.e_max).clamp(-1.0, 1.0)
    scalars = torch.stack(
        [
            state["f_d"] / adapt.f_d_max,
            (e / adapt.e_max).clamp(-1.0, 1.0),
            (state["f_env"] / adapt.f_env_max).clamp(-1.0, 1.0),
            (state["f_ope"] / adapt.f_ope_max).clamp(-1.0, 1.0),
            torch.tanh(state["x_dot"]),
            has_wall,
            has_op,
            gap,
        ],
        dim=-1,
    )
    return torch.cat([torch.softmax(state["w_logits"], dim=-1), scalars], dim=-1)


def agent_step(
    state: dict[str, Tensor],
    action: Tensor,
    schedule: Tensor,
    cfg: PointMassConfig,
    adapt: AdaptationConfig,
    rew: RewardConfig,
) -> tuple[dict[str, Tensor], Tensor]:
    """One 100 Hz agent step for all envs: eq. 29 on `action` [N, 4], then `substeps` × eq. 35; returns (state, reward [N]).

    `schedule` [2, N, T+1] holds the operator's intent force per agent step for both episode slots.

    Pure function of its inputs (no RNG, no Python branching on data), so it can be compiled.
    """
    w_logits, w = integrate_weights(state["w_logits"], action[:, :3], adapt.sigma_w, adapt.dt, check=False)
    f_d = integrate_force(state["f_d"], action[:, 3], adapt.sigma_f, adapt.dt, adapt.f_d_max, check=False)
    t = state["t"]
    env_idx = torch.arange(t.shape[0], device=t.device)
    f_cmd = schedule[state["slot"], env_idx, t.clamp(max=schedule.shape[-1] - 1)]

    m, kp, kv, dt = cfg.mass, cfg.kp, cfg.kv_value, cfg.physics_dt
    adm_gain = m / cfg.lambda_d - 1.0
    w1, w2, w3 = w.unbind(-1)
    x, v, target, wall_pos, has_wall = state["x"], state["x_dot"], state["target"], state["wall_pos"], state["has_wall"]
    moving = "target_speed" in state
    speed = state.get("target_speed")
    damps = cfg.idle_force == "damps"
    f_dist = state.get("disturbance")  # unmeasured: in the dynamics, not in f_ext (what the admittance task sees)
    w_damp, w_fc = w1, w3  # IK's damping weight and force control's weight
    if damps:  # the share of force control that does not push damps as IK does (the Panda env's panda.idle_force)
        idle = w3 * (1.0 - f_d.clamp(0.0, 1.0))
        w_damp, w_fc = w1 + idle, w3 - idle
    sgn = torch.sign(f_cmd)
    hand = cfg.operator_model == "hand"
    grip_min = -1.0 if cfg.operator_grip else 0.0  # a gripping hand brakes a mass that runs ahead of it
    drag = cfg.operator_model == "drag"
    if drag:  # the schedule holds b·u, the grip's force on a mass at rest
        holding = f_cmd != 0
        drag_max = adapt.f_ope_max
        drag_b = drag_max / cfg.operator_v_hand
    if hand:  # the grasp starts when the schedule turns on: remember where and when
        holding = f_cmd != 0
        prev = schedule[state["slot"], env_idx, (t - 1).clamp(min=0, max=schedule.shape[-1] - 1)]
        onset = holding & ((t == 0) | (prev == 0))
        hand_x0 = torch.where(onset, x, state["hand_x0"])
        hand_t0 = torch.where(onset, t, state["hand_t0"])
        elapsed = (t - hand_t0).to(x.dtype) * (cfg.substeps * dt)
    f_env = torch.zeros_like(x)
    f_ope = torch.zeros_like(x)
    for k in range(cfg.substeps):  # 1 kHz sub-steps; a loop over time, not over envs
        pen = x - wall_pos
        contact = has_wall & (pen > 0)
        # Unilateral wall: pushes back (−x) only, never pulls.
        f_env = torch.where(contact, (-cfg.wall_stiffness * pen - cfg.wall_damping * v).clamp(max=0.0), 0.0)
        if hand:  # the hand moves by f_cmd along a minimum-jerk path; the grip is a bounded spring-damper
            s_hand, v_hand = _minimum_jerk(hand_x0, f_cmd, (elapsed + k * dt) / cfg.operator_move_time,
                                           cfg.operator_move_time)
            pull = cfg.operator_hand_stiffness * (s_hand - x) + cfg.operator_hand_damping * (v_hand - v)
            f_ope = torch.where(holding, pull.clamp(-adapt.f_ope_max, adapt.f_ope_max), 0.0)
        elif drag:  # a hand moving at f_cmd/b, through a viscous grip b, bounded by the push's peak force
            f_ope = torch.where(holding, (f_cmd - drag_b * v).clamp(-drag_max, drag_max), 0.0)
        else:  # a hand with a linear force-velocity law: yielding along the push relieves the force
            f_ope = f_cmd * (1.0 - v * sgn / cfg.operator_v_hand).clamp(grip_min, 1.0)
        f_ext = f_env + f_ope
        f_act = f_ext if f_dist is None else f_ext + f_dist  # the force that acts on the mass
        e = target - x
        if moving or damps:  # IK's damping on ė = ẋ_d − ẋ, with the idle share's weight where it damps
            de = (speed - v) if moving else -v
            acc = (f_act + m * (w1 * kp * e + w_damp * kv * de) + w2 * (adm_gain * f_ext - cfg.c_d * v)
                   + w_fc * f_d) / m
        else:
            # eq. 35 (ẍ_pd = 0 for a fixed target)
            acc = (f_act + w1 * m * (kp * e - kv * v) + w2 * (adm_gain * f_ext - cfg.c_d * v) + w3 * f_d) / m
        v = v + acc * dt
        x = x + v * dt
        if moving:
            target = target + speed * dt
    new_state = dict(state)
    new_state.update(x=x, x_dot=v, w_logits=w_logits, f_d=f_d, f_env=f_env, f_ope=f_ope, t=t + 1)
    if moving:
        new_state.update(target=target)
    if hand:
        new_state.update(hand_x0=hand_x0, hand_t0=hand_t0)
    r = reward(target - x, f_env, f_ope, f_d, rew.alpha, adapt.e_max, adapt.f_env_max, adapt.f_ope_max,
               adapt.f_d_max, check=False)  # eq. 30
    return new_state, r


def _minimum_jerk(start: Tensor, distance: Tensor, tau: Tensor, duration: float) -> tuple[Tensor, Tensor]:
    """Position and velocity of a minimum-jerk move by `distance` from `start` at phase `tau` (clipped to [0, 1])."""
    tau = tau.clamp(0.0, 1.0)
    pos = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    vel = 30.0 * tau**2 * (1.0 - tau) ** 2 / duration
    return start + distance * pos, distance * vel
