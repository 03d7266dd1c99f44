"""Reading a tuning run's folder (written by algorithms.tuning.runner): state.json and the CSV logs.

Kept here, beside the plots that read them, so that a3cqp_rl needs nothing from algorithms/.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from a3cqp_rl.exceptions import CheckpointError

__all__ = ["STATE_FORMAT", "read_state", "read_rows"]

STATE_FORMAT = 1


def read_state(out: str | Path) -> dict:
    """OUT/state.json of a tuning run (CheckpointError if missing or unreadable)."""
    path = Path(out) / "state.json"
    if not path.is_file():
        raise CheckpointError(f"no tuning run in {Path(out)} ({path.name} not found)")
    try:
        state = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path} is not a tuning state file: {exc}") from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise CheckpointError(f"{path} is not a tuning state file of format {STATE_FORMAT}")
    return state


def read_rows(out: str | Path, name: str = "evaluations.csv") -> list[dict[str, float]]:
    """OUT/NAME (a CSV of numbers) as dicts column -> float."""
    path = Path(out) / name
    if not path.is_file():
        raise CheckpointError(f"{path.name} not found in {Path(out)}")
    with path.open(newline="") as f:
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
