"""Typed configuration: the papers' tables as dataclasses, loaded from YAML and validated.

Defaults equal Testa et al. 2025 (paper 000): Table I (controller), Table II (state bounds, rate
scales), Table III / eq. 30 (reward weights), Table IV (A2C), Table V (GA). A YAML file only lists
what it changes; unknown keys, wrong types and out-of-range values raise `ConfigError` naming the
file and the dotted key.
"""

from __future__ import annotations

import dataclasses
import difflib
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
    "GeneConfig",
    "NSGA2Config",
    "PandaTuningConfig",
    "FixedControllerConfig",
    "FIXED_TASKS",
    "PointMassConfig",
    "SensorConfig",
    "OperatorConfig",
    "PegInHoleConfig",
    "PolishingConfig",
    "GuidanceConfig",
    "PandaEnvConfig",
    "ExperimentConfig",
    "load_config",
    "read_config_file",
    "project_path",
    "config_from_dict",
    "config_to_dict",
    "ENV_FACTORIES",
    "estimate_memory_bytes",
    "check_memory",
    "check_fits",
]

ENV_FACTORIES: dict[str, str] = {
    "point_mass": "algorithms.make_env:point_mass",
    "panda": "envs.panda:axis_agents",
}
"""Registered env names -> "module:function" building a seeded TorchRL env from (cfg, num_envs, seed). `env:` also
accepts any gymnasium id (run through TorchRL's GymWrapper)."""


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
    lr_schedule: Literal["constant", "linear"] = "constant"
    """'constant' (the paper); 'linear': λη·(1 − fraction of the run done), SB3's linear schedule (TorchRL rollout)."""
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
    reward_scale: float = 1.0
    """Factor on the rewards the update learns from (TorchRL rollout; the logged returns stay unscaled): brings values
    of tasks with large returns (Pendulum: down to ~ −100 at γ 0.9) near the networks' initial output scale."""
    average_last: float = 0.0
    """Fraction in [0, 1) of the run, at its end, whose parameters policy.pt averages uniformly (stochastic weight
    averaging, Izmailov et al. 2018; for A2C, Nikishin et al. 2018). 0 = the last parameters (the paper). Training
    itself uses the raw parameters; the average only smooths the noise the last updates leave in the saved policy."""
    select_policy: Literal["last", "transfer", "panda"] = "last"
    """Which parameters policy.pt holds. "last": the run's last (or average_last's average). "transfer": of the
    parameters at the log rows in the run's last `select_last` fraction, those with the largest transfer margin
    (a3cqp_rl.transfer: raise IK in the Panda's free motion, yield to the operator's push). The point-mass policy
    swings there from one log row to the next, since the surrogate's return hardly depends on it, and a final
    policy that fails either check does not drive the Panda (docs/panda.md, "Keeping the parameters that
    transfer"). "panda": the `select_candidates` rows of that window with the largest margins are each run on
    `select_trials` peg-in-hole trials of the Panda after training (algorithms.panda_select); policy.pt holds the
    one that inserts the most pegs, then yields to the operator, then is the fastest. Training itself is unchanged:
    the same updates, the same random numbers."""
    select_last: float = 0.5
    """Fraction in (0, 1] of the run, at its end, whose log rows `select_policy` transfer or panda chooses among."""
    select_candidates: int = 4
    """`select_policy: panda`: how many of the window's parameters (the largest transfer margins) run on the Panda."""
    select_trials: int = 8
    """`select_policy: panda`: peg-in-hole trials per candidate (each ~2-3 s of CPU)."""
    select_seed: int = 1000
    """`select_policy: panda`: the trials' seed (`a3cqp evaluate --seed`); keep it off the seeds you report."""
    select_config: str = "configs/panda_peg_in_hole.yaml"
    """`select_policy: panda`: the Panda config those trials run under (`a3cqp evaluate --config`), relative to the
    working directory."""
    init_policy: str | None = None
    """Fine-tuning: a policy.pt (or checkpoint.pt, or run folder) whose parameters the run starts from instead of
    the random init: every tensor whose name and shape match (the actor, its log σ, the critic where its input has
    the same width); the rest keeps the init (e.g. a point-mass policy's privileged critic on the Panda env). None:
    from scratch. Resuming a run restores its own checkpoint instead."""
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
                     "checkpoint_every", "log_every", "noise_hold", "reward_scale"):
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
        if not 0.0 < self.select_last <= 1.0:
            err.add("select_last", f"must be in (0, 1], got {self.select_last}")
        if self.select_policy != "last" and self.average_last > 0:
            err.add("select_policy", f"{self.select_policy} keeps one row's parameters, average_last averages many: set "
                    "one of them (average_last: 0 or select_policy: last)")
        for name in ("select_candidates", "select_trials"):
            err.positive(self, name)
        if self.select_seed < 0:
            err.add("select_seed", f"must be >= 0, got {self.select_seed}")
        if not self.select_config.strip():
            err.add("select_config", "must name a Panda config file")
        if not 0.0 <= self.rms_alpha < 1.0:
            err.add("rms_alpha", f"must be in [0, 1), got {self.rms_alpha}")
        if not self.hidden or any(h <= 0 for h in self.hidden):
            err.add("hidden", f"must be a non-empty list of positive sizes, got {self.hidden}")
        if self.critic == "privileged" and self.network != "separate":
            err.add("critic", "'privileged' needs network: separate (a shared trunk would pass the privileged state to the policy)")
        if self.init_policy is not None and not self.init_policy.strip():
            err.add("init_policy", "must be a path to a policy.pt, a checkpoint.pt or a run folder, or null")
        if self.normalize_advantage and self.n_steps * self.num_envs < 2:
            err.add("normalize_advantage", "needs at least two samples per update (n_steps × num_envs): the standard "
                    "deviation of one advantage is undefined")


@dataclass
class GeneConfig:
    """One gene of a tuned genome: a value searched in [low, high] (pygad works on u in [0, 1] per gene)."""

    name: str = ""
    """What the gene sets. GA: an A2C field (`learning_rate`) or a dotted field of the experiment
    (`point_mass.operator_v_hand`); NSGA-II: a name the objective reads."""
    low: float = 0.0
    """Smallest value."""
    high: float = 1.0
    """Largest value."""
    scale: Literal["linear", "log"] = "linear"
    """'log': u maps to low·(high/low)^u (needs low > 0), so each decade gets the same share of the search."""
    type: Literal["float", "int", "level"] = "float"
    """'int': rounded to the nearest integer; 'level': a priority-level selector l = u in [0, 1] mapped as
    paper 002 eq. 4 (l ≤ 0.25 → level 1, ≤ 0.5 → 2, ≤ 0.75 → 3, else 0 = off; a3cqp_rl.control.hierarchy);
    low/high stay 0 and 1."""
    size: int = 1
    """Genes sharing this spec: a vector value name[0..size-1] (e.g. ZDT's 30 variables)."""

    def _check(self, err: _Errors) -> None:
        if not self.name or not all(part.isidentifier() for part in self.name.split(".")):
            err.add("name", f"must be a field name like learning_rate or point_mass.c_d, got {self.name!r}")
        if not (math.isfinite(self.low) and math.isfinite(self.high)) or not self.low < self.high:
            err.add("low", f"the range [{self.low}, {self.high}] is empty or not finite: need low < high")
        if self.scale == "log" and not self.low > 0:
            err.add("low", f"a log-scale gene needs low > 0, got {self.low}")
        if self.type == "level" and (self.low, self.high, self.scale) != (0.0, 1.0, "linear"):
            err.add("type", "a level selector spans [0, 1] linearly (paper 002 eq. 4): leave low, high and scale unset")
        if self.type == "int" and math.floor(self.high) < math.ceil(self.low):
            err.add("type", f"no integer lies in [{self.low}, {self.high}]")
        if self.size < 1:
            err.add("size", f"must be >= 1, got {self.size}")


def _table_iv_genes() -> tuple[GeneConfig, ...]:
    # The five Table IV entries with non-round values (λη, λβ, n, λε, λζ); the paper does not list its ranges.
    return (
        GeneConfig("learning_rate", 1e-6, 1e-2, "log"),
        GeneConfig("ent_coef", 1e-6, 1e-1, "log"),
        GeneConfig("n_steps", 1, 32, "log", "int"),
        GeneConfig("rms_eps", 1e-8, 1e-3, "log"),
        GeneConfig("max_grad_norm", 0.1, 10.0, "log"),
    )


