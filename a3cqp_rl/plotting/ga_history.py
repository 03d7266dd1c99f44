"""A GA run over generations: the fitness of every individual, the best and the spread; and where each gene went
(coloured by fitness, reference values such as the paper's Table IV as dashed lines)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np


def ga_history(rows: Sequence[Mapping[str, float]], fitness: str = "fitness") -> dict[str, np.ndarray]:
    """Per generation [G]: generation, best, median, min of the population, and the best so far."""
    gen = np.array([r["generation"] for r in rows])
    fit = np.array([r[fitness] for r in rows])
    gens = np.unique(gen)
    best = np.array([fit[gen == g].max() for g in gens])
    return {"generation": gens, "best": best, "median": np.array([np.median(fit[gen == g]) for g in gens]),
            "min": np.array([fit[gen == g].min() for g in gens]), "best_so_far": np.maximum.accumulate(best)}


def plot_ga_history(rows: Sequence[Mapping[str, float]], genes: Sequence[str], scales: Sequence[str],
                    out: str | Path, reference: Mapping[str, float] | None = None, fitness: str = "fitness",
                    title: str = "") -> Path:
    """Fitness per generation (every individual, best, median, population spread, best so far) and one panel per
    gene (values per generation coloured by fitness, the best individual's value starred, `reference` dashed);
    `rows` are evaluations.csv's rows. PNG or PDF by the suffix of `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator, NullFormatter, ScalarFormatter

    if not rows:
        raise ValueError("no evaluations to plot")
    h = ga_history(rows, fitness)
    gen = np.array([r["generation"] for r in rows])
    fit = np.array([r[fitness] for r in rows])
    new = np.array([r.get("new", 1.0) for r in rows]) > 0
    ib = int(np.argmax(fit))
    panels = 1 + len(genes)
    cols = min(3, panels)
    nrows = -(-panels // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.0 * cols, 3.6 * nrows), squeeze=False, constrained_layout=True)
    ax = axes.flat[0]
    ax.fill_between(h["generation"], h["min"], h["best"], color="tab:blue", alpha=0.15, label="population min-max")
    ax.scatter(gen[new], fit[new], s=8, color="0.35", label="new individual", zorder=2)
    ax.scatter(gen[~new], fit[~new], s=14, facecolors="none", edgecolors="0.6", label="kept / repeated", zorder=2)
    ax.plot(h["generation"], h["median"], color="tab:blue", lw=1, label="median")
    ax.plot(h["generation"], h["best_so_far"], color="tab:red", lw=2, label="best so far")
    lo = np.percentile(fit, 5)
    ax.set_ylim(lo - 0.1 * (fit.max() - lo) - 1e-9, fit.max() + 0.1 * (fit.max() - lo) + 1e-9)
    ax.set_xlabel("generation")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel(fitness)
    ax.set_title("fitness (lowest 5 % of points cut off)", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    norm = plt.Normalize(lo, fit.max())
    for k, (name, scale) in enumerate(zip(genes, scales)):
        ax = axes.flat[k + 1]
        v = np.array([r[name] for r in rows])
        order = np.argsort(fit)
        sc = ax.scatter(gen[order], v[order], c=np.clip(fit[order], lo, None), cmap="viridis", norm=norm, s=10)
        ax.plot(gen[ib], v[ib], "*", color="tab:red", ms=12, label=f"best {v[ib]:.3g}")
        if reference and name in reference:
            ax.axhline(reference[name], color="0.3", ls="--", lw=1, label=f"reference {reference[name]:.3g}")
        if scale == "log":
            ax.set_yscale("log")
            if np.allclose(v, np.round(v)):  # an integer gene (n_steps): its values as plain integers, not 4×10⁰
                ticks = np.unique(np.concatenate([v, [reference[name]] if reference and name in reference else []]))
                if len(ticks) <= 10:
                    ax.set_yticks(ticks)
                ax.yaxis.set_major_formatter(ScalarFormatter())
                ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("generation")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[panels:]:
        ax.axis("off")
    if len(genes):
        fig.colorbar(sc, ax=axes, label=fitness, shrink=0.8)
    if title:
        fig.suptitle(title)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_ga_run(run: str | Path, out: str | Path | None = None) -> Path:
    """Plot the GA run folder `run` (state.json, evaluations.csv) into `out` (default RUN/ga.png); genes that are
    A2C fields get the paper's Table IV value as reference."""
    from a3cqp_rl.config import A2CConfig
    from a3cqp_rl.tuning_files import read_rows, read_state

    run = Path(run)
    state = read_state(run)
    if state.get("kind") != "ga":
        raise ValueError(f"{run} holds a {state.get('kind')} run, not a GA run")
    rows = read_rows(run)
    paper = A2CConfig()
    reference = {g: float(getattr(paper, g)) for g in state["genes"] if "." not in g and hasattr(paper, g)}
    title = (f"{run}: GA, {state['generation']} generation{'' if state['generation'] == 1 else 's'}, "
             f"{state['evaluations']} trainings, "
             f"{state['seconds'] / 60:.1f} min; dashed: Table IV")
    return plot_ga_history(rows, state["genes"], state["scales"], out or run / "ga.png", reference, title=title)
