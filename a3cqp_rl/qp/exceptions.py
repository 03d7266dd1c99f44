"""Errors raised on purpose by the QP subpackage; all derive from :class:`A3CQPError`."""

from __future__ import annotations

from a3cqp_rl.exceptions import A3CQPError

__all__ = ["QPError", "QPShapeError", "QPBackendError", "QPInfeasibleError", "QPGradientError", "NotAQPError", "NotDPPError"]


class QPError(A3CQPError):
    """Base class of the errors of :mod:`a3cqp_rl.qp`."""


class QPShapeError(QPError, ValueError):
    """QP data with inconsistent shapes, dtypes or batch sizes (the message names the argument)."""


class QPBackendError(QPError, ValueError):
    """An unknown `backend=`, or one that cannot run here (the C route on a GPU or without its library)."""


class QPInfeasibleError(QPError, RuntimeError):
    """`QPLayer` met instances without a solution (infeasible, unbounded, ...) and was asked to raise."""


class QPGradientError(QPError, RuntimeError):
    """`qp_vjp` cannot give gradients: the solution carries no problem data, or that data changed in place since."""


class NotAQPError(QPError, ValueError):
    """A cvxpy problem that is not a quadratic program (second-order, exponential or SDP cones)."""


class NotDPPError(QPError, ValueError):
    """A cvxpy problem that is not DPP, so its matrices are not affine in the parameters."""
