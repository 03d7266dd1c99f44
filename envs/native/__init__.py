"""The eq. 35 point mass in C (`point_mass.h`): the step the C A2C iteration inlines, and a batched step for Python.

`point_mass.h` is a copy of `envs.point_mass.agent_step` / `observe_state` / `auto_reset` for callers where a torch
call per step costs more than the step (the A2C iteration at 4 envs, the single-env gym of the SB3 benchmark);
tests/test_point_mass_native.py and tests/test_a2c_native.py keep it equal to the torch env. `PMParams` mirrors
`pm_params` field by field. `A3CQP_NATIVE_ENV=0` switches the library off (no compiler: one warning).
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import numpy as np

from a3cqp_rl.config import ExperimentConfig
from a3cqp_rl.native_build import LazyLibrary, address

__all__ = ["PMParams", "pm_params", "load", "unsupported", "NativePointMass", "HEADER", "SOURCE", "STATE"]

HEADER = Path(__file__).parent / "point_mass.h"
"""The step every C file including it inlines (a3cqp_rl.native_sources.NATIVE_HEADERS)."""
SOURCE = HEADER.with_name("point_mass.c")
STATE = ("x", "x_dot", "target", "w_logits", "f_d", "wall_pos", "f_env", "f_ope", "has_wall", "t", "scenario", "slot")
"""pm_state's order (the S_* enum of point_mass.c)."""
_DTYPES = {"has_wall": np.uint8, "t": np.int64, "scenario": np.int64, "slot": np.int64}

_log = logging.getLogger(__name__)
_i, _d = ctypes.c_int64, ctypes.c_double


class PMParams(ctypes.Structure):
    """`pm_params` of point_mass.h, field by field."""

    _fields_ = [("N", _i), ("episode_steps", _i), ("substeps", _i), ("sched_len", _i),
                ("mass", _d), ("kp", _d), ("kv", _d), ("physics_dt", _d), ("lambda_d", _d), ("c_d", _d),
                ("wall_stiffness", _d), ("wall_damping", _d), ("operator_v_hand", _d), ("operator_grip_min", _d),
                ("operator_drag", _i),
                ("sigma_w", _d), ("sigma_f", _d), ("adapt_dt", _d), ("f_d_max", _d), ("e_max", _d),
                ("f_env_max", _d), ("f_ope_max", _d), ("alpha", _d * 4)]


C_FIELDS = {
    "point_mass": frozenset({
        "c_d", "depth_max", "depth_min", "disturbance_max", "episode_steps", "idle_force", "kp", "kv", "lambda_d",
        "mass", "operator_force_min", "operator_goal_max", "operator_goal_min", "operator_grip", "operator_hand_damping",
        "operator_hand_stiffness", "operator_model", "operator_move_time", "operator_off_max", "operator_off_min",
        "operator_on_max", "operator_on_min", "operator_target_range", "operator_toward_wall", "operator_v_hand",
        "physics_dt", "random_initial_fraction", "random_initial_weights", "scenario_probs", "substeps", "target_max",
        "target_min", "target_speed_max", "wall_damping", "wall_max", "wall_min", "wall_stiffness"}),
    "adaptation": frozenset({"dt", "e_max", "f_d_max", "f_env_max", "f_ope_max", "sigma_f", "sigma_w"}),
    "reward": frozenset({"alpha"}),
}
"""The config fields point_mass.c was written for (or that it is told to refuse above). A field added to these
sections later is not in the C copy of the step and reward: such a config trains on the torch step instead of being
silently simulated without it (tests/test_point_mass_native.py)."""


def unsupported(cfg: ExperimentConfig) -> str | None:
    """Why the C point mass cannot simulate `cfg` (None when it can)."""
    import dataclasses

    new = [f"{section}.{f.name}" for section, known in C_FIELDS.items()
           for f in dataclasses.fields(getattr(cfg, section)) if f.name not in known]
    if new:
        return f"the C point mass was not written for {', '.join(new)} (a field newer than point_mass.c)"
    if cfg.point_mass.operator_model not in ("push", "drag"):
        return f"the C point mass has the 'push' and 'drag' operators only, not {cfg.point_mass.operator_model!r}"
    if cfg.point_mass.target_speed_max > 0.0:
        return "the C point mass has fixed targets only (point_mass.target_speed_max > 0)"
    if cfg.point_mass.disturbance_max > 0.0:
        return "the C point mass has no unmeasured disturbance force (point_mass.disturbance_max > 0)"
    if cfg.point_mass.operator_toward_wall != 0.5:
        return "the C point mass's operator pushes either way alike (point_mass.operator_toward_wall 0.5)"
    if cfg.point_mass.idle_force != "free":
        return (f"the C point mass has eq. 35's idle force-control share only (point_mass.idle_force 'free'), not "
                f"{cfg.point_mass.idle_force!r}")
    return None


