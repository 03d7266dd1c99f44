"""How `a3cqp evaluate --scene` starts its workers: forked from a server that did their imports once, against spawned.

Runs the same small multi-seed sweep (`--trials 2 --seeds 0-3 --controllers ik` by default, 2 workers), as a fresh
command each time, alternately with A3CQP_WORKER_START=forkserver (the default) and =spawn (each worker imports
torch, torchrl, MuJoCo and the env itself, for every seed's pool). Prints each start method's median wall time, their
ratio, and whether the two wrote the same results (they should: only the start differs).

Usage: python bench/worker_start.py [--quick] [--repeats R] [--seeds LIST] [--trials K]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from a3cqp_rl.cli import help_summary

METHODS = ("forkserver", "spawn")


def _without_wall(doc: object) -> object:
    """The results JSON without its wall-time entries (the rest must be equal between start methods)."""
    if isinstance(doc, dict):
        return {k: _without_wall(v) for k, v in doc.items() if k != "wall_seconds"}
    if isinstance(doc, list):
        return [_without_wall(v) for v in doc]
    return doc


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print the wall time of each start method, the ratio and whether the results agree."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--quick", action="store_true", help="one run each, seeds 0-1")
    p.add_argument("--repeats", type=int, default=3, help="runs per start method, interleaved (default 3)")
    p.add_argument("--seeds", default="0-3", help="the sweep's trial seeds (default 0-3)")
    p.add_argument("--trials", type=int, default=2, help="trials per seed (default 2)")
    args = p.parse_args(argv)
    repeats, seeds = (1, "0-1") if args.quick else (args.repeats, args.seeds)
    if repeats < 1 or args.trials < 1:
        p.error("--repeats and --trials must be >= 1")
    walls: dict[str, list[float]] = {m: [] for m in METHODS}
    results: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for method in METHODS:
                out = Path(tmp) / f"{method}.json"
                cmd = [sys.executable, "-m", "a3cqp_rl.cli", "evaluate", "--scene", "peg_in_hole", "--trials",
                       str(args.trials), "--seeds", seeds, "--controllers", "ik", "--workers", "2", "--quiet",
                       "--json", str(out)]
                t0 = time.perf_counter()
                run = subprocess.run(cmd, capture_output=True, text=True,
                                     env={**os.environ, "A3CQP_WORKER_START": method})
                walls[method].append(time.perf_counter() - t0)
                if run.returncode != 0:
                    print(f"error: the {method} run failed ({run.returncode}):\n{run.stderr[-2000:]}", file=sys.stderr)
                    return 1
                results[method] = _without_wall(json.loads(out.read_text()))
    med = {m: statistics.median(w) for m, w in walls.items()}
    print(f"a3cqp evaluate --scene peg_in_hole --trials {args.trials} --seeds {seeds} --controllers ik --workers 2, "
          f"{repeats} run(s) each, interleaved (median wall, whole command):")
    for m in METHODS:
        print(f"  {m:10s} {med[m]:7.2f} s  ({', '.join(f'{w:.2f}' for w in walls[m])})")
    ratio = med["spawn"] / med["forkserver"]
    print(f"forkserver vs spawn: {f'{ratio:.2f}x faster' if ratio >= 1 else f'{1 / ratio:.2f}x slower'}; same results: "
          f"{'yes' if results['forkserver'] == results['spawn'] else 'NO'}")
    return 0 if results["forkserver"] == results["spawn"] else 1


if __name__ == "__main__":
    sys.exit(main())
