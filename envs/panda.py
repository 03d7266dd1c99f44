"""N simulated Franka Pandas with the A3CQP controller in the loop and six per-axis agents, as a TorchRL env.

Paper 000, sections III-VI: the QP controller (a3cqp_rl.control.A3CQPController) runs at 1 kHz on MuJoCo
(a3cqp_rl.robot.PandaSim, all N arms in one MjData); the adaptation runs at 100 Hz. Each of the six axes of the local
frame L (the tool tip's frame: x, y, z, then rotations about them) has an agent that sees eq. 26's three scalars and
outputs eq. 27's four rates; all six share one policy, so a policy trained on the point mass (obs [..., 3] ->
action [..., 4]) runs here unchanged:

    observation [N, 6, 3] = (|e^L|/ē, |f_env^L|/f̄_env, |f_ope^L|/f̄_ope) per axis   (eq. 25-26)
    action      [N, 6, 4] = (ẇ1, ẇ2, ẇ3, ḟd) per axis ∈ [−1, 1]; beyond: clipped (eq. 27, 29)
    eq. 29 -> local weights w^L [N, 6, 3] (rotated to the world by the controller, eq. 8) and f_d^L [N, 6]
              (one f_d per translational axis in PandaEnvConfig.fd_axes; desired torques are zero)
    reward      [N, 6, 1] = eq. 30 per axis

Force sensing as on the real robot (section V-A): f_env from the wrist F/T sensor (tool below it; PandaSim removes
the tool's weight and inertia), moved to the tool tip; f_ext = J^T† τ_s from the joint torque sensors
(wrench_from_joint_torques); f_ope = f_ext − f_env. Noise and bias: PandaEnvConfig.sensors (off by default).

The operator and the scene procedure (peg-in-hole, polishing, guidance) are in envs/scenarios.py. A robot whose
simulation diverges (non-finite state, joint speed far beyond its limit, a deep contact penetration) ends its own
episode (`terminated` and `diverged` set, one log line) and is put back home; the rest of the batch runs on.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from a3cqp_rl.adaptation import action_of, integrate_force, integrate_weights, observe, reward
from a3cqp_rl.config import ExperimentConfig
from a3cqp_rl.control import A3CQPController, ControllerOptions, wrench_from_joint_torques
from a3cqp_rl.control.frames import pose_error
from a3cqp_rl.robot import PANDA_HOME, PANDA_LIMITS, PandaModel, PandaSim
from a3cqp_rl.robot.sim import ShardedPandaSim, _sim_state, cross3, grid_origins
from envs.native.hand import native_hand
from envs.native.period import WHY, native_period
from envs.native.tick import DONE as NATIVE_DONE
from envs.native.tick import native_tick
from envs.scenarios import Operator, Scene, SceneInput, make_scene, rotvec_to_matrix

__all__ = ["PandaEnv", "PandaAxisAgents", "axis_agents", "agent_done_flags", "AXES", "INFO_KEYS", "TASK_BLENDS"]

logger = logging.getLogger(__name__)

AXES = ("x", "y", "z", "rx", "ry", "rz")
"""The six agents: translations then rotations along/about the local frame L."""
TASK_BLENDS = {"eq35": {"cartesian_regularization": 1.0, "wrench_blend": "weighted_sum"},
               "eq24": {"cartesian_regularization": ControllerOptions.cartesian_regularization,
                        "wrench_blend": "normalized"}}
"""ControllerOptions of PandaEnvConfig.task_blend: "eq35" makes the QP's per-axis blend the weighted sum of the
point-mass surrogate (eq. 35): J q̈* = w1 ẍ_IK (the regularizer weighs the rest of ẍ with 1 − w1) and
f* = w2 f_adm + w3 f_ctc (IK's weight pulls f toward zero); "eq24" keeps the controller's defaults."""
_MEASURED = ("q", "qd", "pos", "rot", "_twist", "f_ext", "f_env", "f_env_true", "f_ope", "_r_handle", "handle_pos")
"""What `PandaEnv._measure` sets for every arm (a partial reset keeps the other arms' values)."""
INFO_KEYS = ("e_local", "f_env_local", "f_ope_local", "weights", "f_d", "phase", "time", "diverged")
"""Per-step entries written next to `observation` (plus the scene's signals, e.g. the peg's misalignment)."""


def to_local(rot: np.ndarray, v6: np.ndarray) -> np.ndarray:
    """World 6-vectors [N, 6] (linear; angular) into the local frames of `rot` [N, 3, 3]: D^T v (eq. 3)."""
    rt = np.swapaxes(rot, 1, 2)
    return np.concatenate([(rt @ v6[:, :3, None])[..., 0], (rt @ v6[:, 3:, None])[..., 0]], axis=1)


class PandaEnv(EnvBase):
    """N Pandas + A3CQP controller + operator + scene; six per-axis agents per arm; batch_size=[num_envs].

    Args:
        num_envs: number of arms N (all in one MuJoCo model).
        config: ExperimentConfig; its `panda` section (PandaEnvConfig) picks the scene, operator, sensing and the
            rotational-axis bounds, `adaptation`/`reward` give Table II/III, `controller` Table I.
        seed: seed of the trial draws, the operator's tremor and the sensor noise (each arm has its own stream,
            spawned from it).
        scene: override of `config.panda.scene`.
        controller_options: ControllerOptions for the A3CQP controller (default: the controller's defaults).
        trial_seeds: one seed per arm instead of `seed` (arms with the same seed run the same trials: the
            evaluation gives every controller the same trials this way).
        controller_factory: builds the arms' controller instead of A3CQPController, called with the same arguments
            (n, model=, config=, options=); e.g. a PopulationController with per-arm gains and priority levels.
        grid: (total, places): put arm i where arm places[i] of a batch of `total` arms would sit in MuJoCo's world
            (a3cqp_rl.robot.sim.grid_origins), so that a share of a batch run on its own computes with the same
            coordinates as in the whole batch (default: the grid of these num_envs arms).
        sim_threads: MuJoCo models the arms are split into, stepped in as many threads (ShardedPandaSim). Default 1
            (one PandaSim). The numbers are the same bit for bit, in contact too (PandaSim's `warmstart`). On a
            loaded 2-core machine 2 threads are slower (docs/panda.md, Benchmark).
    """

    _has_dynamic_specs = False

    def __init__(self, num_envs: int, config: ExperimentConfig | str | Path | None = None, seed: int | None = None,
                 scene: str | None = None, controller_options: ControllerOptions | None = None,
                 trial_seeds: list[int] | None = None, device: str | torch.device = "cpu",
                 controller_factory: Callable[..., A3CQPController] | None = None,
                 sim_threads: int = 1, grid: tuple[int, list[int]] | None = None) -> None:
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if isinstance(config, (str, Path)):  # a YAML file, e.g. configs/panda_peg_in_hole.yaml
            from a3cqp_rl.config import load_config

            config = load_config(config)
        elif config is not None and not isinstance(config, ExperimentConfig):
            raise TypeError(f"config must be an ExperimentConfig (a3cqp_rl.config.load_config) or a YAML path, got "
                            f"{type(config).__name__}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        cfg = config or ExperimentConfig()
        self.cfg, self.pcfg, self.adapt, self.rew = cfg, cfg.panda, cfg.adaptation, cfg.reward
        self.num_envs = n = num_envs
        if trial_seeds is not None and len(trial_seeds) != n:
            raise ValueError(f"trial_seeds needs one seed per arm ({n}), got {len(trial_seeds)}")
        self._trial_seeds = None if trial_seeds is None else [int(x) for x in trial_seeds]
        self._seed_arms(seed)
        scene_name = scene or self.pcfg.scene
        from envs.scenarios import SCENES

        if scene_name not in SCENES:
            raise ValueError(f"unknown scene {scene_name!r}; choose from {sorted(SCENES)}")
        tool = SCENES[scene_name].tool
        self.model = PandaModel(tool=tool)
        home_pos, home_rot = (x[0].numpy() for x in self.model.fk(torch.tensor([PANDA_HOME], dtype=torch.float64)))
        self.dt = 1.0 / cfg.controller.rate_hz
        self.substeps = int(round(self.adapt.dt / self.dt))
        if self.substeps < 1 or abs(self.substeps * self.dt - self.adapt.dt) > 1e-9:
            raise ValueError(f"adaptation.dt ({self.adapt.dt}) must be a multiple of the control period {self.dt}")
        self.operator = Operator(n, self.pcfg.operator, self.dt)
        # the scene needs the handle's home position (guidance goals): from a one-arm simulation of the bare arm
        probe = PandaSim(1, tool=tool)
        probe.observe()
        (h_pos,), _ = probe.site_pose("handle")
        (t_pos,), (t_rot,) = probe.site_pose("tcp")
        (f_pos,), _ = probe.site_pose("ft_site")
        # handle and F/T site in the tool tip's frame (rigidly attached: constant)
        self._o_handle, self._o_ft = t_rot.T @ (h_pos - t_pos), t_rot.T @ (f_pos - t_pos)
        self.scene: Scene = make_scene(scene_name, n, self.operator, home_pos, home_rot, self.pcfg, h_pos)
        if self.pcfg.sensors.tare_time > self.scene.rest_time():
            raise ValueError(f"panda.sensors.tare_time ({self.pcfg.sensors.tare_time} s) must not exceed the "
                             f"{scene_name} scene's rest at home ({self.scene.rest_time()} s): the sensors are tared "
                             "while the arm rests untouched")
        threads = min(int(sim_threads), n)
        if threads < 1:
            raise ValueError(f"sim_threads must be >= 1, got {sim_threads}")
        sim_args = dict(tool=tool, scene=self.scene.mjcf(), q0=PANDA_HOME, timestep=self.dt, control_site="tcp",
                        warmstart=self.pcfg.solver_warmstart, contact_prefilter=self.pcfg.contact_prefilter)
        if grid is not None:
            total, places = grid
            if len(places) != n or min(places) < 0 or max(places) >= total:
                raise ValueError(f"grid places must be {n} arm indices below {total}, got {list(places)}")
            sim_args["origins"] = grid_origins(tool, sim_args["scene"], int(total))[np.asarray(places)]
        self.sim: PandaSim | ShardedPandaSim = (PandaSim(n, **sim_args) if threads == 1 else
                                                ShardedPandaSim(n, parts=threads, **sim_args))
        for m in self.sim.models:  # one diverging arm must not make MuJoCo reset the whole batch (its default on bad
            m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)  # qpos/qvel/qacc)
        opts = dataclasses.replace(controller_options or ControllerOptions(), leak_axes=self.pcfg.state_leak,
                                   qp_failure=self.pcfg.qp_failure, **TASK_BLENDS[self.pcfg.task_blend])
        if self.pcfg.joint_limits_f_ext == "always":
            opts = dataclasses.replace(opts, joint_limits_include_f_ext=True)
        self.ctrl = (controller_factory or A3CQPController)(n, model=self.model, config=cfg.controller, options=opts)
        lim = PANDA_LIMITS
        self._dq_max = np.array(lim.dq_max)
        self._q_lo, self._q_hi = np.array(lim.q_min), np.array(lim.q_max)
        # per-axis bounds (translations: Table II; rotations: PandaEnvConfig)
        p = self.pcfg
        self._fd_mask = np.array([a in p.fd_axes for a in ("x", "y", "z")] + [False] * 3)
        # --- state
        half = 0.5 * self.adapt.sigma_w
        self._ik_logits = np.array([half, -half, -half])
        self.w_logits = np.tile(self._ik_logits, (n, 6, 1))
        self.weights = np.zeros((n, 6, 3))
        self.f_d = np.zeros((n, 6))
        self._idle_leak: np.ndarray | None = None  # extra q* relaxation of `idle_force: damps` [N, 6] (1/s)
        self.t = np.zeros(n)
        self.diverged = np.zeros(n, dtype=bool)
        self.stiffness_scale = np.ones((n, 6))
        """Per-arm, per-local-axis scale of the IK stiffness (1 = Table I), applied by moving the reference
        (x_d' = x + s (x_d − x) in L): lets a variable-impedance baseline run on the same controller."""
        self._override: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._scripted = np.zeros(n, dtype=bool)  # arms whose weights `hold_weights` set this step (not the policy)
        self._ref_step = np.zeros((n, 3))  # how far the scene's reference moved in the last agent step [m], world
        self._engaged = np.zeros(n, dtype=bool)  # pressed along the axis while the reference advances (ik_lead_engaged)
        self._press_pos = np.zeros((n, 3))  # where the press that engaged it began, arm frame [m]
        self._noise: dict[str, np.ndarray] = {}
        self._ft_bias = np.zeros((n, 6))
        self._tau_bias = np.zeros((n, 7))
        self._tared = np.zeros(n, dtype=bool)  # `sensors.tare_time`: zeroed this episode
        self._tare_sum, self._tare_cnt = np.zeros((n, 13)), np.zeros(n)  # (τ_s, F/T in the sensor frame) summed
        # latest measurements (world frame, at the tool tip)
        self.pos, self.rot = np.tile(home_pos, (n, 1)), np.tile(home_rot, (n, 1, 1))
        self.f_env, self.f_ope, self.f_ext = np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 6))
        self.f_env_true = self.f_env
        """The contact wrench without sensor noise, bias or taring (world, at the tool tip): what the scene reads."""
        self._f_sum: np.ndarray | None = None  # (f_env, f_ope) summed over an agent period [2, N, 6]
        self.f_env_obs, self.f_ope_obs = np.zeros((n, 6)), np.zeros((n, 6))
        """With `panda.observation_filter: mean`, the agent period's mean sensed wrenches (world, at the tool tip)."""
        self.tau, self.q, self.qd = np.zeros((n, 7)), np.zeros((n, 7)), np.zeros((n, 7))
        self.handle_pos, self.handle_force = np.zeros((n, 3)), np.zeros((n, 3))
        self._handle_torque = np.zeros((n, 3))
        self._hand = native_hand(self.operator, self.sim if isinstance(self.sim, PandaSim) else None)
        """The operator's hand and its push in C (None: the numpy Operator.wrench and PandaSim.push)."""
        self._period = native_period(n, dq_max=self._dq_max, q_lo=self._q_lo, q_hi=self._q_hi,
                                     speed_factor=self.pcfg.divergence_speed_factor,
                                     penetration=self.pcfg.divergence_penetration, o_ft=self._o_ft,
                                     o_handle=self._o_handle)
        """The period's arithmetic around the read-out in C (None: the numpy `_measure` tail and checks)."""
        self.max_penetration = np.zeros(n)
        """Deepest contact penetration of each arm in the last agent period [m]."""
        self.parked = np.zeros(n, dtype=bool)
        """Arms set aside by `park` (until their reset): no collisions, IK holding, no divergence checks."""
        self.fallbacks = np.zeros(n, dtype=np.int64)
        """Control periods in which the controller's QP fell back to braking, per arm, this episode."""
        self.relaxations = np.zeros(n, dtype=np.int64)
        """Control periods in which the controller's QP failed and its least-violation QP gave the torque, per arm,
        this episode (ControllerOptions.qp_failure)."""
        self.joint_limit_excess = np.full(n, -np.inf)
        """Per arm, this episode: the largest excess of a joint past its datasheet position limit [rad] over the 1 kHz
        control periods (negative: the closest approach, inside the limits), until its episode ends, it is parked or it
        diverges."""
        self.joint_limit_joint = np.full(n, -1, dtype=np.int64)
        """Per arm, this episode: the joint (0-6) of `joint_limit_excess` (-1 before the first control period)."""
        self.joint_speed_ratio = np.zeros(n)
        """Per arm, this episode: the largest |q̇_j| / q̇_max,j (datasheet) over the joints and the 1 kHz control periods
        (> 1: a joint ran faster than its limit), until its episode ends, it is parked or it diverges."""
        self.signal_keys = tuple(self.scene.signals(self._scene_input()).keys())
        """Names of the scene's per-step signals in the output (e.g. the peg's misalignment and depth)."""
        self._make_specs()
        self._native_tick = native_tick(self)
        """The control period in one C call where every piece is native (None: `_tick`'s Python route)."""
        self._reset_arms(np.arange(n))

    def __setattr__(self, name: str, value) -> None:  # noqa: ANN001
        # the 1 kHz loop rebinds its numpy state ~10 times a period; nn.Module's bookkeeping (~6 µs a call) is for
        # parameters, buffers and submodules, which numpy arrays are not
        if isinstance(value, np.ndarray):
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        N, f32, f64, dev = self.batch_size, torch.float32, torch.float64, self.device
        info = {
            "e_local": Unbounded(shape=(*N, 6), dtype=f64, device=dev),
            "f_env_local": Unbounded(shape=(*N, 6), dtype=f64, device=dev),
            "f_ope_local": Unbounded(shape=(*N, 6), dtype=f64, device=dev),
            "weights": Bounded(0.0, 1.0, shape=(*N, 6, 3), dtype=f64, device=dev),
            "f_d": Unbounded(shape=(*N, 6), dtype=f64, device=dev),
            "phase": Unbounded(shape=N, dtype=torch.int64, device=dev),
            "time": Unbounded(shape=N, dtype=f64, device=dev),
            "diverged": Categorical(2, shape=N, dtype=torch.bool, device=dev),
        }
        for k in self.signal_keys:
            info[k] = Unbounded(shape=N, dtype=f64, device=dev)
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, shape=(*N, 6, 3), dtype=f32, device=dev), **info, shape=N)
        self.action_spec = Bounded(-1.0, 1.0, shape=(*N, 6, 4), dtype=f32, device=dev)
        self.reward_spec = Unbounded(shape=(*N, 6, 1), dtype=f32, device=dev)
        flag = Categorical(2, shape=(*N, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=N)

    def _set_seed(self, seed: int | None) -> None:
        """`env.set_seed(seed)`: the arms' generators as construction with `seed` makes them, and their first trial
        drawn as construction draws it, so that `PandaEnv(n, seed=s)` and `env.set_seed(s)` go on to the same
        trials."""
        self._seed_arms(seed)
        self._reset_arms(np.arange(self.num_envs))

    def _seed_arms(self, seed: int | None) -> None:
        """One generator per arm: spawned from `seed`, or the `trial_seeds` given at construction."""
        if self._trial_seeds is not None:
            self.arm_rngs = [np.random.default_rng(s) for s in self._trial_seeds]
        else:
            self.arm_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(self.num_envs)]

    def _draw(self, idx: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        """Standard normal draws [len(idx), *shape] from each arm's own stream."""
        return np.array([self.arm_rngs[i].standard_normal(shape) for i in idx]).reshape(len(idx), *shape)

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        idx = np.arange(self.num_envs) if mask is None else np.flatnonzero(mask.reshape(self.num_envs).cpu().numpy())
        if len(idx):
            self._reset_arms(idx)
        return self._output(done=np.zeros(self.num_envs, dtype=bool), terminated=np.zeros(self.num_envs, dtype=bool))

    def _reset_arms(self, idx: np.ndarray) -> None:
        """Arms `idx` back home, fresh trial, IK weights (or random), new sensor biases."""
        k = len(idx)
        self.sim.reset(np.tile(np.array(PANDA_HOME), (k, 1)), idx=idx.tolist())
        self.ctrl.reset(torch.tensor(np.tile(np.array(PANDA_HOME), (k, 1))), idx=torch.as_tensor(idx))
        half = 0.5 * self.adapt.sigma_w
        rngs = [self.arm_rngs[i] for i in idx]
        if self.pcfg.initial_weights == "random":
            self.w_logits[idx] = np.array([r.uniform(-half, half, (6, 3)) for r in rngs])
            self.f_d[idx] = np.array([r.uniform(0.0, self.adapt.f_d_max, 6) for r in rngs]) * self._fd_mask
        else:
            self.w_logits[idx] = self._ik_logits
            self.f_d[idx] = 0.0
        self.weights[idx] = _softmax(self.w_logits[idx])
        self.t[idx] = 0.0
        self.diverged[idx] = False
        self.parked[idx] = False
        self.fallbacks[idx] = 0
        self.relaxations[idx] = 0
        self.joint_limit_excess[idx] = -np.inf
        self.joint_limit_joint[idx] = -1
        self.joint_speed_ratio[idx] = 0.0
        self.stiffness_scale[idx] = 1.0
        s = self.pcfg.sensors
        self._ft_bias[idx], self._tau_bias[idx] = 0.0, 0.0  # (a previous episode's tare offset goes too)
        if s.ft_force_bias > 0 or s.ft_torque_bias > 0:
            self._ft_bias[idx] = self._draw(idx, (6,)) * np.repeat([s.ft_force_bias, s.ft_torque_bias], 3)
        if s.joint_torque_bias > 0:
            self._tau_bias[idx] = self._draw(idx, (7,)) * s.joint_torque_bias
        self._tared[idx], self._tare_sum[idx], self._tare_cnt[idx] = s.tare_time == 0, 0.0, 0.0
        self.operator.reset(idx)
        self.scene.reset(idx, rngs)
        for body, offset in self.scene.body_offsets().items():  # e.g. the polishing plate's height this trial
            self.sim.move_static_body(body, idx, offset[idx])
        # the read-out is of every arm; the others keep what their last control period measured (read again after
        # its physics step, their next step's reference rules would start from other numbers: a reset must not
        # touch an arm it does not name)
        keep = np.setdiff1d(np.arange(self.num_envs), idx)
        held = {a: getattr(self, a)[keep].copy() for a in _MEASURED} if len(keep) else {}
        self._measure()
        for a, v in held.items():
            getattr(self, a)[keep] = v
        self.f_env_obs[idx], self.f_ope_obs[idx] = self.f_env[idx], self.f_ope[idx]
        self._update_scene()
        self._ref_step[idx] = 0.0  # a fresh reference has not moved yet
        self._engaged[idx] = False

    # ------------------------------------------------------------------ control
    def hold_weights(self, mask: np.ndarray, weights: np.ndarray, f_d: np.ndarray) -> None:
        """For the next step only, arms in `mask` [N] use these local weights [N, 6, 3] and f_d^L [N, 6] instead of
        eq. 29 of their action (scripted baselines); their integrated state follows (w̌ = log w, f_d)."""
        self._override = (np.asarray(mask, dtype=bool), np.asarray(weights, dtype=np.float64),
                          np.asarray(f_d, dtype=np.float64))

    def _adapt(self, action: torch.Tensor) -> None:
        """Eq. 29 for every axis of every arm: rates -> w̌, w = softmax(w̌), f_d (translational f_d axes only)."""
        a = action.to(torch.float64)
        logits, w = integrate_weights(torch.from_numpy(self.w_logits), a[..., :3], self.adapt.sigma_w, self.adapt.dt,
                                      check=False)
        f_d = integrate_force(torch.from_numpy(self.f_d), a[..., 3], self.adapt.sigma_f, self.adapt.dt,
                              self.adapt.f_d_max, check=False)
        self.w_logits, self.weights = logits.numpy().copy(), w.numpy().copy()
        self.f_d = f_d.numpy() * self._fd_mask
        self._scripted = np.zeros(self.num_envs, dtype=bool)
        if self._override is not None:
            mask, w_o, f_o = self._override
            self._scripted = mask.copy()
            self.weights[mask] = w_o[mask]
            self.f_d[mask] = f_o[mask]
            self.w_logits[mask] = np.log(np.clip(w_o[mask], 1e-12, 1.0))
            self._override = None
        if self.parked.any():  # what a parked arm reports: IK, f_d = 0 (the controller leaves it out, h + g holds it)
            p = self.parked
            self.w_logits[p] = self._ik_logits
            self.weights[p] = _softmax(self.w_logits[p])
            self.f_d[p] = 0.0

    def controller_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """The local weights [N, 6, 3] the controller gets and the IK stiffness scale [N, 6] that goes with them.

        `panda.idle_force` decides what the share of force control that does not push, w3 (1 − min(1, f_d / 1 N)),
        does (the same share the per-axis leak treats as not pushing): "free" leaves it to eq. 35, where it commands
        neither wrench nor acceleration; "holds" hands it to IK; "damps" hands it to IK with the reference moved
        toward the tool so that IK's stiffness stays w1 k_p while its damping becomes (w1 + idle) k_v."""
        ones = np.ones(self.weights.shape[:2])
        if self.pcfg.idle_force == "free":
            return self.weights, ones
        idle = self.weights[..., 2] * (1.0 - np.clip(self.f_d, 0.0, 1.0))
        w = self.weights.copy()
        w[..., 0] += idle
        w[..., 2] -= idle
        if self.pcfg.idle_force == "holds":
            return w, ones
        # the reference scale w1 / (w1 + share) only where there is a share (elsewhere IK is the policy's own)
        return w, np.where(idle > 0.0, self.weights[..., 0] / np.maximum(w[..., 0], 1e-300), 1.0)

    def idle_share_leak(self, w_ctrl: np.ndarray) -> np.ndarray | None:
        """The extra relaxation rate [N, 6] (1/s) of the controller's q*, q̇* along each axis of L that `idle_force:
        damps` adds (the controller's `leak_extra`), or None where there is none.

        The controller's per-axis leak relaxes q* at rate leak × (w2 + w3 · min(1, f_d / 1 N)) of the weights it gets,
        and there the idle share counts as IK, whose integral (eq. 5-7) holds the pose. But the share is a damper: it
        has no position of its own to hold. So the share relaxes q* in the proportion the tasks that act do: the
        axis relaxes at leak × a / (w1 + a), a = w2 + w3 · min(1, f_d / 1 N) (the policy's weights). Where the
        operator leads an axis (w2 ≫ w1) the share then follows the operator (in a relocation, where q* would
        otherwise pull the hand back); where IK leads (w1 ≫ w2, as across the hole during an insertion) it keeps
        IK's integral. The controller already relaxes at leak × a_ctrl (a_ctrl of w_ctrl, the weights it gets); this
        returns the difference leak × (a / (w1 + a) − a_ctrl) (≥ 0, 1/s, leak = desired_state_leak), which the
        controller adds to its own rate in the same relaxation."""
        if self.pcfg.idle_force != "damps" or self.pcfg.state_leak != "per_axis":
            return None
        w, m = self.weights, np.clip(self.f_d, 0.0, 1.0)
        idle = w[..., 2] * (1.0 - m)
        if not np.any(idle > 0.0):
            return None
        act = w[..., 1] + w[..., 2] * m
        target = act / np.maximum(w[..., 0] + act, 1e-12)
        given = w_ctrl[..., 1] + w_ctrl[..., 2] * m  # what the controller's own leak does with w_ctrl
        extra = np.where(idle > 0.0, np.clip(target - given, 0.0, 1.0), 0.0)
        return self.ctrl.options.desired_state_leak * extra if np.any(extra > 0.0) else None

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._advance(action_of(tensordict, (self.num_envs, 6, 4)))

    def _advance(self, action: torch.Tensor) -> TensorDictBase:
        """One agent step of a checked action [N, 6, 4] (eq. 29, then 10 control periods); the step's outputs."""
        self._adapt(action)
        self.max_penetration[:] = 0.0
        w_ctrl, scale = self.controller_weights()
        self._idle_leak = self.idle_share_leak(w_ctrl)
        weights, f_d = torch.from_numpy(w_ctrl), torch.from_numpy(self.f_d)
        pos_d, rot_d = self._controller_reference(scale)
        self._draw_noise()
        mean = self.pcfg.observation_filter == "mean"
        self._f_sum = np.zeros((2, self.num_envs, 6)) if mean else None
        if self._native_tick is not None:
            self._native_tick.prepare(weights, f_d, pos_d, rot_d)
        for k in range(self.substeps):
            self._tick(k, weights, f_d, pos_d, rot_d)
        if mean:
            self.f_env_obs, self.f_ope_obs = self._f_sum / self.substeps
        self.t += self.adapt.dt
        before = self.scene.pos_d.copy()
        self._update_scene()
        np.subtract(self.scene.pos_d, before, out=self._ref_step)
        return self._output(done=self._episode_over() | self.diverged, terminated=self.diverged.copy(), reward=True)

    def _controller_reference(self, scale: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The scene's reference, along the tool axis within `ik_bound_tool_axis` of the tool (`ik_bound_blocked`
        ahead of a blocked tool; not held behind a tool in contact whose scene reference moves back) and, in contact
        while the scene's reference advances along the axis, not behind it (`ik_lead_sliding` ahead of a tool sliding
        forward; with `ik_lead_engaged` also for a tool the block pressed in this advance that reads free now; the
        policy's arms), moved toward the tool by
        `stiffness_scale` (times `scale` [N, 6]) where it is not 1 (arm frame)."""
        pos_d, rot_d = self.scene.pos_d.copy(), self.scene.rot_d.copy()
        bound = self.pcfg.ik_bound_tool_axis
        if bound is not None:
            axis = self.rot[:, :, 2]  # local z in the arm frame
            ez = np.einsum("nk,nk->n", pos_d - self.pos, axis)
            # a reference that lags a peg sliding down the bore would pull it back out against the FC half: the
            # point mass's wall targets never lie on the free side of the tool (the return home moves it back: kept)
            # the wrench the agents observe: one noisy 1-kHz sample above the contact threshold in free motion would
            # otherwise set a lead there
            f_env = self.observed_wrenches()[0]
            ref_along = np.einsum("nk,nk->n", self._ref_step, axis)
            contact = self.ctrl.contact_from(torch.from_numpy(f_env)).numpy()
            advancing = ref_along > 0.0
            pressed = np.einsum("nk,nk->n", f_env[:, :3], axis) < -self.pcfg.blocked_force  # pushed back along it
            ahead = contact & advancing
            if self.pcfg.ik_lead_engaged:
                # a peg in the bore touches its walls only now and then: once the block has pressed it back along its
                # axis (the rim) it stays engaged until the procedure's reference stops advancing (the operator's
                # turn, the return home), and its reference is not held behind it there either: read as free, a peg
                # that dropped off the rim into the bore ahead of the schedule was pulled back up to it. A peg that
                # slides straight in is never far ahead of the schedule, which keeps it near the top while the
                # alignment still turns it: driven down tilted, it wedges (docs/panda.md, "A reference not behind
                # a peg between ...")
                # ... but only once the tool is `engaged_depth` past where the press began (between the walls): a peg
                # that hops on the rim after its press reads free there too, and a reference 20 mm ahead of it drove
                # it into the bore while the alignment still turned it, where it wedged tilted (docs/panda.md, "An
                # engaged peg past the rim")
                start = pressed & advancing & ~self._engaged
                self._press_pos[start] = self.pos[start]
                self._engaged = (self._engaged | pressed) & advancing
                depth = np.einsum("nk,nk->n", self.pos - self._press_pos, axis)
                ahead |= self._engaged & (depth >= self.pcfg.engaged_depth)
            # the bound is against a reference that runs on into the block; one the procedure moves back (the return
            # home of --cycles) from a tool in contact pulls a peg the bore still holds out, as the scripted
            # baselines' does, and is not held 20 mm behind it (docs/panda.md, "The return home pulls a held peg out")
            behind = np.where(contact & (ref_along < 0.0), -np.inf, -bound)
            ahead_max = np.full(self.num_envs, bound)
            v_axis = np.einsum("nk,nk->n", self._twist[:, :3], axis)
            # a peg sliding down the bore behind a shallow schedule would follow the schedule's pace (w1 ~ 0.9 there,
            # f_d ~ 0 against the wall's friction); a reference ahead lets eq. 35's IK half carry it down
            lead = np.where(v_axis > self.pcfg.sliding_speed, self.pcfg.ik_lead_sliding, 0.0)
            if self.pcfg.ik_bound_blocked is not None:
                # anti-windup: a reference running on ahead of a tool the block holds only presses it harder (eq. 35's
                # IK half on top of the FC half's f_d), flat onto the rim; the point mass's walls never taught that
                blocked = pressed & (np.abs(v_axis) < self.pcfg.blocked_speed)
                ahead_max[blocked] = self.pcfg.ik_bound_blocked
            # the blocked bound wins over the lead: np.clip is min(max(ez, lo), hi)
            target = np.clip(ez, np.where(ahead, lead, behind), ahead_max)
            moved = (target != ez) & (~self._scripted | self.pcfg.ik_rules_scripted)
            if moved.any():
                pos_d[moved] += (target - ez)[moved, None] * axis[moved]
        s = self.stiffness_scale if scale is None else self.stiffness_scale * scale
        if np.any(s != 1.0):
            e_loc = to_local(self.rot, pose_error(pos_d, rot_d, self.pos, self.rot)) * s
            pos_d = self.pos + (self.rot @ e_loc[:, :3, None])[..., 0]
            rot_d = rotvec_to_matrix((self.rot @ e_loc[:, 3:, None])[..., 0]) @ self.rot
        return torch.from_numpy(pos_d), torch.from_numpy(rot_d)

    def _draw_noise(self) -> None:
        """This agent period's random draws, from each arm's own stream: hand tremor (arms the operator holds) and
        sensor noise (when configured), [N, substeps, dim] each."""
        n, K, sen = self.num_envs, self.substeps, self.pcfg.sensors
        self._noise = {}
        held = np.flatnonzero(self.operator.active)
        if self.pcfg.operator.noise > 0 and len(held):
            hand = np.zeros((n, K, 3))
            hand[held] = self._draw(held, (K, 3))
            self._noise["hand"] = hand
        if sen.ft_force_noise > 0 or sen.ft_torque_noise > 0:
            self._noise["ft"] = self._draw(np.arange(n), (K, 6)) * np.repeat([sen.ft_force_noise, sen.ft_torque_noise], 3)
        if sen.joint_torque_noise > 0:
            self._noise["tau"] = self._draw(np.arange(n), (K, 7)) * sen.joint_torque_noise

    def _tick(self, k: int, weights: torch.Tensor, f_d: torch.Tensor, pos_d: torch.Tensor,
              rot_d: torch.Tensor) -> np.ndarray:
        """One 1 kHz control period (the k-th of the agent period) for all arms; returns the arms that diverged."""
        fast = self._native_tick
        if fast is not None and fast.ready:  # the same in one C call (envs/native/tick.py)
            result = fast.run(k)
            if result >= 0:
                bad = np.zeros(self.num_envs, dtype=bool)
                if fast.diverged:
                    codes = fast.bad_codes()
                    self._log_diverged(codes)
                    bad = codes > 0
                if result == NATIVE_DONE:
                    if bad.any():
                        self._end_diverged(bad)
                else:  # the rest of the period in Python
                    self._control(k, _sim_state(self.sim, kin=True), self._in_episode(), bad, weights, f_d, pos_d,
                                  rot_d)
                if bad.any():  # (the diverged arms leave the checks and the live arms of the periods after)
                    fast.masks()
                return bad
        s = self._measure(k)
        if self._f_sum is not None:
            self._f_sum[0] += self.f_env
            self._f_sum[1] += self.f_ope
        live = self._in_episode()
        if self._period is not None:
            bad = self._native_checks(live)
        else:
            abs_qd = np.abs(self.qd)  # (NaN compares False without a warning: a diverging arm is the finiteness test's)
            bad = self._check_divergence(abs_qd)
            self._track_joint_limits(live, abs_qd)
        return self._control(k, s, live, bad, weights, f_d, pos_d, rot_d)

    def _control(self, k: int, s, live: np.ndarray, bad: np.ndarray, weights: torch.Tensor,  # noqa: ANN001
                 f_d: torch.Tensor, pos_d: torch.Tensor, rot_d: torch.Tensor) -> np.ndarray:
        """The rest of control period k after the sensing (`s`, the SimState) and the checks (`bad` [N]): the
        controller, the operator's hand and mj_step2; returns `bad`."""
        held = torch.from_numpy(self.operator.active) if self.pcfg.joint_limits_f_ext == "operator" else None
        out = self.ctrl.step(s.q, s.qd, s.mass, s.bias, weights, f_d, pos_d, rot_d,
                             f_ext=torch.from_numpy(self.f_ext), f_env=torch.from_numpy(self.f_env), kin=s.kin,
                             leak_extra=None if self._idle_leak is None else torch.from_numpy(self._idle_leak),
                             f_ext_limits=held, active=torch.from_numpy(~self.parked) if self.parked.any() else None)
        self.fallbacks += out.fallback.numpy() & live
        self.relaxations += out.relaxed.numpy() & live
        tau = out.tau.numpy()
        self.tau[:] = tau
        # the operator's hand at the handle (above the F/T sensor: read by the joint torques only)
        hand = self._noise.get("hand")
        if self._hand is not None:  # the same in C (envs/native/hand.py)
            if self._hand(self.t, k * self.dt, self.handle_pos, self._twist, self._r_handle, self.rot, hand, k,
                          self.handle_force, self._handle_torque) and not self._hand.pushes:
                self.sim.push(self.handle_force, site="handle", torque_world=self._handle_torque)
        else:
            v, w, r = self._twist[:, :3], self._twist[:, 3:], self._r_handle
            force, torque = self.operator.wrench(self.t + k * self.dt, self.handle_pos, v + cross3(w, r), self.rot, w,
                                                 None if hand is None else hand[:, k])
            self.handle_force[:] = force
            if np.any(force) or np.any(torque):
                self.sim.push(force, site="handle", torque_world=torque)
        self.sim.step(tau)
        if bad.any():
            self._end_diverged(bad)
        return bad

    def _measure(self, k: int | None = None):  # noqa: ANN202
        """mj_step1 and the sensed quantities at the tool tip (world frame): pose, f_env, f_ext, f_ope; sensor noise of
        the agent period's k-th control period (none for k = None), bias always."""
        s = self.sim.observe()
        sen = self.pcfg.sensors
        noise = self._noise if k is not None else {}
        self.q, self.qd = s.q.numpy(), s.qd.numpy()
        self.pos, self.rot = s.kin.pos.numpy().copy(), s.kin.rot.numpy().copy()
        self._twist = s.kin.twist.numpy()  # the tool tip's [N, 6], m/s and rad/s (world)
        tau = s.tau_ext
        tare = sen.tare_time > 0
        if "tau" in noise or sen.joint_torque_bias > 0 or tare:
            tau = torch.from_numpy(tau.numpy() + self._tau_bias + (noise["tau"][:, k] if "tau" in noise else 0.0))
        ft = s.f_env.numpy().copy()  # world frame, about the F/T site
        true = ft
        if "ft" in noise or sen.ft_force_bias > 0 or sen.ft_torque_bias > 0 or tare:
            true = ft.copy()
            err = self._ft_bias + (noise["ft"][:, k] if "ft" in noise else 0.0)
            ft[:, :3] += (self.rot @ err[:, :3, None])[..., 0]  # sensor frame = tool frame
            ft[:, 3:] += (self.rot @ err[:, 3:, None])[..., 0]
        if tare and not self._tared.all():
            tau, ft = self._tare(k, tau, ft)
        self.f_ext = wrench_from_joint_torques(tau, s.kin.jac, s.mass).numpy()
        if self._period is not None:  # the same in C (envs/native/period.py)
            self.f_ope, self._r_handle, self.handle_pos = self._period.measure(self.pos, self.rot, ft, true, self.f_ext)
            self.f_env, self.f_env_true = ft, true
            return s
        # moment about the tool tip: τ_tip = τ_site + (p_site − p_tip) × F
        lever = self.rot @ self._o_ft
        ft[:, 3:] += cross3(lever, ft[:, :3])
        if true is not ft:
            true[:, 3:] += cross3(lever, true[:, :3])
        self.f_env = ft
        self.f_env_true = true
        self.f_ope = self.f_ext - self.f_env
        self._r_handle = self.rot @ self._o_handle  # the handle from the tool tip [N, 3] (world)
        self.handle_pos = self.pos + self._r_handle
        return s

    def _tare(self, k: int | None, tau: torch.Tensor, ft: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
        """`sensors.tare_time`: sum the readings (τ_s [N, 7], F/T [N, 6] world, about its site) of arms still in their
        tare window, subtract the means from the sensors' offsets when the window ends, and read zero until then."""
        waiting = ~self._tared
        tau, ft = tau.numpy().copy(), ft.copy()
        if k is not None:  # a control period's sample (the reset's read-out carries no noise: not a sample)
            take = waiting & (self.t + k * self.dt < self.pcfg.sensors.tare_time)
            if take.any():
                rt = np.swapaxes(self.rot[take], 1, 2)  # world -> sensor frame
                f_s = np.concatenate([rt @ ft[take, :3, None], rt @ ft[take, 3:, None]], axis=1)[..., 0]
                self._tare_sum[take] += np.concatenate([tau[take], f_s], axis=1)
                self._tare_cnt[take] += 1
            done = waiting & ~take & (self._tare_cnt > 0)
            if done.any():
                mean = self._tare_sum[done] / self._tare_cnt[done, None]
                self._tau_bias[done] -= mean[:, :7]
                self._ft_bias[done] -= mean[:, 7:]  # sensor frame, as the bias
                tau[done] -= mean[:, :7]
                ft[done, :3] -= (self.rot[done] @ mean[:, 7:10, None])[..., 0]
                ft[done, 3:] -= (self.rot[done] @ mean[:, 10:, None])[..., 0]
                self._tared[done] = True
                waiting &= ~done
        tau[waiting], ft[waiting] = 0.0, 0.0
        return torch.from_numpy(tau), ft

    def _check_divergence(self, abs_qd: np.ndarray) -> np.ndarray:
        """Arms newly diverged: non-finite state, joint speed (`abs_qd` = |q̇| [N, 7], rad/s) > factor × limit, or a
        too deep contact."""
        p = self.pcfg
        finite = np.isfinite(self.q).all(1) & np.isfinite(self.qd).all(1)
        fast = (abs_qd > p.divergence_speed_factor * self._dq_max).any(1)
        pen = self.sim.max_penetration()
        np.maximum(self.max_penetration, pen, out=self.max_penetration)
        bad = (~finite | fast | (pen > p.divergence_penetration)) & ~(self.diverged | self.parked)
        if bad.any():
            self._log_diverged(np.where(bad, np.where(~finite, 1, np.where(fast, 2, 3)), 0))
        return bad

    def _native_checks(self, live: np.ndarray) -> np.ndarray:
        """`_check_divergence` and `_track_joint_limits` (arms `live` [N]) in C (envs/native/period.py): the arms
        newly diverged [N]."""
        codes = self._period.checks(self.q, self.qd, self.sim.max_penetration(), self.max_penetration,
                                    self.diverged | self.parked, live, self.joint_limit_excess,
                                    self.joint_limit_joint, self.joint_speed_ratio)
        if codes is None:
            return np.zeros(self.num_envs, dtype=bool)
        self._log_diverged(codes)
        return codes > 0

    def _log_diverged(self, codes: np.ndarray) -> None:
        """One warning per arm newly diverged saying why (`codes` [N]: envs.native.period.WHY's, 0 for the others)."""
        for i in np.flatnonzero(codes):
            reason = WHY[int(codes[i])] + (f" {1e3 * self.max_penetration[i]:.1f} mm" if codes[i] == 3 else "")
            logger.warning("panda env: robot %d diverged at t = %.3f s (%s); its episode ends", i, self.t[i], reason)

    def _track_joint_limits(self, live: np.ndarray, abs_qd: np.ndarray) -> None:
        """`joint_limit_excess` and `joint_speed_ratio` with this control period's joint positions and speeds
        (`abs_qd` = |q̇| [N, 7], rad/s; arms `live` [N] only: those in their episode)."""
        per_joint = np.maximum(self._q_lo - self.q, self.q - self._q_hi)
        # a diverging arm's NaN: the comparisons are False, the values before stay
        over = per_joint.max(1)
        new = (over > self.joint_limit_excess) & live
        fast = (abs_qd / self._dq_max).max(1)
        faster = (fast > self.joint_speed_ratio) & live
        if new.any():
            self.joint_limit_excess[new] = over[new]
            self.joint_limit_joint[new] = per_joint[new].argmax(1)
        if faster.any():
            self.joint_speed_ratio[faster] = fast[faster]

    def _episode_over(self) -> np.ndarray:
        """Arms [N] whose episode is over by its scene or its time (`max_episode_time`), divergence aside."""
        return self.scene.done | (self.t >= self.pcfg.max_episode_time - 1e-9)

    def _in_episode(self) -> np.ndarray:
        """Arms [N] whose episode is under way: not over (scene done, time up), not parked, not diverged. An arm
        left unparked after its episode (`a3cqp evaluate --no-park`) adds nothing to its episode's counts."""
        return ~self._episode_over() & ~self.parked & ~self.diverged

    def park(self, idx: np.ndarray) -> None:
        """Set aside arms `idx` whose episode is over while the batch runs on (until their reset): their collisions
        off (PandaSim.park: a peg left in its bore costs collision and solver time at every step), the controller
        leaves them out (h + g holds them still: `A3CQPController.step`'s `active`), MuJoCo lets them sleep, and
        no divergence checks (their motion no longer counts). The other arms compute the same numbers as without
        it, bit for bit."""
        idx = np.asarray(idx, dtype=np.intp).reshape(-1)
        if len(idx):
            self.sim.park(idx)
            self.parked[idx] = True

    def _end_diverged(self, bad: np.ndarray) -> None:
        """Flag the diverged arms and park them at home (their episode is over; the batch runs on)."""
        idx = np.flatnonzero(bad)
        self.diverged[idx] = True
        self.sim.reset(np.tile(np.array(PANDA_HOME), (len(idx), 1)), idx=idx.tolist())
        self.ctrl.reset(torch.tensor(np.tile(np.array(PANDA_HOME), (len(idx), 1))), idx=torch.as_tensor(idx))
        self.operator.reset(idx)
        self.scene.abort(idx)

    # ------------------------------------------------------------------ scene and outputs
    def _scene_input(self) -> SceneInput:
        # the scene's procedure and metrics read the true contact wrench: sensor noise and bias are the controller's
        # and the agents' problem, not the experimenter's (the same array when the sensors are ideal)
        return SceneInput(t=self.t, pos=self.pos, rot=self.rot, f_env=self.f_env_true, f_ope=self.f_ope, f_d=self.f_d,
                          handle_pos=self.handle_pos)

    def _update_scene(self) -> None:
        self.operator.update(self.t, self.handle_pos, self.rot)
        self.scene.update(self._scene_input())

    def local_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(e^L, f_env^L, f_ope^L) [N, 6] each: the pose error to the current reference and the observed wrenches
        (`observation_filter`) in L."""
        e = pose_error(self.scene.pos_d, self.scene.rot_d, self.pos, self.rot)
        fe, fo = self.observed_wrenches()
        return to_local(self.rot, e), to_local(self.rot, fe), to_local(self.rot, fo)

    def observed_wrenches(self) -> tuple[np.ndarray, np.ndarray]:
        """(f_env, f_ope) [N, 6] as the agents observe them (`observation_filter`: the period's mean or its last
        sample), N and N m in the arm frame."""
        if self.pcfg.observation_filter == "mean":
            return self.f_env_obs, self.f_ope_obs
        return self.f_env, self.f_ope

    def _observation(self, e: torch.Tensor, fe: torch.Tensor, fo: torch.Tensor) -> torch.Tensor:
        a, p = self.adapt, self.pcfg
        if not p.observe_f_env_pull:  # the surrogate's wall never pulls: a pull on an f_d axis reads as no wall
            fe = torch.where(torch.from_numpy(self._fd_mask) & (fe > 0.0), 0.0, fe)
        tr = observe(e[:, :3], fe[:, :3], fo[:, :3], a.e_max, a.f_env_max, a.f_ope_max, check=False)
        rt = observe(e[:, 3:], fe[:, 3:], fo[:, 3:], p.e_max_rot, p.f_env_max_rot, p.f_ope_max_rot, check=False)
        return torch.cat([tr, rt], dim=1)  # eq. 26 per axis [N, 6, 3]

    def _reward(self, e: torch.Tensor, fe: torch.Tensor, fo: torch.Tensor, fd: torch.Tensor) -> torch.Tensor:
        a, p, al = self.adapt, self.pcfg, self.rew.alpha
        tr = reward(e[:, :3], fe[:, :3], fo[:, :3], fd[:, :3], al, a.e_max, a.f_env_max, a.f_ope_max, a.f_d_max,
                    check=False)
        rt = reward(e[:, 3:], fe[:, 3:], fo[:, 3:], fd[:, 3:], al, p.e_max_rot, p.f_env_max_rot, p.f_ope_max_rot,
                    a.f_d_max, check=False)
        return torch.cat([tr, rt], dim=1)  # eq. 30 per axis [N, 6]

    def _output(self, done: np.ndarray, terminated: np.ndarray, reward: bool = False) -> TensorDictBase:
        e, fe, fo = (torch.from_numpy(x) for x in self.local_state())
        fd = torch.from_numpy(self.f_d.copy())
        n = self.num_envs
        done_t = torch.from_numpy(done.copy()).reshape(n, 1)
        term_t = torch.from_numpy(terminated.copy()).reshape(n, 1)
        data = {
            "observation": self._observation(e, fe, fo).to(torch.float32),
            "e_local": e, "f_env_local": fe, "f_ope_local": fo, "weights": torch.from_numpy(self.weights.copy()),
            "f_d": fd, "phase": torch.from_numpy(self.scene.phase.copy()), "time": torch.from_numpy(self.t.copy()),
            "diverged": torch.from_numpy(self.diverged.copy()),
            "done": done_t, "terminated": term_t, "truncated": done_t & ~term_t,
        }
        for k, v in self.scene.signals(self._scene_input()).items():
            data[k] = torch.from_numpy(np.asarray(v, dtype=np.float64))
        if reward:
            r = self._reward(e, fe, fo, fd)
            task = self.scene.reward_term()
            if task is not None:
                r = r + torch.from_numpy(task)[:, None]
            data["reward"] = r.to(torch.float32).unsqueeze(-1)
        return TensorDict(data, batch_size=self.batch_size, device=self.device)


def _softmax(x: np.ndarray) -> np.ndarray:
    z = np.exp(x - x.max(-1, keepdims=True))
    return z / z.sum(-1, keepdims=True)


def agent_done_flags(rollout: TensorDictBase) -> TensorDictBase:
    """Adds ("next", "agent_done") and ("next", "agent_terminated"): the arm's flags [..., N, 1] expanded to the six
    agents' reward shape [..., N, 6, 1], in place, for TorchRL's value estimators.

    PandaEnv keeps TorchRL's multi-agent layout (one done per arm, one reward per axis agent), so a GAE or TD(λ)
    estimator needs the arm's flag once per agent, as TorchRL's MAPPO tutorial expands it by hand; then
    `GAE(...).set_keys(done="agent_done", terminated="agent_terminated")`. PandaAxisAgents needs none of this.
    """
    shape = rollout.get(("next", "reward")).shape
    for key in ("done", "terminated"):
        rollout.set(("next", f"agent_{key}"), rollout.get(("next", key)).unsqueeze(-2).expand(shape))
    return rollout


class PandaAxisAgents(EnvBase):
    """PandaEnv seen as N·6 independent agents (batch_size=[N·6]): obs [N·6, 3], action [N·6, 4], reward [N·6, 1].

    The six per-axis agents of every arm share one policy (paper 000, section IV), so a learner that treats them as
    a batch of separate environments (algorithms.a2c through a TorchRL collector) trains that shared policy. An arm's
    episode ends for all six of its agents, and a reset names all six or none (TorchRL keeps the old observation of
    an agent a reset mask leaves out, which would then not be its arm's).
    """

    _has_dynamic_specs = False

    def __init__(self, num_envs: int, config: ExperimentConfig | None = None, seed: int | None = None,
                 **kwargs) -> None:
        inner = PandaEnv(num_envs, config, seed=seed, **kwargs)
        n = num_envs * 6
        super().__init__(device=inner.device, batch_size=torch.Size([n]))
        self.inner = inner
        self.num_arms = num_envs
        f32, dev = torch.float32, self.device
        self.observation_spec = Composite(observation=Bounded(0.0, 1.0, shape=(n, 3), dtype=f32, device=dev),
                                          shape=(n,))
        self.action_spec = Bounded(-1.0, 1.0, shape=(n, 4), dtype=f32, device=dev)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=f32, device=dev)
        flag = Categorical(2, shape=(n, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=(n,))

    def _flat(self, td: TensorDictBase, reward: bool) -> TensorDictBase:
        n = self.batch_size[0]
        out = {"observation": td["observation"].reshape(n, 3)}
        for k in ("done", "terminated", "truncated"):
            out[k] = td[k].repeat_interleave(6, dim=0)
        if reward:
            out["reward"] = td["reward"].reshape(n, 1)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        inner = None
        if mask is not None:
            per_arm = mask.reshape(self.num_arms, 6)
            arms = per_arm.any(-1, keepdim=True)
            if not bool((per_arm == arms).all()):
                part = torch.nonzero(arms[:, 0] & ~per_arm.all(-1)).flatten().tolist()
                raise ValueError(f"_reset names only some of the six agents of arm(s) {part}: an arm resets as a "
                                 "whole (name all six of its agents)")
            inner = TensorDict({"_reset": arms}, batch_size=self.inner.batch_size)
        return self._flat(self.inner._reset(inner), reward=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = action_of(tensordict, (self.batch_size[0], 4)).reshape(self.num_arms, 6, 4)
        return self._flat(self.inner._advance(action), reward=True)

    def _set_seed(self, seed: int | None) -> None:
        self.inner._set_seed(seed)


def axis_agents(cfg: ExperimentConfig, num_envs: int, seed: int) -> PandaAxisAgents:
    """`env: panda` for training (a3cqp_rl.config.ENV_FACTORIES): `num_envs` arms as num_envs × 6 agents, reset."""
    env = PandaAxisAgents(num_envs, cfg, seed=seed)
    env.reset()
    return env
