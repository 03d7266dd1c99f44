"""Per-instance outcome codes of the batched QP solver."""

from __future__ import annotations

from enum import IntEnum

__all__ = ["QPStatus"]


class QPStatus(IntEnum):
    """Per-instance outcome codes stored in `QPSolution.status`."""

    SOLVED = 0
    """Optimal to the requested tolerance."""
    MAX_ITER = 1
    """Iteration budget exhausted; x is the last iterate (finite)."""
    PRIMAL_INFEASIBLE = 2
    """No x satisfies the constraints (a Farkas certificate was found)."""
    DUAL_INFEASIBLE = 3
    """The objective is unbounded below on the feasible set (a recession direction was found)."""
