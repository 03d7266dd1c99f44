"""`a2c.select_policy: panda`: choose a point-mass run's policy.pt by what its candidates do on the Panda.

The transfer margin (a3cqp_rl.transfer) ranks the parameters of the run's last log rows by a few mean actions: it
is necessary, not sufficient (docs/panda.md, "Keeping the parameters that transfer"). So the rows with the largest
margins are each run, after training, on `a2c.select_trials` peg-in-hole trials of the Panda (learned controller
alone, trial seed `a2c.select_seed`, config `a2c.select_config`: `a3cqp evaluate` on the same trials gives the
same numbers), and policy.pt holds the one that inserts the most pegs; among equals, one that yields to the
operator's push (a3cqp_rl.transfer.yields: the collaborative scenes need it, and it costs microseconds), then the
shortest time over every trial (a miss counted at the time limit), then the largest margin. Like keeping the
checkpoint with the best evaluation return (SB3's EvalCallback), but on the robot the policy is trained for, on
trials kept off the reported ones.

Each candidate's parameters are written to OUT/candidates/update_UUUUUU.pt and its result to
OUT/candidates/selection.json after each evaluation, so a run stopped while selecting resumes there.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from a3cqp_rl import worker_start
from a3cqp_rl.checkpoint import save_atomic, write_text_atomic
from a3cqp_rl.config import A2CConfig

__all__ = ["SELECTION_FILE", "PANDA_SELECTION_KEYS", "select_config_path", "select_on_panda", "rank_key",
           "format_selection"]

SELECTION_FILE = "selection.json"
PANDA_SELECTION_KEYS = ("update", "transfer_margin", "successes", "insertions", "capped_time_mean_s",
                        "insertion_time_mean_s", "trials", "seed", "config")
"""What policy.pt's `panda_selection` records of the chosen candidate."""


def rank_key(row: dict) -> tuple:
    """Sort key of a candidate's row, best first: most pegs inserted, then yielding to the operator, shortest capped
    time, largest margin."""
    return (-row["successes"], not row["yields"], row["capped_time_mean_s"], -row["transfer_margin"], -row["update"])


def select_config_path(hp: A2CConfig) -> Path:
    """`a2c.select_config` as a path; FileNotFoundError naming the working directory if it is not a file."""
    path = Path(hp.select_config)
    if not path.is_file():
        raise FileNotFoundError(f"a2c.select_config: {path} not found (relative to {Path.cwd()})")
    return path


def select_on_panda(candidates: list[tuple[float, int, Tensor]], meta: dict, folder: Path, hp: A2CConfig,
                    log: Callable[[str], None] = print, workers: int | None = None) -> tuple[int, list[dict]]:
    """Run each candidate (margin, update, parameters) on the Panda's peg-in-hole trials, `workers` processes at a
    time (default: the usable cores); return the index of the one policy.pt should hold and every candidate's row
    (update, margin, fingerprint, successes, times [s], whether it yields)."""
    from a3cqp_rl.config import load_config
    from a3cqp_rl.transfer import guided_rates, yields
    from algorithms.policy import fingerprint, load_policy
    from envs.panda_eval import default_workers

    if not candidates:
        raise ValueError("a2c.select_policy: panda has no candidates: no log row fell in the run's last "
                         "a2c.select_last (log more often: a2c.log_every)")
    cfg_path = select_config_path(hp)
    panda_cfg = load_config(cfg_path)
    out = folder / "candidates"
    out.mkdir(exist_ok=True)
    done = _read_rows(out / SELECTION_FILE)
    # a row is reused only for the same parameters on the same trials under the same config text
    trials = {"trials": hp.select_trials, "seed": hp.select_seed, "config": str(cfg_path),
              "config_sha256": hashlib.sha256(cfg_path.read_bytes()).hexdigest()[:16]}
    rows, paths = [], []
    for margin, update, flat in candidates:
        path = out / f"update_{update:06d}.pt"
        save_atomic({"format": 1, "flat": flat.clone(), **meta, "averaged_updates": 0, "selected_update": update,
                     "transfer_margin": margin}, path)
        policy = load_policy(path)
        row = {"update": update, "transfer_margin": margin, "fingerprint": fingerprint(policy), **trials}
        old = next((r for r in done if all(r.get(k) == v for k, v in row.items() if k != "update")), None)
        rows.append({**(old or {}), **row, "yields": yields(guided_rates(policy))})  # yields: microseconds, redone
        paths.append(path)
    todo = [k for k, r in enumerate(rows) if "successes" not in r]
    for k in range(len(rows)):
        if k not in todo:
            log(_line(rows, k, "(measured before)"))
    for k, summary, seconds in _evaluate(paths, todo, hp, panda_cfg, workers or default_workers()):
        rows[k].update({"successes": int(summary["successes"]), "insertions": int(summary["insertions"]),
                        "capped_time_mean_s": float(summary["capped_time_mean_s"]),
                        "insertion_time_mean_s": _finite(summary["insertion_time_mean_s"]), "wall_seconds": seconds})
        log(_line(rows, k, f"({seconds:.0f} s)"))
        kept = [r for r in rows if "successes" in r] + [r for r in done if r not in rows]
        write_text_atomic(out / SELECTION_FILE, json.dumps({"candidates": kept}, indent=1) + "\n")
    best = min(range(len(rows)), key=lambda i: rank_key(rows[i]))
    return best, rows


