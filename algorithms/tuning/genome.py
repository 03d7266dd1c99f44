"""Genomes: pygad searches u in [0, 1] per gene; a `GenomeSpec` decodes u into named values (linear, log, integer,
or a priority-level selector as paper 002 eq. 4)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from a3cqp_rl.config import GeneConfig

__all__ = ["GenomeSpec", "level_from_selector", "LEVEL_BOUNDS"]

LEVEL_BOUNDS = (0.25, 0.5, 0.75)
"""Paper 002 eq. 4: l ≤ 0.25 → level 1, ≤ 0.5 → level 2, ≤ 0.75 → level 3, else the task is off (0)."""


def level_from_selector(selector: np.ndarray | float) -> np.ndarray:
    """Priority level (1, 2, 3, or 0 = deactivated) of a selector l in [0, 1] (paper 002 eq. 4)."""
    level = np.searchsorted(np.asarray(LEVEL_BOUNDS), np.asarray(selector, dtype=float), side="left") + 1
    return np.where(level > len(LEVEL_BOUNDS), 0, level)


@dataclass(frozen=True)
class GenomeSpec:
    """The genes of a genome, in order; gene k of pygad's solution is u_k in [0, 1]."""

    genes: tuple[GeneConfig, ...]

    @property
    def num_genes(self) -> int:
        """Length of pygad's solution vector."""
        return sum(g.size for g in self.genes)

    @property
    def columns(self) -> list[str]:
        """One name per gene: `name`, or `name[i]` for the entries of a vector gene."""
        return [g.name if g.size == 1 else f"{g.name}[{i}]" for g in self.genes for i in range(g.size)]

    def decode_matrix(self, u: np.ndarray) -> np.ndarray:
        """Values [B, D] of genomes u [B, D] (float64; integers and levels as whole numbers)."""
        u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
        out = np.empty_like(u)
        k = 0
        for g in self.genes:
            cols = u[:, k:k + g.size]
            if g.type == "level":
                v = level_from_selector(cols).astype(np.float64)
            else:
                if g.scale == "log":
                    v = g.low * (g.high / g.low) ** cols
                else:
                    v = g.low + cols * (g.high - g.low)
                v = np.where(cols >= 1.0, g.high, np.clip(v, g.low, g.high))  # the ends exactly, despite round-off
                if g.type == "int":
                    v = np.clip(np.rint(v), math.ceil(g.low), math.floor(g.high))
            out[:, k:k + g.size] = v
            k += g.size
        return out

    def as_dicts(self, values: np.ndarray) -> list[dict]:
        """Decoded rows [B, D] as dicts name -> value (int for int/level genes, a list for vector genes)."""
        rows = []
        for row in np.asarray(values):
            d, k = {}, 0
            for g in self.genes:
                cast = int if g.type in ("int", "level") else float
                vals = [cast(x) for x in row[k:k + g.size]]
                d[g.name] = vals[0] if g.size == 1 else vals
                k += g.size
            rows.append(d)
        return rows

    def decode(self, u: np.ndarray) -> list[dict]:
        """Genomes u [B, D] -> one dict name -> value per genome."""
        return self.as_dicts(self.decode_matrix(u))
