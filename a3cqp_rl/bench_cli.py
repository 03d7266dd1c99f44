"""`a3cqp bench NAME [args]`: run one benchmark of the installed `bench` package (the repository's bench/ folder).

NAME: env, train, pendulum, qp, controller, hierarchy, population, panda, tuning, eval, a2c, leak, workers, or all
(all: every one with --quick unless args are given; a single NAME runs with its own defaults, pass --quick for the
short mode). Each benchmark also runs as a script, `python bench/<file>.py --help`.
"""

from __future__ import annotations

import importlib
import sys

BENCHES = {"env": "bench.env_throughput", "train": "bench.train_speed", "pendulum": "bench.pendulum",
           "qp": "bench.qp", "controller": "bench.controller", "hierarchy": "bench.hierarchy",
           "population": "bench.population_step", "panda": "bench.panda_env", "tuning": "bench.tuning",
           "eval": "bench.eval_speed", "a2c": "bench.a2c_cpu", "leak": "bench.leak_extra",
           "workers": "bench.worker_start"}
"""Benchmark name -> module with a `main(argv) -> int` (dispatched by name: a3cqp_rl imports nothing from bench)."""


def main(argv: list[str] | None = None) -> int:
    """Run one benchmark (or all) and return its exit code."""
    argv = list(argv or [])
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    if argv[0] not in (*BENCHES, "all"):
        print(f"error: no benchmark named {argv[0]!r}; choose from {', '.join(BENCHES)} or all", file=sys.stderr)
        return 2
    if argv[0] == "all" and {"-h", "--help"} & set(argv[1:]):  # not the first benchmark's help alone
        print(__doc__ + "\n`a3cqp bench NAME --help` gives one benchmark's options.")
        return 0
    names = list(BENCHES) if argv[0] == "all" else [argv[0]]
    rest = argv[1:] or (["--quick"] if argv[0] == "all" else [])
    rc = 0
    for name in names:
        try:
            module = importlib.import_module(BENCHES[name])
        except ImportError as exc:
            print(f"error: benchmark {name!r} needs {exc.name!r}: pip install -e '.[bench]'", file=sys.stderr)
            rc = max(rc, 2)
            continue
        print(f"=== a3cqp bench {name} ({BENCHES[name]} {' '.join(rest)}) ===", flush=True)
        prog, sys.argv[0] = sys.argv[0], f"a3cqp bench {name}"  # argparse's usage lines name the command typed
        try:
            rc = max(rc, int(module.main(rest) or 0))
        finally:
            sys.argv[0] = prog
    return rc
