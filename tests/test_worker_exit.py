"""a3cqp_rl.worker_exit: a spawned worker sends its result, runs the exit handlers registered after `install` and
skips the interpreter's teardown, with its stdout flushed; without `install` the teardown runs (the test can
fail)."""

from __future__ import annotations

import atexit
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

from a3cqp_rl import worker_exit
from tests.process_probes import Finaliser


def _worker(folder: str, install: bool, out: multiprocessing.Queue) -> None:
    if install:
        worker_exit.install()
        worker_exit.install()  # twice: still one handler
    atexit.register(Path(folder, "handler").write_text, "ran")  # a library's handler, registered later
    global _KEEP
    _KEEP = Finaliser(str(Path(folder, "teardown")))  # a module global: collected only by the teardown
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


def _set_up(folder: str) -> None:
    """A pool's set-up: registers an exit handler, as torch does when imported, and keeps a module global."""
    atexit.register(Path(folder, "handler").write_text, "ran")
    global _KEEP
    _KEEP = Finaliser(str(Path(folder, "teardown")))


def _answer() -> int:
    return 42


def test_a_pool_initializer_installs_it_before_the_set_up(tmp_path: Path) -> None:
    """`initializer("module:function", ...)`: the set-up's exit handler runs, the teardown does not, results arrive."""
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx, initializer=worker_exit.initializer,
                             initargs=("tests.test_worker_exit:_set_up", str(tmp_path))) as pool:
        assert pool.submit(_answer).result(timeout=60) == 42
    assert (tmp_path / "handler").read_text() == "ran"
    assert not (tmp_path / "teardown").exists()
