"""When are the paper's Fig. 5 regions learned, and do they stay? A strip per region (and one for all
four): the fraction of runs whose policy passes `a3cqp_rl.regions` at each checked step, read from the
region columns of each run's metrics.csv (`a2c.region_checks`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from a3cqp_rl.plotting.loss_curves import read_metrics
from a3cqp_rl.regions import REGION_COLUMNS

ROW_LABELS = {"region_w2": r"$\dot w_2$ admittance", "region_w3": r"$\dot w_3$ force ctrl", "region_fd": r"$\dot f_d$",
              "region_w1": r"$\dot w_1$ IK", "regions_ok": "all four"}


def region_history(run_dirs: Sequence[str | Path]) -> tuple[np.ndarray, np.ndarray]:
    """(steps [S], pass fraction over runs [5, S]: region_w2, _w3, _fd, _w1, all four) at the first run's checks."""
    runs = [read_metrics(d) for d in run_dirs]
    if not runs:
        raise ValueError("no runs given")
    for d, r in zip(run_dirs, runs):
        if "regions_ok" not in r or not np.isfinite(r["regions_ok"]).any():
            raise ValueError(f"{d}/metrics.csv has no Fig. 5 region checks (a2c.region_checks was 0, or an older run)")
    first = runs[0]
    steps = first["step"][np.isfinite(first["regions_ok"])]
    keys = [*REGION_COLUMNS[1:], "regions_ok"]
    frac = np.zeros((len(keys), len(steps)))
    for r in runs:
        ok = np.isfinite(r["regions_ok"])
        # runs checked at other steps (another length or config) count with their latest check at or before each step
        idx = np.searchsorted(r["step"][ok], steps, side="right") - 1
        for i, k in enumerate(keys):
            v = r[k][ok] == 4.0 if k == "regions_ok" else r[k][ok] == 1.0
            frac[i] += np.where(idx >= 0, v[np.clip(idx, 0, None)], False)
    return steps, frac / len(runs)


def plot_region_history(run_dirs: Sequence[str | Path], out: str | Path) -> Path:
    """Strips of the Fig. 5 region pass fraction over runs against steps; PNG or PDF by suffix of `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps, frac = region_history(run_dirs)
    keys = [*REGION_COLUMNS[1:], "regions_ok"]
    # each check's cell spans from the previous check to it: the policy at that step
    edges = np.concatenate([[0.0], steps])
    fig, ax = plt.subplots(figsize=(9, 2.8), constrained_layout=True)
    mesh = ax.pcolormesh(edges, np.arange(len(keys) + 1), frac, cmap="Greens", vmin=0.0, vmax=1.0, edgecolors="white",
                         linewidth=0.5)
    ax.set_yticks(np.arange(len(keys)) + 0.5, [ROW_LABELS[k] for k in keys])
    ax.invert_yaxis()
    ax.set_xlabel("steps")
    n = len(run_dirs)
    ax.set_title(f"Fig. 5 regions passed ({n} run{'s' if n > 1 else ''}; a3cqp_rl.regions.check_fig5_regions)")
    fig.colorbar(mesh, ax=ax, label="fraction of runs" if n > 1 else "pass", pad=0.01)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
