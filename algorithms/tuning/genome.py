"""Genomes: pygad searches u in [0, 1] per gene; a `GenomeSpec` decodes u into named values (linear, log, integer,
or a priority-level selector as paper 002 eq. 4)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from a3cqp_rl.config import GeneConfig

__all__ = ["GenomeSpec", "level_from_selector"]

def level_from_selector(selector: np.ndarray | float) -> np.ndarray:
    """Priority level of selectors l in [0, 1] (paper 002 eq. 4, a3cqp_rl.control.hierarchy): 1, 2, 3, or 0 = off."""
    from a3cqp_rl.control.hierarchy import level_from_selector as level  # imported only where a genome has levels

    sel = np.asarray(selector, dtype=np.float64)
    return np.array([level(v) or 0 for v in sel.ravel()], dtype=np.int64).reshape(sel.shape)


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
