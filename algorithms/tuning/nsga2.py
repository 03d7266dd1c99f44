"""NSGA-II on pygad (Deb et al. 2002; as Penco et al. 2020 use it to tune QP weights, priority levels and gains).

    a3cqp pareto --config configs/nsga2_zdt1.yaml [--generations G] [--population P] [--workers W]
                 [--ray ADDRESS] [--out DIR] [--resume] [--quiet]
    a3cqp pareto --out DIR --pick K

Each generation pygad holds 2·P solutions: the P survivors of the last generation and P offspring. pygad's `nsga2`
parent selection keeps the best P of them by Pareto rank, then crowding distance (NSGA-II's elitist survival; the
same P are carried over by keep_elitism), and our mating operator breeds P offspring from them: crowded binary
tournaments (lower rank wins, then larger crowding distance) pick the parents, SBX crosses each pair, and pygad's
polynomial mutation follows. The objectives are a registered function (`nsga2.objective`, see
algorithms.tuning.objectives) of a batch of genomes, all minimised.

OUT holds config.yaml, evaluations.csv and state.json (algorithms.tuning.runner), front.csv (the final population's
Pareto front, sorted by the first objective; K indexes its rows), pareto.png (and pareto_3d.png for three or more
objectives); `--pick K` writes pick_K.yaml: solution K's genes and objective values, or what the objective's
`to_config` makes of them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

from a3cqp_rl.checkpoint import write_text_atomic
from a3cqp_rl.cli import add_set_option, error_exit, help_summary, positive_int
from a3cqp_rl.config import ExperimentConfig
from a3cqp_rl.exceptions import A3CQPError
from a3cqp_rl.tuning_files import read_rows, read_state

from .genome import GenomeSpec
from .objectives import Objective, get_objective
from .pareto import hypervolume, non_dominated
from .runner import Problem, RunResult, Terminated, cli_config, interrupted, run, stop_on_sigterm

__all__ = ["make_problem", "tune_pareto", "crowded_tournament_sbx", "rank_and_crowding", "pareto_front", "read_front",
           "pick", "main"]


def make_problem(cfg: ExperimentConfig) -> tuple[Problem, Objective]:
    """The NSGA-II problem of `cfg.nsga2` (pygad settings, genome, objective)."""
    s = cfg.nsga2
    objective = get_objective(s.objective)
    spec = GenomeSpec(s.genes or objective.genes)
    ga_kwargs = dict(
        num_parents_mating=s.population, keep_elitism=s.population, parent_selection_type=s.parent_selection_type,
        K_tournament=2, crossover_type=crowded_tournament_sbx, crossover_probability=s.crossover_probability,
        sbx_crossover_eta=s.sbx_eta, mutation_type="polynomial", polynomial_mutation_eta=s.polynomial_eta,
        mutation_probability=s.mutation_probability if s.mutation_probability is not None else 1.0 / spec.num_genes,
    )
    problem = Problem(kind="nsga2", spec=spec, evaluate=objective.fn, objectives=objective.objectives, maximize=False,
                      generations=s.generations, population=2 * s.population, ga_kwargs=ga_kwargs,
                      chunk_size=s.chunk_size or objective.chunk_size)
    return problem, objective


def tune_pareto(cfg: ExperimentConfig, out: str | Path, *, workers: int = 1, ray: str | None = None,
                resume: bool = False, progress: bool = True, plots: bool = True) -> RunResult:
    """Run NSGA-II as `cfg.nsga2` says; write OUT's files (front.csv, plots); the runner's result."""
    problem, objective = make_problem(cfg)
    if resume:  # the front of the generations so far would outlive an interrupted resume and be picked from
        for name in ("front.csv", "pareto.png", "pareto_3d.png"):
            (Path(out) / name).unlink(missing_ok=True)
    result = run(problem, cfg, out, workers=workers, ray=ray, resume=resume, progress=progress)
    front = pareto_front(result.values, keep=cfg.nsga2.population)
    _write_front(Path(out), problem, result, front)
    if plots:
        _plot(Path(out), objective)
    return result


# ------------------------------------------------------------------------------------------- mating
def rank_and_crowding(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pareto rank (0 = non-dominated) and crowding distance (inf at a front's ends) of minimised `values` [n, m]."""
    f = np.asarray(values, dtype=np.float64)
    n = len(f)
    rank = np.full(n, -1)
    beaten = (f[None, :, :] <= f[:, None, :]).all(-1) & (f[None, :, :] < f[:, None, :]).any(-1)  # [i, j]: j beats i
    remaining = np.ones(n, dtype=bool)
    r = 0
    while remaining.any():
        members = remaining & ~(beaten & remaining[None, :]).any(1)
        rank[members] = r
        remaining &= ~members
        r += 1
    crowd = np.zeros(n)
    for r in range(rank.max() + 1):
        idx = np.flatnonzero(rank == r)
        for k in range(f.shape[1]):
            order = idx[np.argsort(f[idx, k], kind="stable")]
            span = f[order[-1], k] - f[order[0], k]
            crowd[order[0]] = crowd[order[-1]] = np.inf
            if len(order) > 2 and span > 0:
                crowd[order[1:-1]] += (f[order[2:], k] - f[order[:-2], k]) / span
    return rank, crowd


