"""A3CQP-RL: learning to adapt QP robot controllers online (Testa et al. 2025; Penco et al. 2020)."""

__version__ = "0.1.0"
