"""`a3cqp evaluate --scene peg_in_hole|polishing|guidance`: the learned policy and scripted baselines on the same trials.

    a3cqp evaluate --scene peg_in_hole [--policy runs/mine/policy.pt ...] --trials 26 [--seed 0 | --seeds 0,3-10]
                   [--json F]
                   [--config configs/panda_peg_in_hole.yaml] [--controllers learned,ik,ik_fc,equal,vic]
                   [--cycles 1] [--out RUN] [--controller-config PICK.yaml [PICK.yaml ...]] [--workers N]
                   [--threads 1] [--no-park] [--cache DIR]

Every controller runs the same K trials (trial k has the same seed, hence the same misalignment, operator tremor and
sensor noise, for all of them), in batched simulations: the trials split between `--workers` processes (default:
the CPU cores this process may use, at most `MAX_DEFAULT_WORKERS`),
each simulating its share for every controller in one batch; an arm whose episode is over is parked (no contacts)
while its batch runs on (`--no-park` keeps it colliding). Controllers (the adaptation law in the loop):

- learned: the policy (obs [..., 3] -> action [..., 4], e.g. a point-mass policy) on all six axes, eq. 29.
- ik:      fixed weights, IK only on every axis, f_d = 0.
- ik_fc:   IK, and force control on the tool axis (local z) switched on by the first contact force of a contact phase
           (the paper's scripted trigger, section VI-B1): z weights go linearly to FC in `SWITCH_TIME`, f_d ramps at
           σf to `FC_FORCE`; back to IK when the phase ends.
- equal:   fixed weights 1/3 each on every axis, f_d = `FC_FORCE` on z.
- fixed controllers (`--controller-config FILE`, e.g. a Pareto pick of `a3cqp pareto --pick K`): the file's
           `fixed_controller` section: constant per-axis weights and f_d, its own gains and strict priority levels
           (envs/panda_fixed.py). With any of them, every arm of the batch runs the per-robot controller
           (PopulationController, the Python QP path: slower, the same numbers to rounding for the others).
- vic:     a variable-impedance baseline in the style of robosuite's OSC (impedance gains as actions): IK only, with
           a hand-tuned stiffness schedule per local axis (scales of Table I's k_p, k_θ): 1 in free motion; after
           the first contact force `panda.vic_contact_scale` (soft along the tool axis, stiff across it);
           `panda.vic_operator_scale` while the operator holds the handle.

The scripted baselines know the scene's phase (which phases expect contact or the operator); the learned policy only
sees eq. 26. Peg-in-hole prints Table VI (success rate, insertion time, misalignment at the first contact) next to
the paper's, then the learned policy against each baseline on the same trials (`paired`: the insertion-time
difference over the insertions both made, with its standard error, and the insertions only one of them made;
envs/panda_report.py makes these tables and the JSON document); polishing and guidance print the metrics their
scenes define (envs/scenarios.py). `--seeds` runs the trials of each seed as `--seed` does and pools them (a
difference of a few tenths of a second needs several seeds to show). Several
`--policy` paths (e.g. the runs of a training sweep) are evaluated one after the other on the same trials, and a
line per policy with the scene's headline metrics ends the output (picking a run that transfers). `--cache DIR`
keeps each seed's (and policy's) result as it ends; the same command again reads those back (envs/eval_cache.py).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np
import torch

from a3cqp_rl import worker_start
from a3cqp_rl.checkpoint import STDOUT, write_atomic, write_text_atomic
from a3cqp_rl.cli import add_set_option, error_exit, help_summary, seed_arg
from a3cqp_rl.exceptions import A3CQPError
from a3cqp_rl.run_folder import check_output_path, policy_file
from a3cqp_rl.transfer import (FREE_MOTION_E, GUIDED_OBS, free_motion_rates, guided_rates,  # noqa: F401 (re-exported)
                                raises_ik, yields)
from a3cqp_rl.worker_start import MAX_DEFAULT_WORKERS, default_workers  # noqa: F401 (re-exported)
from envs import eval_cache
from envs.evaluate_cli import PANDA_WORKER_IMPORTS as WORKER_IMPORTS
from envs.panda_report import (EvalResult, format_paired, format_policy_ranking, format_reference_rules, format_table,
                               format_targets, reference_rules, to_json)
from envs.reach import reach_warning

if TYPE_CHECKING:  # annotations only
    from a3cqp_rl.config import ExperimentConfig, FixedControllerConfig, PandaEnvConfig
    from a3cqp_rl.control.controller import ControllerOptions
    from a3cqp_rl.transfer import Policy

__all__ = ["main", "evaluate", "evaluate_seeds", "trial_seeds", "free_motion_rates", "free_motion_warning",
           "guided_rates", "guided_warning", "sensing_warning", "limit_stress", "LimitStress", "CONTROLLERS",
           "load_fixed_controller"]

ARM_BYTES = 2**20
"""Memory one simulated arm holds during an evaluation, its record included, rounded up (measured 2026-12-01: 0.6 MB
per arm of PandaEnv on the peg scene)."""
CONTROLLERS = ("learned", "ik", "ik_fc", "equal", "vic")
FC_FORCE = 10.0
"""Desired contact force of the scripted force-control baselines [N] (half of Table II's f̄_d)."""
SWITCH_TIME = 1.0
"""Time over which the scripted baselines move their weights [s] (σw = 6 takes a task from off to on in ~1 s)."""
RECORD_KEYS = ("time", "phase", "e_local", "f_env_local", "f_ope_local", "weights", "f_d")


def _scripted(env, controllers: list[str], trials: int, latched: np.ndarray, since: np.ndarray,  # noqa: ANN001
              contact_force: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weights [N, 6, 3], f_d [N, 6], stiffness scales [N, 6] and the mask of scripted arms for this step."""
    n = env.num_envs
    task = np.array(env.scene.phase_task)[env.scene.phase]  # what each arm's phase expects: IK, FC or AC
    touching = np.linalg.norm(env.f_env[:, :3], axis=1) > contact_force
    fc_phase = task == "FC"
    latched &= fc_phase
    newly = fc_phase & touching & ~latched
    since[newly] = env.t[newly]
    latched |= newly
    ramp = np.where(latched, np.clip((env.t - since) / SWITCH_TIME, 0.0, 1.0), 0.0)
    f_ramp = np.where(latched, np.clip((env.t - since) * env.adapt.sigma_f, 0.0, FC_FORCE), 0.0)
    W = np.zeros((n, 6, 3))
    W[..., 0] = 1.0
    f_d = np.zeros((n, 6))
    scale = np.ones((n, 6))
    ctrl = np.repeat(np.array(controllers), trials)
    m = ctrl == "ik_fc"
    W[m, 2] = (1.0 - ramp[m, None]) * np.array([1.0, 0.0, 0.0]) + ramp[m, None] * np.array([0.0, 0.0, 1.0])
    f_d[m, 2] = f_ramp[m]
    m = ctrl == "equal"
    W[m] = 1.0 / 3.0
    f_d[m, 2] = FC_FORCE
    m = ctrl == "vic"
    scale[m] = np.where(latched[m, None], np.array(env.pcfg.vic_contact_scale), 1.0)
    op = m & (task == "AC") & env.operator.active
    scale[op] = env.pcfg.vic_operator_scale
    return W, f_d, scale, ctrl != "learned"


def trial_seeds(seed: int, trials: int) -> list[int]:
    """The env seed of each of the `trials` trials of `a3cqp evaluate --seed SEED` (one spawned stream per trial, so
    trial k is the same whatever the number of trials)."""
    return [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(trials)]


def evaluate(scene: str, policy_path: str | Path | None, trials: int, seed: int = 0,
             config: ExperimentConfig | None = None,
             controllers: tuple[str, ...] = CONTROLLERS, cycles: int | None = None,
             progress: bool = True, fixed: Sequence = (), sim_threads: int = 1, workers: int = 1,
             park: bool = True, record_trial: int = 0) -> EvalResult:
    """Run every controller on the same `trials` trials of `scene` (batched simulations); return the metrics.

    `policy_path` None: the config's panda.policy (for the learned controller). `fixed`: FixedControllerConfig
    objects run after `controllers` under their own names. `sim_threads`: PandaEnv's (MuJoCo models and threads).
    `workers` > 1: the trials are split into that many contiguous groups, each run (all controllers) as its own
    batched simulation in its own process; the metrics are the same (each arm sits where it sits in the batch of
    all trials, and MuJoCo solves every arm's constraints on their own, PandaSim's `warmstart`: seed 0's 130 trials
    bit for bit; a smaller batch can still stop MuJoCo's solver at another iteration, a round-off that contact may
    grow). `park`: an arm whose episode is over is parked (PandaEnv.park: no collisions, IK holding) while the
    others run on; its metrics are final by then, and the others' are the same as unparked (to round-off).
    `record_trial`: the trial whose episodes (every controller's) are recorded (`EvalResult.episodes`)."""
    from a3cqp_rl.config import ExperimentConfig, config_from_dict, config_to_dict

    cfg = config or ExperimentConfig()
    if cycles is not None and scene != "peg_in_hole":
        raise ValueError(f"--cycles counts peg-in-hole insertions; the {scene} scene has its own procedure "
                         "(its config section)")
    if cycles is not None:
        d = config_to_dict(cfg)
        d["panda"]["peg_in_hole"]["cycles"] = int(cycles)
        cfg = config_from_dict(d, "<evaluate --cycles>")
    unknown = [c for c in controllers if c not in CONTROLLERS]
    if unknown:
        raise ValueError(f"unknown controller(s) {unknown}; choose from {list(CONTROLLERS)}")
    if "learned" in controllers:
        policy_path = policy_path if policy_path is not None else cfg.panda.policy
        if policy_path is None:
            raise ValueError("the learned controller needs --policy PATH or panda.policy (or leave it out of "
                             "--controllers)")
    by_name = {f.name: f for f in fixed}
    if len(by_name) != len(fixed) or set(by_name) & set(CONTROLLERS):
        raise ValueError(f"fixed controllers need distinct names other than {list(CONTROLLERS)}, got "
                         f"{[f.name for f in fixed]}")
    strong = [f"{f.name} ({f.f_d:g} N)" for f in fixed if f.f_d > cfg.adaptation.f_d_max]
    if strong:  # its own file was checked against its own bound: this scene's may be lower
        raise ValueError(f"fixed controller f_d above this evaluation's adaptation.f_d_max ({cfg.adaptation.f_d_max:g} "
                         f"N), the bound of every other controller's f_d: {', '.join(strong)}")
    names = list(controllers) + list(by_name)
    if not names:
        raise ValueError("no controller to evaluate")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if isinstance(record_trial, bool) or not isinstance(record_trial, int) or not 0 <= record_trial < trials:
        raise ValueError(f"the recorded trial must be one of the trials, 0 .. {trials - 1}, got {record_trial!r}")
    seeds = trial_seeds(seed, trials)
    groups = [g.tolist() for g in np.array_split(np.arange(trials), min(workers, trials))]
    rec = next(i for i, g in enumerate(groups) if record_trial in g)  # the worker that records it
    # each worker's arms sit where they sit in the batch of all trials: the same coordinates, the same round-off
    jobs = [(scene, policy_path, [seeds[k] for k in g], cfg, tuple(controllers), tuple(fixed), sim_threads,
             progress, groups[rec].index(record_trial) if i == rec else None, park,
             None if len(groups) == 1 else (len(names) * trials, [j * trials + k for j in range(len(names)) for k in g]))
            for i, g in enumerate(groups)]
    t_wall = time.perf_counter()
    if len(jobs) == 1:
        parts = [_run_job(jobs[0])]
    else:
        parts = _run_workers(jobs, len(names) * trials, progress)
    seconds = time.perf_counter() - t_wall
    scene_name = parts[0]["scene"]
    metrics = {c: {k: np.concatenate([p["metrics"][c][k] for p in parts]) for k in parts[0]["metrics"][c]}
               for c in names}
    episodes = {c: {**ep, "trial": np.array(record_trial)} for c, ep in parts[rec]["episodes"].items()}
    return EvalResult.from_metrics(scene_name, metrics, episodes, seconds,
                                   float(sum(p["sim_seconds"] for p in parts)), (seed,))


def evaluate_seeds(scene: str, policy_path: str | Path | None, trials: int, seeds: Sequence[int],
                   cache: str | Path | None = None, policy_fingerprint: str | None = None,
                   log: Callable[[str], None] | None = None, **kwargs) -> EvalResult:
    """`evaluate` on the `trials` trials of each seed in `seeds` (each run as `evaluate` runs it alone, so a seed's
    trials give the same numbers as `--seed S`), pooled: every metric over all len(seeds) × trials trials; the
    recorded episodes are the first seed's. `cache`: a folder keeping each seed's result as it ends, read back on
    a rerun with the same settings (envs/eval_cache.py; `log` says which)."""
    if not seeds:
        raise ValueError("seeds must name at least one seed")
    runs = [eval_cache.cached(evaluate, cache, scene, policy_path, trials, int(s), policy_fingerprint, log, **kwargs)
            for s in seeds]
    metrics = {c: {k: np.concatenate([r.metrics[c][k] for r in runs]) for k in runs[0].metrics[c]}
               for c in runs[0].metrics}
    res = EvalResult.from_metrics(runs[0].scene, metrics, runs[0].episodes, sum(r.seconds for r in runs),
                                  sum(r.sim_seconds for r in runs), tuple(int(s) for s in seeds))
    res.read_back = tuple(s for r in runs for s in r.read_back)
    return res


_PROGRESS_QUEUE = None
"""In a worker process of `_run_workers`: the queue its progress goes to (the parent draws one bar for all)."""


def _init_worker(queue) -> None:  # noqa: ANN001
    """Worker process set-up: one torch thread (the workers share the cores), progress to the parent's `queue`."""
    global _PROGRESS_QUEUE
    torch.set_num_threads(1)
    _PROGRESS_QUEUE = queue


class _QueueBar:
    """The part of tqdm's interface `_run` uses, sent to the parent process: arms whose episode ended, the worker's
    simulated time [s]."""

    def __init__(self, queue, worker: int) -> None:  # noqa: ANN001
        self.queue, self.worker = queue, worker

    def update(self, n: int) -> None:
        self.queue.put((self.worker, n, None))

    def set_simulated(self, seconds: float) -> None:
        self.queue.put((self.worker, 0, seconds))

    def close(self) -> None:
        pass


def _run_workers(jobs: list[tuple], arms: int, progress: bool) -> list[dict]:
    """`_run_job` of each job in its own process (forked from a server that has imported `WORKER_IMPORTS`, or
    spawned: `a3cqp_rl.worker_start`); one progress bar over all `arms`, fed by the workers through a queue."""
    import queue as queue_mod
    from concurrent.futures import wait

    ctx = worker_start.context(WORKER_IMPORTS)
    q = ctx.Queue()
    bar = _progress(arms, progress)
    simulated = [0.0] * len(jobs)

    def drain() -> None:
        try:
            while True:
                worker, n, sim = q.get_nowait()
                if sim is None:
                    bar.update(n)
                else:
                    simulated[worker] = sim
                    bar.set_simulated(max(simulated))
        except queue_mod.Empty:
            pass

    jobs = [job + (i,) for i, job in enumerate(jobs)]
    try:
        with worker_start.pool(len(jobs), ctx, "envs.panda_eval:_init_worker", q) as pool:
            futures = [pool.submit(_run_job, job) for job in jobs]
            while not all(f.done() for f in futures):
                wait(futures, timeout=0.5)
                drain()
            parts = [f.result() for f in futures]  # a worker's exception is raised here
        drain()  # what the workers sent as they ended
    finally:
        bar.close()
    return parts


def _run_job(job: tuple) -> dict:
    """`_run(*job)`, the controller's log line per fallback step giving way to the table's count per trial."""
    from a3cqp_rl.control.controller import fallback_log_quiet

    with fallback_log_quiet():
        return _run(*job)


def _run(scene: str, policy_path, trial_seeds: list[int], cfg, controllers: tuple[str, ...],  # noqa: ANN001
         fixed: tuple, sim_threads: int, progress: bool, record: int | None, park: bool,
         grid: tuple[int, list[int]] | None = None, worker: int = 0) -> dict:
    """One batched simulation of every controller on the trials of `trial_seeds`: the per-controller metrics
    (arrays [trials, ...]), the recorded episodes of its trial `record` (an index into `trial_seeds`; None: none)
    and the simulated arm-seconds.
    `park`: arms whose episode is over are parked (PandaEnv.park) until the last one ends. `grid`: PandaEnv's."""
    from envs.panda import PandaEnv
    from envs.panda_fixed import FixedArms

    policy = None
    if "learned" in controllers:
        from algorithms.a2c import load_policy

        policy = load_policy(policy_path)
    by_name = {f.name: f for f in fixed}
    controllers = list(controllers) + list(by_name)
    trials = len(trial_seeds)
    arms = FixedArms([by_name.get(c) for c in controllers for _ in range(trials)]) if fixed else None
    n = len(controllers) * trials
    env = PandaEnv(n, cfg, scene=scene, trial_seeds=list(trial_seeds) * len(controllers),
                   controller_factory=arms.controller_factory if arms else None,
                   sim_threads=sim_threads, grid=grid)
    contact_force = getattr(getattr(env.scene, "cfg", None), "contact_force", 1.0)
    n = env.num_envs
    latched, since = np.zeros(n, dtype=bool), np.zeros(n)
    rec_arms = np.arange(len(controllers)) * trials + (record or 0)  # that trial of each controller
    rec_keys = RECORD_KEYS + env.signal_keys + ("q",)
    episodes = {c: {k: [] for k in rec_keys} for c in controllers} if record is not None else {}
    td = env.reset()
    finished = np.zeros(n, dtype=bool)
    fallbacks = np.zeros(n, dtype=np.int64)  # each trial's QP fallback periods, taken when its episode ends
    relaxed = np.zeros(n, dtype=np.int64)  # and its periods on the least-violation QP
    # in a worker process the parent draws the bar (`_run_workers`)
    bar = _QueueBar(_PROGRESS_QUEUE, worker) if progress and _PROGRESS_QUEUE is not None else _progress(n, progress)
    steps = 0
    while not finished.all():
        W, f_d, scale, scripted = _scripted(env, controllers, trials, latched, since, contact_force)
        if arms is not None:  # fixed controllers: their own constant weights and f_d (scale 1, not 'learned')
            W, f_d = arms.merge(W, f_d)
        env.hold_weights(scripted, W, f_d)
        env.stiffness_scale[:] = scale
        action = torch.zeros(n, 6, 4)
        if policy is not None:
            learned = ~scripted
            action[learned] = policy(td["observation"][learned])
        td["action"] = action
        td = env.step(td)["next"]
        steps += 1
        live = [(rec, j) for j, (rec, arm) in enumerate(zip(episodes.values(), rec_arms)) if not finished[arm]]
        for k in rec_keys if live else ():  # one gather per signal for every recorded arm (fancy indexing copies)
            rows = (env.q if k == "q" else td[k].numpy())[rec_arms]
            for rec, j in live:
                rec[k].append(rows[j])
        newly = td["done"].reshape(n).numpy() & ~finished
        fallbacks[newly] = env.fallbacks[newly]
        relaxed[newly] = env.relaxations[newly]
        if park:
            env.park(np.flatnonzero(newly))
        finished |= newly
        if newly.any():
            bar.update(int(newly.sum()))
        if steps % 100 == 0:
            bar.set_simulated(float(env.t.max()))
    bar.close()
    metrics = env.scene.metrics()
    metrics["diverged"] = env.diverged.copy()
    metrics["joint_limit_excess"] = env.joint_limit_excess.copy()
    metrics["joint_speed_ratio"] = env.joint_speed_ratio.copy()
    metrics["qp_fallbacks"] = fallbacks
    metrics["qp_relaxed"] = relaxed
    per = {c: {k: np.asarray(v)[j * trials:(j + 1) * trials] for k, v in metrics.items()}
           for j, c in enumerate(controllers)}
    meta = {"scene": env.scene.name, "tool": env.scene.tool, "scene_xml": env.scene.mjcf(),
            "phase_names": np.array(env.scene.phase_names), "phase_task": np.array(env.scene.phase_task)}
    # peg-in-hole: the scene's own moments of the recorded trial, per cycle (timed on the true contact wrench)
    moments = ({"contact_time": env.scene.contact_time, "bore_time": env.scene.bore_time}
               if env.scene.name == "peg_in_hole" else {})
    eps = {c: {**{k: np.asarray(v) for k, v in rec.items()}, **meta,
               **{k: np.asarray(v[arm], dtype=float) for k, v in moments.items()}}
           for (c, rec), arm in zip(episodes.items(), rec_arms)}
    return {"scene": env.scene.name, "metrics": per, "episodes": eps, "sim_seconds": steps * env.adapt.dt * n}


def guided_warning(policy: Policy) -> str | None:
    """A warning when a policy does not yield to the operator's push (mean ẇ2 <= 0 or ḟd >= 0 at GUIDED_OBS): on
    the Panda it then pushes back with force control and the operator cannot guide the arm (docs/panda.md,
    "Yielding to the operator is a second draw"); None otherwise."""
    r = guided_rates(policy)
    if yields(r):
        return None
    return (f"warning: under the operator's force (|f_ope|/f̄_ope 0.1-0.5) this policy does not both raise admittance "
            f"and lower f_d (mean ẇ2 {r[1]:+.2f}, ḟd {r[3]:+.2f}): on the Panda the operator will probably not be able "
            "to guide it (polishing relocations, guidance; docs/panda.md)")


def free_motion_warning(policy: Policy) -> str | None:
    """A warning when a policy does not raise IK's weight over admittance's in free motion (mean ẇ1 <= 0 or ẇ2 >= 0
    at FREE_MOTION_E): on the Panda it then lets the reference go (docs/panda.md, "Which point-mass policies
    transfer"); None otherwise."""
    r = free_motion_rates(policy)
    if raises_ik(r):
        return None
    # what the measured policies of each kind inserted (docs/panda.md, "Keeping the parameters that transfer")
    seen = ("every such point-mass policy measured inserted at most 2 of 26 pegs" if r[0] <= 0.0 else
            "of the 7 such point-mass policies measured, 5 inserted at most 5 of 26 pegs, 2 inserted 21 and 24")
    what = "raise IK's weight" if r[0] <= 0.0 else "raise IK's weight over admittance's"
    return (f"warning: in free motion (|e|/ē {FREE_MOTION_E[0]}-{FREE_MOTION_E[-1]}, no force) this policy does not "
            f"{what} (mean ẇ1 {r[0]:+.2f}, ẇ2 {r[1]:+.2f}, ẇ3 {r[2]:+.2f}): on the Panda it will probably not follow "
            f"the reference ({seen}; docs/panda.md)")


def sensing_warning(panda: PandaEnvConfig) -> str | None:
    """A warning when a PandaEnvConfig's sensors are biased but not tared, or noisy while the agents observe single
    samples: a learned policy then yields to phantom operator forces (docs/panda.md, "Imperfect force sensing")."""
    s = panda.sensors
    biased = s.ft_force_bias > 0 or s.ft_torque_bias > 0 or s.joint_torque_bias > 0
    noisy = s.ft_force_noise > 0 or s.ft_torque_noise > 0 or s.joint_torque_noise > 0
    why = [w for w, on in (("biased but not tared (panda.sensors.tare_time: 0)", biased and s.tare_time == 0),
                           ("noisy while the agents observe single samples (panda.observation_filter: last)",
                            noisy and panda.observation_filter == "last")) if on]
    if not why:
        return None
    return ("warning: the force sensors are " + " and ".join(why) + ": the learned policy reads that as an "
            "operator's push and yields to it (with the peg config's sensing: 0-1 of 4 insertions); "
            "configs/panda_peg_in_hole_sensors.yaml tares them and observes each period's mean")


@dataclass(frozen=True)
class LimitStress:
    """Worst case of `limit_stress`: how far the arms went past their datasheet limits."""

    worst_excess: float
    """Largest excess of a joint position past its datasheet limit [rad] (negative: always inside)."""
    joint: int
    """Its joint (1-7)."""
    arm: int
    """Its arm."""
    worst_torque_ratio: float
    """Largest |τ|/τ_max over every joint, arm and control period."""
    diverged: int
    """Arms flagged as diverged at the end."""
    fallbacks: int
    """1 kHz periods of one arm in which the QP failed and the controller braked."""
    worst_speed_ratio: float = math.nan
    """Largest |q̇|/q̇_max over every joint, arm and control period (the env's `joint_speed_ratio`)."""
    relaxed: int = 0
    """1 kHz periods of one arm in which the QP failed and its least-violation QP gave the torque
    (`panda.qp_failure: least_violation`)."""


def limit_stress(num_envs: int, steps: int, seed: int, config: ExperimentConfig | None = None,
                 controller_options: ControllerOptions | None = None,
                 hold: int = 20) -> LimitStress:
    """Random actions, each held for `hold` agent steps, on `num_envs` Pandas for `steps` agent steps (done arms
    reset): the worst joint-position excess (the env's `joint_limit_excess`, every 1 kHz control period), joint-speed
    and torque ratios, divergences and QP fallbacks (the reliability check of docs/panda.md)."""
    from a3cqp_rl.robot import PANDA_LIMITS
    from envs.panda import PandaEnv

    env = PandaEnv(num_envs, config, seed=seed, controller_options=controller_options)
    gen = torch.Generator().manual_seed(seed)
    tau_max = np.array(PANDA_LIMITS.tau_max)
    worst, joint, arm, tau, speed = -np.inf, -1, -1, 0.0, 0.0

    def record(idx: np.ndarray) -> None:  # the episodes of arms `idx` end: their worst excess and speed count
        nonlocal worst, joint, arm, speed
        if not len(idx):
            return
        speed = max(speed, float(env.joint_speed_ratio[idx].max()))
        if env.joint_limit_excess[idx].max() > worst:
            a = int(idx[env.joint_limit_excess[idx].argmax()])
            worst, joint, arm = float(env.joint_limit_excess[a]), int(env.joint_limit_joint[a]), a

    td, action = env.reset(), torch.zeros(num_envs, 6, 4)
    for k in range(steps):
        if k % hold == 0:
            action = torch.rand(num_envs, 6, 4, generator=gen) * 2 - 1
        td["action"] = action
        td = env.step(td)["next"]
        tau = max(tau, float(np.max(np.abs(env.tau) / tau_max)))
        done = td["done"].reshape(num_envs)
        if done.any():
            record(np.flatnonzero(done.numpy()))
            td = env.reset(td.empty().set("_reset", done.reshape(num_envs, 1)))
    record(np.arange(num_envs))
    return LimitStress(worst, joint + 1, arm, tau, int(env.diverged.sum()), env.ctrl.fallback_count, speed,
                       env.ctrl.relaxed_count)


def load_fixed_controller(path: str | Path) -> FixedControllerConfig:
    """The FixedControllerConfig of a YAML file's `fixed_controller` section (what `a3cqp pareto --pick K` writes)."""
    from a3cqp_rl.config import load_config

    if not Path(path).is_file():
        raise FileNotFoundError(f"controller config not found: {path}")
    fixed = load_config(path).fixed_controller
    if fixed is None:
        raise ValueError(f"{path} has no fixed_controller section (write one with `a3cqp pareto --out DIR --pick K`)")
    return fixed


def _progress(arms: int, enabled: bool):  # noqa: ANN202
    """Progress over the batch's arms whose episode is over (an episode's length is known only when it ends)."""
    from tqdm import tqdm

    class Bar(tqdm):
        def set_simulated(self, seconds: float) -> None:
            self.set_postfix_str(f"{seconds:.0f} s into the episodes", refresh=False)

    bar = Bar(total=arms, disable=not enabled, mininterval=2.0, file=sys.stderr,
              bar_format="{l_bar}{bar}| {n}/{total} episodes over [{elapsed}{postfix}]")
    bar.set_simulated(0.0)
    return bar


def _seed_list(text: str) -> list[int]:
    from algorithms.train import parse_seeds  # '0,3-10' -> [0, 3, ..., 10]

    return parse_seeds(text)


def write_episodes(out: Path, episodes: dict[str, dict]) -> list[str]:
    """Each controller's recorded episode to out/episode_<controller>.npz, atomically (a stopped write leaves the
    previous file, not half of one); the episodes of controllers an earlier run in `out` recorded and this one did
    not are removed with their plots (results.json, replaced, no longer describes them). Returns their names."""
    out = Path(out)
    for c, ep in episodes.items():
        write_atomic(out / f"episode_{c}.npz", lambda f, ep=ep: np.savez_compressed(f, **ep))
    stale = sorted(p.stem.removeprefix("episode_") for p in out.glob("episode_*.npz")
                   if p.stem.removeprefix("episode_") not in episodes)
    for c in stale:
        for old in out.glob(f"episode_{c}*"):
            if old.stem in (f"episode_{c}", f"episode_{c}_strip"):  # not another controller's (ik vs ik_fc)
                old.unlink(missing_ok=True)
    return stale


def _json_text(doc: dict) -> str:
    return json.dumps(doc, indent=2)


def _write_json(path: Path, doc: dict) -> None:
    write_text_atomic(path, _json_text(doc))


def _default_config(scene: str) -> Path | None:
    """configs/panda_<scene>.yaml of the working directory, else of this checkout; None where neither exists."""
    from a3cqp_rl.config import project_path

    path = project_path(Path("configs") / f"panda_{scene}.yaml")
    return path if path.is_file() else None


def _policy_file(path: str | Path | None, from_cli: bool, cfg_path: str | Path | None,
                 set_on_cli: bool = False) -> Path | None:
    """The policy.pt that `--policy PATH` (a file or a run folder) or the config's panda.policy names; raises
    FileNotFoundError naming where the path came from. A relative panda.policy is looked for in the working directory,
    then in this checkout (as the config itself: the shipped policy from any folder)."""
    from a3cqp_rl.config import project_path

    if path is None:
        return None
    path = Path(path) if from_cli else project_path(path)
    path = policy_file(path)
    if not path.is_file():
        where = ("" if from_cli else " (panda.policy of --set)" if set_on_cli else
                 (f" (panda.policy of {cfg_path}: the repository ships it; pass --policy PATH, or leave learned out "
                  "of --controllers)"))
        raise FileNotFoundError(f"policy file not found: {path}{where}")
    return path


def _document(args: argparse.Namespace, cfg_path: str | Path | None, res: EvalResult, policy: Path | None,
              prints: str | None, panda: PandaEnvConfig) -> dict:
    """One evaluation's JSON document: the metrics, the run's settings (`panda`: its config) and the policy."""
    doc = to_json(res)
    doc["workers"] = min(args.workers, args.trials)  # the trials split into at most this many groups
    doc["config"], doc["overrides"] = None if cfg_path is None else str(cfg_path), list(args.overrides)
    doc["ik_reference_rules"] = reference_rules(panda)
    if policy is not None:
        doc["policy"], doc["policy_fingerprint"] = str(policy), prints
    return doc


def _print_report(args: argparse.Namespace, cfg_path: str | Path | None, res: EvalResult, policy: Path | None,
                  prints: str | None, doc: dict) -> None:
    """Print one evaluation (`doc`: its JSON document, for the worker count and the reference rules): header, table,
    paired differences, targets."""
    used = doc["workers"]
    which = f"seed {args.seed}" if args.seeds is None else f"seeds {','.join(map(str, args.seeds))} pooled"
    given = f" with {', '.join(args.overrides)}" if args.overrides else ""
    cycles = next(iter(res.summary.values())).get("cycles", 1)
    each = f" of {cycles} insertion cycles each" if cycles > 1 else ""
    # a seed read back from --cache costs nothing now: its wall time is the one measured when it was simulated
    back = len(res.read_back)
    then = ("" if not back else
            f"; {'every seed' if back == len(res.seeds) else f'{back} of {len(res.seeds)} seeds'} read back from "
            f"{args.cache}, the wall time as measured then")
    n = args.trials * len(res.seeds)
    print(f"{res.scene}: {n} trial{'' if n == 1 else 's'} per controller{each}, {which}, config "
          f"{cfg_path or 'defaults'}"
          f"{given}; "
          f"{res.sim_seconds:.0f} s simulated in {res.seconds:.1f} s ({res.sim_seconds / res.seconds:.1f}x real time, "
          f"{used} worker{'s' if used > 1 else ''}{then})")
    if policy is not None:
        print(f"learned: {policy} (parameters {prints})")
    if rules := format_reference_rules(doc["ik_reference_rules"], list(res.summary)):
        print(rules)
    print(format_table(res))
    primary = "learned" if "learned" in res.summary else next(iter(res.summary))
    for lines in (format_paired(res, primary), format_targets(res, primary)):
        if lines:
            print(lines)


def main(argv: list[str] | None = None) -> int:
    """CLI entry for `a3cqp evaluate --scene ...`; returns an exit code."""
    p = _parser()
    args, unknown = p.parse_known_args(argv)
    if unknown:  # the point mass's --episodes given with --scene: say what the scenes take instead
        hint = " (--episodes is the point mass's: the scenes take --trials)" if any(
            u.split("=", 1)[0] == "--episodes" for u in unknown) else ""
        p.error(f"unrecognized arguments: {' '.join(unknown)}{hint}")
    if args.json != STDOUT:
        return _cli(args)
    json_out = sys.stdout
    with contextlib.redirect_stdout(sys.stderr):  # standard output: the JSON alone, for a pipe
        return _cli(args, json_out)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="a3cqp evaluate", description=help_summary(__doc__))
    p.add_argument("--scene", required=True, choices=["peg_in_hole", "polishing", "guidance"],
                   help="the task on the simulated Panda: Table VI's peg-in-hole, Fig. 8's polishing, or free guidance "
                   "by the operator")
    p.add_argument("--policy", nargs="+", default=None, metavar="PATH",
                   help="policy.pt of the learned controller (a run folder also works; default: the config's "
                   "panda.policy); several: each on the same trials, one after the other, then a line per policy")
    p.add_argument("--trials", type=int, default=26, help="trials per controller (default: 26, Table VI's)")
    seeds = p.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=seed_arg, default=0, help="seed of the trials (default: 0)")
    seeds.add_argument("--seeds", type=_seed_list, default=None, metavar="LIST",
                       help="several seeds, e.g. 0,3-10: each seed's trials as --seed runs them, pooled")
    p.add_argument("--config", default=None, help="YAML config (default: configs/panda_<scene>.yaml of the working "
                   "directory, else of this checkout)")
    add_set_option(p, "panda.blocked_force=2.0", "kept in the JSON")
    p.add_argument("--controllers", default=",".join(CONTROLLERS), help="comma-separated subset of "
                   + ",".join(CONTROLLERS))
    p.add_argument("--cycles", type=int, default=None, help="peg-in-hole insertions per episode (Fig. 7: 3)")
    p.add_argument("--json", default=None, help="write the metrics to this JSON file (-: to standard output, the "
                   "report then to standard error)")
    p.add_argument("--out", default=None, help="run folder: results.json and the recorded episodes (episode_*.npz, "
                   "for `a3cqp plot episode`; with --seeds, the first seed's)")
    p.add_argument("--controller-config", nargs="+", default=[], metavar="FILE",
                   help="YAML file(s) with a fixed_controller section (e.g. a Pareto pick), evaluated as extra "
                        "controllers")
    p.add_argument("--threads", type=int, default=1, help="threads (MuJoCo models) the arms' physics is split into "
                   "(default 1; the same numbers; slower on a loaded machine)")
    p.add_argument("--workers", type=int, default=None, help="processes the trials are split among, each simulating "
                   "its share of the trials for every controller (default: the CPU cores this process may use, at most "
                   f"{MAX_DEFAULT_WORKERS}; 1: one batched simulation; any count gives the same numbers but for rare "
                   "round-off)")
    p.add_argument("--no-park", action="store_true", help="keep simulating finished arms' contacts until the last "
                   "episode ends (by default they are parked: the same metrics to round-off, less time)")
    p.add_argument("--record-trial", type=int, default=None, metavar="K",
                   help="the trial whose episodes --out records for `a3cqp plot episode` (default 0)")
    p.add_argument("--cache", default=None, metavar="DIR", help="keep each seed's (and policy's) result in DIR as it "
                   "ends; the same command again reads the finished ones back (a stopped sweep resumes)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _cli(args: argparse.Namespace, json_out: TextIO | None = None) -> int:
    """The evaluation the parsed `args` ask for; `json_out`: the stream of `--json -`."""
    torch.set_num_threads(1)
    docs: list[dict] = []
    try:
        from a3cqp_rl.config import check_fits, load_config, parse_overrides, read_config_file

        if args.trials < 1:
            raise ValueError(f"--trials must be >= 1, got {args.trials}")
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        if args.workers is None:
            args.workers = default_workers()
        if args.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {args.workers}")
        for flag, path, folder in (("--json", args.json, False), ("--out", args.out, True),
                                   ("--cache", args.cache, True)):
            if path is not None and not (flag == "--json" and path == STDOUT):
                check_output_path(path, flag, folder=folder)  # before the simulation, not after it
        if args.record_trial is not None:
            if not 0 <= args.record_trial < args.trials:
                raise ValueError(f"--record-trial {args.record_trial} is not one of the trials, 0 .. "
                                 f"{args.trials - 1} (--trials {args.trials})")
            if not args.out:
                raise ValueError("--record-trial picks the trial that --out records: give --out DIR too")
        cfg_path = args.config if args.config is not None else _default_config(args.scene)
        overrides = parse_overrides(args.overrides)
        if "seed" in overrides:  # the config's seed is training's; the trials are drawn from --seed / --seeds
            raise ValueError(f"--set seed={overrides['seed']} does not choose the trials: use --seed "
                             f"{overrides['seed']} (or --seeds)")
        if cfg_path is not None and "panda" not in read_config_file(cfg_path):  # e.g. a point-mass training config
            raise ValueError(f"{cfg_path} has no panda: section: the Panda scenes' settings would all be defaults; "
                             f"pass configs/panda_{args.scene}.yaml or a config based on it")
        cfg = load_config(cfg_path, overrides)
        if cfg.panda.scene != args.scene:  # the scene's own sections would be the dataclass defaults, unnoticed
            source = ("--set panda.scene" if "scene" in overrides.get("panda", {})
                      else f"{cfg_path or 'the default config'} (panda.scene)")
            raise ValueError(f"{source} is for the {cfg.panda.scene} scene; for --scene {args.scene} pass its config "
                             f"(configs/panda_{args.scene}.yaml) or set panda.scene: {args.scene} in yours")
        controllers = tuple(c.strip() for c in args.controllers.split(",") if c.strip())
        twice = sorted({c for c in controllers if controllers.count(c) > 1})
        if twice:
            raise ValueError(f"--controllers names {', '.join(twice)} more than once")
        check_fits(args.trials * (len(controllers) + len(args.controller_config)) * ARM_BYTES,
                   f"--trials {args.trials:,}: {args.trials * (len(controllers) + len(args.controller_config)):,} "
                   "simulated arms", "fewer trials per seed (--seeds pools seeds one after the other)")
        fixed = [load_fixed_controller(f) for f in args.controller_config]
        named = {}  # `--pick K` names every run's pick K `pareto_K`: two runs' picks can clash
        for path, f in zip(args.controller_config, fixed):
            if f.name in named:
                raise ValueError(f"{path} names its controller {f.name!r}, as does {named[f.name]}: set "
                                 "fixed_controller.name in one of them to tell them apart in the tables")
            named[f.name] = path
        paths = args.policy if args.policy is not None else [cfg.panda.policy]  # the CLI's paths win
        if "learned" not in controllers:
            if args.policy is not None:
                raise ValueError("--policy is for the learned controller, which --controllers leaves out")
            paths = [None]  # no policy is read: a configured one need not exist
        if len(paths) > 1 and args.out:
            raise ValueError("--out records one policy's episodes: give one --policy")
        set_policy = any(o.split("=", 1)[0].strip() == "panda.policy" for o in args.overrides)
        policies = [_policy_file(path, args.policy is not None, cfg_path, set_policy) for path in paths]  # found first
        if policies == [None] and "learned" in controllers:
            if args.controllers != ",".join(CONTROLLERS):  # asked for by name: not silently left out
                raise ValueError(f"--controllers names learned, but neither --policy nor {cfg_path or 'the config'}'s "
                                 "panda.policy gives a policy")
            controllers = tuple(c for c in controllers if c != "learned")
            print(f"no --policy given and no panda.policy in {cfg_path or 'the config'}: evaluating the baselines "
                  "only", file=sys.stderr)
        kw = dict(config=cfg, controllers=controllers, cycles=args.cycles, progress=not args.quiet, fixed=fixed,
                  sim_threads=args.threads, workers=args.workers, park=not args.no_park,
                  record_trial=args.record_trial or 0)
        if policies != [None] and (warning := sensing_warning(cfg.panda)):  # the config's: once for every policy
            print(warning, file=sys.stderr)
        if warning := reach_warning(cfg.panda):  # a hole or a plate moved out of the workspace: say so first
            print(warning, file=sys.stderr)
        from algorithms.policy import load_agent_policy

        agents = "the Panda's per-axis agents need"
        loaded_all = [None if policy is None else load_agent_policy(policy, agents) for policy in policies]  # all first
        for policy, loaded in zip(policies, loaded_all):
            prints = None
            if policy is not None:
                from algorithms.policy import fingerprint

                prints = fingerprint(loaded)
                for warning in (free_motion_warning(loaded), guided_warning(loaded)):
                    if warning:
                        print(warning if len(policies) == 1 else f"{policy}: {warning}", file=sys.stderr)
            log = lambda msg: print(msg, file=sys.stderr)  # noqa: E731
            res = evaluate_seeds(args.scene, policy, args.trials, [args.seed] if args.seeds is None else args.seeds,
                                 cache=args.cache, policy_fingerprint=prints, log=log, **kw)
            docs.append(_document(args, cfg_path, res, policy, prints, cfg.panda))
            # written before anything is printed (a closed pipe cannot lose them), after each policy (a long sweep
            # stopped midway keeps what ran)
            if args.json and json_out is None:
                _write_json(Path(args.json), docs[0] if len(policies) == 1 else {"policies": docs})
            if args.out:  # one policy (checked above)
                _write_json(Path(args.out) / "results.json", docs[0])
                stale = write_episodes(Path(args.out), res.episodes)
                if stale:
                    print(f"{args.out}: removed the earlier run's episodes of {', '.join(stale)} (results.json now "
                          "describes this run)", file=sys.stderr)
            _print_report(args, cfg_path, res, policy, prints, docs[-1])
    except (A3CQPError, OSError, ValueError) as exc:
        return error_exit(exc)
    except KeyboardInterrupt:
        kept = (f"; the seeds that ended are kept in {args.cache} and the same command resumes" if args.cache else
                "" if not (args.json and docs and json_out is None) else f"; the policies that ended are in {args.json}")
        print(f"\ninterrupted{kept}", file=sys.stderr)
        return 130
    if len(docs) > 1:
        print(format_policy_ranking(docs))
    if json_out is not None:
        json_out.write(_json_text(docs[0] if len(docs) == 1 else {"policies": docs}) + "\n")
        json_out.flush()
    elif args.json:
        print(f"wrote {args.json}")
    if args.out:
        out = Path(args.out)
        print(f"wrote {out}/results.json and {out}/episode_<controller>.npz (plot: a3cqp plot episode {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
