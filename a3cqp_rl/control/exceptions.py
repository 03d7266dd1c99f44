"""Errors raised on purpose by a3cqp_rl.control (all derive from A3CQPError)."""

from __future__ import annotations

from a3cqp_rl.exceptions import A3CQPError

__all__ = ["ControlError", "InvalidGainError", "ControlShapeError", "InvalidLevelError"]


class ControlError(A3CQPError):
    """Base class of controller errors."""


class InvalidGainError(ControlError, ValueError):
    """A gain, weight or limit with an invalid value (names the parameter and the value)."""


class ControlShapeError(ControlError, ValueError):
    """A controller input with the wrong shape (names the input, the expected and the actual shape)."""


class InvalidLevelError(ControlError, ValueError):
    """A strict-priority level (or level selector) with an invalid value (names the task and the value)."""
