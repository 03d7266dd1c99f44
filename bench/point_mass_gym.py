"""The point-mass task of `envs.point_mass.PointMassEnv` as a plain single-env `gymnasium.Env` (numpy, no torch).

This is the baseline side of `bench/train_speed.py`: the paper trained Stable-Baselines3 on a Gym
environment, so SB3 gets the *same* task here — same eq. 29 weight/force integration, same
``substeps`` × 1 kHz semi-implicit Euler steps of eq. 35, same eq. 30 reward with clipped
normalised terms, same scenarios, same parameters (read from one `ExperimentConfig`), same episode
length and truncation. `tests/test_point_mass_gym.py` checks it step by step against the TorchRL env
to 1e-9.

Spaces: observation Box(0, 1, (3,), float32) = (|e|/ē, |f_env|/f̄_env, |f_ope|/f̄_ope) (eq. 26);
action Box(-1, 1, (4,), float32) = (ẇ1, ẇ2, ẇ3, ḟd). Episodes never terminate; they are truncated
after ``point_mass.episode_steps`` agent steps.

The physics runs on Python floats (IEEE double, like the TorchRL env's float64): for one env that
is several times faster than numpy scalar arithmetic, which keeps the SB3 baseline as fast as it can
be. Randomness comes from `self.np_random` (gymnasium seeding); all of an episode's randomness is
drawn at reset, in the same order and from the same distributions as `PointMassEnv._sample_episodes`.

``reset(options=...)`` sets an episode's parameters explicitly (after the usual draw, which they
override): ``scenario`` (index into `SCENARIOS` or name), ``target``, ``wall_pos``, ``has_wall``,
``w_logits`` (3 pre-softmax weights), ``f_d``, ``schedule`` (operator intent force per agent step,
``episode_steps + 1`` values). `episode_params()` returns them. The TorchRL env's live values come
from ``PointMassEnv.functional()``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from a3cqp_rl.config import ExperimentConfig, PointMassConfig, load_config

__all__ = ["PointMassGym", "SCENARIOS", "OPTION_KEYS", "operator_schedule"]

SCENARIOS: tuple[str, ...] = PointMassConfig.SCENARIOS
OPTION_KEYS = ("scenario", "target", "wall_pos", "has_wall", "w_logits", "f_d", "schedule")
"""Keys accepted by ``reset(options=...)``."""

Uniform = Callable[[float, float, tuple[int, ...]], np.ndarray]
"""uniform(lo, hi, shape) -> float64 array: the one source of continuous randomness at reset."""


def operator_schedule(cfg: PointMassConfig, f_ope_max: float, n_phases: int, uniform: Uniform) -> np.ndarray:
    """Piecewise-constant operator intent force [N] per agent step, shape [episode_steps + 1].

    Same construction as `PointMassEnv._operator_schedule` for one env: `n_phases` (off, on) pairs,
    each phase off for U(off_min, off_max) s then pushing with ±U(force_min, f̄_ope) N for
    U(on_min, on_max) s; sampled at the agent step times t·Δt.
    """
    K = n_phases
    off = uniform(cfg.operator_off_min, cfg.operator_off_max, (K,))
    on = uniform(cfg.operator_on_min, cfg.operator_on_max, (K,))
    sign = np.where(uniform(0.0, 1.0, (K,)) < 0.5, -1.0, 1.0)
    force = sign * uniform(cfg.operator_force_min, f_ope_max, (K,))
    ends_on = np.cumsum(off + on)
    ends_off = ends_on - on
    boundaries = np.stack((ends_off, ends_on), axis=-1).reshape(2 * K)  # sorted
    agent_dt = cfg.substeps * cfg.physics_dt
    times = np.arange(cfg.episode_steps + 1, dtype=np.float64) * agent_dt
    seg = np.searchsorted(boundaries, times, side="right")
    phase = np.minimum(seg // 2, K - 1)
    is_on = (seg % 2) == 1
    return np.where(is_on, force[phase], 0.0)


class PointMassGym(gym.Env):
    """One point mass under eq. 35 with the A3CQP adaptation law (eq. 29, eq. 30), gymnasium API."""

    metadata = {"render_modes": []}

    def __init__(self, config: ExperimentConfig | str | None = None, render_mode: str | None = None) -> None:
        """`config`: an ExperimentConfig, a YAML path (`load_config`), or None for the paper defaults."""
        if render_mode is not None:
            raise ValueError(f"PointMassGym does not render (render_mode={render_mode!r})")
        cfg = config if isinstance(config, ExperimentConfig) else load_config(config)
        self.config = cfg
        self.cfg, self.adapt, self.rew = cfg.point_mass, cfg.adaptation, cfg.reward
        c, a = self.cfg, self.adapt
        self.observation_space = spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        probs = np.array([c.scenario_probs.get(s, 0.0) for s in SCENARIOS], dtype=np.float64)
        self._scenario_probs = probs / probs.sum()
        episode_s = c.episode_steps * c.substeps * c.physics_dt
        shortest = max(c.operator_on_min + c.operator_off_min, 1e-3)
        self._n_phases = int(math.ceil(episode_s / shortest)) + 2  # as PointMassEnv
        # Constants of the step, as Python floats.
        self._m, self._kp, self._kv, self._dt = c.mass, c.kp, c.kv_value, c.physics_dt
        self._adm_gain = c.mass / c.lambda_d - 1.0
        self._alpha = tuple(float(x) for x in self.rew.alpha)
        self._w_rate = a.sigma_w * a.dt
        self._f_rate = a.sigma_f * a.dt
        self._half = 0.5 * a.sigma_w
        # Episode parameters and state (set by reset).
        self.scenario = 0
        self.target = self.wall_pos = self.f_d = 0.0
        self.has_wall = False
        self.w_logits = [0.0, 0.0, 0.0]
        self.schedule = np.zeros(c.episode_steps + 1)
        self._sched: list[float] = self.schedule.tolist()
        self.x = self.x_dot = self.f_env = self.f_ope = 0.0
        self.t = 0

    # ------------------------------------------------------------------ reset
    def _uniform(self, lo: float, hi: float, shape: tuple[int, ...] = ()) -> np.ndarray:
        return lo + (hi - lo) * self.np_random.random(shape)

    def _sample_episode(self, uniform: Uniform) -> dict[str, Any]:
        """Draw one episode's parameters, in the order of `PointMassEnv._sample_episodes`."""
        c, a = self.cfg, self.adapt
        scen = int(self.np_random.choice(len(SCENARIOS), p=self._scenario_probs))
        has_wall = scen in (2, 3)
        has_op = scen in (1, 3)
        sign = -1.0 if float(uniform(0.0, 1.0, ())) < 0.5 else 1.0
        free_target = sign * float(uniform(c.target_min, c.target_max, ()))
        op_target = float(uniform(-c.operator_target_range, c.operator_target_range, ()))
        wall_pos = float(uniform(c.wall_min, c.wall_max, ()))
        wall_target = wall_pos + float(uniform(c.depth_min, c.depth_max, ()))
        target = wall_target if has_wall else (op_target if has_op else free_target)
        half = self._half
        if c.random_initial_weights:
            w_logits = np.asarray(uniform(-half, half, (3,)), dtype=np.float64)
            f_d = float(uniform(0.0, a.f_d_max, ()))
        else:  # pure IK, no desired force
            w_logits = np.array([half, -half, -half])
            f_d = 0.0
        schedule = operator_schedule(c, a.f_ope_max, self._n_phases, uniform) * float(has_op)
        return {"scenario": scen, "target": target, "wall_pos": wall_pos, "has_wall": has_wall,
                "w_logits": w_logits, "f_d": f_d, "schedule": schedule}

    def _set_episode(self, p: dict[str, Any]) -> None:
        T = self.cfg.episode_steps
        unknown = sorted(set(p) - set(OPTION_KEYS))
        if unknown:
            raise ValueError(f"unknown reset option(s) {unknown}; valid: {list(OPTION_KEYS)}")
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
        self.scenario = scen
        self.target, self.wall_pos, self.f_d = values
        self.has_wall = bool(p["has_wall"])
        self.w_logits = w_logits.tolist()
        self.schedule = schedule.copy()
        self._sched = self.schedule.tolist()
        self.x = self.x_dot = self.f_env = self.f_ope = 0.0
        self.t = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode: draw its parameters, then override them with `options` (see module doc)."""
        super().reset(seed=seed)
        params = self._sample_episode(self._uniform)
        if options:
            unknown = sorted(set(options) - set(OPTION_KEYS))
            if unknown:
                raise ValueError(f"unknown reset option(s) {unknown}; valid: {list(OPTION_KEYS)}")
            params.update(options)
            if "scenario" in options and "has_wall" not in options:
                s = options["scenario"]
                idx = SCENARIOS.index(s) if isinstance(s, str) else int(s)
                params["has_wall"] = idx in (2, 3)
        self._set_episode(params)
        return self._obs(), self._info()

    def episode_params(self) -> dict[str, Any]:
        """This episode's parameters, in the form ``reset(options=...)`` accepts."""
        return {"scenario": self.scenario, "target": self.target, "wall_pos": self.wall_pos,
                "has_wall": self.has_wall, "w_logits": np.array(self.w_logits), "f_d": self.f_d,
                "schedule": self.schedule.copy()}

    # ------------------------------------------------------------------ step
    def step(self, action):
        """One 100 Hz agent step: eq. 29 on `action`, `substeps` × eq. 35, eq. 30 reward."""
        a0, a1, a2, a3 = (float(v) for v in np.asarray(action, dtype=np.float64).reshape(4))
        if not (math.isfinite(a0) and math.isfinite(a1) and math.isfinite(a2) and math.isfinite(a3)):
            raise ValueError(f"action contains NaN or inf: {action!r}")
        c, half = self.cfg, self._half
        # eq. 29a-c: integrate the pre-softmax weights, saturate at ±σw/2; eq. 29e softmax.
        wr = self._w_rate
        l0, l1, l2 = self.w_logits
        l0 = min(max(l0 + wr * min(max(a0, -1.0), 1.0), -half), half)
        l1 = min(max(l1 + wr * min(max(a1, -1.0), 1.0), -half), half)
        l2 = min(max(l2 + wr * min(max(a2, -1.0), 1.0), -half), half)
        mx = max(l0, l1, l2)
        e0, e1, e2 = math.exp(l0 - mx), math.exp(l1 - mx), math.exp(l2 - mx)
        s = e0 + e1 + e2
        w1, w2, w3 = e0 / s, e1 / s, e2 / s
        # eq. 29d
        f_d = min(max(self.f_d + self._f_rate * min(max(a3, -1.0), 1.0), 0.0), self.adapt.f_d_max)
        t = self.t
        f_cmd = self._sched[min(t, len(self._sched) - 1)]
        sgn = (f_cmd > 0.0) - (f_cmd < 0.0)

        m, kp, kv, dt, adm, c_d = self._m, self._kp, self._kv, self._dt, self._adm_gain, c.c_d
        k_wall, c_wall, v_hand = c.wall_stiffness, c.wall_damping, c.operator_v_hand
        wall_pos, has_wall, target = self.wall_pos, self.has_wall, self.target
        x, v = self.x, self.x_dot
        f_env = f_ope = 0.0
        for _ in range(c.substeps):  # 1 kHz semi-implicit Euler
            pen = x - wall_pos
            # Unilateral wall: pushes back (−x) only, never pulls.
            f_env = min(-k_wall * pen - c_wall * v, 0.0) if (has_wall and pen > 0.0) else 0.0
            # Operator hand, linear force-velocity law.
            f_ope = f_cmd * min(max(1.0 - v * sgn / v_hand, 0.0), 1.0)
            f_ext = f_env + f_ope
            e = target - x
            acc = (f_ext + w1 * m * (kp * e - kv * v) + w2 * (adm * f_ext - c_d * v) + w3 * f_d) / m  # eq. 35
            v = v + acc * dt
            x = x + v * dt
        self.x, self.x_dot, self.f_env, self.f_ope = x, v, f_env, f_ope
        self.w_logits = [l0, l1, l2]
        self.f_d = f_d
        self.t = t + 1
        # eq. 30, each ratio clipped to [0, 1]
        ad = self.adapt
        al1, al2, al3, al4 = self._alpha
        r = (-al1 * min(abs(target - x) / ad.e_max, 1.0)
             - al2 * min(abs(f_ope) / ad.f_ope_max, 1.0)
             + al3 * min(abs(f_env) / ad.f_env_max, 1.0)
             - al4 * min(abs(f_d) / ad.f_d_max, 1.0))
        truncated = self.t >= c.episode_steps
        return self._obs(), r, False, truncated, self._info()

    # ------------------------------------------------------------------ helpers
    def _obs(self) -> np.ndarray:
        ad = self.adapt
        return np.array(
            (min(abs(self.target - self.x) / ad.e_max, 1.0),
             min(abs(self.f_env) / ad.f_env_max, 1.0),
             min(abs(self.f_ope) / ad.f_ope_max, 1.0)),
            dtype=np.float32,
        )

    def _info(self) -> dict[str, Any]:
        return {"x": self.x, "x_dot": self.x_dot, "f_env": self.f_env, "f_ope": self.f_ope, "f_d": self.f_d,
                "scenario": self.scenario}

    @property
    def weights(self) -> np.ndarray:
        """Current task weights w = softmax(w̌) (eq. 29e)."""
        lg = np.array(self.w_logits)
        ex = np.exp(lg - lg.max())
        return ex / ex.sum()
