"""Batched, differentiable QP solver in torch and its cvxpy front end (cvxpylayers-style API)."""

from a3cqp_rl.qp.exceptions import NotAQPError, NotDPPError, QPBackendError, QPError, QPInfeasibleError, QPShapeError
from a3cqp_rl.qp.layer import QPLayer
from a3cqp_rl.qp.solver import QPSolution, QPStatus, solve_qp

__all__ = ["solve_qp", "QPSolution", "QPStatus", "QPLayer", "QPError", "QPShapeError", "QPBackendError", "QPInfeasibleError",
           "NotAQPError", "NotDPPError"]
