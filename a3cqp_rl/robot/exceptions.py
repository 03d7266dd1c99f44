"""Errors raised on purpose by a3cqp_rl.robot (all derive from A3CQPError)."""

from __future__ import annotations

from a3cqp_rl.exceptions import A3CQPError

__all__ = ["RobotError", "UnknownToolError", "MjcfError"]


class RobotError(A3CQPError):
    """Base class of robot-model errors."""


class UnknownToolError(RobotError, ValueError):
    """A tool name that has no tool_<name>.xml asset (names the tool and the known ones)."""


class MjcfError(RobotError, RuntimeError):
    """The Panda MJCF could not be composed or parsed (names the file or the marker)."""
