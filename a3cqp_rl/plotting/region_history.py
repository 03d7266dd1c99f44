"""When are the paper's Fig. 5 regions learned, and do they stay? A strip per region (and one for all
four): the fraction of runs whose policy passes `a3cqp_rl.regions` at each checked step, read from the
region columns of each run's metrics.csv (`a2c.region_checks`): the literal check where the runs have it,
else the contrast check."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from a3cqp_rl.plotting.loss_curves import read_runs, steps_axis
from a3cqp_rl.regions import CONTRAST_COLUMNS, LITERAL_COLUMNS

_NAMES = {"w2": r"$\dot w_2$ admittance", "w3": r"$\dot w_3$ force ctrl", "fd": r"$\dot f_d$", "w1": r"$\dot w_1$ IK"}
_COLUMNS = {"contrast": CONTRAST_COLUMNS, "literal": LITERAL_COLUMNS}


def region_history(run_dirs: Sequence[str | Path], check: str = "contrast") -> tuple[np.ndarray, np.ndarray]:
    """(steps [S], pass fraction over runs [5, S]: w2, w3, fd, w1, all four) at every step any run was checked.

    `check`: 'contrast' (columns regions_ok, region_*) or 'literal' (literal_ok, literal_*).
    """
    if check not in _COLUMNS:
        raise ValueError(f"check must be one of {sorted(_COLUMNS)}, got {check!r}")
    total, *per_region = _COLUMNS[check]
    runs = read_runs(run_dirs)
    for d, r in zip(run_dirs, runs):
        if total not in r or not np.isfinite(r[total]).any():
            raise ValueError(f"{d}/metrics.csv has no Fig. 5 region checks (a2c.region_checks was 0, or an older run)")
    steps = np.unique(np.concatenate([r["step"][np.isfinite(r[total])] for r in runs]))
    keys = [*per_region, total]
    frac = np.zeros((len(keys), len(steps)))
    for r in runs:
        ok = np.isfinite(r[total])
        # runs checked at other steps (another length or config) count with their latest check at or before each step,
        # and as not passed before their first
        idx = np.searchsorted(r["step"][ok], steps, side="right") - 1
        for i, k in enumerate(keys):
            v = r[k][ok] == 4.0 if k == total else r[k][ok] == 1.0
            frac[i] += np.where(idx >= 0, v[np.clip(idx, 0, None)], False)
    return steps, frac / len(runs)


def plot_region_history(run_dirs: Sequence[str | Path], out: str | Path) -> Path:
    """Strips of the Fig. 5 region pass fraction over runs against steps; PNG or PDF by suffix of `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tables = read_runs(run_dirs)
    literal = all(LITERAL_COLUMNS[0] in t and np.isfinite(t[LITERAL_COLUMNS[0]]).any() for t in tables)
    check = "literal" if literal else "contrast"
    steps, frac = region_history(run_dirs, check)
    labels = [*(_NAMES[c.split("_")[1]] for c in _COLUMNS[check][1:]), "all four"]
    # each check's cell spans from the previous check to it: the policy at that step; a lone check gets a thin cell
    # at its step (a cell from 0 would read as passed all along)
    first = steps[0] - (steps[1] - steps[0] if len(steps) > 1 else 0.02 * steps[0])
    edges = np.concatenate([[max(first, 0.0)], steps])
    if len(steps) < 2:
        import warnings

        warnings.warn(f"one Fig. 5 check per run (at step {steps[0]:,.0f}): raise a2c.region_checks or lower "
                      "a2c.log_every for a history", stacklevel=2)
    fig, ax = plt.subplots(figsize=(9, 2.8), constrained_layout=True)
    mesh = ax.pcolormesh(edges, np.arange(len(labels) + 1), frac, cmap="Greens", vmin=0.0, vmax=1.0, edgecolors="white",
                         linewidth=0.5)
    ax.set_yticks(np.arange(len(labels)) + 0.5, labels)
    ax.invert_yaxis()
    ax.set_xlim(0.0, steps[-1])
    steps_axis(ax)
    n = len(run_dirs)
    ax.set_title(f"Fig. 5 regions passed, {check} check ({n} run{'s' if n > 1 else ''}; a3cqp_rl.regions)")
    fig.colorbar(mesh, ax=ax, label="fraction of runs" if n > 1 else "pass", pad=0.01)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
