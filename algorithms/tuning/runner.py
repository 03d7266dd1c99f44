"""The generation loop both tuners share: pygad breeds, a pool evaluates, every finished generation is logged and
checkpointed.

Files in OUT:

- ``config.yaml``: the experiment config of the run (a resume must match it; only the generation count may grow).
- ``evaluations.csv``: one row per individual and generation: generation, individual, the decoded genes, the
  objective value(s), seconds (evaluation wall time in its worker, 0 when reused) and new (1 if evaluated in this
  generation, 0 if an earlier value was reused).
- ``state.json``: after each finished generation (0 = the initial population): the population (pygad's genes u in
  [0, 1]), its values, the states of pygad's two random generators, and the run time at each finished generation.
  Written atomically.
- ``pending.csv``: the genomes evaluated since the last finished generation, a row per genome as its chunk ends
  (decoded genes, values, seconds); a resume takes them from there instead of evaluating them again, also when the
  run was stopped before its initial population was done.

Resuming restores the population and the random states of the last finished generation and rebuilds the cache of
evaluated genomes from evaluations.csv, so pygad's next steps draw the same numbers and see the same values: a
killed run ends where an uninterrupted one does. Values are cached by decoded genes (an evaluation is a pure
function of its genes and the config), which also spares re-evaluating a genome that reappears.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from a3cqp_rl.checkpoint import write_text_atomic
from a3cqp_rl.config import ExperimentConfig, config_to_dict
from a3cqp_rl.exceptions import CheckpointError, ConfigError
from a3cqp_rl.run_folder import RunFolder, check_output_path
from a3cqp_rl.tuning_files import STATE_FORMAT, read_rows, read_state

from .genome import GenomeSpec
from .pool import make_pool
from .pygad_ga import GA

__all__ = ["Problem", "RunResult", "run", "build_ga", "read_evaluations", "read_state", "STATE_FORMAT", "Terminated",
           "stop_on_sigterm"]

PENDING = "pending.csv"

Evaluate = Callable[[list[dict], ExperimentConfig], np.ndarray]
"""A batch of decoded genomes and the experiment config -> values [B, M] (float64, finite)."""


@dataclass
class Problem:
    """What a tuner hands the runner."""

    kind: str
    """'ga' or 'nsga2' (written into state.json; plots read it)."""
    spec: GenomeSpec
    evaluate: Evaluate
    """Must be importable by name (a module-level function) so worker processes and Ray tasks can run it."""
    objectives: tuple[str, ...]
    """Names of the M values (CSV columns)."""
    maximize: bool
    """True: pygad maximises the values (GA fitness); False: they are minimised (NSGA-II objectives)."""
    generations: int
    """Generations bred after the initial population."""
    population: int
    """Solutions per generation, as pygad holds them."""
    ga_kwargs: dict
    """pygad.GA settings: parent selection, crossover, mutation, elitism."""
    chunk_size: int | None = None
    """Genomes per task; None = the genomes to evaluate split evenly over the workers."""
    preload: tuple[str, ...] = ()
    """Modules local workers import when they start (so the first evaluation's time is not mostly imports)."""
    cost: Callable[[dict], float] | None = None
    """A genome's expected evaluation time (any unit): the pool starts the costliest first, so a generation's last
    round is not a long evaluation on one worker while the others idle. Results never depend on it."""


@dataclass
class RunResult:
    """A finished run: the last population, every evaluation, timings."""

    out: Path
    generation: int
    """Last finished generation."""
    genes: list[dict]
    """Decoded last population."""
    values: np.ndarray
    """Its values [P, M] (natural sign: fitness or objectives)."""
    rows: list[dict] = field(default_factory=list)
    """evaluations.csv as dicts."""
    seconds: float = 0.0
    """Wall time of the whole run, every part of a resumed one together [s]."""
    evaluations: int = 0
    """Genomes evaluated (cache misses) over the whole run."""
    resumed_from: int | None = None
    """The generation a resumed run started from."""


def run(problem: Problem, cfg: ExperimentConfig, out: str | Path, *, workers: int = 1, ray: str | None = None,
        resume: bool = False, progress: bool = True) -> RunResult:
    """Run (or resume) `problem` under `cfg` (its seed drives pygad) and write OUT's files; the last population."""
    out = Path(out)
    folder = RunFolder.open(out, resume=True)  # one writer at a time, as for a training run
    try:
        result = _run_locked(problem, cfg, out, workers, ray, resume, progress)
    except BaseException:
        folder.close(failed=True)
        raise
    folder.close()
    return result


def _run_locked(problem: Problem, cfg: ExperimentConfig, out: Path, workers: int, ray: str | None, resume: bool,
                progress: bool) -> RunResult:
    state_path = out / "state.json"
    cfg_dict = config_to_dict(cfg)
    columns = ["generation", "individual", *problem.spec.columns, *problem.objectives, "seconds", "new"]
    csv_path = out / "evaluations.csv"
    pending = _read_pending(out, problem) if resume else {}
    if resume and not state_path.exists() and pending:  # stopped within the initial population: start it again
        _check_same_run(out, cfg_dict, problem, {"kind": problem.kind})
        resume = False
        state_path.unlink(missing_ok=True)
        csv_path.unlink(missing_ok=True)
    if resume:
        state = read_state(out)
        _check_same_run(out, cfg_dict, problem, state)
        start_gen = int(state["generation"])
        if start_gen > problem.generations:
            raise ConfigError(f"{out} already holds {start_gen} generations; asked for {problem.generations}")
    else:
        if state_path.exists():
            raise CheckpointError(f"{out} already holds a tuning run: add --resume to continue it, or pick another --out")
        state, start_gen = None, None
        if not pending:  # a new run: another run's evaluations are not its own
            (out / PENDING).unlink(missing_ok=True)
    write_text_atomic(out / "config.yaml", yaml.safe_dump(cfg_dict, sort_keys=False))

    cache: dict[tuple, np.ndarray] = {}
    if resume:
        rows = _truncate_rows(csv_path, columns, start_gen)
        for r in rows:
            cache[tuple(float(r[c]) for c in problem.spec.columns)] = np.array([float(r[c]) for c in problem.objectives])
    else:
        write_text_atomic(csv_path, ",".join(columns) + "\n")

    loop = _Loop(problem, cfg, out, columns, cache, state, start_gen, progress)
    for key, (values, seconds) in pending.items():  # evaluated before the stop: counted as this generation's
        cache[key] = values
        loop.fresh[key] = seconds
    loop.evaluations += len(pending)
    pool = make_pool(workers, ray, problem.preload)
    loop.pool = pool
    try:
        if start_gen is None or start_gen < problem.generations:
            loop.run_ga()
    finally:
        pool.close()
        loop.close_bar()
    state = read_state(out)
    values = np.asarray(state["values"], dtype=np.float64)
    pop = np.asarray(state["population"], dtype=np.float64)
    return RunResult(out=out, generation=int(state["generation"]), genes=problem.spec.decode(pop), values=values,
                     rows=read_evaluations(out), seconds=float(state["seconds"]), evaluations=int(state["evaluations"]),
                     resumed_from=start_gen)


def cli_config(config: str | None, out: str | None, resume: bool, default: str, prefix: str,
               section: str, overrides: dict, sets: Sequence[str] = ()) -> tuple[ExperimentConfig, Path]:
    """The config and output folder of a tuner's CLI run: `config`, else OUT/config.yaml on --resume, else `default`
    (relative to the working directory, else to this checkout); OUT defaults to runs/<prefix>_<config name>;
    `sets` are --set KEY=VALUE items over the file, and `overrides` (the command's own flags; None values dropped)
    go into `section` over both."""
    from a3cqp_rl.config import load_config, parse_overrides, project_path, read_config_file

    if config is None:
        config = str(Path(out) / "config.yaml") if resume and out else str(project_path(default))
        if resume and out and not Path(config).is_file():  # the run's own config: none means no run there
            raise CheckpointError(f"no tuning run in {out} to resume ({config} not found); drop --resume to start one")
    _check_tuner_config(read_config_file(config), config, section)
    # the flags as --set items after the user's, so that a flag wins over a --set of the same key
    items = [*sets, *(f"{section}.{k}={v}" for k, v in overrides.items() if v is not None)]
    out_path = check_output_path(out or Path("runs") / f"{prefix}_{Path(config).stem}", "--out", folder=True)
    return load_config(config, parse_overrides(items)), out_path


TUNERS = {"ga": ("a3cqp tune", "a GA"), "nsga2": ("a3cqp pareto", "an NSGA-II")}
"""Config section -> the command that reads it and what it runs."""


def _check_tuner_config(data: dict, path: str, section: str) -> None:
    """Refuse the other tuner's config (its section would be ignored and the defaults run instead); an NSGA-II run
    needs its section, which names the objective, while a GA may tune a training config with the Table V genes."""
    other = next(k for k in TUNERS if k != section)
    command, what = TUNERS[section]
    if other in data and section not in data:
        raise ConfigError(f"{path} is {TUNERS[other][1]} config ({other}: section, no {section}: section); run it with "
                          f"{TUNERS[other][0]}, or give it a {section}: section for {command}")
    if section == "nsga2" and section not in data:
        raise ConfigError(f"{path} has no nsga2: section (objective, genes); {command} runs {what} search, e.g. "
                          "--config configs/nsga2_peg.yaml")


def interrupted(out: str | Path | None) -> str:
    """The line a tuner prints on Ctrl-C or SIGTERM: which generation OUT holds and how to continue."""
    if out is None:
        return "interrupted"
    path = Path(out) / PENDING
    try:
        kept = max(0, len(path.read_text().splitlines()) - 1) if path.is_file() else 0
    except OSError:
        kept = 0
    since = f"; the {kept} genome(s) evaluated since are kept in {path}" if kept else ""
    try:
        gen = int(read_state(out)["generation"])
    except CheckpointError:
        if kept:
            return (f"interrupted within the initial population; {kept} genome(s) evaluated are kept in {path}, "
                    f"continue with --resume --out {out}")
        return f"interrupted before the initial population was evaluated; nothing in {out} to resume"
    return f"interrupted after generation {gen}{since}; {out}/state.json holds it, continue with --resume --out {out}"


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt (a tuner then says what OUT holds; exit code 143)."""


class stop_on_sigterm:  # noqa: N801 (a context manager used like a function)
    """While active, SIGTERM raises Terminated in the main thread, as Ctrl-C raises KeyboardInterrupt."""

    def __enter__(self) -> stop_on_sigterm:
        import signal
        import threading

        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGTERM, self._raise)
        return self

    @staticmethod
    def _raise(signum: int, frame: object) -> None:
        raise Terminated()

    def __exit__(self, *exc: object) -> None:
        import signal

        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)


def build_ga(problem: Problem, cfg: ExperimentConfig, fitness_func: Callable, state: dict | None = None,
             **callbacks) -> GA:
    """The pygad.GA of `problem` (seeded by cfg.seed; genes u in [0, 1]); from `state`, continuing a saved run."""
    done = int(state["generation"]) if state else 0
    common = dict(num_generations=problem.generations - done, num_genes=problem.spec.num_genes,
                  fitness_func=fitness_func, fitness_batch_size=problem.population,
                  gene_space={"low": 0.0, "high": 1.0}, init_range_low=0.0, init_range_high=1.0, gene_type=float,
                  random_seed=cfg.seed, suppress_warnings=True, **callbacks, **problem.ga_kwargs)
    if state is None:
        return GA(sol_per_pop=problem.population, **common)
    ga = GA(initial_population=np.asarray(state["population"], dtype=np.float64), **common)
    ga.numpy_random_generator.set_state(_numpy_state(state["numpy_rng"]))
    ga.python_random_generator.setstate(_python_state(state["python_rng"]))
    return ga


class _Loop:
    """One pygad run: the fitness callback (cache + pool) and the per-generation checkpoint."""

    def __init__(self, problem: Problem, cfg: ExperimentConfig, out: Path, columns: list[str], cache: dict,
                 state: dict | None, start_gen: int | None, progress: bool) -> None:
        self.p, self.cfg, self.out, self.columns, self.cache = problem, cfg, out, columns, cache
        self.state, self.offset = state, start_gen or 0
        self.seconds0 = float(state["seconds"]) if state else 0.0
        self.times = list(state.get("times", [])) if state else []  # run time at each finished generation [s]
        self.evaluations = int(state["evaluations"]) if state else 0
        self.saved = start_gen if start_gen is not None else -1
        self.fresh: dict[tuple, float] = {}  # genomes evaluated since the last checkpoint -> seconds
        self.t0 = time.perf_counter()
        self.pool = None
        from tqdm.auto import tqdm

        self.bar = tqdm(total=problem.generations + 1, initial=self.saved + 1, unit="gen", desc=problem.kind,
                        disable=not progress, dynamic_ncols=True)

    def run_ga(self) -> None:
        ga = build_ga(self.p, self.cfg, self.fitness, self.state, on_fitness=self.on_fitness,
                      on_generation=self.on_generation)
        ga.run()

    # ---------------------------------------------------------------------------------------- pygad callbacks
    def fitness(self, ga, solutions, indices) -> list:
        """pygad's batch fitness: cached values, the rest evaluated by the pool (values signed for maximisation)."""
        decoded = self.p.spec.decode_matrix(np.asarray(solutions, dtype=np.float64))
        keys = [tuple(float(v) for v in row) for row in decoded]
        todo = list(dict.fromkeys(k for k in keys if k not in self.cache))
        if todo:
            self._evaluate(todo)
        sign = 1.0 if self.p.maximize else -1.0
        vals = [sign * self.cache[k] for k in keys]
        return [float(v[0]) for v in vals] if len(self.p.objectives) == 1 else [v.copy() for v in vals]

    def on_fitness(self, ga, fitness) -> None:
        """Checkpoint the initial population (later ones are saved by on_generation)."""
        self._checkpoint(ga)

    def on_generation(self, ga) -> None:
        """Checkpoint each bred generation."""
        self._checkpoint(ga)

    # ------------------------------------------------------------------------------------------------- work
    def _evaluate(self, todo: list[tuple]) -> None:
        genomes = self.p.spec.as_dicts(np.array(todo, dtype=np.float64))
        size = self.p.chunk_size or math.ceil(len(todo) / self.pool.workers)
        starts = list(range(0, len(todo), size))
        if self.p.cost is not None:  # longest first (a stable sort: ties keep the population's order)
            starts.sort(key=lambda s: -sum(self.p.cost(g) for g in genomes[s:s + size]))
        done = 0
        self.bar.set_postfix_str(f"evaluating {len(todo)} genome(s){self._best_text()}", refresh=True)
        pending = self.out / PENDING
        if not pending.is_file():
            write_text_atomic(pending, ",".join([*self.p.spec.columns, *self.p.objectives, "seconds"]) + "\n")
        for i, values, seconds in self.pool.imap(_evaluate_chunk, [genomes[s:s + size] for s in starts],
                                                 (self.p.evaluate, self.cfg, len(self.p.objectives))):
            chunk = todo[starts[i]:starts[i] + size]
            for key, v in zip(chunk, values):
                self.cache[key] = v
                self.fresh[key] = seconds / len(chunk)
            with pending.open("a") as f:  # kept at once: a stop within the generation loses no finished chunk
                f.write("".join(",".join(repr(float(x)) for x in [*key, *v, seconds / len(chunk)]) + "\n"
                                for key, v in zip(chunk, values)))
                f.flush()
                os.fsync(f.fileno())
            done += len(chunk)
            self.bar.set_postfix_str(f"evaluated {done}/{len(todo)}{self._best_text()}", refresh=True)
        self.evaluations += len(todo)

    def _checkpoint(self, ga) -> None:
        gen = self.offset + ga.generations_completed
        if gen <= self.saved:
            return
        pop = np.asarray(ga.population, dtype=np.float64)
        decoded = self.p.spec.decode_matrix(pop)
        keys = [tuple(float(v) for v in row) for row in decoded]
        values = np.stack([self.cache[k] for k in keys])
        spec_cols = self.p.spec.columns
        lines = []
        seen = set()
        for i, (key, row) in enumerate(zip(keys, self.p.spec.as_dicts(decoded))):
            new = key in self.fresh and key not in seen
            seen.add(key)
            flat = [x for v in row.values() for x in (v if isinstance(v, list) else [v])]
            cells = [gen, i, *flat, *self.cache[key].tolist(), self.fresh.get(key, 0.0) if new else 0.0, int(new)]
            lines.append(",".join(repr(c) if isinstance(c, float) else str(c) for c in cells))
        with (self.out / "evaluations.csv").open("a") as f:  # rows first: a resume drops rows past state.json
            f.write("\n".join(lines) + "\n")
            f.flush()
            os.fsync(f.fileno())
        seconds = self.seconds0 + time.perf_counter() - self.t0
        self.times.append(seconds)
        state = {"format": STATE_FORMAT, "kind": self.p.kind, "generation": gen, "generations": self.p.generations,
                 "genes": spec_cols, "scales": [g.scale for g in self.p.spec.genes for _ in range(g.size)],
                 "objectives": list(self.p.objectives), "maximize": self.p.maximize,
                 "population": pop.tolist(), "values": values.tolist(),
                 "numpy_rng": _plain(ga.numpy_random_generator.get_state()),
                 "python_rng": _plain(ga.python_random_generator.getstate()),
                 "seconds": seconds, "times": self.times, "evaluations": self.evaluations}
        write_text_atomic(self.out / "state.json", json.dumps(state))
        (self.out / PENDING).unlink(missing_ok=True)  # its genomes are in evaluations.csv now
        self.saved = gen
        self.fresh.clear()
        self.bar.update(1)
        self.bar.set_postfix_str(self._best_text().lstrip(", "), refresh=True)

    def _best_text(self) -> str:
        if not self.cache or len(self.p.objectives) != 1:
            return ""
        best = (max if self.p.maximize else min)(float(v[0]) for v in self.cache.values())
        return f", best {self.p.objectives[0]} {best:.4g}"

    def close_bar(self) -> None:
        self.bar.close()


def _evaluate_chunk(genomes: list[dict], evaluate: Evaluate, cfg: ExperimentConfig, m: int) -> list[np.ndarray]:
    """Run `evaluate` on one chunk (in a worker) and check its shape and finiteness."""
    values = np.asarray(evaluate(genomes, cfg), dtype=np.float64).reshape(len(genomes), -1)
    if values.shape[1] != m:
        raise ValueError(f"{evaluate.__name__} returned {values.shape[1]} values per genome, expected {m}")
    if not np.isfinite(values).all():
        raise ValueError(f"{evaluate.__name__} returned non-finite values {values.tolist()} (penalise failures with a "
                         "finite value)")
    return list(values)


# ------------------------------------------------------------------------------------------------- files
def read_evaluations(out: str | Path) -> list[dict]:
    """OUT/evaluations.csv as dicts of floats."""
    return read_rows(out, "evaluations.csv")


def _read_pending(out: Path, problem: Problem) -> dict[tuple, tuple[np.ndarray, float]]:
    """OUT/pending.csv as {decoded genes: (values, seconds)} ({} without one; a row cut short by a kill is dropped)."""
    path = out / PENDING
    if not path.is_file():
        return {}
    genes, m = len(problem.spec.columns), len(problem.objectives)
    lines = path.read_text().splitlines()
    if not lines or lines[0] != ",".join([*problem.spec.columns, *problem.objectives, "seconds"]):
        raise CheckpointError(f"{path} has the columns of another run ({lines[0] if lines else 'empty'}); remove it "
                              "to evaluate those genomes again")
    rows = {}
    for line in lines[1:]:
        try:
            x = [float(v) for v in line.split(",")]
        except ValueError:
            continue
        if len(x) == genes + m + 1:
            rows[tuple(x[:genes])] = (np.array(x[genes:genes + m]), x[-1])
    return rows


def _truncate_rows(path: Path, columns: list[str], last_gen: int) -> list[dict]:
    """Keep the CSV rows of generations <= last_gen (a killed run may have logged one more); return them."""
    if not path.is_file():
        raise CheckpointError(f"{path} is missing; cannot resume")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != columns:
            raise CheckpointError(f"{path} has columns {reader.fieldnames}, this run writes {columns}")
        rows = [r for r in reader if int(r["generation"]) <= last_gen]
    with path.open(newline="") as f:
        lines = f.read().splitlines()
    keep = [lines[0]] + [ln for ln in lines[1:] if ln and int(ln.split(",", 1)[0]) <= last_gen]
    write_text_atomic(path, "\n".join(keep) + "\n")
    return rows


def _check_same_run(out: Path, cfg_dict: dict, problem: Problem, state: dict) -> None:
    """A resume must continue the same run: same kind and config (the generation count may differ)."""
    if state.get("kind") != problem.kind:
        raise CheckpointError(f"{out} holds a {state.get('kind')} run, not a {problem.kind} run")
    saved = yaml.safe_load((out / "config.yaml").read_text()) if (out / "config.yaml").is_file() else None
    if saved is None:
        raise CheckpointError(f"{out}/config.yaml is missing; cannot check that --resume continues the same run")
    a, b = _flatten(saved), _flatten(cfg_dict)
    for key in ("ga.num_generations", "nsga2.generations"):
        a.pop(key, None)
        b.pop(key, None)
    diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    if diff:
        shown = ", ".join(f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in diff[:5])
        raise ConfigError(f"--resume of {out} with a different config ({shown}{', ...' if len(diff) > 5 else ''}); "
                          "only the generation count may change")


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _plain(x):
    """Random-generator states as JSON: tuples and numpy arrays to lists."""
    if isinstance(x, (tuple, list)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _numpy_state(s: list) -> tuple:
    """numpy RandomState.get_state() back from JSON."""
    return (s[0], np.asarray(s[1], dtype=np.uint32), int(s[2]), int(s[3]), float(s[4]))


def _python_state(s: list) -> tuple:
    """random.Random.getstate() back from JSON."""
    return (int(s[0]), tuple(int(v) for v in s[1]), s[2])
