"""Loss curves like paper 000 Fig. 4: policy and value loss against steps, mean and inter-quartile
band (25th-75th percentile) over several runs (seeds), read from each run's metrics.csv."""

from __future__ import annotations

import csv
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def read_metrics(run_dir: str | Path) -> dict[str, np.ndarray]:
    """Columns of RUN/metrics.csv as float arrays; FileNotFoundError with the path if absent."""
    path = Path(run_dir) / "metrics.csv"
    if not Path(run_dir).exists():
        raise FileNotFoundError(f"{run_dir}: no such folder")
    if not path.is_file():
        raise FileNotFoundError(f"no metrics.csv in {run_dir} (is it a training output folder?)")
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            raise ValueError(f"{path} has no rows yet")
        header = [k for k in rows[0] if k is not None]
        for i, r in enumerate(rows):  # csv.DictReader files extra fields under None and fills missing ones with None
            if None in r or None in r.values():
                raise ValueError(f"{path}: data row {i + 1} has another number of fields than the header's "
                                 f"{len(header)}")
        return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}
    except (UnicodeDecodeError, csv.Error, TypeError, ValueError) as exc:
        if str(exc).startswith(str(path)):
            raise
        raise ValueError(f"{path} is not a metrics file a3cqp train wrote (numbers under a header row): "
                         f"{type(exc).__name__}: {exc}") from None


def plot_loss_curves(
    run_dirs: Sequence[str | Path], out: str | Path, metrics: Sequence[str] = ("policy_loss", "value_loss", "episode_reward")
) -> Path:
    """Mean and IQR band over runs of each metric against steps; PNG or PDF by suffix of `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [read_metrics(d) for d in run_dirs]
    if not runs:
        raise ValueError("no runs given")
    steps = runs[0]["step"]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.5 * len(metrics), 3.6), constrained_layout=True)
    for ax, m in zip(np.atleast_1d(axes), metrics):
        # runs of different lengths are compared on the common step grid of the first run
        ys = np.stack([np.interp(steps, r["step"], r[m], right=np.nan) for r in runs])
        with warnings.catch_warnings():  # all-NaN columns (e.g. no episode ended yet) stay NaN, quietly
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(ys, axis=0)
            q25, q75 = np.nanpercentile(ys, 25, axis=0), np.nanpercentile(ys, 75, axis=0)
        ax.plot(steps, mean, lw=1.5, label=f"mean of {len(runs)} run(s)")
        ax.fill_between(steps, q25, q75, alpha=0.3, label="25-75 %")
        ax.set_xlabel("steps")
        ax.set_title(m.replace("_", " "))
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=8)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
