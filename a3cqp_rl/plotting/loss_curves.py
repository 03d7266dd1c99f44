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


def read_runs(run_dirs: Sequence[str | Path]) -> list[dict[str, np.ndarray]]:
    """`read_metrics` of each run, refusing the same folder twice (it would count twice) and runs of different envs
    (OUT/config.yaml's `env`: their losses are not on one scale)."""
    if not run_dirs:
        raise ValueError("no runs given")
    seen: dict[Path, str | Path] = {}
    for d in run_dirs:
        key = Path(d).resolve()
        if key in seen:
            raise ValueError(f"{d} is given twice (also as {seen[key]}): each run counts once")
        seen[key] = d
    envs = {str(d): _env_of(d) for d in run_dirs}
    if len({e for e in envs.values() if e is not None}) > 1:
        raise ValueError("runs of different envs: " + ", ".join(f"{d} ({e})" for d, e in envs.items() if e)
                         + "; plot each env's runs on their own")
    return [read_metrics(d) for d in run_dirs]


def _env_of(run_dir: str | Path) -> str | None:
    """The `env` OUT/config.yaml names (None without one)."""
    import yaml

    path = Path(run_dir) / "config.yaml"
    try:
        data = yaml.safe_load(path.read_text()) if path.is_file() else None
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return None
    return str(data.get("env")) if isinstance(data, dict) and data.get("env") is not None else None


def warn_short(run_dirs: Sequence[str | Path], runs: Sequence[dict[str, np.ndarray]]) -> None:
    """A warning per run with fewer than two logged rows: its curve is a point (a2c.log_every counts updates)."""
    for d, r in zip(run_dirs, runs):
        if len(r["step"]) < 2:
            warnings.warn(f"{d}/metrics.csv has {len(r['step'])} row: its curve is one point; lower a2c.log_every "
                          "(updates between rows) for a curve", stacklevel=3)


def aligned(runs: Sequence[dict[str, np.ndarray]], metric: str) -> tuple[np.ndarray, np.ndarray]:
    """(steps [S], values [R, S]): every run's `metric` on the union of the logged steps, NaN outside the run's own
    range (runs of other lengths or log_every; the result does not depend on the runs' order but for the rows)."""
    steps = np.unique(np.concatenate([r["step"] for r in runs]))
    return steps, np.stack([np.interp(steps, r["step"], r[metric], left=np.nan, right=np.nan) for r in runs])


def steps_axis(ax, label: str = "steps") -> None:  # noqa: ANN001
    """An x axis of steps with few, engineering-formatted ticks (10k, 2M), readable on narrow panels."""
    from matplotlib.ticker import EngFormatter, MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))
    ax.set_xlabel(label)


def plot_loss_curves(
    run_dirs: Sequence[str | Path], out: str | Path, metrics: Sequence[str] = ("policy_loss", "value_loss", "episode_reward")
) -> Path:
    """Mean and IQR band over runs of each metric against steps; PNG or PDF by suffix of `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = read_runs(run_dirs)
    warn_short(run_dirs, runs)
    few = len(aligned(runs, "step")[0]) <= 30  # markers: a short series drawn as a bare line is invisible
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.5 * len(metrics), 3.6), constrained_layout=True)
    for ax, m in zip(np.atleast_1d(axes), metrics):
        steps, ys = aligned(runs, m)
        with warnings.catch_warnings():  # all-NaN columns (e.g. no episode ended yet) stay NaN, quietly
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(ys, axis=0)
            q25, q75 = np.nanpercentile(ys, 25, axis=0), np.nanpercentile(ys, 75, axis=0)
        count = np.isfinite(ys).sum(0)
        label = f"mean of {len(runs)} runs" if len(runs) > 1 else "one run"
        if len(runs) > 1 and count[count > 0].min(initial=len(runs)) < len(runs):
            label += " (fewer where some end)"
        ax.plot(steps, mean, lw=1.5, marker="o" if few else None, ms=3, label=label)
        if len(runs) > 1:
            ax.fill_between(steps, q25, q75, alpha=0.3, label="25-75 %")
        if not np.isfinite(mean).any():
            why = "no episode ended in a logged window" if m == "episode_reward" else "no finite values"
            ax.text(0.5, 0.5, f"no data:\n{why}", transform=ax.transAxes, ha="center", va="center", color="grey")
        steps_axis(ax)
        ax.set_ylabel(m.replace("_", " "))
        ax.set_title(m.replace("_", " "))
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=8)
    names = [str(d) for d in run_dirs]
    fig.suptitle(", ".join(names) if len(names) <= 3 else f"{names[0]} ... {names[-1]} ({len(names)} runs)",
                 fontsize=9)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