def crowded_tournament_sbx(parents: np.ndarray, offspring_size: tuple[int, int], ga) -> np.ndarray:
    """pygad crossover hook: crowded binary tournaments among `parents`, then SBX on each pair (genes in [0, 1]).

    SBX as in Deb's NSGA-II code and pymoo: a pair is crossed with probability `ga.crossover_probability`, each gene
    of a crossed pair with probability 1/2, with distribution index `ga.sbx_crossover_eta`; the two children are
    exchanged gene by gene with probability 1/2. Random numbers come from pygad's own generator (checkpointed).
    """
    rng = ga.numpy_random_generator
    n_off, d = offspring_size
    n = len(parents)
    fitness = np.asarray(ga.last_generation_fitness, dtype=np.float64)[ga.last_generation_parents_indices]
    rank, crowd = rank_and_crowding(-fitness)  # pygad maximises; our objectives are minimised
    pairs = (n_off + 1) // 2
    a, b = rng.randint(0, n, size=(2, 2 * pairs))
    a_wins = (rank[a] < rank[b]) | ((rank[a] == rank[b]) & (crowd[a] > crowd[b]))
    tie = (rank[a] == rank[b]) & (crowd[a] == crowd[b])
    a_wins = np.where(tie, rng.random_sample(2 * pairs) < 0.5, a_wins)
    chosen = np.where(a_wins, a, b)
    p1 = parents[chosen[:pairs]].astype(np.float64)
    p2 = parents[chosen[pairs:]].astype(np.float64)

    eta = float(ga.sbx_crossover_eta)
    y1, y2 = np.minimum(p1, p2), np.maximum(p1, p2)
    delta = y2 - y1
    cross = ((rng.random_sample((pairs, 1)) < ga.crossover_probability) & (rng.random_sample((pairs, d)) < 0.5)
             & (delta > 1e-14))
    u = rng.random_sample((pairs, d))
    safe = np.where(delta > 1e-14, delta, 1.0)

    def spread(beta: np.ndarray) -> np.ndarray:  # β_q of SBX's bounded form
        alpha = 2.0 - beta ** -(eta + 1.0)
        return np.where(u <= 1.0 / alpha, (u * alpha) ** (1.0 / (eta + 1.0)),
                        (1.0 / (2.0 - u * alpha)) ** (1.0 / (eta + 1.0)))

    c1 = np.clip(0.5 * (y1 + y2 - spread(1.0 + 2.0 * y1 / safe) * delta), 0.0, 1.0)
    c2 = np.clip(0.5 * (y1 + y2 + spread(1.0 + 2.0 * (1.0 - y2) / safe) * delta), 0.0, 1.0)
    swap = rng.random_sample((pairs, d)) < 0.5
    k1 = np.where(cross, np.where(swap, c2, c1), p1)
    k2 = np.where(cross, np.where(swap, c1, c2), p2)
    return np.concatenate([k1, k2])[:n_off]


# ------------------------------------------------------------------------------------------- results
def pareto_front(values: np.ndarray, keep: int | None = None) -> np.ndarray:
    """Row indices of the non-dominated `values` [n, m] (minimised), unique, sorted by the first objective; with
    `keep`, among the `keep` rows NSGA-II's survival would keep (rank, then crowding distance)."""
    values = np.asarray(values, dtype=np.float64)
    idx = np.flatnonzero(non_dominated(values))
    if keep is not None and len(idx) > keep:
        rank, crowd = rank_and_crowding(values)
        idx = np.lexsort((-crowd, rank))[:keep]
        idx = idx[rank[idx] == 0]
    _, first = np.unique(values[idx], axis=0, return_index=True)  # twins of one point: keep one
    idx = idx[np.sort(first)]
    return idx[np.lexsort(values[idx].T[::-1])]


def _write_front(out: Path, problem: Problem, result: RunResult, front: np.ndarray) -> None:
    import csv
    import io

    cols = ["k", *problem.spec.columns, *problem.objectives]
    pop = np.asarray(read_state(out)["population"], dtype=np.float64)
    decoded = problem.spec.decode_matrix(pop)
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(cols)
    for k, i in enumerate(front):
        w.writerow([k, *(repr(float(v)) for v in decoded[i]), *(repr(float(v)) for v in result.values[i])])
    write_text_atomic(out / "front.csv", text.getvalue())


def read_front(out: str | Path) -> list[dict]:
    """OUT/front.csv as dicts (floats)."""
    if not (Path(out) / "front.csv").is_file():
        raise A3CQPError(f"no Pareto front in {Path(out)} (front.csv not found; has the run finished?)")
    return read_rows(out, "front.csv")


def _plot(out: Path, objective: Objective) -> list[Path]:
    """pareto.png (and pareto_3d.png); the objective's known front, if any, goes to known_front.csv first."""
    from a3cqp_rl.plotting.pareto import plot_pareto_run

    if objective.reference_front is not None:
        known = np.asarray(objective.reference_front(200))
        lines = [",".join(objective.objectives)] + [",".join(repr(float(v)) for v in row) for row in known]
        write_text_atomic(out / "known_front.csv", "\n".join(lines) + "\n")
    return plot_pareto_run(out)


