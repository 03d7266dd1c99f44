"""a3cqp_rl.worker_exit: a spawned worker sends its result, runs the exit handlers registered after `install` and
skips the interpreter's teardown, with its stdout flushed; without `install` the teardown runs (the test can
fail). A pool's workers end when the process that made the pool is killed."""

from __future__ import annotations

import atexit
import multiprocessing
import os
import signal
import subprocess
import sys
import time
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
                             initargs=(os.getpid(), "tests.test_worker_exit:_set_up", str(tmp_path))) as pool:
        assert pool.submit(_answer).result(timeout=60) == 42
    assert (tmp_path / "handler").read_text() == "ran"
    assert not (tmp_path / "teardown").exists()


def _record_pid(folder: str) -> None:
    """A pool's set-up: the worker's pid to folder/worker_<pid>."""
    Path(folder, f"worker_{os.getpid()}").touch()


OWNER = """
import sys, time
from a3cqp_rl import worker_start
with worker_start.pool(2, worker_start.context(), "tests.test_worker_exit:_record_pid", sys.argv[1]) as pool:
    jobs = [pool.submit(time.sleep, 300) for _ in range(2)]  # both workers busy, the owner waiting on them
    jobs[0].result()
"""


def _alive(pid: int) -> bool:
    return not worker_exit._owner_gone(pid)


@pytest.mark.parametrize("method", ["forkserver", "spawn"])
def test_the_workers_end_when_the_pools_owner_is_killed(tmp_path: Path, method: str) -> None:
    """Killed (SIGKILL: no handler of its own runs) while both workers are busy, the owner leaves none behind; it is
    not reaped yet (a zombie) when they go."""
    env = {**os.environ, "A3CQP_WORKER_START": method}
    owner = subprocess.Popen([sys.executable, "-c", OWNER, str(tmp_path)], env=env, cwd=Path(__file__).parents[1])
    try:
        deadline = time.monotonic() + 120
        while len(list(tmp_path.glob("worker_*"))) < 2:
            assert owner.poll() is None and time.monotonic() < deadline, "the workers never started"
            time.sleep(0.1)
        workers = [int(p.name.removeprefix("worker_")) for p in tmp_path.glob("worker_*")]
        assert all(_alive(w) for w in workers)
        owner.send_signal(signal.SIGKILL)
        deadline = time.monotonic() + 10
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(_alive(w) for w in workers), "a worker outlived its pool's owner"
    finally:
        owner.kill()
        owner.wait()


def test_an_ended_process_not_yet_reaped_counts_as_gone() -> None:
    """The poll that stands in for a pidfd: a live process is there, a zombie and a reaped one are not."""
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    assert not worker_exit._owner_gone(p.pid)
    p.kill()
    deadline = time.monotonic() + 10
    while not worker_exit._owner_gone(p.pid) and time.monotonic() < deadline:  # a zombie until waited for
        time.sleep(0.01)
    assert worker_exit._owner_gone(p.pid)
    p.wait()
    assert worker_exit._owner_gone(p.pid)
