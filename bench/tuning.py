"""Tuning speed: the Table V GA per generation with 1 and 2 local workers, and NSGA-II's loop on ZDT1.

GA: `algorithms.tuning.ga.tune` on configs/ga_point_mass.yaml (Table V: 8 solutions, 7 new trainings per bred
generation) with S steps per trial, run once with 1 worker and once with 2 (same seed: the two runs must log
identical evaluations, which is checked). A bred generation's time is the difference of the run times state.json
records at consecutive generations; the median over the G bred generations is reported, and the full Table V run
(50 generations) projected as generation 0 + 50 medians. Generation 0 holds 8 trainings plus the workers' start.
The CPU time of each run (this process and its workers) shows how much of the 2 cores it got: on a shared machine
the wall times, and so the 2-worker speed-up, depend on what else runs.

NSGA-II: the seconds per generation of `a3cqp pareto` on ZDT1 (population 100: 200 solutions in pygad) with our
vectorised non-dominated sort (algorithms/tuning/pygad_ga.py) against pygad's own, the same run otherwise.

ZDT (the optimiser's reference check): on ZDT1 and ZDT2 with the configs' budget (configs/nsga2_zdt*.yaml:
population 100, 150 generations = 15,200 evaluations), the hypervolume (reference point (1.1, 1.1)) of our final
front and of pymoo's NSGA2 (pop_size 100, the same number of evaluations) on the same seeds; pymoo is a dev extra.

Panda (`--only panda`): genome evaluations per second of the Panda objective (configs/nsga2_peg.yaml, P random
genomes, 1 trial each, episodes cut at H simulated seconds) with the population in one batched simulation
(`nsga2.panda.batch: population`, PopulationController) against one simulation per genome (`per_genome`), median over
R repeats each, alternating; the two must give the same objectives to rounding (checked).

Usage: python bench/tuning.py [--generations G] [--steps S] [--quick] [--only ga|nsga2|zdt|panda] [--seeds N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from a3cqp_rl.cli import help_summary

_ROOT = Path(__file__).resolve().parents[1]
if str(_ROOT) not in sys.path:
    sys.path.insert(0, str(_ROOT))


def _cpu_seconds() -> float:
    """CPU time of this process and its finished children (the pool's workers once shut down) [s]."""
    import resource

    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _ga_run(workers: int, generations: int, steps: int, out: Path) -> tuple[list[float], float]:
    """(seconds per bred generation, generation 0's seconds) of one GA run."""
    from a3cqp_rl.config import load_config
    from algorithms.tuning.ga import tune
    from algorithms.tuning.runner import read_state

    cfg = load_config(_ROOT / "configs" / "ga_point_mass.yaml",
                      {"ga": {"num_generations": generations, "steps_per_trial": steps}})
    tune(cfg, out, workers=workers, progress=False, plots=False)
    times = read_state(out)["times"]
    return [b - a for a, b in zip(times, times[1:])], times[0]


def bench_ga(generations: int, steps: int) -> None:
    """Per-generation time with 1 and 2 workers, and the projected Table V run."""
    print(f"GA, Table V (8 solutions, 7 new trainings per generation), {steps:,} steps per trial, "
          f"{generations} bred generations; load before: {os.getloadavg()[0]:.2f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        res = {}
        for w in (1, 2):
            t0, c0 = time.perf_counter(), _cpu_seconds()
            per_gen, gen0 = _ga_run(w, generations, steps, Path(tmp) / f"w{w}")
            wall, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
            res[w] = (statistics.median(per_gen), gen0, wall)
            print(f"  {w} worker{'s' if w > 1 else ' '}: median {res[w][0]:6.1f} s per generation "
                  f"(min {min(per_gen):.1f}, max {max(per_gen):.1f}); generation 0 {gen0:.1f} s; "
                  f"projected Table V run (gen 0 + 50 generations): {(gen0 + 50 * res[w][0]) / 60:.1f} min; "
                  f"CPU {cpu:.0f} s in {wall:.0f} s wall ({cpu / wall:.2f} cores busy)", flush=True)
        same = _csv_without_seconds(Path(tmp) / "w1") == _csv_without_seconds(Path(tmp) / "w2")
    print(f"  2 workers vs 1: {res[1][0] / res[2][0]:.2f}x per generation; identical evaluations: {same}")
    print(f"  load after: {os.getloadavg()[0]:.2f} (2 cores)")
    if not same:
        raise SystemExit("the 1- and 2-worker runs differ")


def _csv_without_seconds(out: Path) -> list[list[str]]:
    import csv

    with (out / "evaluations.csv").open() as f:
        rows = list(csv.reader(f))
    k = rows[0].index("seconds")
    return [r[:k] + r[k + 1:] for r in rows]


def bench_nsga2(generations: int) -> None:
    """NSGA-II seconds per generation on ZDT1 with our non-dominated sort and with pygad's."""
    import pygad

    from a3cqp_rl.config import load_config
    from algorithms.tuning.nsga2 import tune_pareto
    from algorithms.tuning.pygad_ga import GA
    from algorithms.tuning.runner import read_state

    cfg = load_config(_ROOT / "configs" / "nsga2_zdt1.yaml", {"nsga2": {"generations": generations}})
    print(f"NSGA-II on ZDT1, population 100 (200 solutions in pygad), {generations} generations", flush=True)
    rates = {}
    ours = GA.non_dominated_sorting
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("ours", "pygad"):
            GA.non_dominated_sorting = ours if name == "ours" else pygad.GA.non_dominated_sorting
            try:
                tune_pareto(cfg, Path(tmp) / name, progress=False, plots=False)
            finally:
                GA.non_dominated_sorting = ours
            times = read_state(Path(tmp) / name)["times"]
            rates[name] = statistics.median(b - a for a, b in zip(times, times[1:]))
            print(f"  {name:>5} sort: {rates[name] * 1e3:7.1f} ms per generation", flush=True)
        same = _csv_without_seconds(Path(tmp) / "ours") == _csv_without_seconds(Path(tmp) / "pygad")
    print(f"  ours vs pygad's sort: {rates['pygad'] / rates['ours']:.1f}x per generation; identical runs: {same}")


def bench_zdt(seeds: int, generations: int = 150, population: int = 100) -> None:
    """Hypervolume of our NSGA-II and pymoo's NSGA2 on ZDT1/ZDT2 at the same budget, per seed, as a markdown table."""
    try:
        from pymoo.algorithms.moo.nsga2 import NSGA2
        from pymoo.optimize import minimize
        from pymoo.problems import get_problem
    except ImportError:
        print("ZDT reference check needs pymoo (pip install pymoo, or the dev extra); skipped")
        return
    from a3cqp_rl.config import load_config
    from algorithms.tuning.nsga2 import read_front, tune_pareto
    from algorithms.tuning.pareto import hypervolume

    budget = 2 * population + generations * population
    ideal = {"zdt1": 1.21 - 1 / 3, "zdt2": 1.21 - 2 / 3}
    print(f"ZDT reference check: population {population}, {generations} generations = {budget:,} evaluations, "
          f"hypervolume to (1.1, 1.1); {seeds} seeds")
    print("| problem | seed | ours | pymoo NSGA2 | ours / pymoo | ours [s] | pymoo [s] |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for problem in ("zdt1", "zdt2"):
        a, b = [], []
        for seed in range(seeds):
            cfg = load_config(_ROOT / "configs" / f"nsga2_{problem}.yaml",
                              {"seed": seed, "nsga2": {"generations": generations, "population": population}})
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                tune_pareto(cfg, Path(tmp) / "run", progress=False, plots=False)
                t_ours = time.perf_counter() - t0
                front = [[r["f1"], r["f2"]] for r in read_front(Path(tmp) / "run")]
            t0 = time.perf_counter()
            res = minimize(get_problem(problem), NSGA2(pop_size=population), ("n_evals", budget), seed=seed)
            t_pymoo = time.perf_counter() - t0
            a.append(hypervolume(front, (1.1, 1.1)))
            b.append(hypervolume(res.F, (1.1, 1.1)))
            print(f"| {problem} | {seed} | {a[-1]:.4f} | {b[-1]:.4f} | {a[-1] / b[-1]:.3f} | {t_ours:.1f} | "
                  f"{t_pymoo:.1f} |", flush=True)
        print(f"| **{problem} mean** | | **{statistics.mean(a):.4f}** | **{statistics.mean(b):.4f}** | "
              f"**{statistics.mean(a) / statistics.mean(b):.3f}** | | |")
        print(f"({problem}: the known front's hypervolume is {ideal[problem]:.4f})")


def bench_panda(genomes: int, horizon: float, repeats: int) -> None:
    """Genome evaluations per second of the Panda objective: the population batch against one simulation per genome."""
    import numpy as np
    import torch

    from a3cqp_rl.config import load_config
    from algorithms.tuning.genome import GenomeSpec

    torch.set_num_threads(1)  # as the objective itself (panda_objectives.panda): a second thread only contends
    from algorithms.tuning.panda_objectives import GENES, evaluate_fixed, fixed_from_genome

    spec = GenomeSpec(GENES)
    u = np.random.default_rng(0).random((genomes, spec.num_genes))
    fixed = [fixed_from_genome(g, f"g{i}") for i, g in enumerate(spec.as_dicts(spec.decode_matrix(u)))]
    print(f"Panda objective (peg-in-hole), {genomes} random genomes x 1 trial, episodes cut at {horizon:g} s, "
          f"{repeats} repeats; load before: {os.getloadavg()[0]:.2f}", flush=True)
    rates: dict[str, list[float]] = {"population": [], "per_genome": []}
    values = {}
    for _ in range(repeats):
        for batch in rates:
            cfg = load_config(_ROOT / "configs" / "nsga2_peg.yaml",
                              {"panda": {"max_episode_time": horizon}, "nsga2": {"panda": {"trials": 1, "batch": batch}}})
            res = evaluate_fixed(fixed, cfg)
            rates[batch].append(genomes / res.wall_seconds)
            values[batch] = res.objectives
    for batch, r in rates.items():
        print(f"  {batch:>10}: {statistics.median(r):6.3f} genome evaluations/s ({horizon:g} s episodes), "
              f"{statistics.median(r) * horizon:5.2f}x real time in aggregate", flush=True)
    same = np.allclose(values["population"], values["per_genome"], rtol=1e-6, atol=1e-9)
    print(f"  population batch vs per genome: {statistics.median(rates['population']) / statistics.median(rates['per_genome']):.2f}x; "
          f"same objectives: {same}")


def main(argv: list[str] | None = None) -> int:
    """Run the tuning benchmarks; returns an exit code."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--generations", type=int, default=3, help="GA generations bred after the initial one")
    p.add_argument("--steps", type=int, default=1_000_000, help="agent steps per GA trial (Table V run: 1e6)")
    p.add_argument("--quick", action="store_true", help="1 generation of 1e5-step trials; NSGA-II 10 generations")
    p.add_argument("--only", choices=["ga", "nsga2", "zdt", "panda"], default=None)
    p.add_argument("--genomes", type=int, default=8, help="genomes of the Panda benchmark")
    p.add_argument("--horizon", type=float, default=2.0, help="simulated seconds per Panda episode")
    p.add_argument("--repeats", type=int, default=3, help="repeats of the Panda benchmark")
    p.add_argument("--seeds", type=int, default=5, help="seeds of the ZDT reference check")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    if args.quick:
        args.generations, args.steps = 1, 100_000
    if args.only in (None, "ga"):
        bench_ga(args.generations, args.steps)
    if args.only in (None, "nsga2"):
        bench_nsga2(10 if args.quick else 30)
    if args.only in (None, "zdt"):
        bench_zdt(1 if args.quick else args.seeds, generations=30 if args.quick else 150)
    if args.only in (None, "panda"):
        bench_panda(4 if args.quick else args.genomes, 0.5 if args.quick else args.horizon,
                    1 if args.quick else args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
