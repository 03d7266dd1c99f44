"""Helpers for the worker-process tests (test_worker_exit, test_worker_start)."""

from __future__ import annotations


class Finaliser:
    """Writes `path` when the interpreter's teardown collects it (kept in a module global, it is collected only then)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __del__(self, _open=open) -> None:  # noqa: ANN001 (open bound now: the teardown may clear modules first)
        with _open(self.path, "w") as f:
            f.write("torn down")
