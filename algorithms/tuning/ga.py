"""Genetic-algorithm tuning of the A2C hyper-parameters (A3CQP, Testa et al. 2025: eq. 33-34, Table V) on pygad.

    a3cqp tune --config configs/ga_point_mass.yaml [--generations G] [--steps-per-trial S] [--workers W]
               [--ray ADDRESS] [--out DIR] [--resume] [--quiet]

A genome sets the `ga.genes` of the experiment config (default: λη, λβ, n, λε, λζ, the five Table IV entries with
non-round values); a trial trains A2C on the config with those values for `ga.steps_per_trial` steps, and its
fitness is `ga.fitness`:

- ``episode_reward`` (eq. 34): F = the mean return of the last N = `ga.fitness_episodes` training episodes, averaged
  over `ga.trials` seeds. A diverged training scores the lowest return an episode can have (eq. 30 with every
  penalty at its bound for the whole episode).
- ``behaviour``: the mean return of the trained policy over the closed-loop evaluation scenarios of
  envs/point_mass_eval.py (held-out operator and wall models), so the GA selects for behaviour.

pygad runs Table V exactly (50 generations, 8 solutions, 4 parents, steady-state selection, 1 parent kept,
single-point crossover, random mutation of 10 % of the genes); generation 0 is the random initial population.
OUT holds config.yaml, evaluations.csv and state.json (algorithms.tuning.runner), best.yaml (the best trial's
config: `a3cqp train --config OUT/best.yaml` trains it again) and ga.png.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from a3cqp_rl.checkpoint import write_text_atomic
from a3cqp_rl.cli import add_set_option, error_exit, help_summary, positive_int
from a3cqp_rl.config import A2CConfig, ExperimentConfig, config_from_dict, config_to_dict
from a3cqp_rl.exceptions import A3CQPError, ConfigError

from .genome import GenomeSpec
from .runner import Problem, RunResult, Terminated, cli_config, interrupted, run, stop_on_sigterm

__all__ = ["FITNESS", "make_problem", "tune", "trial_config", "episode_reward", "behaviour", "write_best", "main"]


def trial_config(cfg: ExperimentConfig, genes: dict, seed: int) -> ExperimentConfig:
    """The config one trial trains: `cfg` with the genes' values, ga.steps_per_trial steps, seed `seed`."""
    d = config_to_dict(cfg)
    for name, value in genes.items():
        section, _, field = name.rpartition(".")
        d[section or "a2c"][field] = value
    d["a2c"]["total_steps"] = cfg.ga.steps_per_trial
    d["a2c"]["region_checks"] = 0  # the fitness does not look at them
    d["seed"] = seed
    return config_from_dict(d, "<GA trial>")


def _worst_return(cfg: ExperimentConfig) -> float:
    """The lowest eq. 30 return an episode can have: every penalty term at its bound (each ratio is clipped to 1)."""
    a1, a2, _, a4 = cfg.reward.alpha
    return -(a1 + a2 + a4) * cfg.point_mass.episode_steps


def _train(tc: ExperimentConfig, out: Path | None = None):
    import torch

    from algorithms.a2c import train

    torch.set_num_threads(1)
    return train(tc, out, total_steps=tc.a2c.total_steps)


