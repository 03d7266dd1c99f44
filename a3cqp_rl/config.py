"""Typed configuration: the papers' tables as dataclasses, loaded from YAML and validated.

Defaults equal Testa et al. 2025 (paper 000): Table I (controller), Table II (state bounds, rate
scales), Table III / eq. 30 (reward weights), Table IV (A2C), Table V (GA). A YAML file only lists
what it changes; unknown keys, wrong types and out-of-range values raise `ConfigError` naming the
file and the dotted key.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from a3cqp_rl.exceptions import ConfigError

__all__ = [
    "AdaptationConfig",
    "RewardConfig",
    "ControllerConfig",
    "A2CConfig",
    "GAConfig",
    "PointMassConfig",
    "ExperimentConfig",
    "load_config",
    "config_from_dict",
    "config_to_dict",
]


@dataclass
class AdaptationConfig:
    """Normalisation bounds (Table II) and integration rates of eq. 29."""

    e_max: float = 1.0
    """ē: position error bound used to normalise the observation [m]."""
    f_env_max: float = 30.0
    """f̄_env: environment contact force bound [N]."""
    f_ope_max: float = 15.0
    """f̄_ope: operator force bound [N]."""
    f_d_max: float = 20.0
    """f̄_d: upper bound of the desired contact force [N] (eq. 29d)."""
    sigma_w: float = 6.0
    """σw: weight-rate scale; also bounds the pre-softmax weights to ±σw/2 (eq. 29a-c)."""
    sigma_f: float = 10.0
    """σf: desired-force rate scale [N/s] (eq. 29d)."""
    dt: float = 0.01
    """Δt: agent period [s] (100 Hz)."""

    def _check(self, err: _Errors) -> None:
        for name in ("e_max", "f_env_max", "f_ope_max", "f_d_max", "sigma_w", "sigma_f", "dt"):
            err.positive(self, name)


@dataclass
class RewardConfig:
    """Eq. 30 reward weights (Table III)."""

    alpha: tuple[float, float, float, float] = (0.5, 20.0, 2.0, 1.0)
    """(α1 error, α2 operator force, α3 environment force, α4 desired force), all >= 0."""

    def _check(self, err: _Errors) -> None:
        if any(a < 0 for a in self.alpha):
            err.add("alpha", f"weights must be >= 0, got {self.alpha}")


@dataclass
class ControllerConfig:
    """QP controller parameters (Table I) and limits used on the Panda (section V-B)."""

    cp: float = 3.0
    """c_p: joint position feedback gain of q̈_pd (eq. 5)."""
    cv: float = 5.0
    """c_v: joint velocity feedback gain of q̈_pd (eq. 5)."""
    kp: float = 150.0
    """k_p: Cartesian translational stiffness of the IK task [1/s²] (eq. 11)."""
    k_theta: float = 20.0
    """k_θ: Cartesian rotational stiffness of the IK task [1/s²] (eq. 11)."""
    kq: float = 10.0
    """k_q: joint centering gain [1/s²] (eq. 23)."""
    lambda_d: float = 5.0
    """Λd: desired apparent mass of the admittance [kg] (eq. 18)."""
    c_d: float = 5.0
    """Cd: desired damping of the admittance [N s/m] (eq. 18)."""
    epsilon: float = 1e-4
    """ε: weight of the joint centering task (eq. 24)."""
    mu: float = 0.4
    """μ: friction coefficient of the friction-pyramid constraint."""
    force_limit: float = 20.0
    """Wrench box, forces [N] (section V-B)."""
    torque_limit: float = 5.0
    """Wrench box, torques [N m] (section V-B)."""
    rate_hz: float = 1000.0
    """Controller rate [Hz]."""

    def _check(self, err: _Errors) -> None:
        for f in dataclasses.fields(self):
            err.positive(self, f.name)


@dataclass
class A2CConfig:
    """Synchronous n-step A2C (eq. 31) with RMSProp (eq. 32); defaults = Table IV."""

    learning_rate: float = 4.25339846e-6
    """λη: RMSProp learning rate."""
    ent_coef: float = 3.371768978e-4
    """λβ: entropy bonus weight (eq. 31d)."""
    n_steps: int = 4
    """n: rollout length per environment between updates."""
    rms_eps: float = 3.938214948e-5
    """λε: RMSProp epsilon, inside the square root (eq. 32)."""
    max_grad_norm: float = 4.24498881
    """λζ: global gradient-norm clipping threshold."""
    gamma: float = 0.99
    """λγ: discount factor, in (0, 1]."""
    vf_coef: float = 0.5
    """λv: value loss weight (eq. 31c)."""
    gae_lambda: float = 1.0
    """GAE λ in [0, 1]: 1 = the paper's n-step returns; lower trades bias for variance (SB3's gae_lambda)."""
    rms_alpha: float = 0.99
    """λα: RMSProp decay factor."""
    rms_init: float = 0.0
    """Initial RMSProp accumulator g: 0 as torch.optim.RMSprop (SB3 default), 1 as TF/RMSpropTFLike."""
    num_envs: int = 4
    """Parallel environments (the paper's 4 agents)."""
    total_steps: int = 1_000_000
    """Agent steps in all environments together (the paper's 1e6)."""
    network: Literal["separate", "shared"] = "separate"
    """'separate': SB3-style policy and value MLPs; 'shared': one trunk, two heads (the paper)."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer sizes (tanh)."""
    critic: Literal["policy", "privileged"] = "policy"
    """Value-network input: 'policy' = the eq. 26 observation (the paper); 'privileged' = plus the
    simulator state the return depends on (task weights, f_d, signed e and forces, velocity, scenario),
    an asymmetric actor-critic; the policy's input is eq. 26's either way. Needs network 'separate'."""
    log_std_init: float = 0.0
    """Initial log standard deviation of the state-independent Gaussian policy."""
    bound_coef: float = 0.0
    """Weight of a penalty on policy means outside [-1, 1] (0 = off, the paper; rl_games' bounds_loss_coef)."""
    noise_hold: int = 1
    """Agent steps each exploration-noise draw is held (1 = white noise, SB3/paper; k > 1 like gSDE's sde_sample_freq)."""
    normalize_advantage: bool = False
    """Normalise advantages per batch (SB3 default: off)."""
    average_last: float = 0.0
    """Fraction in [0, 1) of the run, at its end, whose parameters policy.pt averages uniformly (stochastic weight
    averaging, Izmailov et al. 2018; for A2C, Nikishin et al. 2018). 0 = the last parameters (the paper). Training
    itself uses the raw parameters; the average only smooths the noise the last updates leave in the saved policy."""
    checkpoint_every: int = 5000
    """Updates between checkpoints."""
    log_every: int = 250
    """Updates between metric rows in metrics.csv."""
    region_checks: int = 20
    """Paper Fig. 5 region checks (a3cqp_rl.regions, ~20 ms each) written to metrics.csv over a run, on evenly
    spaced log rows and the last one (0 = none): shows when each region is learned, and whether it stays."""
    compile: bool = True
    """torch.compile the rollout and update steps (one-time cost of ~30-60 s, then several times faster)."""
    rollout: Literal["auto", "torchrl"] = "auto"
    """'auto': the env's fused fast path when it has one (PointMassEnv), else a TorchRL Collector; 'torchrl': always the Collector."""
    backend: Literal["auto", "torch", "native"] = "auto"
    """Fused path only: 'torch' = rollout + update as torch code (compiled with `compile`); 'native' = the same
    iteration in C (algorithms/native, PointMassEnv on the CPU; an error if unavailable); 'auto' = C for at most
    512 samples per update (n_steps × num_envs), where it is faster, else torch."""

    def _check(self, err: _Errors) -> None:
        for name in ("learning_rate", "rms_eps", "max_grad_norm", "n_steps", "num_envs", "total_steps",
                     "checkpoint_every", "log_every", "noise_hold"):
            err.positive(self, name)
        for name in ("ent_coef", "vf_coef", "rms_init", "bound_coef", "region_checks"):
            if getattr(self, name) < 0:
                err.add(name, f"must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.gamma <= 1.0:
            err.add("gamma", f"must be in (0, 1], got {self.gamma}")
        if not 0.0 <= self.gae_lambda <= 1.0:
            err.add("gae_lambda", f"must be in [0, 1], got {self.gae_lambda}")
        if not 0.0 <= self.average_last < 1.0:
            err.add("average_last", f"must be in [0, 1), got {self.average_last}")
        if not 0.0 <= self.rms_alpha < 1.0:
            err.add("rms_alpha", f"must be in [0, 1), got {self.rms_alpha}")
        if not self.hidden or any(h <= 0 for h in self.hidden):
            err.add("hidden", f"must be a non-empty list of positive sizes, got {self.hidden}")
        if self.critic == "privileged" and self.network != "separate":
            err.add("critic", "'privileged' needs network: separate (a shared trunk would pass the privileged state to the policy)")


@dataclass
class GAConfig:
    """pygad genetic algorithm over A2C hyper-parameters (Table V); fitness eq. 34."""

    num_generations: int = 50
    num_parents_mating: int = 4
    sol_per_pop: int = 8
    num_genes: int = 5
    parent_selection_type: str = "sss"
    """Steady-state selection."""
    keep_parents: int = 1
    crossover_type: str = "single_point"
    mutation_type: str = "random"
    mutation_percent_genes: float = 10.0

    def _check(self, err: _Errors) -> None:
        for name in ("num_generations", "num_parents_mating", "sol_per_pop", "num_genes"):
            err.positive(self, name)
        if self.num_parents_mating > self.sol_per_pop:
            err.add("num_parents_mating", "must be <= sol_per_pop")
        if not 0 < self.mutation_percent_genes <= 100:
            err.add("mutation_percent_genes", "must be in (0, 100]")


@dataclass
class PointMassConfig:
    """1-DoF point-mass surrogate (eq. 35) and its scenarios.

    Frame: x along the tool axis [m]; the wall, when present, lies on the +x side and the desired
    force f_d pushes towards +x. Each episode samples one scenario with the given probabilities:

    - ``free``: no wall, no operator; target at ±[target_min, target_max] from the start.
    - ``operator``: target near the start (±operator_target_range); the operator pushes with a
      piecewise-constant intent force of random sign and magnitude in [operator_force_min,
      f̄_ope], on for [on_min, on_max] s and off for [off_min, off_max] s. Like a human hand
      (a linear force-velocity law) the force the sensor measures drops as the mass moves along
      the push: f_ope = F·clip(1 − ẋ·sgn(F)/operator_v_hand, 0, 1), so yielding (admittance) pays.
    - ``wall``: a unilateral spring-damper wall at wall_distance in [wall_min, wall_max] from the
      start, the target wall_depth in [depth_min, depth_max] behind its surface (unreachable):
      pushing with the force-control task is what pays.
    - ``wall_operator``: both.

    Initial weights (pre-softmax) and f_d are sampled uniformly in their ranges when
    ``random_initial_weights`` so that training visits the whole action-state space.
    """

    mass: float = 10.0
    """Λ: point mass [kg] (eq. 35)."""
    kp: float = 150.0
    """K_p: IK stiffness per unit mass [1/s²]."""
    kv: float | None = None
    """K_v: IK damping per unit mass [1/s]; None means 2·√K_p (critically damped)."""
    lambda_d: float = 5.0
    """Λd: desired admittance mass [kg]."""
    c_d: float = 5.0
    """Cd: admittance damping [N s/m]."""
    physics_dt: float = 0.001
    """Integration step [s] (1 kHz, like the QP)."""
    substeps: int = 10
    """Physics steps per agent step (10 → agent at 100 Hz)."""
    episode_steps: int = 500
    """Agent steps per episode before truncation (500 = 5 s)."""
    scenario_probs: dict[str, float] = field(
        default_factory=lambda: {"free": 0.25, "operator": 0.25, "wall": 0.3, "wall_operator": 0.2}
    )
    """Probability of each scenario per reset; keys among free, operator, wall, wall_operator."""
    target_min: float = 0.02
    """free: smallest target distance [m]."""
    target_max: float = 0.5
    """free: largest target distance [m]."""
    operator_target_range: float = 0.02
    """operator: target within ± this of the start [m]."""
    operator_force_min: float = 3.0
    """operator: smallest push magnitude [N] (largest is f̄_ope)."""
    operator_v_hand: float = 0.3
    """operator: hand speed along the push at which the measured force vanishes [m/s]."""
    operator_grip: bool = False
    """operator: the hand holds on to the handle: a mass running ahead of the push faster than operator_v_hand is
    braked by it, f_ope = F·clip(1 − ẋ·sgn(F)/operator_v_hand, −1, 1) (down to −F at twice that speed). False: the
    hand lets go of a mass that runs away (the force stops at 0)."""
    operator_on_min: float = 0.5
    operator_on_max: float = 2.0
    """operator: push duration range [s]."""
    operator_off_min: float = 0.3
    operator_off_max: float = 2.0
    """operator: pause duration range [s]."""
    wall_min: float = 0.0
    wall_max: float = 0.1
    """wall: distance from the start to the wall surface [m]."""
    depth_min: float = 0.0
    depth_max: float = 0.01
    """wall: target depth behind the wall surface [m]."""
    wall_stiffness: float = 5000.0
    """wall: spring stiffness [N/m] (a stiff table, several kN/m)."""
    wall_damping: float = 50.0
    """wall: damping while in contact [N s/m]."""
    random_initial_weights: bool = True
    """Start each episode from random (w̌, f_d) instead of pure IK with f_d = 0."""
    random_initial_fraction: float = 1.0
    """With random_initial_weights: the fraction of episodes that start from random (w̌, f_d); the others start
    from pure IK with f_d = 0, as a deployed robot does (so the policy also learns to raise f_d from zero)."""
    operator_model: Literal["push", "drag", "hand"] = "push"
    """How the operator makes its force.
    'push': the piecewise-constant intent force F above, measured through the linear force-velocity law
    f_ope = F·clip(1 − ẋ·sgn(F)/operator_v_hand, 0, 1) (the paper's surrogate, and the default).
    'drag': the operator's hand moves with a half-sine speed profile over each push, u = u_peak·sin(π τ) (τ the
    fraction of the push done, u_peak = operator_v_hand·|F|/f̄_ope), so it starts and stops smoothly, and drags the
    mass through a viscous grip b = f̄_ope/operator_v_hand: f_ope = clip(b (u − ẋ), ±f̄_ope). A mass that keeps
    moving when the hand slows down is braked by the grip, so an undamped one (force control with f_d = 0) costs
    more than admittance.
    'hand': the operator grasps the mass and moves their hand from the grasp position by a displacement D along a
    minimum-jerk path of operator_move_time, through a spring-damper grip, f_ope = clip(k_h (s − x) + d_h (ṡ − ẋ),
    ±f̄_ope) with s the hand's position (an evaluation model training does not use; `envs.point_mass_eval`). The
    schedule then holds D [m] while holding (0: not holding), drawn as ±U(operator_goal_min, operator_goal_max) with
    the same on/off phases."""
    operator_hand_stiffness: float = 300.0
    """hand operator: grip stiffness k_h [N/m]."""
    operator_hand_damping: float = 30.0
    """hand operator: grip damping d_h [N s/m]."""
    operator_goal_min: float = 0.1
    operator_goal_max: float = 0.3
    """hand operator: range of the hand's displacement per grasp [m] (random sign)."""
    operator_move_time: float = 0.8
    """hand operator: duration of the minimum-jerk hand motion [s] (the hand then stays at its goal until letting go)."""

    SCENARIOS: typing.ClassVar[tuple[str, ...]] = ("free", "operator", "wall", "wall_operator")

    def _check(self, err: _Errors) -> None:
        for name in ("mass", "kp", "lambda_d", "c_d", "physics_dt", "substeps", "episode_steps",
                     "target_max", "operator_v_hand", "operator_on_max", "operator_off_max",
                     "wall_stiffness", "operator_move_time"):
            err.positive(self, name)
        if self.kv is not None and self.kv < 0:
            err.add("kv", f"must be >= 0 or null, got {self.kv}")
        for lo, hi in (("target_min", "target_max"), ("operator_on_min", "operator_on_max"),
                       ("operator_off_min", "operator_off_max"), ("wall_min", "wall_max"),
                       ("depth_min", "depth_max"), ("operator_goal_min", "operator_goal_max")):
            a, b = getattr(self, lo), getattr(self, hi)
            if a < 0 or a > b:
                err.add(lo, f"must satisfy 0 <= {lo} <= {hi}, got {a} > {b}" if a > b else f"must be >= 0, got {a}")
        if self.operator_model == "hand" and not self.operator_goal_min > 0:
            err.add("operator_goal_min", f"must be > 0 for the hand operator (a displacement of 0 means 'not holding'), "
                    f"got {self.operator_goal_min}")
        if not 0.0 <= self.random_initial_fraction <= 1.0:
            err.add("random_initial_fraction", f"must be in [0, 1], got {self.random_initial_fraction}")
        for name in ("operator_target_range", "operator_force_min", "wall_damping", "operator_hand_stiffness",
                     "operator_hand_damping"):
            if getattr(self, name) < 0:
                err.add(name, f"must be >= 0, got {getattr(self, name)}")
        unknown = set(self.scenario_probs) - set(self.SCENARIOS)
        if unknown:
            err.add("scenario_probs", f"unknown scenario(s) {sorted(unknown)}; choose from {list(self.SCENARIOS)}")
        probs = list(self.scenario_probs.values())
        if any(p < 0 for p in probs) or sum(probs) <= 0:
            err.add("scenario_probs", "probabilities must be >= 0 and not all zero")

    @property
    def kv_value(self) -> float:
        """K_v actually used [1/s]."""
        return 2.0 * math.sqrt(self.kp) if self.kv is None else self.kv


@dataclass
class ExperimentConfig:
    """One experiment: environment, adaptation law, reward, learner, GA and controller settings."""

    seed: int = 0
    """Random seed (torch, numpy, environments)."""
    env: str = "point_mass"
    """Environment name (``point_mass``)."""
    point_mass: PointMassConfig = field(default_factory=PointMassConfig)
    adaptation: AdaptationConfig = field(default_factory=AdaptationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    a2c: A2CConfig = field(default_factory=A2CConfig)
    ga: GAConfig = field(default_factory=GAConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)

    def _check(self, err: _Errors) -> None:
        if self.env not in ("point_mass",):
            err.add("env", f"unknown environment {self.env!r}; choose from ['point_mass']")
        if self.point_mass.episode_steps < self.a2c.n_steps:
            # fused rollouts draw one pending episode per env per iteration
            err.add("point_mass.episode_steps", f"must be >= a2c.n_steps ({self.a2c.n_steps}), got {self.point_mass.episode_steps}")


# --------------------------------------------------------------------------------------------
# Loading and validation


class _Errors:
    """Collects validation messages with their dotted key paths."""

    def __init__(self, prefix: str = "") -> None:
        self.prefix = prefix
        self.messages: list[str] = []

    def add(self, key: str, msg: str) -> None:
        self.messages.append(f"{self.prefix}{key}: {msg}")

    def positive(self, obj: Any, name: str) -> None:
        value = getattr(obj, name)
        if not (value > 0) or (isinstance(value, float) and not math.isfinite(value)):
            self.add(name, f"must be a finite number > 0, got {value}")


def _convert(tp: Any, value: Any, key: str, source: str) -> Any:
    """Convert a YAML value to the annotated type, or raise ConfigError naming the key."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(inner[0], value, key, source)
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{source}: {key}: must be one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {key}: expected a mapping, got {type(value).__name__}")
        return _build(tp, value, f"{key}.", source)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{source}: {key}: expected a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]", source) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{source}: {key}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, f"{key}[{i}]", source) for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {key}: expected a mapping, got {type(value).__name__}")
        return {str(k): _convert(args[1], v, f"{key}.{k}", source) for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)  # 1e6 is read by YAML as a float
            raise ConfigError(f"{source}: {key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str):
            # PyYAML (YAML 1.1) reads "1e-6" without a dot as a string: accept numeric strings.
            try:
                return float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{source}: {key}: unsupported type {tp}")  # pragma: no cover


def _build(cls: type, data: dict, prefix: str, source: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"{source}: unknown key(s) {', '.join(prefix + str(k) for k in unknown)}; "
            f"valid keys under {prefix.rstrip('.') or 'top level'}: {sorted(names)}"
        )
    kwargs = {k: _convert(hints[k], v, prefix + k, source) for k, v in data.items()}
    return cls(**kwargs)


def _validate(obj: Any, prefix: str, source: str) -> None:
    err = _Errors(prefix)
    obj._check(err)
    if err.messages:
        raise ConfigError(f"{source}: invalid value(s):\n  " + "\n  ".join(err.messages))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _validate(value, f"{prefix}{f.name}.", source)


def config_from_dict(data: dict | None, source: str = "<dict>") -> ExperimentConfig:
    """Build and validate an ExperimentConfig from a plain dict (as read from YAML)."""
    cfg = _build(ExperimentConfig, data or {}, "", source)
    _validate(cfg, "", source)
    return cfg


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> ExperimentConfig:
    """Load `path` (YAML, safe_load) over the paper defaults; `overrides` is a nested dict applied last."""
    data: dict = {}
    source = "<defaults>"
    if path is not None:
        path = Path(path)
        source = str(path)
        if not path.is_file():
            raise ConfigError(f"{source}: config file not found")
        try:
            loaded = yaml.safe_load(path.read_text())
        except yaml.YAMLError as exc:
            raise ConfigError(f"{source}: not valid YAML: {exc}") from None
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"{source}: top level must be a mapping, got {type(loaded).__name__}")
        data = loaded or {}
    if overrides:
        data = _merge(data, overrides)
    return config_from_dict(data, source)


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def config_to_dict(cfg: Any) -> dict:
    """Plain-YAML-serialisable dict of a config dataclass (tuples become lists)."""

    def plain(v: Any) -> Any:
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return {k: plain(v) for k, v in dataclasses.asdict(cfg).items()}
