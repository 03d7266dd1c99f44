"""The Panda transfer checks over training, one panel per run: the margin of `a3cqp_rl.transfer` and the four rates
it is the minimum of (metrics.csv's transfer columns), with the update `a2c.select_policy: transfer` kept."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from a3cqp_rl.plotting.loss_curves import read_runs, steps_axis

__all__ = ["TERMS", "kept_update", "plot_transfer_history"]

TERMS = (("free_w1", 1.0, "free ẇ1"), ("free_w2", -1.0, "−free ẇ2"), ("guided_w2", 1.0, "guided ẇ2"),
         ("guided_fd", -1.0, "−guided ḟd"))
"""(metrics.csv column, sign, label): the terms whose minimum is the transfer margin; each > 0 where its check passes."""


def kept_update(run_dir: str | Path) -> int | None:
    """The update whose parameters RUN/policy.pt holds under `a2c.select_policy: transfer` (None: the last ones, or no
    policy.pt yet)."""
    import torch

    path = Path(run_dir) / "policy.pt"
    if not path.is_file():
        return None
    value = torch.load(path, weights_only=True).get("selected_update")
    return None if value is None else int(value)


def _select_last(run_dir: str | Path) -> float | None:
    """The run's `a2c.select_last` from OUT/config.yaml (None without one)."""
    import yaml

    try:
        data = yaml.safe_load((Path(run_dir) / "config.yaml").read_text())
        return float(data["a2c"]["select_last"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None


def plot_transfer_history(run_dirs: Sequence[str | Path], out: str | Path) -> Path:
    """One panel per run of the transfer margin and its terms against steps; PNG or PDF by suffix of `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tables = read_runs(run_dirs)
    for d, t in zip(run_dirs, tables):
        if "transfer_margin" not in t or not np.isfinite(t["transfer_margin"]).any():
            raise ValueError(f"{Path(d) / 'metrics.csv'} has no transfer columns: they are written for the per-axis "
                             "agents' policy (eq. 26 observation, four actions) by a3cqp train since 2026-11-29")
    cols = min(4, len(tables))
    rows = math.ceil(len(tables) / cols)
    # (a panel at least 8.4 wide alone: the two-line title fits)
    fig, axes = plt.subplots(rows, cols, figsize=(max(4.2 * cols, 8.4), 2.9 * rows + 0.6), sharey=True, squeeze=False,
                             constrained_layout=True)
    for ax, d, t in zip(axes.flat, run_dirs, tables):
        steps = t["step"]
        mark = "o" if len(steps) <= 30 else None  # a short series drawn as a bare line is invisible
        for column, sign, label in TERMS:
            if column in t:  # free_w2 came a little after the other columns
                ax.plot(steps, sign * t[column], lw=0.8, alpha=0.75, marker=mark, ms=2.5, label=label)
        ax.plot(steps, t["transfer_margin"], color="k", lw=1.6, marker=mark, ms=3, label="margin (their minimum)")
        ax.axhline(0.0, color="grey", lw=0.6)
        kept = kept_update(d)
        name = Path(d).name or str(d)
        if kept is not None:
            per_update = float(t["step"][0] / t["update"][0])
            ax.axvline(kept * per_update, color="tab:red", ls="--", lw=1.2, label="kept by select_policy")
            name += f" (kept: update {kept:,})"
            last = _select_last(d)
            if last is not None:  # the rows the selection chose among: a better margin before them was not a candidate
                ax.axvspan(steps[-1] * (1.0 - last), steps[-1], color="tab:red", alpha=0.06, lw=0,
                           label=f"searched (the last {last:.0%})")
        ax.set_title(name, fontsize=9)
        ax.set_ylim(-1.05, 1.05)
        steps_axis(ax)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(tables):]:
        ax.set_visible(False)
    handles, labels = axes[0][0].get_legend_handles_labels()  # below the panels, not over the curves
    fig.legend(handles, labels, fontsize=7, loc="outside lower center", ncol=min(len(labels), 4))
    fig.suptitle("Panda transfer checks over training (a3cqp_rl.transfer)\nevery line > 0: raises IK over admittance in "
                 "free motion and yields to the operator", fontsize=9)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
