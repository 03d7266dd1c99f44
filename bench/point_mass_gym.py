"""The point-mass task of `envs.point_mass.PointMassEnv` as a single-env `gymnasium.Env`: the SB3 baseline's env.

A thin wrapper, no copy of the task: episodes are drawn by a `PointMassEnv(1)` (same scenarios, same sampling, seeded
from gymnasium's `np_random`), and each step is the C point mass (`envs.native`, the step the C A2C iteration uses),
or, where no C compiler exists, the torch env's `agent_step` (same numbers, ~30x slower). The paper trained
Stable-Baselines3 on a Gym environment, so `bench/train_speed.py` gives SB3 the *same* task this way;
`tests/test_point_mass_gym.py` checks it step by step against the TorchRL env.

Spaces: observation Box(0, 1, (3,), float32) = (|e|/ē, |f_env|/f̄_env, |f_ope|/f̄_ope) (eq. 26); action
Box(-1, 1, (4,), float32) = (ẇ1, ẇ2, ẇ3, ḟd). Episodes never terminate; they are truncated after
``point_mass.episode_steps`` agent steps.

``reset(options=...)`` sets an episode's parameters explicitly (after the usual draw, which they override):
``scenario`` (index into `SCENARIOS` or name), ``target``, ``wall_pos``, ``has_wall``, ``w_logits`` (3 pre-softmax
weights), ``f_d``, ``schedule`` (operator intent force per agent step, ``episode_steps + 1`` values).
`episode_params()` returns them.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from a3cqp_rl.config import ExperimentConfig, PointMassConfig, load_config
from envs import native
from envs.point_mass import PointMassEnv, agent_step

__all__ = ["PointMassGym", "SCENARIOS", "OPTION_KEYS"]

SCENARIOS: tuple[str, ...] = PointMassConfig.SCENARIOS
OPTION_KEYS = ("scenario", "target", "wall_pos", "has_wall", "w_logits", "f_d", "schedule")
"""Keys accepted by ``reset(options=...)``."""


class PointMassGym(gym.Env):
    """One point mass under eq. 35 with the A3CQP adaptation law (eq. 29, eq. 30), gymnasium API."""

    metadata = {"render_modes": []}

    def __init__(self, config: ExperimentConfig | str | None = None, render_mode: str | None = None) -> None:
        """`config`: an ExperimentConfig, a YAML path (`load_config`), or None for the paper defaults."""
        if render_mode is not None:
            raise ValueError(f"PointMassGym does not render (render_mode={render_mode!r})")
        cfg = config if isinstance(config, ExperimentConfig) else load_config(config)
        self.config, self.cfg = cfg, cfg.point_mass
        self.observation_space = spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self._sampler: PointMassEnv | None = None  # draws episodes; seeded at the first reset
        self._native = native.NativePointMass(cfg) if native.load() is not None and not native.unsupported(cfg) else None
        self._action = np.zeros((1, 4), dtype=np.float32)
        self._params: dict[str, Any] = {}
        self._torch_state: dict[str, torch.Tensor] = {}
        self._torch_schedule = torch.zeros(2, 1, self.cfg.episode_steps + 1, dtype=torch.float64)
        self._obs_now = np.zeros(3, dtype=np.float32)
        self._reward = 0.0

    # ------------------------------------------------------------------ reset
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode: draw its parameters, then override them with `options` (see module doc)."""
        super().reset(seed=seed)
        if self._sampler is None or seed is not None:
            self._sampler = PointMassEnv(1, self.config, seed=int(self.np_random.integers(2**62)))
        self._sampler.reset()
        state, schedule = self._sampler.functional()
        params = {"scenario": int(state["scenario"][0]), "target": float(state["target"][0]),
                  "wall_pos": float(state["wall_pos"][0]), "has_wall": bool(state["has_wall"][0]),
                  "w_logits": state["w_logits"][0].numpy().copy(), "f_d": float(state["f_d"][0]),
                  "schedule": schedule[int(state["slot"][0]), 0].numpy().copy()}
        if options:
            unknown = sorted(set(options) - set(OPTION_KEYS))
            if unknown:
                raise ValueError(f"unknown reset option(s) {unknown}; valid: {list(OPTION_KEYS)}")
            params.update(options)
            if "scenario" in options and "has_wall" not in options:
                s = options["scenario"]
                params["has_wall"] = (SCENARIOS.index(s) if isinstance(s, str) else int(s)) in (2, 3)
        self._set_episode(params)
        return self._obs_now.copy(), self._info()

    def _set_episode(self, p: dict[str, Any]) -> None:
        T = self.cfg.episode_steps
        scen = p["scenario"]
        if isinstance(scen, str):
            if scen not in SCENARIOS:
                raise ValueError(f"unknown scenario {scen!r}; choose from {list(SCENARIOS)}")
            scen = SCENARIOS.index(scen)
        scen = int(scen)
        if not 0 <= scen < len(SCENARIOS):
            raise ValueError(f"scenario index must be in [0, {len(SCENARIOS)}), got {scen}")
        w_logits = np.asarray(p["w_logits"], dtype=np.float64).reshape(-1)
        schedule = np.asarray(p["schedule"], dtype=np.float64).reshape(-1)
        if w_logits.shape != (3,):
            raise ValueError(f"w_logits must hold 3 values, got shape {w_logits.shape}")
        if schedule.shape != (T + 1,):
            raise ValueError(f"schedule must hold episode_steps + 1 = {T + 1} values, got shape {schedule.shape}")
        values = [float(p[k]) for k in ("target", "wall_pos", "f_d")]
        if not (np.isfinite(values).all() and np.isfinite(w_logits).all() and np.isfinite(schedule).all()):
            raise ValueError("reset options contain NaN or inf")
        self._params = {"scenario": scen, "target": values[0], "wall_pos": values[1], "has_wall": bool(p["has_wall"]),
                        "w_logits": w_logits.copy(), "f_d": values[2], "schedule": schedule.copy()}
        if self._native is not None:
            self._native.set_episode(0, **self._params)
        else:
            z = torch.zeros(1, dtype=torch.float64)
            self._torch_state = {
                "x": z.clone(), "x_dot": z.clone(), "target": torch.tensor([values[0]], dtype=torch.float64),
                "w_logits": torch.from_numpy(w_logits.copy()).unsqueeze(0), "f_d": torch.tensor([values[2]], dtype=torch.float64),
                "wall_pos": torch.tensor([values[1]], dtype=torch.float64),
                "has_wall": torch.tensor([bool(p["has_wall"])]), "t": torch.zeros(1, dtype=torch.int64),
                "f_env": z.clone(), "f_ope": z.clone(), "scenario": torch.tensor([scen]),
                "slot": torch.zeros(1, dtype=torch.int64)}
            self._torch_schedule[0, 0] = torch.from_numpy(schedule)
        ad = self.config.adaptation
        self._obs_now[:] = (min(abs(values[0]) / ad.e_max, 1.0), 0.0, 0.0)  # at rest at x = 0, no force yet

    def episode_params(self) -> dict[str, Any]:
        """This episode's parameters, in the form ``reset(options=...)`` accepts."""
        return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in self._params.items()}

    # ------------------------------------------------------------------ step
    def step(self, action):
        """One 100 Hz agent step: eq. 29 on `action`, `substeps` × eq. 35, eq. 30 reward."""
        self._action[0] = np.asarray(action, dtype=np.float32).reshape(4)
        if not np.isfinite(self._action).all():
            raise ValueError(f"action contains NaN or inf: {action!r}")
        if self._native is not None:
            rewards, obs = self._native.step(self._action)
            self._reward, self._obs_now[:] = float(rewards[0]), obs[0]
        else:
            from envs.point_mass import observe_state

            ex = self.config
            self._torch_state, r = agent_step(self._torch_state, torch.from_numpy(self._action).double(),
                                              self._torch_schedule, ex.point_mass, ex.adaptation, ex.reward)
            self._reward = float(r[0])
            self._obs_now[:] = observe_state(self._torch_state, ex.adaptation, dtype=torch.float32)[0].numpy()
        truncated = self.t >= self.cfg.episode_steps
        return self._obs_now.copy(), self._reward, False, truncated, self._info()

    # ------------------------------------------------------------------ state
    def _get(self, key: str) -> float:
        if self._native is not None:
            return self._native.state[key][0].item()
        return self._torch_state[key][0].item()

    @property
    def t(self) -> int:
        """Agent steps since the episode started."""
        return int(self._get("t"))

    @property
    def x(self) -> float:
        """Position [m] (the episode starts at 0)."""
        return self._get("x")

    @property
    def scenario(self) -> int:
        """Index of this episode's scenario in SCENARIOS."""
        return int(self._params["scenario"])

    @property
    def has_wall(self) -> bool:
        """Whether this episode has a wall."""
        return bool(self._params["has_wall"])

    @property
    def target(self) -> float:
        """Target position [m]."""
        return float(self._params["target"])

    def _info(self) -> dict[str, Any]:
        return {k: self._get(k) for k in ("x", "x_dot", "f_env", "f_ope", "f_d")} | {"scenario": self.scenario}

    @property
    def weights(self) -> np.ndarray:
        """Current task weights w = softmax(w̌) (eq. 29e)."""
        lg = (self._native.state["w_logits"][0] if self._native is not None
              else self._torch_state["w_logits"][0].numpy())
        ex = np.exp(lg - lg.max())
        return ex / ex.sum()