def pick(out: str | Path, k: int) -> Path:
    """Write OUT/pick_K.yaml for row K of OUT/front.csv; its path."""
    out = Path(out)
    from a3cqp_rl.config import load_config

    front = read_front(out)
    if not front:
        raise A3CQPError(f"--pick {k}: {out / 'front.csv'} holds no solution (a run that has not finished a "
                         "generation, or not a front written by a3cqp pareto)")
    if not 0 <= k < len(front):
        raise A3CQPError(f"--pick {k}: the front in {out} has solutions 0..{len(front) - 1}")
    state = read_state(out)
    cfg = load_config(out / "config.yaml")
    problem, objective = make_problem(cfg)
    row = front[k]
    genome = problem.spec.as_dicts(np.array([[row[c] for c in problem.spec.columns]]))[0]
    values = {n: row[n] for n in state["objectives"]}
    data = objective.to_config(genome, cfg, k) if objective.to_config else {"genes": genome, "objectives": values}
    path = out / f"pick_{k}.yaml"
    header = (f"# Pareto solution {k} of {len(front)} of the NSGA-II run in {out} (objective {cfg.nsga2.objective}: "
              + ", ".join(f"{n} = {v:.6g}" for n, v in values.items()) + ")\n")
    write_text_atomic(path, header + yaml.safe_dump(data, sort_keys=False))
    return path


# ----------------------------------------------------------------------------------------------- CLI
def main(argv: list[str] | None = None) -> int:
    """`a3cqp pareto`: run / resume NSGA-II, or pick a Pareto solution; returns an exit code."""
    with stop_on_sigterm():  # SIGTERM stops as Ctrl-C does: OUT keeps what was evaluated, and the command says so
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    p = argparse.ArgumentParser(prog="a3cqp pareto", description=help_summary(__doc__))
    p.add_argument("--config", default=None, help="YAML config (default: configs/nsga2_zdt1.yaml; OUT/config.yaml "
                                                  "with --resume or --pick)")
    p.add_argument("--generations", type=positive_int, default=None,
                   help="generations after the initial one (>= 1; nsga2.generations)")
    p.add_argument("--population", type=positive_int, default=None, help="survivors per generation (nsga2.population)")
    p.add_argument("--workers", type=positive_int, default=1, help="local worker processes (default 1: this process)")
    p.add_argument("--ray", default=None, metavar="ADDRESS", help="run evaluations as Ray tasks: 'auto', host:port, "
                                                                  "or 'local' (a Ray instance on this machine)")
    p.add_argument("--out", default=None, help="output folder (default: runs/pareto_<config name>)")
    p.add_argument("--resume", action="store_true", help="continue the run in OUT from its last finished generation")
    p.add_argument("--pick", type=int, default=None, metavar="K", help="write solution K of OUT/front.csv as a YAML")
    add_set_option(p, "panda.operator.timeout=4", "OUT/config.yaml keeps the result")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)

    out = None
    try:
        if args.pick is not None:
            if not args.out:
                raise A3CQPError("--pick needs --out DIR (a finished run)")
            if args.overrides:
                raise A3CQPError("--set applies to a run; --pick reads OUT/front.csv as the run wrote it")
            run_only = [f for f, given in (("--resume", args.resume), ("--generations", args.generations),
                                           ("--population", args.population), ("--workers", args.workers != 1),
                                           ("--ray", args.ray), ("--config", args.config)) if given]
            if run_only:
                verb = "apply" if len(run_only) > 1 else "applies"
                raise A3CQPError(f"{', '.join(run_only)} {verb} to a run; --pick reads OUT/front.csv as the run wrote "
                                 "it (give --pick K --out DIR alone)")
            print(f"wrote {pick(args.out, args.pick)}")
            return 0
        cfg, out = cli_config(args.config, args.out, args.resume, "configs/nsga2_zdt1.yaml", "pareto", "nsga2",
                              {"generations": args.generations, "population": args.population}, args.overrides)
        result = tune_pareto(cfg, out, workers=args.workers, ray=args.ray, resume=args.resume, progress=not args.quiet)
        front = read_front(out)
        objective = get_objective(cfg.nsga2.objective)
        hv = ""
        if objective.reference_point:
            pts = np.array([[r[n] for n in objective.objectives] for r in front])
            hv = f", hypervolume {hypervolume(pts, objective.reference_point):.4f} (reference {objective.reference_point})"
        gens = f"{result.generation} generation{'' if result.generation == 1 else 's'}"
        print(f"NSGA-II: {gens}, {result.evaluations} evaluations in {result.seconds:.1f} s; "
              f"Pareto front of {len(front)} solutions{hv}")
        print(f"results in {out}/: front.csv (pick one with --pick K), evaluations.csv, pareto.png")
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (stop_on_sigterm)
        print(f"\n{interrupted(out)}", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
    except (A3CQPError, FileNotFoundError, ValueError) as exc:
        return error_exit(exc)
    return 0
