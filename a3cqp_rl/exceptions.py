"""Package-wide error types: every error this package raises on purpose derives from A3CQPError."""


class A3CQPError(Exception):
    """Base class of all errors raised on purpose by a3cqp_rl, envs and algorithms."""


class ConfigError(A3CQPError, ValueError):
    """A configuration file or value is invalid (names the file and the key)."""


class CheckpointError(A3CQPError, RuntimeError):
    """A checkpoint is missing, truncated or from an incompatible run."""


class TrainingDiverged(A3CQPError, FloatingPointError):
    """Training produced non-finite parameters or losses (names the step and what to lower)."""
