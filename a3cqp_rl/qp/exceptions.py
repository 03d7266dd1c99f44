"""Errors raised on purpose by the QP subpackage; all derive from :class:`A3CQPError`."""

from __future__ import annotations

from a3cqp_rl.exceptions import A3CQPError

__all__ = ["QPError", "QPShapeError", "NotAQPError", "NotDPPError"]


class QPError(A3CQPError):
    """Base class of the errors of :mod:`a3cqp_rl.qp`."""


class QPShapeError(QPError, ValueError):
    """QP data with inconsistent shapes, dtypes or batch sizes (the message names the argument)."""


class NotAQPError(QPError, ValueError):
    """A cvxpy problem that is not a quadratic program (second-order, exponential or SDP cones)."""


class NotDPPError(QPError, ValueError):
    """A cvxpy problem that is not DPP, so its matrices are not affine in the parameters."""