def pm_params(cfg: ExperimentConfig, num_envs: int) -> PMParams:
    """`pm_params` for `num_envs` envs of `cfg` (point_mass, adaptation and reward sections)."""
    c, ad = cfg.point_mass, cfg.adaptation
    p = PMParams(N=num_envs, episode_steps=c.episode_steps, substeps=c.substeps, sched_len=c.episode_steps + 1,
                 mass=c.mass, kp=c.kp, kv=c.kv_value, physics_dt=c.physics_dt, lambda_d=c.lambda_d, c_d=c.c_d,
                 wall_stiffness=c.wall_stiffness, wall_damping=c.wall_damping, operator_v_hand=c.operator_v_hand,
                 operator_grip_min=-1.0 if c.operator_grip else 0.0, operator_drag=int(c.operator_model == "drag"),
                 sigma_w=ad.sigma_w, sigma_f=ad.sigma_f, adapt_dt=ad.dt, f_d_max=ad.f_d_max, e_max=ad.e_max,
                 f_env_max=ad.f_env_max, f_ope_max=ad.f_ope_max)
    p.alpha[:] = [float(a) for a in cfg.reward.alpha]
    return p


def _bind(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    lib.pm_params_size.restype = lib.pm_state_count.restype = ctypes.c_int64
    if lib.pm_params_size() != ctypes.sizeof(PMParams):
        raise RuntimeError("pm_params in point_mass.h and envs.native.PMParams differ")
    if lib.pm_state_count() != len(STATE):
        raise RuntimeError("the state table of point_mass.c and envs.native.STATE differ")
    lib.pm_step.argtypes = [ctypes.c_void_p] * 6
    lib.pm_step.restype = None
    return lib


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_ENV", _bind, _log, "envs: native point mass", "no native point mass",
                       depends=(HEADER,))


def load() -> ctypes.CDLL | None:
    """The compiled library, or None (A3CQP_NATIVE_ENV=0, or no compiler / failed build: one warning)."""
    return _library.get()


class NativePointMass:
    """N point masses stepped by the C library: numpy state arrays (the torch env's state dict) and one call per step.

    Holds one episode per env (no pending one): `set_episode` starts it, `step` advances all envs.
    """

    def __init__(self, cfg: ExperimentConfig, num_envs: int = 1) -> None:
        """Bind the library for `num_envs` envs of `cfg`; RuntimeError if the library is unavailable."""
        lib = load()
        if lib is None:
            raise RuntimeError("the native point mass is unavailable (no C compiler, or A3CQP_NATIVE_ENV=0)")
        why = unsupported(cfg)
        if why:
            raise ValueError(why)
        self.lib, self.num_envs = lib, num_envs
        self.params = pm_params(cfg, num_envs)
        self.state = {k: np.zeros((num_envs, 3) if k == "w_logits" else num_envs, dtype=_DTYPES.get(k, np.float64))
                      for k in STATE}
        self.schedule = np.zeros((1, num_envs, cfg.point_mass.episode_steps + 1))  # slot 0 only
        self.rewards = np.zeros(num_envs)
        self.obs = np.zeros((num_envs, 3), dtype=np.float32)
        self._table = (ctypes.c_void_p * len(STATE))(*(address(self.state[k]) for k in STATE))
        self._params_ref = ctypes.byref(self.params)
        self._args = (self._params_ref, self._table, address(self.schedule), None, address(self.rewards),
                      address(self.obs))

    def set_episode(self, i: int, target: float, wall_pos: float, has_wall: bool, scenario: int,
                    w_logits, f_d: float, schedule) -> None:
        """Start env `i`'s episode from rest: its parameters and operator schedule [episode_steps + 1]."""
        s = self.state
        s["target"][i], s["wall_pos"][i], s["has_wall"][i], s["scenario"][i] = target, wall_pos, has_wall, scenario
        s["w_logits"][i], s["f_d"][i] = w_logits, f_d
        for k in ("x", "x_dot", "f_env", "f_ope", "t", "slot"):
            s[k][i] = 0
        self.schedule[0, i] = schedule

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One agent step of all envs with `actions` [N, 4] (float32, C-contiguous); (rewards [N], obs [N, 3]).

        The returned arrays are this object's buffers: valid until the next step.
        """
        p, table, sched, _, rew, obs = self._args
        self.lib.pm_step(p, table, sched, address(actions), rew, obs)
        return self.rewards, self.obs