@dataclass
class GAConfig:
    """pygad genetic algorithm over A2C hyper-parameters (section IV-C): settings of Table V, fitness eq. 34.

    pygad mutates max(1, ⌊10 % · genes⌋) genes per offspring (1 of 5 here), each replaced by a uniform draw in
    its range (uniform in the exponent for log genes).
    """

    num_generations: int = 50
    """Generations bred after the initial population (Table V: 50)."""
    num_parents_mating: int = 4
    """Solutions selected as parents (Table V: 4)."""
    sol_per_pop: int = 8
    """Population size (Table V: 8)."""
    parent_selection_type: Literal["sss", "rws", "sus", "rank", "random", "tournament"] = "sss"
    """pygad parent selection; 'sss' = steady-state (Table V)."""
    keep_parents: int = 1
    """Parents carried into the next population (Table V: 1; -1 = all)."""
    keep_elitism: int = 0
    """Best solutions carried over; pygad's default of 1 would override keep_parents, so Table V needs 0."""
    crossover_type: Literal["single_point", "two_points", "uniform", "scattered"] = "single_point"
    """pygad crossover (Table V: single point)."""
    mutation_type: Literal["random", "swap", "inversion", "scramble"] = "random"
    """pygad mutation (Table V: random)."""
    mutation_percent_genes: float = 10.0
    """Percentage of genes mutated per offspring (Table V: 10)."""
    genes: tuple[GeneConfig, ...] = field(default_factory=_table_iv_genes)
    """The genome (default: λη, λβ, n, λε, λζ of Table IV)."""
    fitness: str = "episode_reward"
    """'episode_reward': eq. 34, the mean return of the last `fitness_episodes` training episodes; 'behaviour': the
    mean return of the trained policy on the closed-loop evaluation scenarios (envs/point_mass_eval.py)."""
    fitness_episodes: int = 100
    """N of eq. 34 (100 = the window of SB3's ep_rew_mean, the paper's library)."""
    steps_per_trial: int = 1_000_000
    """Agent steps of each trial training (the paper's 1e6)."""
    trials: int = 1
    """Trainings per genome, with seeds seed, seed+1, ...; the fitness is their mean."""

    @property
    def num_genes(self) -> int:
        """Genes in the genome (Table V: 5)."""
        return sum(g.size for g in self.genes)

    def _check(self, err: _Errors) -> None:
        for name in ("num_generations", "num_parents_mating", "sol_per_pop", "fitness_episodes", "steps_per_trial",
                     "trials"):
            err.positive(self, name)
        if self.num_parents_mating > self.sol_per_pop:
            err.add("num_parents_mating", "must be <= sol_per_pop")
        if not -1 <= self.keep_parents <= self.num_parents_mating:
            err.add("keep_parents", f"must be in [-1, num_parents_mating], got {self.keep_parents}")
        if not 0 <= self.keep_elitism < self.sol_per_pop:
            err.add("keep_elitism", f"must be in [0, sol_per_pop), got {self.keep_elitism}")
        if not 0 < self.mutation_percent_genes <= 100:
            err.add("mutation_percent_genes", "must be in (0, 100]")
        if not self.genes:
            err.add("genes", "at least one gene is needed")
        names = [g.name for g in self.genes]
        for dup in sorted({n for n in names if names.count(n) > 1}):
            err.add("genes", f"{dup!r} appears more than once")
        for i, gene in enumerate(self.genes):
            sub = _Errors(f"{err.prefix}genes[{i}].")
            gene._check(sub)
            if not sub.messages:
                _check_experiment_gene(gene, sub)
            err.messages += sub.messages


def _check_experiment_gene(gene: GeneConfig, err: _Errors) -> None:
    """A GA gene must name a numeric experiment field whose checks accept both ends of the range."""
    section, _, name = gene.name.rpartition(".")
    section = section or "a2c"
    section_cls = typing.get_type_hints(ExperimentConfig).get(section)
    if "." in section or section_cls is None or not dataclasses.is_dataclass(section_cls):
        err.add("name", f"unknown config section {section!r} in {gene.name!r}; use an A2C field or e.g. point_mass.c_d")
        return
    hints = typing.get_type_hints(section_cls)
    if name not in hints:
        err.add("name", f"unknown {section} field {name!r}; valid: {sorted(hints)}")
        return
    field_type = hints[name]
    if field_type is int and gene.type != "int":
        err.add("type", f"{section}.{name} is an integer: set type: int")
    elif field_type is float and gene.type != "float":
        err.add("type", f"{section}.{name} is a real number: set type: float")
    elif field_type not in (int, float):
        err.add("name", f"{section}.{name} is not a number ({field_type}) and cannot be a gene")
        return
    if gene.size != 1:
        err.add("size", f"{section}.{name} is a single number: size must be 1")
        return
    for end in ("low", "high"):
        value = getattr(gene, end)
        obj = section_cls(**{name: int(round(value)) if field_type is int else value})
        sub = _Errors()
        obj._check(sub)
        problems = [m for m in sub.messages if m.startswith(f"{name}:")]
        if problems:
            err.add(end, f"{value} is not a valid {section}.{name} ({problems[0]})")


@dataclass
class PandaTuningConfig:
    """The Panda objective of NSGA-II (algorithms/tuning/panda_objectives.py, paper 002 eq. 5-6 on the Panda scenes).

    Every genome (a fixed controller: FixedControllerConfig) runs `trials` trials of each scene; trial k of a scene is
    the same for every genome (seeded from `trial_seed`): the misalignment, the operator's tremor, the sensor noise
    and bias of `panda.sensors`, and a factor on the operator's stiffness, damping and force bound drawn uniformly in
    `operator_force_scale`. The three objectives, all minimised, are means over the trials:
    tracking [cm] (pose error where the scene expects IK to lead, orientation as arc length at `lever`),
    interaction [N] (|f_ope| while the operator acts + contact-force error while the peg touches the block),
    failure (failed insertion + lost episode fraction + fallback, torque-saturation and joint-limit fractions).
    """

    scenes: tuple[str, ...] = ("peg_in_hole",)
    """Scenes each genome runs (envs/scenarios.py): peg_in_hole, guidance, polishing."""
    trials: int = 2
    """Trials per scene and genome."""
    trial_seed: int = 1000
    """Seed of the trials (a different stream than `a3cqp evaluate --seed 0`: tuned on other trials than tested)."""
    operator_force_scale: tuple[float, ...] = (0.7, 1.3)
    """Range of the per-trial factor on the operator's stiffness, damping and force bound (robustness)."""
    contact_force: float = 10.0
    """Pressing force along the tool axis the interaction objective asks for while the peg touches the block [N]
    (the scripted force-control baseline's f_d)."""
    lever: float = 0.1
    """Orientation errors count as the arc length at this radius in the tracking objective [m] (paper 002: cm)."""
    failure_tracking: float = 50.0
    """α_F1 of eq. 6: tracking [cm] charged for the rest of the horizon after a robot diverged."""
    failure_interaction: float = 50.0
    """α_F2 of eq. 6: interaction [N] charged for the rest of the horizon after a robot diverged."""
    joint_limit_margin: float = 0.01
    """A joint within this distance of its datasheet limit counts as at the limit [rad]."""
    batch: Literal["population", "per_genome"] = "population"
    """"population": the genomes of an evaluation task share one simulation per scene (PopulationController);
    "per_genome": one simulation per genome (the slower reference of the benchmark)."""

    def _check(self, err: _Errors) -> None:
        known = ("peg_in_hole", "guidance", "polishing")
        bad = [s for s in self.scenes if s not in known]
        if not self.scenes or bad or len(set(self.scenes)) != len(self.scenes):
            err.add("scenes", f"must be distinct names among {list(known)}, got {list(self.scenes)}")
        for name in ("trials", "contact_force", "lever", "failure_tracking", "failure_interaction"):
            err.positive(self, name)
        if self.joint_limit_margin < 0:
            err.add("joint_limit_margin", f"must be >= 0, got {self.joint_limit_margin}")
        if len(self.operator_force_scale) != 2 or not 0 < self.operator_force_scale[0] <= self.operator_force_scale[1]:
            err.add("operator_force_scale", f"must be a range 0 < low <= high, got {list(self.operator_force_scale)}")