def episode_reward(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """Eq. 34 per genome [B, 1]: the mean return of the last N training episodes, averaged over ga.trials seeds."""
    n = cfg.ga.fitness_episodes
    out = []
    for genes in genomes:
        scores = []
        for t in range(cfg.ga.trials):
            tc = trial_config(cfg, genes, cfg.seed + t)
            try:
                returns = _train(tc).episode_returns[-n:]
            except FloatingPointError:  # diverged
                returns = [_worst_return(tc)]
            if not returns:
                raise ConfigError(f"ga.steps_per_trial = {cfg.ga.steps_per_trial} ends no training episode "
                                  f"({tc.a2c.num_envs} envs × {tc.point_mass.episode_steps} steps each): eq. 34 needs some")
            scores.append(float(np.mean(returns)))
        out.append([float(np.mean(scores))])
    return np.asarray(out)


def behaviour(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """Per genome [B, 1]: the trained policy's mean closed-loop return over envs.point_mass_eval's scenarios."""
    import tempfile

    from algorithms.a2c import load_policy
    from envs.point_mass_eval import evaluate

    out = []
    for genes in genomes:
        scores = []
        for t in range(cfg.ga.trials):
            tc = trial_config(cfg, genes, cfg.seed + t)
            with tempfile.TemporaryDirectory() as tmp:
                try:
                    res = _train(tc, Path(tmp) / "trial")
                    policy = load_policy(res.policy_path)
                    scores.append(evaluate({"trial": policy}, config=tc, seed=cfg.seed).return_mean("trial"))
                except FloatingPointError:
                    scores.append(_worst_return(tc))
        out.append([float(np.mean(scores))])
    return np.asarray(out)


FITNESS: dict[str, Callable[[list[dict], ExperimentConfig], np.ndarray]] = {
    "episode_reward": episode_reward,
    "behaviour": behaviour,
}
"""`ga.fitness` names: genomes and config -> fitness [B, 1], maximised."""


def make_problem(cfg: ExperimentConfig, fitness: Callable | None = None) -> Problem:
    """The Table V problem of `cfg.ga` (fitness: `cfg.ga.fitness` from FITNESS unless given)."""
    g = cfg.ga
    preload: tuple[str, ...] = ()
    if fitness is None:
        preload = ("torch", "algorithms.a2c", "envs.point_mass")
        if g.fitness not in FITNESS:
            raise ConfigError(f"ga.fitness: unknown fitness {g.fitness!r}; choose from {sorted(FITNESS)}")
        if g.fitness == "behaviour" and importlib.util.find_spec("envs.point_mass_eval") is None:
            raise ConfigError("ga.fitness: 'behaviour' needs the closed-loop evaluation envs/point_mass_eval.py, "
                              "which this installation lacks")
        fitness = FITNESS[g.fitness]
        if g.fitness == "episode_reward":
            _check_trial_length(cfg)
    ga_kwargs = dict(num_parents_mating=g.num_parents_mating, parent_selection_type=g.parent_selection_type,
                     keep_parents=g.keep_parents, keep_elitism=g.keep_elitism, crossover_type=g.crossover_type,
                     mutation_type=g.mutation_type, mutation_percent_genes=g.mutation_percent_genes)
    return Problem(kind="ga", spec=GenomeSpec(g.genes), evaluate=fitness, objectives=("fitness",), maximize=True,
                   generations=g.num_generations, population=g.sol_per_pop, ga_kwargs=ga_kwargs, chunk_size=1,
                   preload=preload, cost=functools.partial(trial_cost, cfg))


def _check_trial_length(cfg: ExperimentConfig) -> None:
    """Refuse, before any training, a trial too short for any genome's envs to finish an episode (eq. 34 averages
    the last ones): an env runs ceil(steps / (n_steps · envs)) · n_steps ≤ steps / envs + n_steps steps."""
    bounds = {g.name.removeprefix("a2c."): g for g in cfg.ga.genes}
    envs = math.ceil(bounds["num_envs"].low) if "num_envs" in bounds else cfg.a2c.num_envs
    n_steps = math.floor(bounds["n_steps"].high) if "n_steps" in bounds else cfg.a2c.n_steps
    episode = cfg.point_mass.episode_steps
    if cfg.ga.steps_per_trial / envs + n_steps < episode:
        raise ConfigError(f"ga.steps_per_trial = {cfg.ga.steps_per_trial:,} ends no training episode ({envs} envs, "
                          f"each needs {episode} steps): eq. 34 needs some; give at least {envs * episode:,}")


def trial_cost(cfg: ExperimentConfig, genes: dict) -> float:
    """A genome's expected training time [CPU s on the C iteration, 2026-11-25]: per 1e6 steps ~4.2 s plus ~1.3 s / n
    (per-update work: the weight transposes, gradient norm and RMSProp over all parameters), times the trials."""
    n = float(genes.get("n_steps", genes.get("a2c.n_steps", cfg.a2c.n_steps)))
    return cfg.ga.trials * cfg.ga.steps_per_trial / 1e6 * (4.2 + 1.3 / max(n, 1.0))


def tune(cfg: ExperimentConfig, out: str | Path, *, workers: int = 1, ray: str | None = None, resume: bool = False,
         progress: bool = True, plots: bool = True, fitness: Callable | None = None) -> RunResult:
    """Run (or resume) the GA of `cfg.ga`; write OUT's files, best.yaml and ga.png; the runner's result."""
    problem = make_problem(cfg, fitness)
    result = run(problem, cfg, out, workers=workers, ray=ray, resume=resume, progress=progress)
    write_best(cfg, result, Path(out) / "best.yaml")
    if plots:
        from a3cqp_rl.plotting.ga_history import plot_ga_run

        plot_ga_run(out)
    return result


def best_row(result: RunResult) -> dict:
    """The evaluation with the highest fitness (the earliest among equals)."""
    return max(result.rows, key=lambda r: (r["fitness"], -r["generation"], -r["individual"]))


def write_best(cfg: ExperimentConfig, result: RunResult, path: Path) -> Path:
    """Write the best trial's config (without the tuning sections) as a YAML `a3cqp train --config` accepts."""
    spec = GenomeSpec(cfg.ga.genes)
    row = best_row(result)
    genes = spec.as_dicts(np.array([[row[c] for c in spec.columns]]))[0]
    d = config_to_dict(trial_config(cfg, genes, cfg.seed))
    d.pop("ga", None)
    d.pop("nsga2", None)
    d["a2c"]["region_checks"] = A2CConfig().region_checks
    lines = [f"# Best of the GA run in {result.out} (Table V, {result.generation} generations, "
             f"{result.evaluations} trainings): {cfg.ga.fitness} fitness {row['fitness']:.6g}, found in generation "
             f"{int(row['generation'])}.",
             f"# Trained there for {cfg.ga.steps_per_trial:,} steps on seed {cfg.seed}; reproduce with "
             f"`a3cqp train --config {path}`.",
             "# Genes: " + ", ".join(f"{k} = {v:.6g}" for k, v in genes.items())]
    write_text_atomic(path, "\n".join(lines) + "\n" + yaml.safe_dump(d, sort_keys=False))
    return path


def _comparison(genes: dict) -> str:
    """Found values beside the paper's Table IV (the A2C defaults) for A2C genes."""
    paper = A2CConfig()
    lines = [f"  {'gene':<16} {'found':>12} {'Table IV':>12}"]
    for k, v in genes.items():
        ref = getattr(paper, k, None) if "." not in k else None
        lines.append(f"  {k:<16} {v:>12.6g} {'' if ref is None else f'{ref:>12.6g}'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """`a3cqp tune`: run or resume the GA; returns an exit code."""
    with stop_on_sigterm():  # SIGTERM stops as Ctrl-C does: OUT keeps what was evaluated, and the command says so
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    p = argparse.ArgumentParser(prog="a3cqp tune", description=help_summary(__doc__))
    p.add_argument("--config", default=None,
                   help="YAML config (default: configs/ga_point_mass.yaml; OUT/config.yaml with --resume)")
    p.add_argument("--generations", type=positive_int, default=None,
                   help="generations after the initial one (>= 1; ga.num_generations)")
    p.add_argument("--steps-per-trial", type=positive_int, default=None,
                   help="agent steps per trial training (ga.steps_per_trial)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="local worker processes, one training each (default 1)")
    p.add_argument("--ray", default=None, metavar="ADDRESS", help="run trials as Ray tasks: 'auto', host:port, or "
                                                                  "'local' (a Ray instance on this machine)")
    p.add_argument("--out", default=None, help="output folder (default: runs/tune_<config name>)")
    p.add_argument("--resume", action="store_true", help="continue the run in OUT from its last finished generation")
    add_set_option(p, "ga.sol_per_pop=12", "OUT/config.yaml keeps the result")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)

    out = None
    try:
        cfg, out = cli_config(args.config, args.out, args.resume, "configs/ga_point_mass.yaml", "tune", "ga",
                              {"num_generations": args.generations, "steps_per_trial": args.steps_per_trial},
                              args.overrides)
        import torch

        torch.set_num_threads(1)
        result = tune(cfg, out, workers=args.workers, ray=args.ray, resume=args.resume, progress=not args.quiet)
        row = best_row(result)
        spec = GenomeSpec(cfg.ga.genes)
        genes = spec.as_dicts(np.array([[row[c] for c in spec.columns]]))[0]
        per_gen = result.seconds / (result.generation + 1)  # the initial population counts as one
        gens = f"{result.generation} generation{'' if result.generation == 1 else 's'}"
        print(f"GA: {gens}, {result.evaluations} trainings in {result.seconds / 60:.1f} min "
              f"({per_gen:.1f} s per generation); best fitness {row['fitness']:.4g} (generation "
              f"{int(row['generation'])}):\n{_comparison(genes)}")
        print(f"results in {out}/: best.yaml (a3cqp train --config {out}/best.yaml), evaluations.csv, ga.png")
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (stop_on_sigterm)
        print(f"\n{interrupted(out)}", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
    except (A3CQPError, FileNotFoundError, ValueError) as exc:
        return error_exit(exc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
