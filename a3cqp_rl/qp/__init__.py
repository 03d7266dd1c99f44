"""Batched, differentiable QP solver in torch and its cvxpy front end (cvxpylayers-style API)."""

from a3cqp_rl.qp.exceptions import (NotAQPError, NotDPPError, QPBackendError, QPError, QPGradientError, QPInfeasibleError,
                                    QPShapeError)
from a3cqp_rl.qp.layer import QPLayer
from a3cqp_rl.qp.solver import QPSolution, QPStatus, solve_qp
from a3cqp_rl.qp.vjp import QPGrad, qp_vjp

__all__ = ["solve_qp", "qp_vjp", "QPSolution", "QPGrad", "QPStatus", "QPLayer", "QPError", "QPShapeError",
           "QPBackendError", "QPInfeasibleError", "QPGradientError", "NotAQPError", "NotDPPError"]
