"""NSGA-II objectives on the simulated Panda: paper 002 eq. 5-6 for fixed controllers on the peg-in-hole scene.

    a3cqp pareto --config configs/nsga2_peg.yaml [--generations G] [--population P] [--workers W] [--out DIR]
    a3cqp pareto --out DIR --pick K          # DIR/pick_K.yaml: `a3cqp evaluate --controller-config DIR/pick_K.yaml`

A genome is a fixed controller (`FixedControllerConfig`): per task (ik, ac, fc, jc, cartesian_regularizer) a soft
weight, a level selector l ∈ [0, 1] (eq. 4: level 1, 2, 3 or off) and the task's gains; f_d along the tool axis.
Gene names are `task.parameter`:

    ik.w, ac.w, fc.w         local per-axis weights in [0, 1]: size 1 (all six axes), 2 (translations, rotations),
                             3 (x-y across the tool, z along it, rotations) or 6 (x, y, z, rx, ry, rz)
    jc.w                     multiplier of the JC weight (ε, ε_N; 1 = Table I)
    cartesian_regularizer.w  its γ
    <task>.level             level selector (type: level)
    ik.kp, ik.k_theta, ac.lambda_d, ac.c_d, jc.kq, fc.f_d   gains [SI], f_d [N]

A task without genes keeps the default of FixedControllerConfig (Table I, level 1, IK weight 1, others 0).

Each genome runs `nsga2.panda.trials` trials of each scene in `nsga2.panda.scenes`, the same trials for every genome
(misalignment, operator tremor, sensor noise and bias from `panda.sensors`, and a per-trial factor on the operator's
strength). The objectives (all minimised, means over the trials), in the structure of eq. 5-6:

- tracking [cm] (f1): mean pose error where the scene expects IK to lead (before the contact, holding a taught pose):
  100 (|p − p_d| + ℓ θ), θ the orientation error, ℓ = `lever` (paper 002 sums position and arc length in cm);
- interaction [N] (f2): mean |f_ope| while the operator acts + mean contact-force error while the tool touches in a
  force-control phase: |pressing force − `contact_force`| + |force across the tool axis|;
- failure (f3): failed insertion (1 per failed peg trial) + the fraction of control periods with the QP's fallback
  brake + with torque saturation + the fraction of agent steps with a joint at its limit;
- eq. 6: a robot that diverges at step i of the horizon I (`panda.max_episode_time`) adds α_F1 (I − i)/I to f1,
  α_F2 (I − i)/I to f2 and 1 + (I − i)/I to f3 (`failure_tracking`, `failure_interaction`).

The genomes of one evaluation task share one simulation per scene (`PopulationController`: per-arm gains and
levels), so a task's values depend on its batch only through round-off (MuJoCo solves the arms' contacts
together); `nsga2.chunk_size` fixes the batches whatever the number of workers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from a3cqp_rl.config import (ExperimentConfig, FixedControllerConfig, GeneConfig, config_from_dict,
                             config_to_dict)
from a3cqp_rl.exceptions import ConfigError
from a3cqp_rl.robot import PANDA_LIMITS

from .objectives import register

__all__ = ["GENES", "OBJECTIVES", "fixed_from_genome", "evaluate_fixed", "FixedScores", "trial_draws", "panda",
           "pick_config"]

OBJECTIVES = ("tracking_cm", "interaction_n", "failure")
GENES: tuple[GeneConfig, ...] = (
    GeneConfig("ik.w", 0.0, 1.0, size=3), GeneConfig("ik.level", type="level"),
    GeneConfig("ik.kp", 10.0, 1000.0, "log"), GeneConfig("ik.k_theta", 2.0, 200.0, "log"),
    GeneConfig("ac.w", 0.0, 1.0, size=3), GeneConfig("ac.level", type="level"),
    GeneConfig("ac.lambda_d", 0.5, 50.0, "log"), GeneConfig("ac.c_d", 0.5, 50.0, "log"),
    GeneConfig("fc.w", 0.0, 1.0, size=3), GeneConfig("fc.level", type="level"), GeneConfig("fc.f_d", 0.0, 20.0),
    GeneConfig("jc.w", 0.01, 100.0, "log"), GeneConfig("jc.level", type="level"), GeneConfig("jc.kq", 1.0, 100.0, "log"),
    GeneConfig("cartesian_regularizer.w", 1e-4, 1.0, "log"), GeneConfig("cartesian_regularizer.level", type="level"),
)
"""The default genome (22 genes): weights (x-y, z, rotations) of IK, AC, FC; every task's level; Table I's gains."""

_GAINS = {("ik", "kp"): "kp", ("ik", "k_theta"): "k_theta", ("ac", "lambda_d"): "lambda_d", ("ac", "c_d"): "c_d",
          ("jc", "kq"): "kq", ("fc", "f_d"): "f_d", ("jc", "w"): "jc_weight",
          ("cartesian_regularizer", "w"): "cartesian_regularization"}
_AXES = {1: [0, 0, 0, 0, 0, 0], 2: [0, 0, 0, 1, 1, 1], 3: [0, 0, 1, 2, 2, 2], 6: [0, 1, 2, 3, 4, 5]}
"""Weight gene size -> which entry each local axis (x, y, z, rx, ry, rz) takes."""


def fixed_from_genome(genome: dict, name: str = "fixed") -> FixedControllerConfig:
    """The fixed controller a decoded genome (gene name -> value) defines; unknown gene names raise ConfigError."""
    fixed = FixedControllerConfig(name=name)
    levels, weights, gains = dict(fixed.levels), dict(fixed.weights), {}
    for key, value in genome.items():
        task, _, param = key.partition(".")
        if param == "level" and task in levels:
            levels[task] = int(value)
        elif param == "w" and task in ("ik", "ac", "fc"):
            vals = [float(v) for v in (value if isinstance(value, list) else [value])]
            if len(vals) not in _AXES:
                raise ConfigError(f"nsga2.genes: {key} needs size 1, 2, 3 or 6 (axes grouped as documented in "
                                  f"algorithms/tuning/panda_objectives.py), got {len(vals)}")
            weights[task] = tuple(vals[i] for i in _AXES[len(vals)])
        elif (task, param) in _GAINS:
            gains[_GAINS[(task, param)]] = float(value)
        else:
            raise ConfigError(f"nsga2.genes: {key!r} is not a gene of the Panda objective (task.w, task.level, "
                              f"ik.kp, ik.k_theta, ac.lambda_d, ac.c_d, jc.kq, fc.f_d; tasks {list(levels)})")
    d = {**config_to_dict(fixed), "levels": levels, "weights": {k: list(v) for k, v in weights.items()}, **gains}
    return config_from_dict({"fixed_controller": d}, f"<genome {name}>").fixed_controller


def trial_draws(cfg: ExperimentConfig) -> tuple[list[int], np.ndarray]:
    """The tuning trials: one env seed per trial and the operator-strength factor of each (the same every call)."""
    from envs.panda_eval import trial_seeds

    t = cfg.nsga2.panda
    seeds = trial_seeds(t.trial_seed, t.trials)  # the trials `a3cqp evaluate --seed trial_seed` runs
    lo, hi = t.operator_force_scale
    scales = np.array([np.random.default_rng([s, 1]).uniform(lo, hi) for s in seeds])
    return seeds, scales


@dataclass
class FixedScores:
    """What `evaluate_fixed` measured for B controllers on T trials of each scene."""

    objectives: np.ndarray
    """[B, 3] (OBJECTIVES), means over the trials of every scene."""
    per_trial: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    """Scene -> quantity -> [B, T] (the three objectives per trial, success, diverged, ...)."""
    simulated_seconds: float = 0.0
    """Simulated arm-seconds, all arms and scenes together."""
    wall_seconds: float = 0.0


def evaluate_fixed(fixed: list[FixedControllerConfig], cfg: ExperimentConfig) -> FixedScores:
    """Run every fixed controller on the tuning trials of each scene of `cfg.nsga2.panda`; objectives and details."""
    t0 = time.perf_counter()
    seeds, scales = trial_draws(cfg)
    out = FixedScores(objectives=np.zeros((len(fixed), len(OBJECTIVES))))
    batches = [fixed] if cfg.nsga2.panda.batch == "population" else [[f] for f in fixed]
    for scene in cfg.nsga2.panda.scenes:
        parts = [_rollout(batch, cfg, scene, seeds, scales) for batch in batches]
        per = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "sim_seconds"}
        out.per_trial[scene] = per
        out.objectives += np.stack([per[k].mean(1) for k in OBJECTIVES], axis=1) / len(cfg.nsga2.panda.scenes)
        out.simulated_seconds += sum(p["sim_seconds"] for p in parts)
    out.wall_seconds = time.perf_counter() - t0
    return out


def _rollout(fixed: list[FixedControllerConfig], cfg: ExperimentConfig, scene: str, seeds: list[int],
             scales: np.ndarray) -> dict:
    """One batched simulation: controller b on trial t is arm b·T + t. Per-controller, per-trial scores [B, T]."""
    import torch

    from envs.panda import PandaEnv
    from envs.panda_fixed import FixedArms

    B, T, tc = len(fixed), len(seeds), cfg.nsga2.panda
    n = B * T
    arms = FixedArms([f for f in fixed for _ in range(T)])
    env = PandaEnv(n, cfg, scene=scene, trial_seeds=seeds * B, controller_factory=arms.controller_factory)
    env.operator.force_scale[:] = np.tile(scales, B)
    td = env.reset()
    ctrl = arms.controller
    ctrl.saturated_periods[:] = 0
    task = np.array(env.scene.phase_task)
    last_phase = len(env.scene.phase_names) - 1
    contact_force = getattr(getattr(env.scene, "cfg", None), "contact_force", 1.0)
    q_lo = np.array(PANDA_LIMITS.q_min) + tc.joint_limit_margin
    q_hi = np.array(PANDA_LIMITS.q_max) - tc.joint_limit_margin
    acc = {k: np.zeros(n) for k in ("trk", "n_trk", "ope", "n_ope", "ctc", "n_ctc", "steps", "at_limit")}
    finished = np.zeros(n, dtype=bool)
    end_time = np.zeros(n)
    action = torch.zeros(n, 6, 4)
    steps = 0
    while not finished.all():
        arms.hold(env)
        td["action"] = action
        td = env.step(td)["next"]
        steps += 1
        live = ~finished
        phase = env.scene.phase
        e, f_env = td["e_local"].numpy(), td["f_env_local"].numpy()
        ik = live & (task[phase] == "IK") & (phase != last_phase)
        trk = 100.0 * (np.linalg.norm(e[:, :3], axis=1) + tc.lever * np.linalg.norm(e[:, 3:], axis=1))
        acc["trk"] += np.where(ik, trk, 0.0)
        acc["n_trk"] += ik
        op = live & env.operator.active
        acc["ope"] += np.where(op, np.linalg.norm(td["f_ope_local"].numpy()[:, :3], axis=1), 0.0)
        acc["n_ope"] += op
        touching = live & (task[phase] == "FC") & (np.linalg.norm(f_env[:, :3], axis=1) > contact_force)
        # the block pushes the tool back along its axis: pressing force = −f_env^L_z (local z points into the hole)
        err = np.abs(-f_env[:, 2] - tc.contact_force) + np.linalg.norm(f_env[:, :2], axis=1)
        acc["ctc"] += np.where(touching, err, 0.0)
        acc["n_ctc"] += touching
        acc["at_limit"] += live & ((env.q < q_lo) | (env.q > q_hi)).any(1)
        acc["steps"] += live
        done = td["done"].reshape(n).numpy()
        end_time[live & done] = env.t[live & done]
        finished |= done
    horizon = cfg.panda.max_episode_time
    lost = np.where(env.diverged, np.clip((horizon - end_time) / horizon, 0.0, 1.0), 0.0)
    periods = np.maximum(acc["steps"], 1.0) * env.substeps
    mean = lambda s, c: np.where(acc[c] > 0, acc[s] / np.maximum(acc[c], 1.0), 0.0)  # noqa: E731
    tracking = mean("trk", "n_trk") + tc.failure_tracking * lost
    interaction = mean("ope", "n_ope") + mean("ctc", "n_ctc") + tc.failure_interaction * lost
    metrics = env.scene.metrics()
    success = metrics["success"].all(1) & ~env.diverged if "success" in metrics else np.ones(n, dtype=bool)
    failure = ((~success).astype(float) if "success" in metrics else 0.0) + env.diverged * (1.0 + lost) \
        + env.fallbacks / periods + ctrl.saturated_periods / periods + acc["at_limit"] / np.maximum(acc["steps"], 1.0)
    res = {"tracking_cm": tracking, "interaction_n": interaction, "failure": failure, "success": success,
           "diverged": env.diverged.copy(), "fallback_fraction": env.fallbacks / periods,
           "saturation_fraction": ctrl.saturated_periods / periods,
           "joint_limit_fraction": acc["at_limit"] / np.maximum(acc["steps"], 1.0),
           "operator_force_n": mean("ope", "n_ope"), "contact_force_error_n": mean("ctc", "n_ctc"),
           "episode_s": acc["steps"] * env.adapt.dt}
    out = {k: np.asarray(v, dtype=float).reshape(B, T) for k, v in res.items()}
    out["sim_seconds"] = float(steps * env.adapt.dt * n)
    return out


def pick_config(genome: dict, cfg: ExperimentConfig, k: int) -> dict:
    """`a3cqp pareto --pick K` of a Panda run: the fixed controller as a config `a3cqp evaluate` reads."""
    fixed = fixed_from_genome(genome, name=f"pareto_{k}")
    return {"fixed_controller": config_to_dict(fixed)}


@register("panda", objectives=OBJECTIVES, genes=GENES, chunk_size=8,
          reference_point=(50.0, 50.0, 3.0), to_config=pick_config)
def panda(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """Paper 002 eq. 5-6 on the Panda scenes for a batch of genomes: [B, 3] (tracking cm, interaction N, failure)."""
    import torch

    torch.set_num_threads(1)
    fixed = [fixed_from_genome(g, name=f"genome_{i}") for i, g in enumerate(genomes)]
    from a3cqp_rl.control.controller import fallback_log_quiet

    with fallback_log_quiet():  # a genome whose QP falls back is scored for it (the failure objective)
        return evaluate_fixed(fixed, cfg).objectives
