"""Pareto fronts and the hypervolume indicator, for objectives that are minimised."""

from __future__ import annotations

import numpy as np

__all__ = ["non_dominated", "hypervolume"]


def non_dominated(values: np.ndarray) -> np.ndarray:
    """Mask [n] of the rows of `values` [n, m] that no other row dominates (<= everywhere, < somewhere)."""
    f = np.asarray(values, dtype=np.float64)
    beaten = ((f[None, :, :] <= f[:, None, :]).all(-1) & (f[None, :, :] < f[:, None, :]).any(-1)).any(1)
    return ~beaten


def hypervolume(values: np.ndarray, reference: np.ndarray | tuple) -> float:
    """Volume of objective space [.., m] dominated by `values` [n, m] and bounded by `reference` [m] (minimised
    objectives; points not strictly better than the reference on every objective add nothing)."""
    f = np.asarray(values, dtype=np.float64).reshape(-1, len(reference))
    ref = np.asarray(reference, dtype=np.float64)
    f = f[(f < ref).all(1)]
    if len(f) == 0:
        return 0.0
    f = f[non_dominated(f)]
    if f.shape[1] == 2:  # exact sweep: sorted by f1, each point adds the slab up to the previous point's f2
        f = f[np.lexsort((f[:, 1], f[:, 0]))]
        f2_above = np.concatenate([[ref[1]], f[:-1, 1]])
        return float(np.sum((ref[0] - f[:, 0]) * (f2_above - f[:, 1])))
    from pygad.utils.quality_indicators import hypervolume as pygad_hypervolume

    return float(pygad_hypervolume(-f, -ref))  # pygad's WFG algorithm takes maximised fitness
