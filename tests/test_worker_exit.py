"""a3cqp_rl.worker_exit: a spawned worker sends its result, runs the exit handlers registered after `install` and
skips the interpreter's teardown, with its stdout flushed; without `install` the teardown runs (the test can
fail)."""

from __future__ import annotations

import atexit
import multiprocessing
from pathlib import Path

import pytest

from a3cqp_rl import worker_exit


class _Finaliser:
    """Writes `path` when the interpreter's teardown collects it."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __del__(self) -> None:
        Path(self.path).write_text("torn down")


def _worker(folder: str, install: bool, out: multiprocessing.Queue) -> None:
    if install:
        worker_exit.install()
        worker_exit.install()  # twice: still one handler
    atexit.register(Path(folder, "handler").write_text, "ran")  # a library's handler, registered later
    global _KEEP
    _KEEP = _Finaliser(str(Path(folder, "teardown")))  # a module global: collected only by the teardown
    print("unflushed", end="")  # noqa: T201 (stdout is flushed before the process ends)
    out.put(41 + 1)


@pytest.mark.parametrize("install", [True, False])
def test_a_worker_sends_its_result_runs_later_handlers_and_skips_the_teardown(tmp_path: Path, install: bool,
                                                                              capfd: pytest.CaptureFixture) -> None:
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    p = ctx.Process(target=_worker, args=(str(tmp_path), install, out))
    p.start()
    assert out.get(timeout=60) == 42
    p.join(timeout=60)
    assert p.exitcode == 0
    assert (tmp_path / "handler").read_text() == "ran"
    assert (tmp_path / "teardown").exists() is not install
    assert "unflushed" in capfd.readouterr().out
