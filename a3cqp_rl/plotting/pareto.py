"""Pareto front of a multi-objective tuning run: every evaluation (shaded by generation) and the final front,
in 2-D (each pair of objectives) and, for three or more objectives, 3-D."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations
from pathlib import Path

import numpy as np


def plot_pareto(values: np.ndarray, generation: np.ndarray, front: np.ndarray, names: Sequence[str],
                out: str | Path, reference: np.ndarray | None = None) -> list[Path]:
    """Scatter `values` [n, m] (coloured by `generation` [n]) with `front` [k, m] (numbered 0..k-1, the rows of
    front.csv) over each pair of objectives into `out`; for m >= 3 also a 3-D view of the first three into
    OUT_3d.png. `reference` [r, m]: a known front drawn as a line. Returns the files written (PNG or PDF)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values, front = np.asarray(values, dtype=float), np.asarray(front, dtype=float).reshape(-1, len(names))
    m = len(names)
    if values.ndim != 2 or values.shape[1] != m or m < 2:
        raise ValueError(f"need values [n, {m}] with at least 2 objectives, got shape {values.shape}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    pairs = list(combinations(range(m), 2))
    cols = min(3, len(pairs))
    rows = -(-len(pairs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.4 * rows), squeeze=False, constrained_layout=True)
    order = np.argsort(generation, kind="stable")
    for ax, (i, j) in zip(axes.flat, pairs):
        sc = ax.scatter(values[order, i], values[order, j], c=np.asarray(generation)[order], cmap="viridis", s=6,
                        alpha=0.5, linewidths=0)
        if reference is not None:
            ref = np.asarray(reference)
            ax.plot(ref[:, i], ref[:, j], color="0.3", lw=1, ls="--", label="known front")
        ax.plot(front[:, i], front[:, j], "o", color="tab:red", ms=4, label=f"final front ({len(front)})")
        if len(front) <= 30:
            for k, p in enumerate(front):
                ax.annotate(str(k), (p[i], p[j]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        # frame the front and what lies just behind it: early generations can be orders of magnitude away; and the
        # known front, the distance to which is the point of drawing it
        lo, hi = (front.min(0), front.max(0)) if len(front) else (values.min(0), values.max(0))
        if reference is not None and len(reference):
            lo = np.minimum(lo, np.asarray(reference, dtype=float).min(0))
        span = np.where(hi - lo > 0, hi - lo, np.maximum(np.abs(hi), 1.0))
        top = np.minimum(values.max(0), hi + 0.6 * span) + 0.05 * span
        ax.set_xlim(lo[i] - 0.08 * span[i], top[i])
        ax.set_ylim(lo[j] - 0.08 * span[j], top[j])
        ax.set_xlabel(_label(names[i]))
        ax.set_ylabel(_label(names[j]))
        ax.legend(fontsize=7, loc="upper right")
    for ax in list(axes.flat)[len(pairs):]:
        ax.axis("off")
    gens = np.unique(np.asarray(generation))
    bar = fig.colorbar(sc, ax=axes, label="generation", shrink=0.8)
    if len(gens) <= 12:  # whole generations, not 0.2 steps
        bar.set_ticks(gens)
    fig.suptitle(f"{len(values)} evaluated genomes; all objectives minimised")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    written = [out]
    if m >= 3:
        fig = plt.figure(figsize=(6.5, 5.5), constrained_layout=True)
        ax = fig.add_subplot(projection="3d")
        near = (values[order, :3] <= front[:, :3].max(0) + 0.65 * np.ptp(front[:, :3], 0)).all(1)
        ax.scatter(*values[order][near, :3].T, c=np.asarray(generation)[order][near], cmap="viridis", s=4, alpha=0.3)
        ax.scatter(*front[:, :3].T, color="tab:red", s=14, label=f"final front ({len(front)})")
        lo, hi = front[:, :3].min(0), front[:, :3].max(0)
        span = np.where(hi - lo > 0, hi - lo, 1.0)
        top = np.minimum(values[:, :3].max(0), hi + 0.6 * span) + 0.05 * span
        ax.set_xlim(lo[0] - 0.08 * span[0], top[0])
        ax.set_ylim(lo[1] - 0.08 * span[1], top[1])
        ax.set_zlim(lo[2] - 0.08 * span[2], top[2])
        ax.set_xlabel(_label(names[0]))
        ax.set_ylabel(_label(names[1]))
        ax.set_zlabel(_label(names[2]))
        ax.legend(fontsize=7)
        path = out.with_name(out.stem + "_3d" + out.suffix)
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


_UNITS = {"_cm": " [cm]", "_mm": " [mm]", "_n": " [N]", "_s": " [s]", "_deg": " [deg]"}


def _label(name: str) -> str:
    """An objective's column name as an axis label: `tracking_cm` -> `tracking [cm]`."""
    for suffix, unit in _UNITS.items():
        if name.endswith(suffix):
            return name[: -len(suffix)].replace("_", " ") + unit
    return name.replace("_", " ")


def plot_pareto_run(run: str | Path, out: str | Path | None = None) -> list[Path]:
    """Plot the NSGA-II run folder `run` (state.json, evaluations.csv, front.csv, and known_front.csv when the
    objective has a known front) into `out` (default RUN/pareto.png)."""
    from a3cqp_rl.tuning_files import read_rows, read_state

    run = Path(run)
    state = read_state(run)
    if state.get("kind") != "nsga2":
        raise ValueError(f"{run} holds a {state.get('kind')} run, not an NSGA-II run")
    names = state["objectives"]
    rows = [r for r in read_rows(run) if r["new"]]  # each evaluated genome once (not kept survivors again)
    front = read_rows(run, "front.csv")
    known = read_rows(run, "known_front.csv") if (run / "known_front.csv").is_file() else None
    return plot_pareto(np.array([[r[n] for n in names] for r in rows]), np.array([r["generation"] for r in rows]),
                       np.array([[r[n] for n in names] for r in front]), names, out or run / "pareto.png",
                       reference=None if known is None else np.array([[r[n] for n in names] for r in known]))