def _evaluate(paths: list[Path], todo: list[int], hp: A2CConfig, panda_cfg, workers: int):  # noqa: ANN001, ANN202
    """Yield (index, learned controller's summary, wall seconds) for each candidate in `todo` as it ends: each is
    `a3cqp evaluate --workers 1` on the selection trials, in a process of its own when `workers` > 1 (the
    candidates, not the trials, are spread: eight arms hardly fill one core)."""
    jobs = [(k, str(paths[k]), hp.select_trials, hp.select_seed, panda_cfg) for k in todo]
    if workers <= 1 or len(jobs) <= 1:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # the arms' tiny networks and QPs: threads cost more than they give
        try:
            yield from map(_evaluate_one, jobs)
        finally:
            torch.set_num_threads(threads)
        return
    from concurrent.futures import as_completed

    from envs.evaluate_cli import PANDA_WORKER_IMPORTS

    # forked from a fresh server that has imported the Panda env once (not from this process: no forked torch state)
    ctx = worker_start.context(PANDA_WORKER_IMPORTS)
    with worker_start.pool(min(workers, len(jobs)), ctx, "algorithms.panda_select:_init_worker") as pool:
        for future in as_completed([pool.submit(_evaluate_one, job) for job in jobs]):
            yield future.result()


def _init_worker() -> None:
    """Worker process set-up: one torch thread (the arms' tiny networks and QPs)."""
    torch.set_num_threads(1)


def _evaluate_one(job: tuple) -> tuple[int, dict, float]:
    """One candidate on the selection trials: (index, the learned controller's summary, wall seconds)."""
    from envs.panda_eval import evaluate

    k, path, trials, seed, cfg = job
    res = evaluate("peg_in_hole", path, trials, seed, config=cfg, controllers=("learned",), progress=False, workers=1)
    return k, res.summary["learned"], res.seconds


def _line(rows: list[dict], k: int, note: str) -> str:
    r = rows[k]
    return (f"candidate {k + 1}/{len(rows)}: update {r['update']:,} (transfer margin {r['transfer_margin']:+.2f}): "
            f"{r['successes']}/{r['insertions']} pegs, {r['capped_time_mean_s']:.2f} s {note}")


def format_selection(rows: list[dict], chosen: int) -> str:
    """The candidates' table, the chosen one marked."""
    lines = ["   update  margin   pegs  yields  time, misses at the limit [s]"]
    for i, r in enumerate(rows):
        lines.append(f"{'*' if i == chosen else ' '} {r['update']:>7,}  {r['transfer_margin']:+.2f}  "
                     f"{r['successes']:>3}/{r['insertions']:<3} {'yes' if r['yields'] else 'no':<6}  "
                     f"{r['capped_time_mean_s']:.2f}")
    return "\n".join(lines)


def _finite(v) -> float | None:  # noqa: ANN001
    return float(v) if v is not None and math.isfinite(float(v)) else None


def _read_rows(path: Path) -> list[dict]:
    """The rows a previous selection in this folder wrote (none if absent or unreadable)."""
    try:
        return list(json.loads(path.read_text())["candidates"])
    except (OSError, ValueError, KeyError, TypeError):
        return []


