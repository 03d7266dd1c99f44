"""`a3cqp bench NAME [args]`: run a benchmark script from the repository's bench/ folder.

NAME: env (bench/env_throughput.py), train (bench/train_speed.py), qp (bench/qp.py),
controller (bench/controller.py), eval (bench/eval_speed.py), or all (each with --quick unless args are given).
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

BENCHES = {"env": "env_throughput.py", "train": "train_speed.py", "qp": "qp.py", "controller": "controller.py",
           "eval": "eval_speed.py"}


def main(argv: list[str] | None = None) -> int:
    """Run one benchmark (or all) and return its exit code."""
    argv = list(argv or [])
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in (*BENCHES, "all"):
        print(__doc__)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    bench_dir = Path(__file__).resolve().parents[1] / "bench"
    if not bench_dir.is_dir():
        print(f"error: {bench_dir} not found; benchmarks run from a source checkout (pip install -e .)", file=sys.stderr)
        return 2
    names = list(BENCHES) if argv[0] == "all" else [argv[0]]
    rest = argv[1:] or (["--quick"] if argv[0] == "all" else [])
    rc = 0
    sys.path.insert(0, str(bench_dir))
    for name in names:
        script = bench_dir / BENCHES[name]
        if not script.is_file():
            print(f"[{name}] {script.name} is not in this checkout yet; skipped")
            continue
        print(f"=== a3cqp bench {name} ({script.name} {' '.join(rest)}) ===", flush=True)
        module = runpy.run_path(str(script), run_name="a3cqp_bench")
        rc = max(rc, int(module["main"](rest) or 0))
    return rc