@dataclass
class NSGA2Config:
    """Multi-objective tuning with NSGA-II on pygad (Penco et al., paper 002): soft weights, levels, gains.

    pygad holds 2·population solutions: the `population` survivors of the last generation and as many offspring;
    each generation keeps the best `population` of both by Pareto rank and crowding distance (NSGA-II's elitism),
    mates them at random (SBX) and mutates the offspring (polynomial mutation).
    """

    objective: str = "zdt1"
    """Registered objective (algorithms.tuning.objectives): a function from a batch of genomes to objective vectors,
    all minimised."""
    population: int = 100
    """Survivors per generation (paper 002: 100)."""
    generations: int = 300
    """Generations bred after the initial population (paper 002: 300)."""
    genes: tuple[GeneConfig, ...] = ()
    """The genome; empty = the objective's own genes."""
    parent_selection_type: Literal["nsga2", "tournament_nsga2"] = "nsga2"
    """'nsga2': the survivors (rank, then crowding distance) are the parents; 'tournament_nsga2': binary
    tournaments on rank and crowding distance."""
    crossover_probability: float = 0.9
    """Probability that a mating pair is crossed (SBX); otherwise the children copy the parents."""
    sbx_eta: float = 15.0
    """SBX distribution index (larger = children nearer their parents)."""
    mutation_probability: float | None = None
    """Probability per gene of a polynomial mutation; None = 1 / genes."""
    polynomial_eta: float = 20.0
    """Polynomial-mutation distribution index."""
    chunk_size: int | None = None
    """Genomes per evaluation task (a worker evaluates one task at a time); None = the objective's choice. A fixed
    size keeps each task's batch the same whatever the number of workers."""
    panda: PandaTuningConfig = field(default_factory=PandaTuningConfig)
    """Settings of the Panda objective (ignored by the others)."""

    def _check(self, err: _Errors) -> None:
        for name in ("population", "generations", "sbx_eta", "polynomial_eta"):
            err.positive(self, name)
        if self.population < 2:
            err.add("population", f"must be >= 2, got {self.population}")
        if not 0.0 <= self.crossover_probability <= 1.0:
            err.add("crossover_probability", f"must be in [0, 1], got {self.crossover_probability}")
        if self.mutation_probability is not None and not 0.0 <= self.mutation_probability <= 1.0:
            err.add("mutation_probability", f"must be in [0, 1] or null, got {self.mutation_probability}")
        if self.chunk_size is not None and self.chunk_size < 1:
            err.add("chunk_size", f"must be >= 1 or null, got {self.chunk_size}")
        names = [g.name for g in self.genes]
        for dup in sorted({n for n in names if names.count(n) > 1}):
            err.add("genes", f"{dup!r} appears more than once")
        for i, gene in enumerate(self.genes):
            sub = _Errors(f"{err.prefix}genes[{i}].")
            gene._check(sub)
            err.messages += sub.messages


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
    target_speed_max: float = 0.0
    """free: the target moves at a constant speed drawn per episode in ±target_speed_max [m/s] (a reference to
    follow, as the Panda's IK phases follow moving ones), and IK's damping acts on ė = ẋ_d − ẋ. 0 (the default, the
    paper's surrogate): a fixed target. Torch env only (the C point mass refuses it)."""
    disturbance_max: float = 0.0
    """free: a constant force on the mass drawn per episode in ±disturbance_max [N] that no sensor measures (neither
    f_env nor f_ope: the Panda's model errors and moving references leave a tracking error that IK has to hold
    against), so lowering IK's weight at a small error lets the mass drift. 0 (the default, the paper's surrogate):
    none. Torch env only (the C point mass refuses it)."""
    idle_force: Literal["free", "damps"] = "free"
    """What the share of force control that does not push, w3 (1 − min(1, f_d / 1 N)), does. 'free' (the default):
    eq. 35, nothing. 'damps': what the Panda env's `panda.idle_force: damps` makes of it, IK's damping with weight
    w1 + share and force control's weight w3 − share, IK's stiffness unchanged. Torch env only."""
    operator_target_range: float = 0.02
    """operator: target within ± this of the start [m]."""
    operator_force_min: float = 3.0
    """operator: smallest push magnitude [N] (largest is f̄_ope)."""
    operator_toward_wall: float = 0.5
    """operator: probability that a push (hand operator: a move) points to +x, the side the wall and f_d are on. 0.5
    (the default): either way alike. Lower: the operator more often pulls the tool off the surface than onto it, as
    in the disengagements of Fig. 7, so force control under the operator's force costs more often than it helps
    (measured at 0.25: more runs yield, fewer insert; docs/panda.md, "Two more surrogates"). Torch env only (the C
    point mass refuses it)."""
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
        if not (self.target_speed_max >= 0.0 and math.isfinite(self.target_speed_max)):
            err.add("target_speed_max", f"must be a finite speed >= 0 [m/s], got {self.target_speed_max}")
        if not (self.disturbance_max >= 0.0 and math.isfinite(self.disturbance_max)):
            err.add("disturbance_max", f"must be a finite force >= 0 [N], got {self.disturbance_max}")
        if not 0.0 <= self.operator_toward_wall <= 1.0:
            err.add("operator_toward_wall", f"must be a probability in [0, 1], got {self.operator_toward_wall}")
        if self.idle_force not in ("free", "damps"):
            err.add("idle_force", f"must be 'free' or 'damps', got {self.idle_force!r}")
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
class SensorConfig:
    """Force sensing on the simulated Panda (section V-A): F/T sensor and joint torque sensors; all off by default.

    Noise is white Gaussian per 1 kHz sample and component; a bias is drawn once per episode (Gaussian, the given
    standard deviation) and stays constant, in the sensor frame for the F/T sensor and per joint for the torques.
    """

    ft_force_noise: float = 0.0
    """F/T force noise standard deviation [N]."""
    ft_torque_noise: float = 0.0
    """F/T torque noise standard deviation [N m]."""
    ft_force_bias: float = 0.0
    """Standard deviation of the per-episode F/T force bias [N]."""
    ft_torque_bias: float = 0.0
    """Standard deviation of the per-episode F/T torque bias [N m]."""
    joint_torque_noise: float = 0.0
    """Joint torque sensor noise standard deviation [N m] (enters f_ext = J^T† τ_s)."""
    joint_torque_bias: float = 0.0
    """Standard deviation of the per-episode joint torque bias [N m]."""
    tare_time: float = 0.0
    """Taring, as done before a task on a real robot [s]: over the first `tare_time` s of each episode, while the arm
    rests at home, the F/T sensor's and the joint torque sensors' readings (bias and noise included) are averaged,
    and the means are subtracted from then on; until then the sensed wrenches read zero (nothing is fed to the
    controller or the agents before the sensors are zeroed). 0: no taring. Must not exceed the scene's rest at home
    (peg-in-hole `settle_time`, polishing `rest_time`, guidance `pause`)."""

    @property
    def ideal(self) -> bool:
        """No noise, bias or taring: the simulator's wrenches are what is sensed."""
        return all(getattr(self, f.name) == 0 for f in dataclasses.fields(self))

    def _check(self, err: _Errors) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (v >= 0 and math.isfinite(v)):
                err.add(f.name, f"must be a finite number >= 0, got {v}")


