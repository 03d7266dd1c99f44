"""Markdown summary of a GA run folder (a3cqp tune): the run, fitness per generation, the best distinct genomes,
and the best genes beside the paper's Table IV.

    python docs/experiments/ga_summary.py RUN_DIR [--every K] [--top N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl

from a3cqp_rl.config import A2CConfig
from a3cqp_rl.tuning_files import read_rows, read_state


def main() -> None:
    """Print the summary."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run")
    p.add_argument("--every", type=int, default=5, help="a table row every K generations")
    p.add_argument("--top", type=int, default=5, help="best distinct genomes listed")
    args = p.parse_args()
    state = read_state(args.run)
    rows = read_rows(args.run)
    genes = state["genes"]
    times = state.get("times", [])
    new = [r for r in rows if r["new"]]
    print(f"{state['generation']} generations, {len(rows)} individuals, {state['evaluations']} trainings, "
          f"{state['seconds'] / 60:.1f} min; training time per trial: median "
          f"{statistics.median(r['seconds'] for r in new):.1f} s (min {min(r['seconds'] for r in new):.1f}, "
          f"max {max(r['seconds'] for r in new):.1f})")
    if len(times) > 1:
        per_gen = [b - a for a, b in zip(times, times[1:])]
        print(f"time per bred generation: median {statistics.median(per_gen):.1f} s; generation 0: {times[0]:.1f} s")
    print()
    print("| generation | best so far | population best | median | worst | trainings |")
    print("|---:|---:|---:|---:|---:|---:|")
    best = -float("inf")
    last = int(state["generation"])
    for g in range(last + 1):
        fit = [r["fitness"] for r in rows if r["generation"] == g]
        best = max(best, max(fit))
        if g % args.every == 0 or g == last:
            n = sum(1 for r in rows if r["generation"] == g and r["new"])
            print(f"| {g} | {best:.1f} | {max(fit):.1f} | {statistics.median(fit):.1f} | {min(fit):.1f} | {n} |")
    print()
    seen, top = set(), []
    for r in sorted(rows, key=lambda r: -r["fitness"]):
        key = tuple(r[k] for k in genes)
        if key not in seen:
            seen.add(key)
            top.append(r)
        if len(top) == args.top:
            break
    print("| rank | fitness | first in generation | " + " | ".join(genes) + " |")
    print("|---:|---:|---:|" + "---:|" * len(genes))
    for i, r in enumerate(top):
        first = min(int(x["generation"]) for x in rows if all(x[k] == r[k] for k in genes))
        print(f"| {i + 1} | {r['fitness']:.1f} | {first} | " + " | ".join(f"{r[k]:.4g}" for k in genes) + " |")
    paper = A2CConfig()
    print()
    print("| gene | GA best | Table IV | ratio |")
    print("|---|---:|---:|---:|")
    for k in genes:
        ref = getattr(paper, k)
        print(f"| {k} | {top[0][k]:.4g} | {ref:.4g} | {top[0][k] / ref:.3g} |")


if __name__ == "__main__":
    main()
