"""Pool workers forked from a server that has done their imports once (Linux, macOS); spawned elsewhere.

Why: `a3cqp evaluate --scene` runs its trials in one worker process per core. A spawned worker imports torch,
torchrl, MuJoCo and the Panda env before it simulates, ~2.5 s of CPU each: on 2 cores the simulations began 3.8-4.2 s
after the command started (2026-11-29). multiprocessing's fork server does those imports once, in its own process,
which `start` launches before the command imports anything itself; each worker is then a fork of it, ready at once.
The simulations begin ~1 s sooner (a multi-seed sweep gains that for every seed), and every number is the same.

What a fork must not carry over (hence this module rather than `get_context("forkserver")` alone):
* a thread pool: GNU OpenMP cannot use threads it created before a fork. The server's first import,
  `a3cqp_rl.fork_server_setup`, puts torch on one thread, as every worker is, before any import runs a torch op;
  OpenBLAS (numpy) stops and restarts its own threads around a fork. (That import also spares the server its
  interpreter's teardown when the command ends.)
* the server's environment, fixed when it started: `pool` gives each worker the parent's, as of the pool's
  creation, as a spawned worker gets it. (multiprocessing itself sends the working directory and sys.path.)

`A3CQP_WORKER_START=spawn` spawns the workers instead (`a3cqp bench workers` compares the two; the same numbers).
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import signal
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.context import BaseContext

from a3cqp_rl import worker_exit

__all__ = ["context", "start", "pool", "default_workers", "MAX_DEFAULT_WORKERS"]

SERVER_SETUP = "a3cqp_rl.fork_server_setup"
START_METHODS = ("forkserver", "spawn")
"""Values of the environment variable A3CQP_WORKER_START (default: the first)."""
MAX_DEFAULT_WORKERS = 8
"""The most worker processes `a3cqp evaluate --scene` starts unless told (each holds ~0.5 GB: torch, its MuJoCo model
and controller)."""


def default_workers() -> int:
    """A pool's size when not given: the CPU cores this process may use (its affinity), at most `MAX_DEFAULT_WORKERS`."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity outside Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_DEFAULT_WORKERS))


def context(preload: Sequence[str] = ()) -> BaseContext:
    """The multiprocessing context for pool workers: a fork server that imports `preload` (module names) once, where
    the platform has one and A3CQP_WORKER_START does not say spawn; spawn otherwise."""
    method = os.environ.get("A3CQP_WORKER_START", START_METHODS[0]).strip().lower()
    if method not in START_METHODS:
        raise ValueError(f"A3CQP_WORKER_START must be one of {', '.join(START_METHODS)}, got {method!r}")
    if method == "spawn" or "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload([SERVER_SETUP, *preload])  # (no effect once the server runs: it keeps its imports)
    return ctx


def start(preload: Sequence[str] = ()) -> bool:
    """Start the fork server now, so that it imports `preload` while this process goes on; False where workers are
    spawned instead (nothing started)."""
    if context(preload).get_start_method() != "forkserver":
        return False
    from multiprocessing import forkserver

    forkserver.ensure_running()
    atexit.unregister(_end_server)
    atexit.register(_end_server)
    return True


def _end_server() -> None:
    # At this process's exit the server would only notice after its imports, holding the command's stdout till then
    # (a command that stops at a bad argument waited ~2 s for it). CPython keeps the server's pid private.
    module = sys.modules.get("multiprocessing.forkserver")
    pid = getattr(getattr(module, "_forkserver", None), "_forkserver_pid", None)
    if pid is not None:
        try:
            os.kill(pid, signal.SIGTERM)
        except OSError:  # already gone
            pass


def pool(workers: int, ctx: BaseContext, target: str, *args: object) -> ProcessPoolExecutor:
    """A process pool of `workers` in `ctx` (`context`) whose workers get this process's environment and run
    `target(*args)` ("module:function") at set-up; spawned ones end without their interpreter's teardown, which the
    pool's shutdown would wait for, and every one ends with this process, killed or not (`worker_exit`)."""
    return ProcessPoolExecutor(workers, mp_context=ctx, initializer=_initializer,
                               initargs=(dict(os.environ), os.getpid(), target, *args))


def _initializer(environ: dict[str, str], owner: int, target: str, *args: object) -> None:
    """A pool worker's set-up: the parent's environment, then `worker_exit.initializer(owner, target, *args)` (a
    forked worker's parent is the fork server: `owner` is the process that made the pool)."""
    if dict(os.environ) != environ:
        os.environ.clear()
        os.environ.update(environ)
    worker_exit.initializer(owner, target, *args)