@dataclass
class OperatorConfig:
    """Simulated operator: a bounded, delayed, noisy 6-D spring-damper hand holding the handle above the F/T sensor.

    On a grasp the hand's attractor moves from the handle's position to the intent's goal at `speed`, the force
    f = K (x_hand − x) − D ẋ (x, ẋ of the handle as seen `delay` s ago) − D_i ẋ(now) fades in over `grip_time`, is
    clipped to `max_force`, and the hand keeps the grasp orientation with a rotational spring-damper (clipped to
    `max_torque`).
    The hand releases (force fades out) `hold_time` after the handle reached the goal, or at `timeout`.
    """

    stiffness: float = 200.0
    """Hand translational stiffness K [N/m]."""
    damping: float = 60.0
    """Hand translational damping D [N s/m] (with the 0.1 s delay, K = 300 / D = 30 sets the admittance of Table I
    oscillating; a human arm holding a handle is well damped)."""
    max_force: float = 15.0
    """Bound on |f_ope| [N] (Table II's f̄_ope)."""
    rot_stiffness: float = 3.0
    """Hand rotational stiffness [N m/rad] (the grip keeps the tool's orientation)."""
    rot_damping: float = 0.3
    """Hand rotational damping [N m s/rad]."""
    max_torque: float = 1.0
    """Bound on the hand's torque [N m]."""
    delay: float = 0.1
    """Reaction delay of the hand [s] (it acts on the handle state this long ago)."""
    intrinsic_damping: float = 0.0
    """Hand translational damping D_i [N s/m] on the handle's present velocity, without the delay: the arm's
    muscles resist motion before any reaction does. 0 (default): the whole hand is delayed, and near a goal or as a
    peg comes free it can swing with the admittance at ~1-3 Hz (docs/panda.md, "The operator's swing")."""
    noise: float = 0.2
    """Standard deviation of the hand's force tremor [N] (white, 1 kHz; 0 = none)."""
    speed: float = 0.1
    """Speed of the hand's attractor toward the goal [m/s]."""
    grip_time: float = 0.2
    """Force fade-in on grasp and fade-out on release [s]."""
    hold_time: float = 0.5
    """Time the hand stays at the goal before releasing [s]."""
    goal_tolerance: float = 0.01
    """Distance of the handle to the goal counted as reached [m]."""
    timeout: float = 8.0
    """The hand releases this long after grasping even if the goal was not reached [s]."""
    release_speed: float = 0.0
    """The hand lets go at a reached goal only once the handle moves slower than this [m/s] (as a person lets go of
    an arm that has come to rest; the timeout still releases). 0 (default): `hold_time` after the goal was reached,
    whatever the handle's speed."""

    def _check(self, err: _Errors) -> None:
        for name in ("stiffness", "max_force", "speed", "grip_time", "goal_tolerance", "timeout"):
            err.positive(self, name)
        for name in ("damping", "intrinsic_damping", "rot_stiffness", "rot_damping", "max_torque", "delay", "noise",
                     "hold_time", "release_speed"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                err.add(name, f"must be a finite number >= 0, got {v}")


PEG_DIAMETER = 0.020
"""Diameter of the peg tool [m] (a3cqp_rl/robot/assets/tool_peg.xml): a hole must be wider to take it."""
HOLE_DIAMETER_MAX = 0.1
"""Widest bore the peg block holds [m]: twice its ring's outer apothem (a3cqp_rl.robot.scenes.HoleGeometry)."""


@dataclass
class PegInHoleConfig:
    """Peg-in-hole scene and procedure (paper 000, section VI-B1, Table VI, Fig. 7); lengths in m, times in s.

    Procedure per cycle: home -> approach pose above the hole, offset by the trial's misalignment (translation in a
    random horizontal direction, tilt about a random horizontal axis) and reached within `approach_tolerance` ->
    the reference moves to the contact pose (on the hole axis, aligned, tip at the rim): z over `descent_time`,
    x-y and orientation over `align_time` (both minimum-jerk), so the peg meets the rim misaligned -> first contact
    (|f_env| > `contact_force`) -> insertion: the reference then goes on down at `insert_speed` to `insert_depth`
    below the rim (the inserted pose); success when the peg tip is `success_depth` below the rim, inside the bore,
    within `time_limit` of the first contact. Insertion time = first contact to success. Then the operator
    disengages the peg (pulls the handle `disengage_lift` up; the reference stays, as in Fig. 7; a peg not inserted
    within the time limit only with cycles > 1 or `disengage_failed`) and, if cycles remain, the reference returns
    home over `return_time` and the next cycle starts (with `restart_needs_extraction`, only if the peg has left the
    bore by then).
    """

    hole_center: tuple[float, ...] = (0.45, 0.0)
    """Hole axis (x, y) in the arm's base frame [m] (the "known table position")."""
    hole_top: float = 0.30
    """Height of the rim [m]."""
    hole_diameter: float = 0.0205
    """Hole diameter [m] (paper: Ø 20.5 mm; the peg tool is Ø 20.0 mm)."""
    hole_depth: float = 0.04
    """Bore depth [m]."""
    hole_segments: int = 32
    """Boxes forming the bore (a3cqp_rl.robot.scenes.HoleGeometry)."""
    friction: float = 0.3
    """Sliding friction of the block."""
    misalign_translation: tuple[float, ...] = (0.0123, 0.00424)
    """Mean and standard deviation of the approach pose's horizontal offset from the hole axis [m] (Table VI)."""
    misalign_rotation_deg: tuple[float, ...] = (3.66, 0.45)
    """Mean and standard deviation of the approach pose's tilt [deg] (Table VI)."""
    approach_height: float = 0.03
    """Peg tip above the rim at the approach pose [m]."""
    settle_time: float = 0.5
    """Time at home before the approach [s]."""
    approach_time: float = 2.0
    """Minimum-jerk time from home to the approach pose [s]."""
    approach_tolerance: float = 0.003
    """Position error [m] below which the approach pose counts as reached (lenient: the pose is misaligned anyway)."""
    descent_time: float = 1.0
    """Minimum-jerk time of the reference's descent to the contact pose [s]."""
    align_time: float = 8.0
    """Minimum-jerk time of the reference's horizontal and angular alignment with the hole [s]."""
    insert_speed: float = 0.004
    """Speed of the reference's descent below the rim after the contact pose [m/s] (a slow ramp: the force an IK
    reference behind the rim builds is what the agents feel as the first contact)."""
    insert_depth: float = 0.025
    """Depth of the inserted pose's tip below the rim, where the reference's descent stops [m]."""
    contact_force: float = 1.0
    """Sensed |f_env| [N] that counts as the first contact."""
    success_depth: float = 0.02
    """Peg tip depth below the rim that counts as inserted [m]."""
    time_limit: float = 15.0
    """Time from the first contact within which the insertion must succeed [s]."""
    cycles: int = 1
    """Insertions per episode (Fig. 7 shows three)."""
    operator_disengage: bool = True
    """After each insertion the operator pulls the peg out at the handle (else the reference alone returns home)."""
    disengage_failed: bool = False
    """Cycles = 1: the operator also pulls at a peg not inserted within `time_limit` (else that trial ends at its
    time limit: its metrics are final, and no next approach needs the block cleared). With cycles > 1 a failed
    insertion is always disengaged. (On: an arm that does not yield, as IK only, holds the hand until its
    `operator.timeout`, 8 s of a five-controller evaluation's tail.)"""
    disengage_lift: float = 0.12
    """How far up the operator pulls the handle [m]."""
    return_time: float = 2.0
    """Minimum-jerk time of the reference back home between cycles [s]."""
    time_cost: float = 0.0
    """Reward added to every axis of L per agent period while an insertion is under way (from the first contact to
    success or the time limit): −time_cost. Eq. 30 has no term for the insertion time, and its +α3|f_env| favours
    pressing on the rim over sliding down the bore; a minimum-time term for training on the Panda (0: eq. 30 alone)."""
    restart_needs_extraction: bool = True
    """Cycles > 1: the next cycle starts only if the peg left the bore (tip above the rim) during the disengagement or
    the return; a peg still jammed ends the episode, its remaining insertions not made. (Without it the next approach
    drags a jammed peg across the block: 70-155 N on the F/T sensor, a joint 13-14 mrad into MuJoCo's default soft
    end stop; docs/panda.md, "Three insertions per episode".)"""

    def _check(self, err: _Errors) -> None:
        for name in ("hole_top", "hole_diameter", "hole_depth", "approach_height", "approach_time",
                     "approach_tolerance", "descent_time", "align_time", "contact_force", "success_depth",
                     "time_limit", "cycles", "return_time", "disengage_lift", "insert_speed", "insert_depth"):
            err.positive(self, name)
        if not PEG_DIAMETER < self.hole_diameter < HOLE_DIAMETER_MAX:
            err.add("hole_diameter", f"must be between the peg's diameter ({PEG_DIAMETER} m) and the block's ring "
                                     f"({HOLE_DIAMETER_MAX} m), exclusive, got {self.hole_diameter}")
        if self.insert_depth >= self.hole_depth:
            err.add("insert_depth", f"must be < hole_depth ({self.hole_depth}), got {self.insert_depth}")
        if self.insert_depth <= self.success_depth:  # a reference that stops short leaves IK nothing to push with
            err.add("insert_depth", f"must be > success_depth ({self.success_depth}), got {self.insert_depth}")
        for name in ("friction", "settle_time", "time_cost"):
            if getattr(self, name) < 0:
                err.add(name, f"must be >= 0, got {getattr(self, name)}")
        if self.hole_segments < 8:
            err.add("hole_segments", f"must be >= 8, got {self.hole_segments}")
        if self.success_depth >= self.hole_depth:
            err.add("success_depth", f"must be < hole_depth ({self.hole_depth}), got {self.success_depth}")
        for name in ("hole_center", "misalign_translation", "misalign_rotation_deg"):
            if len(getattr(self, name)) != 2:
                err.add(name, f"needs 2 values, got {len(getattr(self, name))}")
        for name in ("misalign_translation", "misalign_rotation_deg"):
            if any(v < 0 for v in getattr(self, name)):
                err.add(name, f"mean and standard deviation must be >= 0, got {getattr(self, name)}")


@dataclass
class PolishingConfig:
    """Polishing scene and procedure (paper 000, section VI-B2, Fig. 8); lengths in m, times in s.

    A disc tool on a plate: rest -> down to the polishing pose (`preload` below the plate's top) -> the x-y
    reference traces a circle of `circle_radius` for `polish_time` -> the operator relocates the working zone
    (grasps the handle, lifts by `lift` and moves by the next offset of `relocations`; while grasped the reference
    follows the tool, as in Fig. 8) -> released, the robot holds the taught pose for `hold_time` -> back down at the
    new place; one polishing period per relocation.
    """

    plate_center: tuple[float, ...] = (0.45, 0.0)
    """Plate centre (x, y) [m]."""
    plate_top: float = 0.25
    """Height of the plate's top face [m]."""
    plate_half_size: tuple[float, ...] = (0.2, 0.3)
    """Plate half sides (x, y) [m]."""
    friction: float = 0.3
    """Sliding friction of the plate."""
    friction_solref: tuple[float, ...] = (0.3, 1.0)
    """MuJoCo solreffriction (time constant [s], damping ratio) of the disc-plate contact's frictional rows (elliptic
    cone; the normal keeps the plate's 4 ms). With the normal's solref also on friction, the sliding disc hopped on
    the plate (contact in 18-34 % of the samples, 0-100 N spikes): docs/panda.md, "Why the plate's friction has its
    own solref"."""
    start_offset: tuple[float, ...] = (0.0, 0.0)
    """First working zone relative to the plate centre (x, y) [m]."""
    relocations: tuple[tuple[float, float], ...] = ((0.0, -0.12), (0.0, 0.24), (0.0, -0.12))
    """Operator moves of the working zone (dx, dy) [m], one after each polishing period."""
    circle_radius: float = 0.03
    """Radius of the circular x-y reference [m]."""
    circle_period: float = 4.0
    """Period of one circle [s]."""
    preload: float = 0.005
    """Polishing pose: disc this far below the plate's top [m]."""
    rest_time: float = 1.0
    """Time at rest before the first approach [s]."""
    approach_time: float = 2.0
    """Minimum-jerk time down to the polishing pose [s]."""
    polish_time: float = 10.0
    """Time on each zone after the approach [s]."""
    lift: float = 0.06
    """How far the operator lifts the tool while relocating [m]."""
    hold_time: float = 1.5
    """Time the robot holds the taught pose after the operator releases [s]."""
    contact_force: float = 1.0
    """Sensed |f_env| [N] that counts as contact."""
    plate_top_spread: float = 0.002
    """Per trial, the plate's top is this standard deviation [m] (clipped at two) off `plate_top`, which is all the
    procedure's reference knows: what force control is for (0: every trial at `plate_top`)."""
    zone_spread: float = 0.03
    """Per trial, the first working zone is drawn uniformly in a disc of this radius [m] about `start_offset`."""
    relocation_turn_deg: float = 45.0
    """Per trial, the operator's moves (`relocations`) are turned about the vertical by an angle drawn uniformly
    within ± this [deg]."""

    def _check(self, err: _Errors) -> None:
        for name in ("plate_top", "circle_radius", "circle_period", "approach_time", "polish_time", "contact_force"):
            err.positive(self, name)
        for name in ("preload", "rest_time", "lift", "hold_time", "friction", "plate_top_spread", "zone_spread",
                     "relocation_turn_deg"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                err.add(name, f"must be a finite number >= 0, got {v}")
        for name in ("plate_center", "plate_half_size", "start_offset"):
            if len(getattr(self, name)) != 2:
                err.add(name, f"needs 2 values (x, y), got {len(getattr(self, name))}")
        if any(h <= 0 for h in self.plate_half_size):
            err.add("plate_half_size", f"must be > 0, got {self.plate_half_size}")
        if not self.relocations:
            err.add("relocations", "needs at least one (dx, dy)")
        if len(self.friction_solref) != 2 or not all(v > 0 for v in self.friction_solref):
            err.add("friction_solref", f"needs (time constant [s], damping ratio), both > 0, "
                                       f"got {self.friction_solref}")


@dataclass
class GuidanceConfig:
    """Free guidance: the operator moves the tool to each waypoint and releases it there; the reference is the last
    released ("taught") pose, so between grasps IK holds it. Lengths in m, times in s."""

    waypoints: tuple[tuple[float, float, float], ...] = ((0.10, 0.10, -0.05), (0.05, -0.15, 0.0),
                                                          (-0.05, 0.0, 0.05))
    """Handle goals relative to the handle's position at home (x, y, z) [m], visited in order."""
    pause: float = 1.5
    """Time between a release and the next grasp (and before the first) [s]."""
    waypoint_turn_deg: float = 0.0
    """Per trial, the waypoints are turned about the vertical through the handle's home position by an angle drawn
    uniformly within ± this [deg] (0: every trial visits `waypoints` as listed)."""
    waypoint_spread: float = 0.0
    """Per trial, each waypoint is moved by a draw uniform in a ball of this radius [m], before the turn."""
    reference_follows: bool = False
    """While the operator guides, the reference position follows the tool, as x_d does in the paper's polishing
    relocations (section VI-B2, Fig. 8); False: it stays at the last taught pose, and IK pulls back against the
    hand."""

    def _check(self, err: _Errors) -> None:
        if not self.waypoints:
            err.add("waypoints", "needs at least one (x, y, z)")
        for k, w in enumerate(self.waypoints):
            if len(w) != 3 or not all(math.isfinite(v) for v in w):
                err.add("waypoints", f"waypoint {k + 1} needs 3 finite numbers (x, y, z) [m], got {list(w)}")
        if not (self.pause >= 0 and math.isfinite(self.pause)):
            err.add("pause", f"must be a finite number >= 0, got {self.pause}")
        if not (0 <= self.waypoint_turn_deg <= 180):
            err.add("waypoint_turn_deg", f"must be within [0, 180] deg, got {self.waypoint_turn_deg}")
        if not (self.waypoint_spread >= 0 and math.isfinite(self.waypoint_spread)):
            err.add("waypoint_spread", f"must be a finite distance >= 0 [m], got {self.waypoint_spread}")


@dataclass
class PandaEnvConfig:
    """N simulated Pandas with the A3CQP controller and six per-axis agents (paper 000, eq. 25-29, section VI).

    Translational axes use Table II's bounds (AdaptationConfig); Table II has none for the rotational axes of the
    local frame L, so these are chosen here: ē = 1 rad (the same number as 1 m: "reasonably high"), and torque
    bounds = Table II's force bounds times a 0.1 m lever (a hand or a contact about 10 cm from the tool tip).
    """

    scene: Literal["peg_in_hole", "polishing", "guidance"] = "peg_in_hole"
    """Which scene and procedure (envs/scenarios.py)."""
    e_max_rot: float = 1.0
    """ē for the rotational axes [rad]."""
    f_env_max_rot: float = 3.0
    """f̄_env for the rotational axes [N m]."""
    f_ope_max_rot: float = 1.5
    """f̄_ope for the rotational axes [N m]. The peg config sets 3.0: the handle is 0.19 m from the tool tip, and a
    hand pulling a peg out there read as a full push on 1.5 tilted the peg into a wedge (docs/panda.md, "The
    operator's moment at the handle"); guidance and polishing, where the hand turns a free tool, keep 1.5."""
    fd_axes: tuple[str, ...] = ("x", "y", "z")
    """Local translational axes whose agent sets a desired force f_d (eq. 29d); the others, and every rotational
    axis, keep f_d = 0 (desired torques are zero)."""
    initial_weights: Literal["ik", "random"] = "ik"
    """Start of each episode: pure IK with f_d = 0 (w̌ = (σw/2, −σw/2, −σw/2)), or random like the point mass."""
    max_episode_time: float = 120.0
    """Episodes are truncated after this simulated time [s] even if the procedure has not finished."""
    state_leak: Literal["per_axis", "min_w1"] = "per_axis"
    """ControllerOptions.leak_axes of the env's controller: how the integrated references q*, q̇* (eq. 6-7) relax
    toward the measured state where IK does not lead. "per_axis" (per local axis, so force control on z leaves the
    integral action of eq. 5-7 on the axes IK still tracks; without it the peg stays on the rim, held by friction:
    docs/panda.md) or "min_w1" (one rate for all joints, set by the smallest w1 of the six axes)."""
    task_blend: Literal["eq35", "eq24"] = "eq35"
    """How the env's controller blends the three tasks on each axis of L. "eq35": as the point-mass surrogate the
    adaptation is trained on (eq. 35, a weighted sum: ẍ = w1 ẍ_IK on the acceleration, f* = w2 f_adm + w3 f_ctc on
    the wrench), i.e. ControllerOptions(cartesian_regularization=1, wrench_blend="weighted_sum"). "eq24": the QP's
    defaults (γ = 0.01: IK realised in full for any w1 ≫ γ; f* = (w2 f_adm + w3 f_ctc) / (w2 + w3)). With "eq24"
    the weights w = (0.5, 0, 0.5), f_d = 20 N that the point-mass policy reaches in contact command full IK plus
    20 N instead of the half-stiffness and 10 N it was trained with. Peg-in-hole, 26 trials, the same point-mass
    policy: 24/26 with "eq35", 9/26 with "eq24" (docs/panda.md)."""
    idle_force: Literal["damps", "holds", "free"] = "damps"
    """What the share of force control that does not push, w3 (1 − min(1, f_d / 1 N)) on an axis of L, does in the
    controller (the share the per-axis leak, `state_leak: per_axis`, already counts as not pushing). "free": eq. 35
    as is: it commands neither wrench nor acceleration, so the axis coasts; after the operator lets go in the
    guidance scene the arm drifts ~0.1 m from the taught pose. "damps" (default): it damps like IK (IK's damping
    is (w1 + share) k_v, its stiffness stays w1 k_p). "holds": it goes to IK (stiffness too), which also resists
    the operator while guiding. Measured in docs/panda.md ("The idle force-control share")."""
    observation_filter: Literal["last", "mean"] = "last"
    """What the agents observe (eq. 26) and are rewarded on (eq. 30) of the sensed wrenches f_env, f_ope, sampled
    at 1 kHz, once per 10 ms agent period: "last", the last control period's sample; "mean", the mean of the
    period's ten samples (anti-aliasing before the 100 Hz adaptation, as a real sensor chain filters before it
    decimates). In contact, MuJoCo loses a pressed peg's contact for single 1 ms steps in 4-9 % of the pressing
    periods (the peg separates from the rim by less than a µm), so about one "last" sample in twenty reads no
    contact (docs/panda.md, "Contact dropouts"). The tool-axis rules (`ik_bound_tool_axis`, `ik_bound_blocked`,
    `ik_lead_sliding`) test contact and press on the same observed wrench. The scene's metrics use the samples as
    before."""
    observe_f_env_pull: bool = True
    """Whether the agents observe f_env on the `fd_axes` where it pulls the tool toward the surface (against f_d's
    push side). The surrogate's wall only pushes back (eq. 35: f_env ≤ 0 along the axis f_d pushes on), and eq. 26
    observes |f_env|, so a pull reads to the policy as a wall pressed hard. False: such a pull reads 0, as no wall
    (e.g. the bore's friction holding a peg the operator pulls out, where the point-mass policy would otherwise
    raise f_d toward f̄_d against the operator; docs/panda.md, "A peg held in the bore"). The reward, the tool-axis
    rules and the recorded signals keep the sensed wrench."""
    joint_limits_f_ext: Literal["off", "operator", "always"] = "off"
    """Where the controller's joint-limit rows count the measured external wrench f_ext, so that an external force
    cannot carry a joint past its limit: "always" (ControllerOptions.joint_limits_include_f_ext: under random weights
    in the guidance scene no joint reached its limit on four seeds; without it joint 6 reached its end stop, 1.6-1.8
    mrad deep on seeds 1-3, 10-17 mrad with MuJoCo's default soft stop), "operator" (an arm
    while the operator holds its handle: the peg pulled out of its bore; configs/panda_peg_in_hole.yaml) or "off"
    (default: in stiff contact, the peg on the rim, the contact's impulses make the QP infeasible and the controller
    brakes; docs/panda.md, "External forces carry the joints past their limits")."""
    qp_failure: Literal["brake", "least_violation"] = "brake"
    """What an arm whose QP fails gets (ControllerOptions.qp_failure): "brake" (default) the fallback brake, with no
    wrench; "least_violation" the same QP with the joint-limit rows of its actual acceleration soft, so that its
    joints give way as little as the torque limits force them to and its tasks go on (docs/panda.md, "A
    least-violation step for a failed QP": on the peg its numbers match the brake's, and `make peg` runs longer)."""
    ik_bound_tool_axis: float | None = None
    """How far [m] the reference that the IK task of a policy-driven arm pulls toward may be from the tool along the
    tool axis (local z); None: the scene's reference as it is. On the peg the procedure's reference goes on down at
    4 mm/s while the peg sits on the hole's rim, so z's IK half (w1 = 0.5 in contact) presses harder and harder
    (9 to 22 N; the scripted IK + FC presses 10 N) and friction holds the peg off the axis. 20 mm on the peg
    (configs/panda_peg_in_hole.yaml) caps that press: the median insertion 0.2 s sooner (docs/panda.md, "A bound on
    the tool axis's IK error"). With a bound, a tool in contact (|f_env| > the controller's contact threshold) whose
    scene reference advanced along the axis in its last update gets a reference not behind it either: a schedule
    that lags the peg down the bore does not pull it back (docs/panda.md, "An IK reference that does not lag the
    peg"). A scene reference that moved back along the axis in its last update (the return home of `--cycles`) is
    not held behind the tool: it pulls a peg the bore holds out, as the baselines' does (docs/panda.md, "The return
    home pulls a held peg out"). Arms whose weights `PandaEnv.hold_weights` sets (the scripted baselines) keep the
    scene's reference."""
    ik_bound_blocked: float | None = None
    """With `ik_bound_tool_axis`: how far [m] that reference may run ahead of a blocked tool along the tool axis, a
    tool pressed back along its axis by more than `blocked_force` (f_env) that moves along it slower than
    `blocked_speed`; None: the bound alone. 0 on the peg (configs/panda_peg_in_hole.yaml): a peg on the rim is
    pressed by z's force-control half alone, and the reference does not wind up behind the block (anti-windup), so
    the peg is not pressed flat onto the rim (docs/panda.md, "The IK reference held at a blocked tool")."""
    ik_lead_sliding: float = 0.0
    """With `ik_bound_tool_axis`: how far [m] at least that reference is ahead of a tool in contact that slides
    forward along its axis faster than `sliding_speed` while its scene reference advances (`ik_bound_blocked` wins
    for a blocked tool); 0 (default): at the tool. 20 mm on the peg (configs/panda_peg_in_hole.yaml): a peg that
    enters the bore ahead of the procedure's z schedule goes down at its own pace (docs/panda.md, "A reference that
    leads a sliding peg")."""
    ik_lead_engaged: bool = False
    """With `ik_bound_tool_axis`: whether a tool the block has pressed back along its axis (by more than
    `blocked_force`) while its scene reference advances stays engaged until that reference stops advancing, and gets
    the rules of a tool in contact (its reference not behind it, `ik_lead_sliding` ahead while it slides) also where
    it reads no contact (a peg between the bore's walls, which it touches only now and then); false (dataclass
    default): only a tool in contact. Without it a peg that drops off the rim into the bore ahead of the procedure's z
    schedule reads free there, and IK pulls it back up to the schedule: with the x-y alignment in 4 s instead of 8 the
    learned peg took 1.0 s down the bore against IK + FC's 0.2 s, with z at 2 mm/s 2.9 s. True in the peg config
    (docs/panda.md, "A reference not behind a peg between the bore's walls")."""
    engaged_depth: float = 0.0
    """With `ik_lead_engaged`: how far [m] along its axis past where the engaging press began (the rim) an engaged
    tool must be before it keeps the rules of a tool in contact where it reads free: between the bore's walls, not
    hopping on the rim. 0 (default): at or past it. 2 mm on the peg (docs/panda.md, "An engaged peg past the rim")."""
    sliding_speed: float = 0.001
    """Speed forward along the tool axis [m/s] above which a tool in contact slides (`ik_lead_sliding`): above the
    jitter of a peg on the rim, below a peg's pace down the bore."""
    blocked_force: float = 5.0
    """f_env along the tool axis, pushing the tool back [N], above which a still tool is blocked (`ik_bound_blocked`)."""
    blocked_speed: float = 0.005
    """Speed along the tool axis [m/s] below which a pressed tool is blocked (`ik_bound_blocked`)."""
    ik_rules_scripted: bool = False
    """Whether the tool-axis rules (`ik_bound_tool_axis`, `ik_bound_blocked`, `ik_lead_sliding`, `ik_lead_engaged`)
    also place the IK reference of the arms whose weights `PandaEnv.hold_weights` sets (the scripted baselines of
    `a3cqp evaluate`); false (default): those keep the procedure's reference, as the paper's scripted controller
    does. True compares every controller with the same reference along the tool axis (docs/panda.md, "The baselines
    with the learned arms' reference rules", "Every set of seeds again, with the rule past the press")."""
    vic_contact_scale: tuple[float, ...] = (2.0, 2.0, 1.0 / 3.0, 1.0, 1.0, 1.0)
    """The variable-impedance baseline's (`a3cqp evaluate --controllers vic`) scales of Table I's k_p, k_θ per local
    axis (x, y, z, rx, ry, rz of L) from its first contact on: a hand-tuned schedule, stiff across the tool axis, soft
    along it (docs/panda.md, "Where VIC's like-for-like lead comes from": its x and y set its time on the rim)."""
    vic_operator_scale: tuple[float, ...] = (0.2, 0.2, 0.2, 0.5, 0.5, 0.5)
    """The variable-impedance baseline's scales while the operator holds the handle (compliant)."""
    policy: str | None = None
    """The learned adaptation policy `a3cqp evaluate --scene` runs when no --policy is given: a policy.pt or a run
    folder, relative to the working directory, else to the checkout's root (None: --policy is needed for the learned
    controller)."""
    divergence_speed_factor: float = 3.0
    """A robot whose joint speed exceeds this multiple of its datasheet limit counts as diverged."""
    divergence_penetration: float = 0.01
    """A robot with a contact deeper than this [m] counts as diverged."""
    solver_warmstart: bool = False
    """MuJoCo's constraint-solver warm start (a3cqp_rl.robot.PandaSim's `warmstart`). Off (default): every arm's
    contact solve starts from its own unconstrained accelerations, so a trial computes the same numbers with any
    `--threads` or parking and, but for rare round-off, `--workers`. On: MuJoCo's choice, made once for the whole
    model, which made an arm's numbers in contact depend on the other arms in its batch (docs/panda.md, "The same
    numbers across workers and threads")."""
    contact_prefilter: bool = True
    """Drop, before MuJoCo's narrow phase, the tool-box collision pairs that a plane keeps apart (PandaSim's
    `contact_prefilter`, a3cqp_rl.robot.contact_filter): exact, the same contacts and numbers bit for bit, and the
    peg-in-hole evaluation ~10 % faster (docs/panda.md, "An exact contact pre-filter"). Off: MuJoCo's own pairs."""
    operator: OperatorConfig = field(default_factory=OperatorConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    peg_in_hole: PegInHoleConfig = field(default_factory=PegInHoleConfig)
    polishing: PolishingConfig = field(default_factory=PolishingConfig)
    guidance: GuidanceConfig = field(default_factory=GuidanceConfig)

    def _check(self, err: _Errors) -> None:
        for name in ("e_max_rot", "f_env_max_rot", "f_ope_max_rot", "max_episode_time", "divergence_speed_factor",
                     "divergence_penetration"):
            err.positive(self, name)
        if self.ik_bound_tool_axis is not None and not self.ik_bound_tool_axis > 0:
            err.add("ik_bound_tool_axis", f"must be a distance > 0 [m] or null, got {self.ik_bound_tool_axis}")
        if self.ik_bound_blocked is not None:
            if self.ik_bound_tool_axis is None:
                err.add("ik_bound_blocked", "needs ik_bound_tool_axis (the bound it tightens while the tool is blocked)")
            elif not 0.0 <= self.ik_bound_blocked <= self.ik_bound_tool_axis:
                err.add("ik_bound_blocked", f"must be a distance in [0, ik_bound_tool_axis = {self.ik_bound_tool_axis}] "
                        f"[m] or null, got {self.ik_bound_blocked}")
        if self.ik_lead_sliding != 0.0 and (self.ik_bound_tool_axis is None
                                             or not 0.0 <= self.ik_lead_sliding <= self.ik_bound_tool_axis):
            err.add("ik_lead_sliding", "needs ik_bound_tool_axis and must be a distance in [0, ik_bound_tool_axis] "
                    f"[m], got {self.ik_lead_sliding}")
        if self.ik_lead_engaged and self.ik_bound_tool_axis is None:
            err.add("ik_lead_engaged", "needs ik_bound_tool_axis (the rules it extends to a tool between the walls)")
        if not self.engaged_depth >= 0:
            err.add("engaged_depth", f"must be a distance >= 0 [m], got {self.engaged_depth}")
        if not self.sliding_speed >= 0:
            err.add("sliding_speed", f"must be a speed >= 0 [m/s], got {self.sliding_speed}")
        if not self.blocked_force > 0:
            err.add("blocked_force", f"must be a force > 0 [N], got {self.blocked_force}")
        if not self.blocked_speed > 0:
            err.add("blocked_speed", f"must be a speed > 0 [m/s], got {self.blocked_speed}")
        if self.policy is not None and not self.policy.strip():
            err.add("policy", "must be a path to a policy.pt or a run folder, or null")
        bad = [a for a in self.fd_axes if a not in ("x", "y", "z")]
        if bad or len(set(self.fd_axes)) != len(self.fd_axes):
            err.add("fd_axes", f"must be distinct names among x, y, z, got {list(self.fd_axes)}")
        for name in ("vic_contact_scale", "vic_operator_scale"):
            scales = getattr(self, name)
            if len(scales) != 6 or not all(math.isfinite(v) and v > 0 for v in scales):
                err.add(name, f"needs 6 finite scales > 0 (x, y, z, rx, ry, rz), got {list(scales)}")


FIXED_TASKS = ("ik", "ac", "fc", "jc", "cartesian_regularizer")
"""Tasks of a fixed controller (a3cqp_rl.control.population.TASKS)."""


def _fixed_levels() -> dict[str, int]:
    return {name: 1 for name in FIXED_TASKS}


def _fixed_weights() -> dict[str, tuple[float, ...]]:
    return {"ik": (1.0,) * 6, "ac": (0.0,) * 6, "fc": (0.0,) * 6}


@dataclass
class FixedControllerConfig:
    """A fixed controller on the Panda (paper 002's "control configuration"): constant per-axis task weights and f_d,
    strict priority levels and gains, all the same for a whole episode (no adaptation). NSGA-II tunes them
    (`a3cqp pareto --config configs/nsga2_peg.yaml`, `--pick K` writes one), `a3cqp evaluate --controller-config`
    runs one next to the learned policy and the scripted baselines. Defaults: Table I gains, IK only, one level."""

    name: str = "fixed"
    """Name of the controller in evaluation tables."""
    levels: dict[str, int] = field(default_factory=_fixed_levels)
    """Priority level of each task: 1 (highest) .. 3, 0 = off (paper 002 eq. 3-4); tasks not named: level 1."""
    weights: dict[str, tuple[float, ...]] = field(default_factory=_fixed_weights)
    """Local per-axis weights (x, y, z, rx, ry, rz of the tool frame L) of ik, ac, fc, each in [0, 1] (eq. 8);
    a task not named: 0 on every axis."""
    f_d: float = 0.0
    """Desired contact force along the tool axis (local z) [N], 0 .. adaptation.f_d_max (eq. 20-21)."""
    kp: float = 150.0
    """IK k_p [1/s²] (Table I)."""
    k_theta: float = 20.0
    """IK k_θ [1/s²] (Table I)."""
    lambda_d: float = 5.0
    """AC Λd [kg] (Table I)."""
    c_d: float = 5.0
    """AC Cd [N s/m] (Table I)."""
    kq: float = 10.0
    """JC k_q [1/s²] (Table I)."""
    jc_weight: float = 1.0
    """Multiplier of the JC weight (ε of Table I and ControllerOptions.jc_nullspace_weight)."""
    cartesian_regularization: float = 1e-2
    """γ of the Cartesian acceleration regularizer (ControllerOptions.cartesian_regularization)."""

    def _check(self, err: _Errors) -> None:
        builtin = ("learned", "ik", "ik_fc", "equal", "vic")  # envs/panda_eval.py's controllers
        if not self.name or any(c in self.name for c in ",\n") or self.name in builtin:
            err.add("name", f"must be a non-empty name without commas, other than the built-in controllers, got "
                            f"{self.name!r}")
        for task, level in self.levels.items():
            if task not in FIXED_TASKS:
                err.add("levels", f"unknown task {task!r}; tasks: {list(FIXED_TASKS)}")
            elif not 0 <= level <= 3:
                err.add(f"levels.{task}", f"must be 1, 2, 3 or 0 (off), got {level}")
        for task, w in self.weights.items():
            if task not in ("ik", "ac", "fc"):
                err.add("weights", f"unknown task {task!r}; weighted tasks: ik, ac, fc")
            elif len(w) != 6 or not all(0.0 <= v <= 1.0 for v in w):
                err.add(f"weights.{task}", f"needs 6 values in [0, 1] (x, y, z, rx, ry, rz), got {list(w)}")
        for name in ("kp", "k_theta", "lambda_d"):
            err.positive(self, name)
        for name in ("c_d", "kq", "jc_weight", "cartesian_regularization", "f_d"):
            if not getattr(self, name) >= 0:
                err.add(name, f"must be >= 0, got {getattr(self, name)}")

    def level_row(self) -> tuple[int, ...]:
        """Levels in FIXED_TASKS order (0 = off)."""
        return tuple(int(self.levels.get(name, 1)) for name in FIXED_TASKS)

    def weight_matrix(self) -> list[list[float]]:
        """Local weights [6 axes][ik, ac, fc]."""
        cols = [self.weights.get(name, (0.0,) * 6) for name in ("ik", "ac", "fc")]
        return [[float(c[a]) for c in cols] for a in range(6)]


MAX_SEED = 2**63 - 1
"""The largest seed a config or a command line takes."""


@dataclass
class ExperimentConfig:
    """One experiment: environment, adaptation law, reward, learner, GA and controller settings."""

    seed: int = 0
    """Random seed (torch, numpy, environments)."""
    env: str = "point_mass"
    """Environment: a registered name (``point_mass``, ``panda``; `ENV_FACTORIES`) or any gymnasium id (e.g.
    ``Pendulum-v1``)."""
    point_mass: PointMassConfig = field(default_factory=PointMassConfig)
    adaptation: AdaptationConfig = field(default_factory=AdaptationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    a2c: A2CConfig = field(default_factory=A2CConfig)
    ga: GAConfig = field(default_factory=GAConfig)
    nsga2: NSGA2Config = field(default_factory=NSGA2Config)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    panda: PandaEnvConfig = field(default_factory=PandaEnvConfig)
    """The simulated Panda env (envs/panda.py): scene, operator, sensing, the rotational-axis bounds."""
    fixed_controller: FixedControllerConfig | None = None
    """A fixed controller (a Pareto pick): `a3cqp evaluate --controller-config FILE` reads this section."""

    def _check(self, err: _Errors) -> None:
        if not 0 <= self.seed <= MAX_SEED:  # torch's generators take 64-bit seeds; trials add small offsets
            err.add("seed", f"must be an integer in [0, 2**63 - 1], got {self.seed}")
        if self.env not in ENV_FACTORIES and not _is_gym_id(self.env):
            err.add("env", f"unknown environment {self.env!r}: neither a registered env ({sorted(ENV_FACTORIES)}) "
                           "nor a gymnasium id (e.g. Pendulum-v1)")
        if self.env == "point_mass" and self.point_mass.episode_steps < self.a2c.n_steps:
            # fused rollouts draw one pending episode per env per iteration
            err.add("point_mass.episode_steps", f"must be >= a2c.n_steps ({self.a2c.n_steps}), got {self.point_mass.episode_steps}")
        if self.fixed_controller is not None and self.fixed_controller.f_d > self.adaptation.f_d_max:
            err.add("fixed_controller.f_d", f"must be <= adaptation.f_d_max ({self.adaptation.f_d_max}), got "
                                            f"{self.fixed_controller.f_d}")


def _is_gym_id(name: str) -> bool:
    """Whether gymnasium knows `name` (gymnasium is imported only for names that are not registered here)."""
    try:
        import gymnasium
    except ImportError:  # pragma: no cover - a runtime dependency
        return False
    return name in gymnasium.registry


# --------------------------------------------------------------------------------------------
# Memory


def estimate_memory_bytes(cfg: ExperimentConfig) -> int:
    """Rough peak memory of training `cfg` [bytes]: the envs' part plus the network's (`_memory_parts`)."""
    return sum(_memory_parts(cfg).values())


def _memory_parts(cfg: ExperimentConfig) -> dict[str, int]:
    """Rough peak memory [bytes] per config key that sets it.

    a2c.num_envs, per point-mass env: the double-buffered operator schedule (2 × (episode_steps + 1) float64), the
    state and its pending episode; per sample of a rollout (n_steps × num_envs): observations, actions, rewards,
    flags and each hidden layer's activations (float32), about three times over (the update's forward, backward and
    copies). a2c.hidden: the actor's and the critic's parameters (float32), held about eight times over (parameters,
    gradient, RMSProp's square average, the parameter average, the transfer candidates, a checkpoint being written).
    """
    a = cfg.a2c
    obs, act = 16, 8  # generous for the point mass (3 / 4; 3 + privileged critic input) and small gym tasks
    per_env = 2 * (cfg.point_mass.episode_steps + 1) * 8 + 40 * 8 if cfg.env == "point_mass" else 64 * 8
    per_sample = 4 * (2 * obs + act + 4 + 2 * sum(a.hidden)) * 3
    sizes = [obs, *a.hidden]
    params = sum((i + 1) * o for i, o in zip(sizes, [*a.hidden, act])) + sum((i + 1) * o for i, o in zip(sizes, [*a.hidden, 1]))
    return {"a2c.num_envs": int(a.num_envs * (per_env + a.n_steps * per_sample)), "a2c.hidden": 4 * 8 * params}


def _available_memory() -> int | None:
    """MemAvailable of /proc/meminfo [bytes], or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_memory(cfg: ExperimentConfig, source: str = "config", available: int | None = None) -> None:
    """ConfigError naming the key that needs the most (a2c.num_envs or a2c.hidden) when `estimate_memory_bytes(cfg)`
    exceeds 80 % of the available memory."""
    parts = _memory_parts(cfg)
    key = max(parts, key=parts.get)
    what = f"{cfg.a2c.num_envs} envs" if key == "a2c.num_envs" else f"a network of hidden sizes {list(cfg.a2c.hidden)}"
    check_fits(sum(parts.values()), f"{source}: {key}: {what}",
               "fewer envs" if key == "a2c.num_envs" else "smaller layers", available)


def check_fits(need: int, what: str, advice: str, available: int | None = None) -> None:
    """ConfigError "`what` need(s) about X GiB, more than 80 % of the Y GiB available; use `advice`" when `need`
    [bytes] exceeds 80 % of the available memory (`available`, default: MemAvailable; unknown: no check)."""
    have = _available_memory() if available is None else available
    if have is not None and need > 0.8 * have:
        raise ConfigError(f"{what} need about {need / 2**30:.1f} GiB, more than 80 % of the {have / 2**30:.1f} GiB "
                          f"available; use {advice}")


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
            self.add(name, f"must be an integer >= 1, got {value}" if isinstance(value, int)
                     else f"must be a finite number > 0, got {value}")


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
        if isinstance(value, bool):  # YAML 1.1 reads an unquoted off/no as false and on/yes as true
            word = {False: "off", True: "on"}[value]
            if word in args:
                return word
            raise ConfigError(f"{source}: {key}: must be one of {list(args)}, got {value!r} (YAML reads unquoted "
                              "on/off/yes/no as true/false: quote the word)")
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
            if isinstance(value, str):  # PyYAML (YAML 1.1) reads "1e6" without a dot as a string
                try:
                    value = float(value)
                except ValueError:
                    pass
            if isinstance(value, float) and value.is_integer():
                return int(value)  # 1.0e6 is read by YAML as a float
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
        close = {k: difflib.get_close_matches(str(k), names, n=1) for k in unknown}  # a typo names its key
        named = [prefix + str(k) + (f" (did you mean {prefix + close[k][0]}?)" if close[k] else "") for k in unknown]
        raise ConfigError(
            f"{source}: unknown key(s) {', '.join(named)}; "
            f"valid keys under {prefix.rstrip('.') or 'top level'}: {sorted(names)}"
        )
    kwargs = {k: _convert(hints[k], v, prefix + k, source) for k, v in data.items()}
    return cls(**kwargs)


NON_FINITE_OK: frozenset[str] = frozenset()
"""Dotted float fields that may be NaN or inf (none today): every other float must be finite."""


def _non_finite(obj: Any, prefix: str) -> list[str]:
    """Messages for float fields (also inside tuples, dicts, optionals) of `obj` holding NaN or inf."""
    out = []
    for f in dataclasses.fields(obj):
        key, value = f"{prefix}{f.name}", getattr(obj, f.name)
        items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, tuple) else [(None, value)]
        for i, v in items:
            if isinstance(v, float) and not math.isfinite(v) and key not in NON_FINITE_OK:
                where = key if i is None else f"{key}.{i}" if isinstance(value, dict) else f"{key}[{i}]"
                out.append(f"{where}: must be a finite number, got {v}")
    return out


def _validate(obj: Any, prefix: str, source: str) -> None:
    err = _Errors(prefix)
    err.messages += _non_finite(obj, prefix)
    if not err.messages:  # range checks on NaN would only repeat the message
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


CHECKOUT = Path(__file__).resolve().parents[1]
"""The project's checkout (its configs/ and policies/)."""


def project_path(path: str | Path) -> Path:
    """`path` where it exists (relative to the working directory), else the same relative path in this checkout where
    that exists (a command run from another folder finds the shipped configs and policies), else `path` unchanged."""
    path = Path(path)
    if path.is_absolute() or path.exists() or not (CHECKOUT / path).exists():
        return path
    return CHECKOUT / path


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> ExperimentConfig:
    """Load `path` (YAML, safe_load) over the paper defaults; `overrides` is a nested dict applied last.

    A top-level `base: OTHER.yaml` (relative to the file) reads that file first and applies this one over it, key by
    key, so that a training config can share every setting of the evaluation config it is judged with."""
    data: dict = {}
    source = "the built-in defaults (paper Tables I-V)"
    if path is not None:
        source = str(path)
        data = _read_with_base(Path(path), ())
    if not overrides:
        return config_from_dict(data, source)
    try:
        merged = _merge(data, overrides)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    labelled = source + " with the command's overrides"
    try:
        return config_from_dict(merged, labelled)
    except ConfigError as exc:
        if path is None:
            raise
        try:  # the same error from the file alone is the file's (not the options', e.g. --no-compile's)
            config_from_dict(data, source)
        except ConfigError as own:
            if str(own)[len(source):] == str(exc)[len(labelled):]:
                raise own from None
        raise


def read_config_file(path: str | Path) -> dict:
    """The mapping a YAML config file gives (merged over its `base` files), before defaults and validation."""
    return _read_with_base(Path(path), ())


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict:
    """The nested dict of command-line overrides `KEY=VALUE` (KEY dotted, e.g. panda.blocked_force; VALUE read as
    YAML: 1.0, [z], null, true), for `load_config(path, overrides)`; a key given twice keeps the last value."""
    out: dict = {}
    for item in items:
        key, sep, text = item.partition("=")
        parts = [p.strip() for p in key.split(".")]
        if not sep or not all(parts):
            what = "no '=' between KEY and VALUE" if not sep else "an empty part in KEY"
            raise ConfigError(f"--set {item!r}: {what}; expected KEY=VALUE, KEY a config key (dotted for a section's: "
                              "seed=3, panda.blocked_force=2.0)")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML: {' '.join(str(exc).split())}") from None
        node = out
        for k, p in enumerate(parts[:-1]):
            if p in node and not isinstance(node[p], dict):
                raise ConfigError(f"--set {item!r}: {'.'.join(parts[:k + 1])} is also given a value, not keys inside it "
                                  "(a section: SECTION.KEY=VALUE)")
            node = node.setdefault(p, {})
        if isinstance(node.get(parts[-1]), dict) and not isinstance(value, dict):
            raise ConfigError(f"--set {item!r}: {key.strip()} is a section, also given keys inside it "
                              "(SECTION.KEY=VALUE)")
        node[parts[-1]] = value
    return out


def _read_with_base(path: Path, chain: tuple[Path, ...]) -> dict:
    """The mapping of the YAML file `path`, merged over its `base` file's (recursively); `chain`: the files that
    named it as their base, to report a loop."""
    source = str(path)
    if path.is_dir():
        raise ConfigError(f"{source}: is a folder, expected a YAML config file")
    if not path.is_file():
        where = f" (the base of {chain[-1]})" if chain else ""
        raise ConfigError(f"{source}: config file not found{where}")
    try:
        text = path.read_bytes().decode("utf-8")
        loaded = yaml.safe_load(text)
        dup = _duplicate_key(text)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{source}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset {exc.start}); "
                          "expected a YAML file") from None
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: not valid YAML: {' '.join(str(exc).split())}") from None
    if loaded is not None and not isinstance(loaded, dict):
        raise ConfigError(f"{source}: top level must be a mapping, got {type(loaded).__name__}")
    if dup:
        raise ConfigError(f"{source}: {dup}")
    data = dict(loaded or {})
    if "base" not in data:
        return data
    base = data.pop("base")
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"{source}: base: expected the path of another config file, got {base!r}")
    base_path = path.parent / base
    if base_path.resolve() in [p.resolve() for p in (*chain, path)]:
        names = " -> ".join(str(p) for p in (*chain, path, base_path))
        raise ConfigError(f"{source}: base: the files name each other as base ({names})")
    base_data = _read_with_base(base_path, (*chain, path))
    try:
        return _merge(base_data, data)
    except ConfigError as exc:
        raise ConfigError(f"{source} over its base {base_path}: {exc}") from None


def _duplicate_key(text: str) -> str | None:
    """The first key written twice in one mapping of a YAML text, as a message, or None (safe_load keeps the last
    value without a word)."""
    def walk(node: yaml.Node, where: str) -> str | None:  # noqa: ANN001
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for k, v in node.value:
                key = k.value if isinstance(k, yaml.ScalarNode) else None
                if key is not None and key in seen:
                    return (f"{where}{key}: given twice (lines {seen[key] + 1} and {k.start_mark.line + 1}); the "
                            "second would silently win")
                seen.setdefault(key, k.start_mark.line)
                found = walk(v, f"{where}{key}.")
                if found:
                    return found
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                found = walk(v, f"{where}[{i}].")
                if found:
                    return found
        return None

    root = yaml.compose(text, Loader=yaml.SafeLoader)  # nodes only: nothing is constructed
    return None if root is None else walk(root, "")


def _merge(base: dict, over: dict, where: str = "") -> dict:
    """`over` merged into `base`, section by section; a section over a value that is not one is a ConfigError (it
    would hide the bad value)."""
    out = dict(base)
    for k, v in over.items():
        old = out.get(k)
        if isinstance(v, dict) and old is not None and not isinstance(old, dict):
            raise ConfigError(f"{where}{k}: expected a mapping, got {type(old).__name__}")
        out[k] = _merge(old, v, f"{where}{k}.") if isinstance(v, dict) and isinstance(old, dict) else v
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
